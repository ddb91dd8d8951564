"""Real instrument files (tests/data/realdata/, MIT licences beside them, README there says where
each comes from) read through metrology.formats.readers, with the figures the source library's
own tests assert; damaged variants refused in one line naming the file (exit 2 via `doe inspect`)."""

from pathlib import Path

import numpy as np
import pytest

from doedesign.cli import main
from metrology.formats.measurement import MeasurementFileError
from metrology.formats.readers import read_measurement
from metrology.formats.x3p import read_x3p, write_x3p

DATA = Path(__file__).resolve().parents[1] / "data" / "realdata"
FORMATS = DATA / "surface-formats"
AFM = DATA / "afm-nanosurf-binary-arrays"


def test_x3p_non_square_pixels_read_as_they_are():
    m = read_measurement(FORMATS / "x3p-2.x3p")
    assert m.shape == (650, 650)
    assert m.pixel_size_m * 650 == pytest.approx(82.9767313942749e-6, rel=1e-9)
    assert m.pitches_m[0] * 650 == pytest.approx(204.4783737930349e-6, rel=1e-9)
    h = m.height_m
    assert np.isfinite(h).all()
    assert np.sqrt(np.mean((h - h.mean()) ** 2)) == pytest.approx(77.28033273597876e-9, rel=1e-9)
    sq = m.square_pixels()
    assert sq.pixel_size_y_m is None and sq.shape[1] == 650
    assert sq.shape[0] == round(649 * 204.4783737930349 / 82.9767313942749) + 1


def test_sur_non_measured_points_are_nan():
    # sur-3 marks 233009 of 512 x 512 points not measured (zmin - 2); the README's 1.920e-3 rms
    # is that of all points, the 29135 measured ones give 1.1132e-3 (SurfaceTopography's test).
    m = read_measurement(FORMATS / "sur-3.sur")
    assert m.shape == (512, 512)
    assert m.pixel_size_m * 512 == pytest.approx(0.151319552, rel=1e-6)
    assert np.count_nonzero(~m.valid) == 233009
    v = m.height_m[m.valid]
    assert v.std() == pytest.approx(1.1131994265859693e-3, rel=1e-6)


@pytest.mark.parametrize("name, shape, size_m, channel", [
    ("afm-nanosurf-binary-arrays/circles.nid", (256, 256), 50e-6, "Scan forward (Topography)"),
    ("afm-nanosurf-binary-arrays/squares_holes.nid", (256, 256), 50e-6, "Scan forward (Topography)"),
    ("surface-formats/nid-1.nid", (256, 256), 20e-6, "Scan forward (Z-Axis)"),
    ("surface-formats/di-3.di", (256, 256), 10e-6, "ZSensor"),
    ("surface-formats/opdx-3.opdx", (1, 3001), 49.983344425752584e-6, "Height"),
])
def test_afm_and_profiler_files(name, shape, size_m, channel):
    m = read_measurement(DATA / name)
    assert m.shape == shape
    assert m.pixel_size_m * shape[1] == pytest.approx(size_m, rel=1e-9)
    assert m.metadata["channel"] == channel
    span = np.ptp(m.height_m[m.valid])
    assert 1e-9 < span < 5e-6


def test_afm_scans_hold_about_490_nm_steps():
    for name in ("circles.nid", "squares_holes.nid"):
        h = read_measurement(AFM / name).height_m
        lo, hi = np.percentile(h, [2, 98])
        assert 300e-9 < hi - lo < 1.2e-6


def test_x3p_written_reads_back_with_surfacetopography(tmp_path):
    from SurfaceTopography import open_topography

    h = np.random.default_rng(0).normal(0, 1e-8, (30, 50))
    h[3, 4] = np.nan
    path = write_x3p(tmp_path / "a.x3p", h, 1e-6, 2e-6, comment="levelled")
    t = open_topography(str(path)).topography()
    assert t.nb_grid_pts == (50, 30)
    assert t.physical_sizes == pytest.approx((50e-6, 60e-6))
    assert np.allclose(np.ma.filled(t.heights(), np.nan).T, h, equal_nan=True)
    back = read_x3p(path)
    assert back.pitches_m == pytest.approx((2e-6, 1e-6))


CASES = ["afm-nanosurf-binary-arrays/circles.nid", "surface-formats/di-3.di", "surface-formats/sur-3.sur",
         "surface-formats/opdx-3.opdx", "surface-formats/x3p-2.x3p"]


