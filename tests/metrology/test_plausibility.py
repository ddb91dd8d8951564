"""The physical ranges hold what real instruments write and refuse what none can.

The project holds no vendor files, so the instrument cases below are files written in the
instrument's own format with the header values that instrument writes, stored the way it
stores them (float32 in MetroPro headers and Mx converters). Every range is then probed on
both edges, the edge value written as float32 into each format that carries the field (it
must read), and at twice the edge (it must be refused, naming the file and the field).
"""

import h5py
import numpy as np
import pytest

from doedesign.cli import main
from metrology.formats.measurement import MeasurementFileError
from metrology.formats.plausibility import RANGES, within
from metrology.formats.readers import read_measurement
from metrology.formats.writers import write_asc, write_dat, write_datx, write_measurement

F32 = np.float32


def _height(shape=(6, 8), step_m=100e-9):
    h = -(np.arange(np.prod(shape)).reshape(shape) % 4) * step_m
    h[1, 2] = np.nan
    return h


def _datx_f32(path, height, pixel, unit="NanoMeters", wavelength_m=632.8e-9, s=0.5, o=1.0, dtype=np.float64):
    """A .datx whose header numbers are stored as float32, as Mx stores the X Converter."""
    write_datx(path, height, pixel, unit=unit, wavelength_m=wavelength_m, intf_scale_factor=s,
               obliquity_factor=o, dtype=dtype, no_data=np.finfo(dtype).max)
    with h5py.File(path, "a") as f:
        dset = f["Data/Surface"][next(iter(f["Data/Surface"]))]
        for name, value in (("Wavelength", wavelength_m), ("Interferometric Scale Factor", s),
                            ("Obliquity Factor", o)):
            dset.attrs[name] = np.array([value], dtype=F32)
        conv = np.dtype([("Category", "S16"), ("BaseUnit", "S16"), ("HeightUnit", "S16"), ("Parameters", "<f4", (4,))])
        for axis in "XY":
            dset.attrs[f"{axis} Converter"] = np.array([(b"LateralCat", b"Meters", b"Meters", [0, pixel, 0, 0])],
                                                       dtype=conv)
    return path


# -- real instruments: name, builder(tmp_path) -> path, pixel size the file holds -------------------------
INSTRUMENTS = [
    ("Zygo Mx datx, 1 mm lateral resolution in float32 (refused before)",
     lambda t: _datx_f32(t / "mx_1mm.datx", _height(), 1e-3), F32(1e-3)),
    ("Verifire/GPI 300 mm aperture on a 1k camera (0.3 mm), MetroPro dat",
     lambda t: write_dat(t / "verifire.dat", _height(), 0.3e-3), F32(0.3e-3)),
    ("800 mm Fizeau aperture on a 1k camera (0.8 mm), datx",
     lambda t: _datx_f32(t / "fizeau800.datx", _height(), 0.8e-3), F32(0.8e-3)),
    ("stitched metre-class optic binned to 5 mm, npz",
     lambda t: write_measurement(t / "stitched.npz", _height(), 5e-3), 5e-3),
    ("NewView/Nexview 100x objective with 2x zoom (~43 nm), O = 1.1, datx in fringes",
     lambda t: _datx_f32(t / "newview.datx", _height(), 43e-9, unit="Fringes", wavelength_m=570e-9, o=1.1),
     F32(43e-9)),
    ("Keyence VK-X / Sensofar S neox 150x (~70 nm), xyz export",
     lambda t: write_measurement(t / "confocal.xyz", _height(), 70e-9), 70e-9),
    ("AFM: 100 nm scan over 512 px (0.2 nm), npz",
     lambda t: write_measurement(t / "afm.npz", _height(step_m=2e-9), 100e-9 / 512), 100e-9 / 512),
    ("IR Fizeau at 10.6 um (CO2), dat",
     lambda t: write_dat(t / "co2.dat", _height(), 0.2e-3, wavelength_m=10.6e-6), F32(0.2e-3)),
    ("DUV Fizeau at 193 nm, asc",
     lambda t: write_asc(t / "duv.asc", _height(), 0.1e-3, wavelength_m=193e-9), 0.1e-3),
    ("germanium plate in double pass, S = 1/(2(n-1)) = 0.167, dat",
     lambda t: write_dat(t / "ge.dat", _height(), 50e-6, wavelength_m=10.6e-6, intf_scale_factor=0.167), F32(50e-6)),
    ("grazing incidence at 87 deg, O = 19, datx in fringes",
     lambda t: _datx_f32(t / "grazing.datx", _height(), 20e-6, unit="Fringes", o=19.0), F32(20e-6)),
    ("coherence scan of a 20 mm step, float32 heights in metres",
     lambda t: _datx_f32(t / "step20mm.datx", np.where(np.eye(6, 8) > 0, -0.02, 0.0), 2e-6, unit="Meters",
                         dtype=np.float32), F32(2e-6)),
]


@pytest.mark.parametrize("name,build,pixel", INSTRUMENTS, ids=[i[0] for i in INSTRUMENTS])
def test_real_instrument_files_read(tmp_path, name, build, pixel):
    meas = read_measurement(build(tmp_path))
    assert meas.pixel_size_m == pytest.approx(float(pixel), rel=1e-12)
    assert np.isfinite(meas.height_m).sum() > 0


def test_the_refused_mx_file_reads_through_the_cli(tmp_path, capsys):
    path = _datx_f32(tmp_path / "mx.datx", _height(), 1e-3)
    assert main(["inspect", str(path), "--json"]) == 0
    assert "0.0010000000474974513" in capsys.readouterr().out


