"""`doe import` / `doe export`: a blazed grating and a Fresnel lens, as phase or height, from
every format, give the levels computed by hand; export then import is the identity; bad input
is one line and exit 2."""

import numpy as np
import pytest

from doedesign.cli import main
from doedesign.design import Design
from doedesign.materials import FUSED_SILICA

WL = 550e-9
H2PI = float(FUSED_SILICA.height_2pi_m(WL))


def _grating(n_levels):
    # A continuous blaze of 2 pi per 8 px; a pixel's phase at its centre.
    cols = np.arange(24)
    phase = np.tile(2 * np.pi * ((cols + 0.3) / 8 % 1.0), (6, 1))  # off the rounding ties
    # By hand: depth d = (2 pi - phase) h2pi / 2 pi after the wrap into (-h2pi, 0]; level = round(d / step) mod N.
    depth_steps = (-(phase / (2 * np.pi)) % 1.0) * n_levels
    return phase, (np.floor(depth_steps + 0.5) % n_levels).astype(int)


def _write(path, arr):
    ext = path.suffix
    if ext == ".npy":
        np.save(path, arr)
    elif ext == ".npz":
        np.savez(path, phase=arr)
    elif ext == ".mat":
        import scipy.io
        scipy.io.savemat(path, {"phase": arr})
    elif ext == ".h5":
        import h5py
        with h5py.File(path, "w") as f:
            f["phase"] = arr
    elif ext == ".csv":
        np.savetxt(path, arr, delimiter=",")
    elif ext == ".txt":
        np.savetxt(path, arr)
    elif ext == ".tif":
        import tifffile
        tifffile.imwrite(path, arr.astype(np.float32))


@pytest.mark.parametrize("ext", [".npy", ".npz", ".mat", ".h5", ".csv", ".txt", ".tif"])
@pytest.mark.parametrize("n_levels", [2, 8, 16])
def test_blazed_grating_phase_gives_the_levels_by_hand(tmp_path, ext, n_levels):
    phase, expected = _grating(n_levels)
    src = tmp_path / f"g{ext}"
    _write(src, phase)
    out = tmp_path / "d.npz"
    assert main(["import", str(src), "--out", str(out), "--pitch-um", "5.4", "--phase-at-nm", "550",
                 "--levels", str(n_levels)]) == 0
    d = Design.load(out)
    assert d.n_levels == n_levels and d.pitch_m == pytest.approx(5.4e-6)
    assert np.array_equal(d.levels, expected)


def test_png_with_full_scale_and_height_in_nm(tmp_path):
    from PIL import Image
    phase, expected = _grating(16)
    counts = np.round(phase / (2 * np.pi) * 256).astype(np.uint8)
    Image.fromarray(counts).save(tmp_path / "g.png")
    out = tmp_path / "d.npz"
    assert main(["import", str(tmp_path / "g.png"), "--out", str(out), "--pitch-um", "5.4", "--phase-at-nm", "550",
                 "--full-scale-rad", str(2 * np.pi)]) == 0
    assert np.array_equal(Design.load(out).levels, expected)
    np.save(tmp_path / "h.npy", phase / (2 * np.pi) * H2PI * 1e9)
    assert main(["import", str(tmp_path / "h.npy"), "--out", str(out), "--pitch-um", "5.4", "--height-unit", "nm"]) == 0
    assert np.array_equal(Design.load(out).levels, expected)


def test_radial_fresnel_lens_profile_expands_to_the_levels_by_hand(tmp_path):
    f, pitch, n = 0.05, 5.4e-6, 40
    r = np.arange(n) * pitch
    phase = -np.pi * r ** 2 / (WL * f)  # unwrapped lens phase
    np.save(tmp_path / "p.npy", phase)
    out = tmp_path / "d.npz"
    assert main(["import", str(tmp_path / "p.npy"), "--out", str(out), "--pitch-um", "5.4", "--phase-at-nm", "550",
                 "--levels", "8"]) == 0
    d = Design.load(out)
    assert d.shape == (2 * n - 1, 2 * n - 1)
    rr = np.hypot(*np.meshgrid(np.arange(2 * n - 1) - (n - 1), np.arange(2 * n - 1) - (n - 1), indexing="ij")) * pitch
    ph = -np.pi * rr ** 2 / (WL * f)
    by_hand = (np.floor(((-(ph / (2 * np.pi))) % 1.0) * 8 + 0.5) % 8).astype(int)
    inside = rr <= (n - 1) * pitch
    # The interpolated profile differs from the exact lens where the phase crosses a level boundary.
    assert np.mean(d.levels[inside] == by_hand[inside]) > 0.9
    assert d.aperture is not None and not d.aperture[0, 0] and d.aperture[n - 1, n - 1]