@pytest.mark.parametrize("name", CASES)
@pytest.mark.parametrize("keep", [0.0, 0.01, 0.3])
def test_truncated_file_refused_in_one_line(tmp_path, capsys, name, keep):
    src = (DATA / name).read_bytes()
    bad = tmp_path / Path(name).name
    bad.write_bytes(src[:int(len(src) * keep)])
    assert main(["inspect", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert str(bad) in err and "Traceback" not in err and len(err.splitlines()) == 1


def test_nid_header_claiming_a_huge_grid_refused(tmp_path):
    text = (AFM / "circles.nid").read_bytes()
    bad = tmp_path / "huge.nid"
    bad.write_bytes(text.replace(b"Lines=256", b"Lines=999999999").replace(b"Points=256", b"Points=999999999"))
    with pytest.raises(MeasurementFileError) as exc:
        read_measurement(bad)
    assert str(bad) in str(exc.value)


# -- Dektak CSV (a stylus line scan; the export prints x rounded to 0.1 um) -------------------------
DEKTAK = FORMATS / "dektak-1.csv"


def _dektak_columns(path):
    """The scan data (um) parsed here with the csv module: the independent estimate."""
    import csv

    rows = list(csv.reader(path.read_text(encoding="latin-1").splitlines()))
    start = next(i for i, r in enumerate(rows) if r and r[0] == "Scan Data") + 3  # blank line, column names
    data = np.array([[float(r[0]), float(r[1])] for r in rows[start:] if r and r[0]])
    return data[:, 0], data[:, 1]


def test_dektak_read_with_its_spacing_and_height_range():
    m = read_measurement(DEKTAK)
    x_um, z_um = _dektak_columns(DEKTAK)
    assert m.shape == (1, x_um.size) and m.metadata["format"] == "dektak_csv"
    # The header declares Length 1500.0 um and Resolution 0.156 um/sample (printed to 3
    # digits); the points read cover the length, the spacing agrees with the resolution.
    assert m.pixel_size_m * m.shape[1] == pytest.approx(1500.0e-6, rel=1e-6)
    assert abs(m.pixel_size_m - 0.156e-6) <= 0.0005e-6
    # x printed to 0.1 um: the steps read 0.1 or 0.2, the spacing is none of them.
    assert set(np.round(np.diff(x_um), 6)) == {0.1, 0.2}
    h = m.height_m[0]
    assert np.isfinite(h).all()
    assert h.min() == pytest.approx(z_um.min() * 1e-6, rel=1e-12)
    assert h.max() == pytest.approx(z_um.max() * 1e-6, rel=1e-12)
    np.testing.assert_allclose(h, z_um * 1e-6, rtol=1e-12)
    assert m.metadata["tip_radius_m"] == pytest.approx(2.5e-6)


def test_dektak_rms_height_agrees_with_the_libraries_figure():
    # README: rms height 4.763596 um, SurfaceTopography's piecewise-linear rms over the file's
    # printed (rounded) positions. The same integral over the uniform 0.15625 um grid differs
    # only by the rounding of x (a few 1e-5 of it).
    m = read_measurement(DEKTAK)
    h, d = m.height_m[0] * 1e6, m.pixel_size_m * 1e6
    a, b = h[:-1], h[1:]
    length = d * (h.size - 1)
    mean = np.sum(a + b) / 2 * d / length
    square = np.sum(a * a + a * b + b * b) / 3 * d / length
    assert np.sqrt(square - mean ** 2) == pytest.approx(4.763596, rel=1e-4)


def test_dektak_inspect_and_mx_csv_still_mx(tmp_path, capsys):
    import json

    assert main(["inspect", "--json", str(DEKTAK)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["pixel_size_m"] == pytest.approx(0.15625e-6, rel=1e-6)
    assert summary["height_max_m"] - summary["height_min_m"] == pytest.approx((16.58112 + 0.00933) * 1e-6, rel=1e-9)
    mx = tmp_path / "mx.csv"
    mx.write_text("X (um),Y (um)\n0,0.1\n0.5,0.2\n1.0,0.3\n")
    assert read_measurement(mx).metadata["format"] == "mx_profile_csv"


def _dektak_lines():
    return DEKTAK.read_bytes().split(b"\r\n")


def _dektak_cut_at_line_end(tmp_path):
    lines = _dektak_lines()
    return lines[:len(lines) // 2]


def _with_header(key, value):
    lines = _dektak_lines()
    i = next(i for i, line in enumerate(lines) if line.startswith(key + b","))
    lines[i] = key + b"," + value
    return lines


def _with_row(index_from_end, x=None, height=None):
    """The scan row ``index_from_end`` from the end with its x or its height replaced."""
    lines = _dektak_lines()
    row = [i for i, line in enumerate(lines) if line[:1].isdigit() or line[:1] == b"-"][-index_from_end]
    fields = lines[row].split(b",")
    fields[0] = fields[0] if x is None else x
    fields[1] = fields[1] if height is None else height
    lines[row] = b",".join(fields)
    return lines


DEKTAK_BAD = [
    ("cut at 50 % inside a line", lambda: [DEKTAK.read_bytes()[:len(DEKTAK.read_bytes()) // 2]], "truncated"),
    ("cut at a line end", lambda: _dektak_cut_at_line_end(None), "truncated"),
    ("header only", lambda: _dektak_lines()[:40], None),
    ("Length 1e9 um", lambda: _with_header(b"Length", b"1e9 um"), "Length"),
    ("x going back", lambda: _with_row(100, x=b"3.0"), "not increasing"),
    ("x skipping 100 um", lambda: _with_row(100, x=b"1600.0"), None),
    ("height 1e30 um", lambda: _with_row(50, height=b"1e30"), "heights"),
    ("height text", lambda: _with_row(50, height=b"abc"), None),
    ("random bytes after the header", lambda: [b"Scan Parameters", bytes(np.random.default_rng(3).integers(
        0, 256, 50_000, dtype=np.uint8))], None),
]


@pytest.mark.parametrize("name,build,match", DEKTAK_BAD, ids=[c[0] for c in DEKTAK_BAD])
def test_damaged_dektak_refused_in_one_line(tmp_path, capsys, name, build, match):
    bad = tmp_path / "dektak.csv"
    bad.write_bytes(b"\r\n".join(build()))
    assert main(["inspect", str(bad)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert str(bad) in err and "Traceback" not in err and len(err.splitlines()) == 1 and not captured.out, err
    assert match is None or match in err, err


def test_nid_claim_within_the_size_slack_refused_by_its_frames(tmp_path, capsys):
    # 2048 x 2048 points of 2 bytes in 4 frames: under the 16x slack of the pixel-count check
    # (4.2e6 points for a 529 kB file), but 33.5 MB of frames against 524288 bytes after '#!'.
    text = (AFM / "circles.nid").read_bytes()
    bad = tmp_path / "claims.nid"
    bad.write_bytes(text.replace(b"Lines=256", b"Lines=2048").replace(b"Points=256", b"Points=2048"))
    assert main(["inspect", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert str(bad) in err and "33554432 bytes of data in 4 frames" in err and "holds 524288" in err, err


@pytest.mark.parametrize("edit, match", [
    (lambda raw: raw[:raw.index(b"\n#!") + 1], "no '#!' data marker"),
    (lambda raw: raw.replace(b"SaveBits=16", b"SaveBits=12"), "not a whole number of bytes"),
    (lambda raw: raw.replace(b"Points=256", b"Points=-256"), "negative"),
    (lambda raw: raw.replace(b"Lines=256", b"Lines=lots"), "cannot read as ezd"),  # the library's parse
])
def test_nid_header_frames_checked(tmp_path, capsys, edit, match):
    bad = tmp_path / "frames.nid"
    bad.write_bytes(edit((AFM / "circles.nid").read_bytes()))
    assert main(["inspect", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert str(bad) in err and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert match in err, err


def test_line_pitch_takes_printed_rounding_only_where_the_format_rounds():
    from metrology.formats.profile import line_pitch, printed_quantum

    true = np.arange(2000) * 0.15625
    printed = np.round(true, 1)
    assert printed_quantum(printed) == pytest.approx(0.1) and printed_quantum(true) == pytest.approx(1e-5)
    assert printed_quantum(np.arange(2000) / 3) == 0.0  # printed in full precision
    assert line_pitch("p", printed, rounded=True) == pytest.approx(0.15625, rel=1e-6)
    with pytest.raises(MeasurementFileError, match="not uniformly spaced"):
        line_pitch("p", printed)  # an export that prints x in full does not round it
    shifted = printed.copy()
    shifted[1000] += 0.2  # two printed digits off: not rounding any more
    with pytest.raises(MeasurementFileError, match="p: .* not uniformly spaced"):
        line_pitch("p", shifted, rounded=True)