def test_float32_rule():
    for lo, hi in ((1e-11, 1e-2), (-0.1, 0.1), (10e-9, 20e-6)):
        for edge in (lo, hi):
            assert within(float(F32(edge)), lo, hi) and within(edge, lo, hi)
            assert within(float(np.nextafter(F32(edge), F32(np.inf))), lo, hi)
            assert within(float(np.nextafter(F32(edge), F32(-np.inf))), lo, hi)
        assert not within(2 * hi if hi > 0 else hi / 2, lo, hi)
        assert not within(lo / 2 if lo > 0 else 2 * lo, lo, hi)
    assert not within(float("nan"), 0, 1) and not within(float("inf"), 0, 1)


# -- edges: every range, each format carrying it; the edge reads, twice beyond it is refused ----------------
def _outside(key, side):
    lo, hi = RANGES[key].lo, RANGES[key].hi
    if side == "lo":
        return lo / 2 if lo > 0 else 2 * lo
    return 2 * hi if hi > 0 else hi / 2


def _edge(key, side):
    return float(F32(getattr(RANGES[key], side)))


def _writer(fmt, key, value):
    """(builder(tmp_path) -> path, the field name the refusal must give) with ``value`` in ``key``."""
    h = _height(step_m=1e-9)
    if key == "height_m":
        flat = np.zeros((6, 8))
        flat[2, 3] = value
        if fmt == "datx":
            return (lambda t: _datx_f32(t / "h.datx", flat, 1e-6, unit="Meters", dtype=np.float32)), "heights reach"
        return (lambda t: np.savez(t / "h.npz", height_m=flat.astype(np.float32), pixel_size_m=F32(1e-6))
                or t / "h.npz"), "heights reach"
    if fmt == "datx":
        kw = {"pixel_size_m": dict(pixel=value), "wavelength_m": dict(wavelength_m=value, unit="Fringes"),
              "intf_scale_factor": dict(s=value, unit="Fringes"), "obliquity_factor": dict(o=value, unit="Fringes")}[key]
        pixel = kw.pop("pixel", 1e-6)
        field = {"pixel_size_m": "X Converter pixel size", "wavelength_m": "Wavelength",
                 "intf_scale_factor": "Interferometric Scale Factor", "obliquity_factor": "Obliquity Factor"}[key]
        return (lambda t: _datx_f32(t / "x.datx", h, pixel, **kw)), field
    if fmt in ("dat", "asc"):
        kw = {"pixel_size_m": {}, "wavelength_m": dict(wavelength_m=value),
              "intf_scale_factor": dict(intf_scale_factor=value), "obliquity_factor": dict(obliquity_factor=value)}[key]
        pixel = value if key == "pixel_size_m" else 1e-6
        write = write_dat if fmt == "dat" else write_asc
        # MetroPro headers are float32: the .dat writer rounds like the instrument; the .asc
        # export prints the float32 value's digits.
        kw = {k: float(F32(v)) for k, v in kw.items()}
        field = "lateral_res_m" if key == "pixel_size_m" else key
        return (lambda t: write(t / f"x.{fmt}", h, float(F32(pixel)), **kw)), field
    if fmt == "npz":
        return (lambda t: np.savez(t / "x.npz", height_m=h, pixel_size_m=F32(value)) or t / "x.npz"), "pixel_size_m"
    raise AssertionError(fmt)


FORMATS_OF = {"pixel_size_m": ("datx", "dat", "asc", "npz"), "wavelength_m": ("datx", "dat", "asc"),
              "intf_scale_factor": ("datx", "dat", "asc"), "obliquity_factor": ("datx", "dat", "asc"),
              "height_m": ("datx", "npz")}
EDGES = [(key, fmt, side) for key, fmts in FORMATS_OF.items() for fmt in fmts for side in ("lo", "hi")]


def test_every_range_is_probed():
    assert set(FORMATS_OF) == set(RANGES)


@pytest.mark.parametrize("key,fmt,side", EDGES, ids=[f"{k}-{f}-{s}" for k, f, s in EDGES])
def test_value_on_the_edge_reads(tmp_path, key, fmt, side):
    build, _ = _writer(fmt, key, _edge(key, side))
    meas = read_measurement(build(tmp_path))
    if key == "pixel_size_m":
        assert meas.pixel_size_m == pytest.approx(_edge(key, side), rel=1e-6)
    if key == "height_m":
        assert np.nanmax(np.abs(meas.height_m)) == pytest.approx(abs(_edge(key, side)), rel=1e-6)


@pytest.mark.parametrize("key,fmt,side", EDGES, ids=[f"{k}-{f}-{s}" for k, f, s in EDGES])
def test_value_twice_beyond_the_edge_is_refused(tmp_path, key, fmt, side):
    build, field = _writer(fmt, key, _outside(key, side))
    path = build(tmp_path)
    with pytest.raises(MeasurementFileError) as exc:
        read_measurement(path)
    assert str(path) in str(exc.value) and field in str(exc.value), str(exc.value)


def test_nan_pixel_names_the_file(tmp_path, capsys):
    path = write_dat(tmp_path / "nan.dat", _height(), float("nan"))
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and "lateral_res_m = nan" in err and "Traceback" not in err
    with pytest.raises(MeasurementFileError, match="nan.dat: pixel_size_m \\(given\\) = nan"):
        read_measurement(path, pixel_size_m=float("nan"))
