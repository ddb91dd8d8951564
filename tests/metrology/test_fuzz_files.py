"""Adversarial measurement and design files, built here: every case must end in a clean refusal
(:class:`~doedesign.errors.DoeError` naming the file) or, where the data may be partly valid,
in a measurement that says which pixels are invalid. Never a traceback, a hang, gigabytes of
memory or a silently wrong height.

The named cases assert the refusal (the message names the field or the problem); the sweep
cases (truncations and byte corruptions of every format) assert only that the outcome is
clean and, when accepted, physically plausible.
"""

import json
import os
import struct
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest

from doedesign.design import Design
from doedesign.errors import DesignFileError, DoeError
from doedesign.fileio import MAX_INPUT_ARRAY_BYTES
from metrology.formats import plausibility
from metrology.formats.measurement import MeasurementFileError
from metrology.formats.readers import read_measurement
from metrology.formats.writers import write_datx, write_measurement
from metrology.formats.zygo_dat import FIELDS

PIXEL = 1.1e-6
FORMATS = ("dat", "datx", "xyz", "asc", "csv", "npy", "npz", "tif")


def _height(shape=(12, 10)):
    rng = np.random.default_rng(1)
    h = -rng.integers(0, 16, shape) * 74.7e-9 + rng.normal(0, 1e-9, shape)
    h[min(2, shape[0] - 1), min(3, shape[1] - 1)] = np.nan
    return h


def _write(tmp_path, fmt, name="base"):
    path = tmp_path / f"{name}.{fmt}"
    h = _height((1, 40)) if fmt == "csv" else _height()
    write_measurement(path, h, PIXEL)
    return path


def _refused(path, match, **kw):
    with pytest.raises(MeasurementFileError) as exc:
        read_measurement(path, **kw)
    message = str(exc.value)
    assert str(path) in message and "Traceback" not in message and "allow_pickle" not in message
    assert match in message, message
    return message


def _edit_ascii(path, line, field, value):
    """Replace whitespace field ``field`` (0-based) of header line ``line`` (1-based)."""
    lines = path.read_text(encoding="latin-1").split("\n")
    tokens = lines[line - 1].split(" ")
    tokens[field] = value
    lines[line - 1] = " ".join(tokens)
    path.write_text("\n".join(lines), encoding="latin-1")
    return path


def _edit_dat(path, field, value):
    raw = bytearray(path.read_bytes())
    offset, code = FIELDS[field]
    struct.pack_into(">" + code, raw, offset, value)
    path.write_bytes(bytes(raw))
    return path


def _asc_counts(path, token):
    """Replace the first phase count of an .asc with ``token``."""
    lines = path.read_text(encoding="latin-1").split("\n")
    marks = [i for i, line in enumerate(lines) if line.strip() == "#"]
    first = marks[1] + 1  # the phase block follows the intensity block's '#'
    lines[first] = " ".join([token] + lines[first].split(" ")[1:])
    path.write_text("\n".join(lines), encoding="latin-1")
    return path


def _fake_npy_header(shape, dtype="<f8"):
    header = {"descr": dtype, "fortran_order": False, "shape": shape}
    buf = np.lib.format.header_data_from_array_1_0(np.zeros(1))
    del buf
    text = repr(header).encode("latin1")
    pad = 64 - (10 + len(text) + 1) % 64
    body = text + b" " * pad + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(body)) + body


# -- named cases: (id, builder(tmp_path) -> path, expected text in the refusal) ----------------------
def _xyz_claims(tmp_path, rows, cols):
    path = tmp_path / "claim.xyz"
    write_measurement(path, _height((2, 2)), PIXEL)
    return _edit_ascii(_edit_ascii(path, 4, 2, str(cols)), 4, 3, str(rows))


def _xyz_duplicate(tmp_path):
    path = _write(tmp_path, "xyz")
    lines = path.read_text(encoding="latin-1").split("\n")
    end = lines.index("#")
    lines[end + 2] = lines[end + 1].rsplit(" ", 1)[0] + " 0.5"  # pixel (0, 0) again
    path.write_text("\n".join(lines), encoding="latin-1")
    return path


def _npz(tmp_path, **arrays):
    path = tmp_path / "x.npz"
    np.savez(path, **arrays)
    return path


def _npz_claim(tmp_path, shape):
    path = tmp_path / "claim.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("height_m.npy", _fake_npy_header(shape) + b"\0" * 64)
        zf.writestr("pixel_size_m.npy", _npy_bytes(np.float64(PIXEL)))
    return path