@pytest.mark.parametrize("what, ext", [("levels", ".npy"), ("levels", ".png"), ("height", ".csv"), ("phase", ".mat"),
                                       ("phase", ".h5"), ("height", ".tif"), ("levels", ".npz")])
def test_export_then_import_is_the_identity(tmp_path, what, ext):
    phase, expected = _grating(8)
    src = tmp_path / "g.npy"
    np.save(src, phase)
    d1 = tmp_path / "d1.npz"
    assert main(["import", str(src), "--out", str(d1), "--pitch-um", "5.4", "--phase-at-nm", "550", "--levels", "8"]) == 0
    f = tmp_path / f"x{ext}"
    assert main(["export", str(d1), "--what", what, "--out", str(f)]) == 0
    d2 = tmp_path / "d2.npz"
    if what == "levels":
        opts = ["--phase-at-nm", "550", "--full-scale-rad", str(2 * np.pi * 256 / 8)] if ext == ".png" else None
        if opts is None:  # levels as numbers: back as height in nm
            h = -Design.load(d1).level_step_m() * 1e9
            from doedesign.importer import read_map
            arr, _ = read_map(f)
            np.save(tmp_path / "h.npy", arr * h)
            f, opts = tmp_path / "h.npy", ["--height-unit", "nm"]
    elif what == "height":
        opts = ["--height-unit", "m"]
    else:
        opts = ["--phase-at-nm", "550"]
    assert main(["import", str(f), "--out", str(d2), "--pitch-um", "5.4", "--levels", "8", *opts]) == 0
    if what == "levels" and ext == ".png":
        # Grey count k stands for k * 2 pi / 8 of phase: level N - k (mod N), by the sign convention.
        assert np.array_equal(Design.load(d2).levels, (-Design.load(d1).levels) % 8)
    else:
        assert np.array_equal(Design.load(d2).levels, Design.load(d1).levels)


@pytest.mark.parametrize("case, message", [
    ("nopitch", "pitch"), ("nan", "NaN"), ("rgb", "3-channel"), ("rank", "2-D"), ("notphase", "2 pi")])
def test_bad_input_is_one_line_naming_the_file(tmp_path, capsys, case, message):
    src = tmp_path / "m.npy"
    args = ["--pitch-um", "5.4", "--phase-at-nm", "550"]
    if case == "nopitch":
        np.save(src, np.zeros((4, 4)))
        args = ["--phase-at-nm", "550"]
    elif case == "nan":
        np.save(src, np.full((4, 4), np.nan))
    elif case == "rgb":
        from PIL import Image
        src = tmp_path / "m.png"
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(src)
        args += ["--full-scale-rad", "6.28"]
    elif case == "rank":
        np.save(src, np.zeros((2, 3, 4)))
    else:
        np.save(src, np.linspace(0, 300, 16).reshape(4, 4))
        args += ["--wrapped"]
    out = tmp_path / "d.npz"
    assert main(["import", str(src), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(src) in err[0] and message in err[0]
    assert not out.exists()


def test_matlab_v73_file_is_read_through_hdf5_and_transposed_back(tmp_path):
    import h5py
    phase, expected = _grating(16)
    src = tmp_path / "g73.mat"
    with h5py.File(src, "w", userblock_size=512) as f:
        f["phase"] = phase.T  # MATLAB writes column-major: the file holds the transpose
    with open(src, "r+b") as fh:  # the 128-byte MATLAB 7.3 header in the user block
        fh.write(b"MATLAB 7.3 MAT-file, written by the test".ljust(116) + b"\0" * 8 + b"\x00\x02" + b"IM")
    out = tmp_path / "d.npz"
    assert main(["import", str(src), "--out", str(out), "--pitch-um", "5.4", "--phase-at-nm", "550"]) == 0
    assert np.array_equal(Design.load(out).levels, expected)


def test_several_arrays_need_array(tmp_path, capsys):
    phase, expected = _grating(4)
    np.savez(tmp_path / "two.npz", phase=phase, other=np.zeros((3, 3)))
    out = tmp_path / "d.npz"
    base = ["import", str(tmp_path / "two.npz"), "--out", str(out), "--pitch-um", "5.4", "--phase-at-nm", "550",
            "--levels", "4"]
    assert main(base) == 2 and "--array" in capsys.readouterr().err
    assert main(base + ["--array", "phase"]) == 0
    assert np.array_equal(Design.load(out).levels, expected)