def _npy_bytes(array):
    import io

    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def _zip_bomb(tmp_path):
    """A small .npz whose member inflates far beyond the input limit (zeros compress ~1000:1)."""
    path = tmp_path / "bomb.npz"
    n = (MAX_INPUT_ARRAY_BYTES + 2**20) // 8
    side = int(np.sqrt(n)) + 1
    chunk = b"\0" * 2**24
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open("height_m.npy", "w", force_zip64=True) as fh:
            fh.write(_fake_npy_header((side, side)))
            left = side * side * 8
            while left > 0:
                fh.write(chunk[:min(left, len(chunk))])
                left -= len(chunk)
    return path


def _datx_chunked_claim(tmp_path):
    import h5py

    path = tmp_path / "claim.datx"
    write_datx(path, _height(), PIXEL)
    with h5py.File(path, "a") as f:
        name = next(iter(f["Data/Surface"]))
        attrs = dict(f["Data/Surface"][name].attrs)
        del f["Data/Surface"][name]
        big = f.create_dataset(f"Data/Surface/{name}", shape=(100000, 100000), dtype="f4", chunks=(256, 256))
        for k, v in attrs.items():
            big.attrs[k] = v
    return path


def _datx(tmp_path, **kw):
    path = tmp_path / "x.datx"
    write_datx(path, _height(), PIXEL, **kw)
    return path


def _replace_surface(tmp_path, make, name="links.datx"):
    """A .datx whose surface dataset is replaced by ``make(f, surface_path, values)`` (attributes kept)."""
    import h5py

    path = tmp_path / name
    write_datx(path, _height(), PIXEL)
    with h5py.File(path, "a") as f:
        where = f"/Data/Surface/{next(iter(f['Data/Surface']))}"
        values, attrs = f[where][()], dict(f[where].attrs)
        del f[where]
        made = make(f, where, values)
        if made is not None:
            for k, v in attrs.items():
                made.attrs[k] = v
    return path


def _other_file(tmp_path, values=None):
    """A second, valid .datx beside the first (whose surface an external link would read)."""
    other = tmp_path / "other.datx"
    write_datx(other, np.full((12, 10), 1e-6) if values is None else values, PIXEL)
    return other


def _external_link(tmp_path):
    import h5py

    other = _other_file(tmp_path)
    with h5py.File(other, "r") as g:
        target = f"/Data/Surface/{next(iter(g['Data/Surface']))}"
    return _replace_surface(tmp_path, lambda f, where, v: f.__setitem__(where, h5py.ExternalLink(other.name, target)))


def _external_group(tmp_path):
    """/Data itself is an external link: the MetaData path walks through it."""
    import h5py

    _other_file(tmp_path)
    path = tmp_path / "group.datx"
    write_datx(path, _height(), PIXEL)
    with h5py.File(path, "a") as f:
        del f["Data"]
        f["Data"] = h5py.ExternalLink("other.datx", "/Data")
    return path


def _external_storage(tmp_path, target):
    """The surface's raw values live in ``target`` (another file's bytes, /dev/zero)."""
    def make(f, where, values):
        if target == "file":
            raw = tmp_path / "raw.bin"
            raw.write_bytes(np.ones(values.shape, "<f8").tobytes())  # 1 um everywhere, not the surface
            ext = [(str(raw), 0, values.nbytes)]
        else:
            ext = [(target, 0, values.nbytes)]
        return f.create_dataset(where, shape=values.shape, dtype="<f8", external=ext)
    return _replace_surface(tmp_path, make)


def _virtual(tmp_path):
    import h5py

    other = _other_file(tmp_path)

    def make(f, where, values):
        with h5py.File(other, "r") as g:
            name = f"/Data/Surface/{next(iter(g['Data/Surface']))}"
        layout = h5py.VirtualLayout(shape=values.shape, dtype="<f8")
        layout[:] = h5py.VirtualSource(str(other), name, shape=values.shape)
        return f.create_virtual_dataset(where, layout)
    return _replace_surface(tmp_path, make)


def _soft_to_external(tmp_path):
    """The surface is a soft link (inside the file) to an external link."""
    import h5py

    other = _other_file(tmp_path)

    def make(f, where, values):
        with h5py.File(other, "r") as g:
            name = f"/Data/Surface/{next(iter(g['Data/Surface']))}"
        f["/Elsewhere/surface"] = h5py.ExternalLink(other.name, name)
        f[where] = h5py.SoftLink("/Elsewhere/surface")
    return _replace_surface(tmp_path, make)


def _soft_loop(tmp_path):
    import h5py

    def make(f, where, values):
        f["/Loop/a"] = h5py.SoftLink("/Loop/b")
        f["/Loop/b"] = h5py.SoftLink("/Loop/a")
        f[where] = h5py.SoftLink("/Loop/a")
    return _replace_surface(tmp_path, make)


def _external_metadata(tmp_path):
    import h5py

    other = _other_file(tmp_path)
    path = tmp_path / "meta.datx"
    write_datx(path, _height(), PIXEL)
    with h5py.File(path, "a") as f:
        del f["MetaData"]
        f["MetaData"] = h5py.ExternalLink(other.name, "/MetaData")
    return path


DATX_LINKS = [
    ("datx surface is an external link", _external_link, "external link"),
    ("datx /Data is an external link", _external_group, "external link"),
    ("datx surface stored in another file", lambda t: _external_storage(t, "file"), "external file"),
    ("datx surface stored in /dev/zero", lambda t: _external_storage(t, "/dev/zero"), "external file"),
    ("datx virtual surface from another file", _virtual, "virtual dataset"),
    ("datx soft link to an external link", _soft_to_external, "external link"),
    ("datx soft link loop", _soft_loop, "soft links"),
    ("datx MetaData is an external link", _external_metadata, "external link"),
]


def _csv_long_field(tmp_path):
    path = tmp_path / "long.csv"
    path.write_text("X (um),Y (um)\n0," + "1" * 200_000 + "\n1,2\n")
    return path


def _fifo(tmp_path, fmt):
    path = tmp_path / f"pipe.{fmt}"
    os.mkfifo(path)
    return path


NAMED = [
    # physical plausibility of header quantities
    ("asc wavelength in nm", lambda t: _edit_ascii(_write(t, "asc"), 8, 2, "632.8"), "wavelength_m"),
    ("asc scale factor 3e38", lambda t: _edit_ascii(_write(t, "asc"), 8, 1, "3e38"), "intf_scale_factor"),
    ("asc obliquity 1e9", lambda t: _edit_ascii(_write(t, "asc"), 8, 4, "1e9"), "obliquity_factor"),
    ("asc lateral res 1e30", lambda t: _edit_ascii(_write(t, "asc"), 8, 6, "1e30"), "lateral_res_m"),
    ("xyz lateral res 1e30", lambda t: _edit_ascii(_write(t, "xyz"), 8, 6, "1e30"), "lateral_res_m"),
    ("xyz wavelength 632.8", lambda t: _edit_ascii(_write(t, "xyz"), 8, 2, "632.8"), "wavelength_m"),
    ("dat wavelength 632.8", lambda t: _edit_dat(_write(t, "dat"), "wavelength_in", 632.8), "wavelength_m"),
    ("dat scale factor 3e38", lambda t: _edit_dat(_write(t, "dat"), "intf_scale_factor", 3e38), "intf_scale_factor"),
    ("dat lateral res 1e30", lambda t: _edit_dat(_write(t, "dat"), "lateral_res", 1e30), "lateral_res_m"),
    ("datx wavelength 632.8 (fringes)", lambda t: _datx(t, unit="Fringes", wavelength_m=632.8), "Wavelength = 632.8"),
    ("datx pixel 1e30", lambda t: _datx(t) if False else _datx_pixel(t, 1e30), "pixel size"),
    ("npz heights 1e18 m", lambda t: _npz(t, height_m=np.full((4, 4), 1e18), pixel_size_m=PIXEL), "heights reach"),
    ("npz heights in nm", lambda t: _npz(t, height_m=np.full((4, 4), -300.0), pixel_size_m=PIXEL), "heights reach"),
    ("npz pixel 5 m", lambda t: _npz(t, height_m=np.zeros((4, 4)), pixel_size_m=5.0), "pixel size"),
    # data that cannot be what they claim
    ("asc count nan", lambda t: _asc_counts(_write(t, "asc"), "nan"), "phase count"),
    ("asc count 1e30", lambda t: _asc_counts(_write(t, "asc"), "1e30"), "phase count"),
    ("asc count fractional", lambda t: _asc_counts(_write(t, "asc"), "12.5"), "phase count"),
    ("asc count inf", lambda t: _asc_counts(_write(t, "asc"), "inf"), "phase count"),
    ("xyz duplicate pixel", _xyz_duplicate, "more than once"),
    ("npz all nan", lambda t: _npz(t, height_m=np.full((4, 4), np.nan), pixel_size_m=PIXEL), "no valid pixel"),
    # sizes claimed beyond the content
    ("xyz 20000 x 20000 header", lambda t: _xyz_claims(t, 20000, 20000), "claims"),
    ("xyz 100000 x 100000 header", lambda t: _xyz_claims(t, 100000, 100000), "claims"),
    ("npy 100000 x 100000 header",
     lambda t: (t / "c.npy").write_bytes(_fake_npy_header((100000, 100000)) + b"\0" * 64) and t / "c.npy", "claims"),
    ("npy header longer than data",
     lambda t: (t / "d.npy").write_bytes(_fake_npy_header((100, 100)) + b"\0" * 64) and t / "d.npy", "truncated"),
    ("npz 100000 x 100000 member", lambda t: _npz_claim(t, (100000, 100000)), "claims"),
    ("npz member longer than data", lambda t: _npz_claim(t, (100, 100)), "truncated"),
    ("datx chunked 100000 x 100000", _datx_chunked_claim, "claims"),
    # wrong types
    ("npz object array", lambda t: _npz(t, height_m=np.array([[{"a": 1}]], dtype=object)), "objects"),
    ("npz complex pixel", lambda t: _npz(t, height_m=np.zeros((4, 4)), pixel_size_m=np.complex128(1e-6 + 1j)),
     "one real number"),
    ("npz text pixel", lambda t: _npz(t, height_m=np.zeros((4, 4)), pixel_size_m="1e-6"), "one real number"),
    ("npz text heights", lambda t: _npz(t, height_m=np.array([["a", "b"]]), pixel_size_m=PIXEL), "2-D numeric"),
    ("asc inf in integer field", lambda t: _edit_ascii(_write(t, "asc"), 4, 2, "inf"), "not a number"),
    ("asc nan in integer field", lambda t: _edit_ascii(_write(t, "asc"), 4, 3, "nan"), "not a number"),
    ("csv field over the parser limit", _csv_long_field, "field"),
    ("datx text surface", lambda t: _datx_text(t), "not numbers"),
    # data from outside the file read as the surface
    *DATX_LINKS,
    # not a regular file
    *[(f"{fmt} named pipe", lambda t, fmt=fmt: _fifo(t, fmt), "not a regular file") for fmt in FORMATS],
    ("folder as input", lambda t: (t / "d.datx").mkdir() or t / "d.datx", "folder"),
]


def _datx_pixel(tmp_path, pixel):
    path = tmp_path / "px.datx"
    write_datx(path, _height(), pixel)
    return path


def _datx_text(tmp_path):
    import h5py

    path = _datx(tmp_path)
    with h5py.File(path, "a") as f:
        name = next(iter(f["Data/Surface"]))
        attrs = dict(f["Data/Surface"][name].attrs)
        del f["Data/Surface"][name]
        d = f.create_dataset(f"Data/Surface/{name}", data=np.array([[b"a", b"b"], [b"c", b"d"]]))
        for k, v in attrs.items():
            d.attrs[k] = v
    return path


@pytest.mark.parametrize("name,build,match", NAMED, ids=[n[0] for n in NAMED])
def test_named_case_is_refused_cleanly(tmp_path, name, build, match):
    _refused(build(tmp_path), match)


@pytest.mark.parametrize("name,build,match", DATX_LINKS, ids=[n[0] for n in DATX_LINKS])
def test_datx_outside_data_refused_by_the_cli(tmp_path, capsys, name, build, match):
    from doedesign.cli import main

    path = build(tmp_path)
    assert main(["inspect", str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and str(path) in captured.err and match in captured.err, captured.err
    assert "Traceback" not in captured.err and not captured.out


def test_datx_soft_link_inside_the_file_reads(tmp_path):
    import h5py

    def make(f, where, values):
        real = f.create_dataset("/Elsewhere/surface", data=values)
        f[where] = h5py.SoftLink("/Elsewhere/surface")
        return real
    meas = read_measurement(_replace_surface(tmp_path, make))
    expected = read_measurement(write_datx(tmp_path / "plain.datx", _height(), PIXEL))
    np.testing.assert_array_equal(meas.height_m, expected.height_m)


def test_zip_bomb_refused_before_inflating(tmp_path):
    import tracemalloc

    path = _zip_bomb(tmp_path)
    assert path.stat().st_size < 8 * 2**20
    tracemalloc.start()
    _refused(path, "inflates")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 50 * 2**20


def test_datx_no_data_below_the_data_marks_only_itself(tmp_path):
    path = _datx(tmp_path, no_data=-1.0)  # NaN written as -1 m: below every height
    meas = read_measurement(path)
    assert np.count_nonzero(~meas.valid) == 1 and not meas.valid[2, 3]


def test_out_of_range_timestamp_is_dropped_not_a_traceback(tmp_path):
    meas = read_measurement(_edit_ascii(_write(tmp_path, "asc"), 8, 7, "1e30"))
    assert meas.metadata["timestamp"] is None


def test_plausible_ranges_keep_every_writer_default(tmp_path):
    """The rules refuse nothing a real file holds: every format's own export reads back."""
    for fmt in FORMATS:
        meas = read_measurement(_write(tmp_path, fmt), pixel_size_m=PIXEL if fmt == "npy" else None)
        assert meas.pixel_size_m == pytest.approx(PIXEL, rel=1e-6)


# -- sweep: truncations and byte corruptions of every format ------------------------------------------
def _sweep_cases():
    cases = []
    for fmt in FORMATS:
        for frac in (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99):
            cases.append((fmt, "truncate", frac))
        for seed in range(6):
            cases.append((fmt, "corrupt", seed))
    return cases


SWEEP = _sweep_cases()


@pytest.mark.parametrize("fmt,kind,arg", SWEEP, ids=[f"{f}-{k}-{a}" for f, k, a in SWEEP])
def test_damaged_file_is_refused_or_plausible(tmp_path, fmt, kind, arg):
    path = _write(tmp_path, fmt)
    raw = bytearray(path.read_bytes())
    if kind == "truncate":
        raw = raw[:int(len(raw) * arg)]
    else:
        rng = np.random.default_rng(arg)
        for i in rng.integers(0, len(raw), 8):
            raw[i] = int(rng.integers(0, 256))
    path.write_bytes(bytes(raw))
    message = _refused_or_plausible(path)
    assert message is None or "allow_pickle" not in message


def _refused_or_plausible(path):
    """The one-line refusal of ``path`` (naming it), or None where it was read as plausible data."""
    try:
        meas = read_measurement(path)
    except DoeError as exc:
        assert str(path) in str(exc)
        return str(exc)
    # Accepted: it must satisfy the physical rules (they ran inside read_measurement).
    plausibility.check_measurement(path, meas)
    return None


# -- design files ---------------------------------------------------------------------------------------
def _design_npz(tmp_path, **override):
    step = Design(np.zeros((2, 2)), 5.4e-6).height_2pi_m() / 16
    levels = np.arange(16, dtype=np.int16).reshape(4, 4)
    fields = dict(height_m=-levels * step, pitch_m=np.float64(5.4e-6), material=np.str_("fused_silica"),
                  design_wavelength_m=np.float64(550e-9), levels=levels,
                  metadata=np.str_(json.dumps({"name": "d", "format_version": 1})))
    for k, v in override.items():
        if k.startswith("meta_"):
            meta = json.loads(str(fields["metadata"]))
            meta[k[5:]] = v
            fields["metadata"] = np.str_(json.dumps(meta))
        else:
            fields[k] = v
    path = tmp_path / "design.npz"
    np.savez(path, **fields)
    return path


def _levels_off(tmp_path):
    levels = np.arange(16, dtype=np.int16).reshape(4, 4)
    bad = levels.copy()
    bad[1, 2] = 0
    return _design_npz(tmp_path, levels=bad)


DESIGNS = [
    ("name is a number", dict(meta_name=42), "name"),
    ("name is null", dict(meta_name=None), "name"),
    ("name too long", dict(meta_name="x" * 5000), "name"),
    ("format_version text", dict(meta_format_version="1"), "format_version"),
    ("format_version 1.5", dict(meta_format_version=1.5), "format_version"),
    ("camera not an object", dict(meta_camera=[1, 2]), "camera"),
    ("complex pitch", dict(pitch_m=np.complex128(5.4e-6 + 1j)), "pitch_m"),
    ("text pitch", dict(pitch_m=np.str_("5.4e-6")), "pitch_m"),
    ("material a number", dict(material=np.float64(1.0)), "material"),
    ("levels all zero", dict(levels=np.zeros((4, 4), np.int16)), "levels contradict"),
    ("object levels", dict(levels=np.array([[None]], dtype=object)), "objects"),
]


@pytest.mark.parametrize("name,override,match", DESIGNS, ids=[d[0] for d in DESIGNS])
def test_bad_design_file_refused(tmp_path, name, override, match):
    with pytest.raises(DesignFileError) as exc:
        Design.load(_design_npz(tmp_path, **override))
    assert match in str(exc.value) and "allow_pickle" not in str(exc.value)


def test_levels_disagreeing_with_heights_name_count_and_first_pixel(tmp_path):
    with pytest.raises(DesignFileError, match=r"at 1 pixel\(s\); first at row 1, col 2"):
        Design.load(_levels_off(tmp_path))
    assert Design.load(_design_npz(tmp_path)).levels[3, 3] == 15


# -- JSON inside user files: nesting deeper than the parser's recursion, integers over the digit limit --------
DEEP_JSON = "[" * 50_000 + "]" * 50_000
HUGE_INT_JSON = '{"name": ' + "9" * 5000 + "}"
HOSTILE_JSON = [("nested 50000 deep", DEEP_JSON, "nested too deeply"),
                ("5000-digit integer", HUGE_INT_JSON, "not valid JSON")]


def _one_line_refusal(capsys, argv, path):
    from doedesign.cli import main

    assert main(argv) == 2, argv
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and str(path) in captured.err, captured.err
    assert "Traceback" not in captured.err and "RecursionError" not in captured.err
    return captured.err


@pytest.mark.parametrize("name,text,match", HOSTILE_JSON, ids=[h[0] for h in HOSTILE_JSON])
def test_hostile_design_metadata_is_one_line(tmp_path, capsys, name, text, match):
    path = _design_npz(tmp_path, metadata=np.str_(text))
    with pytest.raises(DesignFileError, match=match):
        Design.load(path)
    out = tmp_path / "out"
    for argv in (["inspect", str(path)], ["diagnose", "--design", str(path), "--measured", str(path), "--out", str(out)]):
        assert match in _one_line_refusal(capsys, argv, path)
    assert not out.exists()


@pytest.mark.parametrize("name,text,match", HOSTILE_JSON, ids=[h[0] for h in HOSTILE_JSON])
def test_hostile_json_in_metrology_files(tmp_path, capsys, name, text, match, caplog):
    from metrology.calibration.dualpixel import CrosstalkCalibration
    from metrology.calibration.psfstack import read_stack

    stack = tmp_path / "stack.npz"
    np.savez(stack, psf=np.ones((2, 1, 16, 16)), wavelengths_m=np.array([550e-9]), pixel_pitch_m=np.float64(5.4e-6),
             views=np.array(["coded", "uncoded"]), info=np.str_(text))
    with pytest.raises(DoeError, match=match):
        read_stack(stack)
    out = tmp_path / "out"
    design = Design(np.zeros((16, 16)), 5.4e-6).save(tmp_path / "flat.npz")
    _one_line_refusal(capsys, ["diagnose", "--design", str(design), "--measured-psf", str(stack), "--out", str(out)],
                      stack)
    cal = tmp_path / "crosstalk.npz"
    np.savez(cal, ratio=np.zeros((2, 4, 16)), raw_ratio=np.zeros((2, 4, 16)), metadata=np.str_(text))
    with pytest.raises(DoeError, match=match):
        CrosstalkCalibration.load(cal)
    captures = tmp_path / "caps"
    captures.mkdir()
    for kind in ("sum", "view"):
        np.save(captures / f"550nm_{kind}.npy", np.ones((32, 32)))
    _one_line_refusal(capsys, ["calibrate", "psf", "--captures", str(captures), "--crosstalk", str(cal),
                               "--out", str(out)], cal)
    assert not out.exists()
    # A measurement's metadata is provenance: unreadable, it is left out with a warning.
    meas = tmp_path / "meas.npz"
    np.savez(meas, height_m=np.zeros((4, 4)), pixel_size_m=np.float64(1e-6), metadata=np.str_(text))
    assert read_measurement(meas).metadata["format"] == "npz"
    assert match in caplog.text


# -- formats read through libraries (SurfaceTopography, x3pio): real files damaged, through the CLI -------
# Each case: a file cut at 50 %, random bytes with the format's extension (and behind its magic),
# a header claiming a huge grid. Refused in one line naming the file, exit status 2, nothing on
# stdout, and the traced peak memory small (nothing allocated from the claim).
REAL = Path(__file__).resolve().parents[1] / "data" / "realdata"
LIB_FILES = {
    "nid": REAL / "afm-nanosurf-binary-arrays" / "circles.nid",
    "nid-1": REAL / "surface-formats" / "nid-1.nid",
    "di": REAL / "surface-formats" / "di-3.di",
    "spm": REAL / "surface-formats" / "di-3.di",  # NanoScope files carry either extension
    "sur": REAL / "surface-formats" / "sur-3.sur",
    "opdx": REAL / "surface-formats" / "opdx-3.opdx",
    "x3p": REAL / "surface-formats" / "x3p-2.x3p",
    "dektak": REAL / "surface-formats" / "dektak-1.csv",
    "gwy": None,  # written by SurfaceTopography's own Gwyddion writer (no real file at hand)
    "opd": None,  # written here to the layout SurfaceTopography's OPD reader declares (no real file)
    "plu": None,  # written here to the layout of its Sensofar PLU reader (no real file)
}
EXT = {"nid-1": ".nid", "dektak": ".csv"}
MAGIC = {"nid": b"[DataSet]\r\n", "di": b"\\*File list\r\n", "spm": b"\\*File list\r\n", "sur": b"DIGITAL SURF",
         "opdx": b"VCA DATA\x01\x00\x00\x55", "x3p": b"PK\x03\x04", "dektak": b"Scan Parameters\r\n",
         "gwy": b"GWYP", "vk4": b"VK4_\0\0\0\0", "mdt": struct.pack("<I", 0xFF93B001), "plu": b"", "opd": b""}
LIB_PEAK_BYTES = 64 * 2**20


def _opd_bytes(nx=64, ny=48):
    """A Wyko .opd: a directory of 24-byte entries (name, type, length, attribute), then the
    payloads; the raster holds float32 heights in waves, scaled by Wavelength (nm) / Mult."""
    data = np.random.default_rng(5).normal(0, 0.05, (nx, ny)).astype("<f4")
    blocks = [("RAW_DATA", 3, struct.pack("<HHH", nx, ny, 4) + data.tobytes()),
              ("Wavelength", 7, struct.pack("<f", 632.8)), ("Mult", 6, struct.pack("<h", 1)),
              ("Pixel_size", 7, struct.pack("<f", 0.001)), ("Aspect", 7, struct.pack("<f", 1.0))]

    def entry(name, kind, length):
        return struct.pack("<16shlH", name.encode(), kind, length, 0)

    head = b"\x01\x00" + entry("Directory", 0, 24 * (len(blocks) + 1))
    return head + b"".join(entry(n, k, len(p)) for n, k, p in blocks) + b"".join(p for _, _, p in blocks)


def _plu_bytes(nx=64, ny=48):
    """A Sensofar .plu: date, time, comment; calibration (rows, columns, um per pixel); the
    measurement configuration (a topography); one layer of float32 heights in micrometres."""
    z = np.random.default_rng(6).normal(0, 0.05, (ny, nx)).astype("<f4")
    out = b"2026-12-02 10:00:00".ljust(128, b"\0") + struct.pack("<I", 0) + bytes(256)
    out += struct.pack("<IIIfffffff", ny, nx, 0, 1.0, 0.5, 0.5, 0.0, 0.0, 1.0, 0.0)
    out += struct.pack("<IIIII", 3, 0, 0, 0, 0)  # type 3: topography; area type 0
    out += struct.pack("<IIIIIdfII", nx, ny, nx, ny, 0, 0.0, 0.0, 0, 0)
    out += struct.pack("<BBBBB3BI", 0, 1, 0, 0, 0, 0, 0, 0, 0)  # one layer, no images
    return out + struct.pack("<II", ny, nx) + z.tobytes() + struct.pack("<ff", float(z.min()), float(z.max()))


def _lib_source(tmp_path, key):
    if LIB_FILES.get(key) is not None:
        return LIB_FILES[key].read_bytes()
    if key == "opd":
        return _opd_bytes()
    if key == "plu":
        return _plu_bytes()
    from SurfaceTopography import Topography

    path = tmp_path / "source.gwy"
    heights = np.random.default_rng(4).normal(0, 1e-8, (64, 48))
    Topography(heights, (64e-6, 48e-6), unit="m").to_gwy(str(path))
    return path.read_bytes()


def _lib_path(tmp_path, key, name):
    return tmp_path / f"{name}{EXT.get(key, '.' + key)}"


def _x3p_claim(raw, size):
    import hashlib
    import io
    import re

    src, out = zipfile.ZipFile(io.BytesIO(raw)), io.BytesIO()
    xml = src.read("main.xml")
    xml = re.sub(rb"<SizeX>\d+</SizeX>", b"<SizeX>%d</SizeX>" % size, xml)
    xml = re.sub(rb"<SizeY>\d+</SizeY>", b"<SizeY>%d</SizeY>" % size, xml)
    with zipfile.ZipFile(out, "w") as dst:
        dst.writestr("main.xml", xml)
        dst.writestr("bindata/data.bin", src.read("bindata/data.bin"))
        dst.writestr("md5checksum.hex", hashlib.md5(xml).hexdigest().encode() + b" *main.xml\n")
    return out.getvalue()


def _gwy_claim(raw, size):
    for key in (b"xres\0i", b"yres\0i"):
        at = raw.index(key) + len(key)
        raw = raw[:at] + struct.pack("<i", size) + raw[at + 4:]
    return raw


def _opdx_claim(raw, size):
    key = b"NumPoints\x0b"  # the profile's point count, a uint64 item
    at = raw.index(key) + len(key)
    return raw[:at] + struct.pack("<Q", size) + raw[at + 8:]


def _sur_claim(raw, size):
    raw = bytearray(raw)
    struct.pack_into("<iiI", raw, 108, size, size, size * size)  # nb_grid_pts_x, _y, nb_points
    return bytes(raw)


HUGE_CLAIMS = {
    "nid": lambda raw: raw.replace(b"Lines=256", b"Lines=999999999").replace(b"Points=256", b"Points=999999999"),
    "nid-1": lambda raw: raw.replace(b"Lines=256", b"Lines=999999999").replace(b"Points=256", b"Points=999999999"),
    "di": lambda raw: raw.replace(b"\\Samps/line: 256", b"\\Samps/line: 99999").replace(
        b"\\Number of lines: 256", b"\\Number of lines: 99999"),
    "spm": lambda raw: raw.replace(b"\\Samps/line: 256", b"\\Samps/line: 99999").replace(
        b"\\Number of lines: 256", b"\\Number of lines: 99999"),
    "sur": lambda raw: _sur_claim(raw, 60000),
    "x3p": lambda raw: _x3p_claim(raw, 100000),
    "gwy": lambda raw: _gwy_claim(raw, 100000),
    "opdx": lambda raw: _opdx_claim(raw, 10**12),
    "opd": lambda raw: raw.replace(struct.pack("<HHH", 64, 48, 4), struct.pack("<HHH", 65535, 65535, 4), 1),
    "plu": lambda raw: raw.replace(struct.pack("<II", 48, 64), struct.pack("<II", 100000, 100000)),
}


def _lib_cases():
    cases = [(f"{k} cut at 50 %", k, "half") for k in LIB_FILES]
    cases += [(f"{k} random bytes", k, "random") for k in MAGIC]
    cases += [(f"{k} magic then random bytes", k, "magic") for k in MAGIC if MAGIC[k]]
    cases += [(f"{k} header claims a huge grid", k, "claim") for k in HUGE_CLAIMS]
    return cases


LIB_CASES = _lib_cases()


def _lib_damaged(tmp_path, key, kind):
    rng = np.random.default_rng(sum(map(ord, key + kind)))
    noise = rng.integers(0, 256, 200_000, dtype=np.uint8).tobytes()
    if kind == "random":
        data = noise
    elif kind == "magic":
        data = MAGIC[key] + noise
    else:
        raw = _lib_source(tmp_path, key)
        data = raw[:len(raw) // 2] if kind == "half" else HUGE_CLAIMS[key](raw)
        assert data != raw
    path = _lib_path(tmp_path, key, f"bad-{kind}")
    path.write_bytes(data)
    return path


def test_library_format_sources_read(tmp_path):
    """The undamaged sources read: each damage below is what makes its file refused."""
    for key in LIB_FILES:
        path = _lib_path(tmp_path, key, "good")
        path.write_bytes(_lib_source(tmp_path, key))
        assert read_measurement(path).height_m.size > 1000, key
    # The .opd built here: 1 um pixels (Pixel_size 0.001 mm), heights 0.05 waves rms of 632.8 nm.
    opd = read_measurement(_lib_path(tmp_path, "opd", "good"))
    assert opd.shape == (48, 64) and opd.pixel_size_m == pytest.approx(1e-6, rel=1e-6)
    assert opd.height_m.std() == pytest.approx(0.05 * 632.8e-9, rel=0.05)
    # The .plu built here: 0.5 um pixels, heights 0.05 um rms.
    plu = read_measurement(_lib_path(tmp_path, "plu", "good"))
    assert plu.shape == (48, 64) and plu.pixel_size_m == pytest.approx(0.5e-6, rel=1e-6)
    assert plu.height_m.std() == pytest.approx(0.05e-6, rel=0.05)


@pytest.mark.parametrize("name,key,kind", LIB_CASES, ids=[c[0] for c in LIB_CASES])
def test_library_format_damage_refused_in_one_line(tmp_path, capsys, name, key, kind):
    import tracemalloc

    import SurfaceTopography.IO  # noqa: F401  (imported before tracing: importing is not the file's cost)
    import x3pio  # noqa: F401

    from doedesign.cli import main

    path = _lib_damaged(tmp_path, key, kind)
    tracemalloc.start()
    try:
        with warnings.catch_warnings(record=True) as caught:  # a warning would print beside the error
            warnings.simplefilter("always")
            code = main(["inspect", str(path)])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert not caught, [str(w.message) for w in caught]
    captured = capsys.readouterr()
    assert code == 2, captured.out
    err = captured.err.strip()
    assert str(path) in err and len(err.splitlines()) == 1 and "Traceback" not in err and not captured.out, err
    assert peak < LIB_PEAK_BYTES, f"{name}: traced peak {peak / 2**20:.0f} MB"


LIB_CORRUPT = [(key, seed) for key in LIB_FILES for seed in range(4)]


@pytest.mark.parametrize("key,seed", LIB_CORRUPT, ids=[f"{k}-corrupt-{s}" for k, s in LIB_CORRUPT])
def test_library_file_with_corrupt_header_bytes_is_refused_or_plausible(tmp_path, key, seed):
    raw = bytearray(_lib_source(tmp_path, key))
    rng = np.random.default_rng(seed)
    for i in rng.integers(0, min(len(raw), 40_000), 16):  # the header and the first data
        raw[i] = int(rng.integers(0, 256))
    path = _lib_path(tmp_path, key, "corrupt")
    path.write_bytes(bytes(raw))
    message = _refused_or_plausible(path)
    assert message is None or "\n" not in message
