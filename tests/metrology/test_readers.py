"""Profilometer readers and writers: round trips, analytic conversions, bad files.

Hand-built files (packed here byte by byte, not with the package's writers) pin the
conversions to the published formulas: height = counts * S * O * wavelength / R with
R = 4096 / 32768 / 131072, and value * S * O * wavelength for .datx fringes.
"""

import json
import struct

import h5py
import numpy as np
import pytest

from doedesign.cli import main
from doedesign.errors import DoeError
from metrology.formats.measurement import Measurement, MeasurementFileError
from metrology.formats.readers import detect_format, read_measurement
from metrology.formats.writers import (write_asc, write_dat, write_datx, write_measurement, write_npy, write_npz,
                               write_profile_csv, write_tiff, write_xyz)

WL = 632.8e-9
R = {0: 4096, 1: 32768, 2: 131072}


@pytest.fixture
def surface():
    """A 16-level-like staircase with noise and a few invalid pixels (metres)."""
    rng = np.random.default_rng(1)
    h = -(np.arange(48)[np.newaxis, :] % 16) * 75e-9 + rng.normal(0, 2e-9, (36, 48))
    h[5, 7] = h[0, 0] = h[35, 47] = np.nan
    return h


def step_m(phase_res, s=0.5, o=1.0, wl=WL):
    return s * o * float(np.float32(wl)) / R[phase_res]


def hand_dat(path, counts, phase_res=1, sign=0, magic=0x881B036F, fmt=1, size=834, nb=0,
             wl=WL, s=0.5, lateral=2e-6, extra=b"", ac_n_bytes=None):
    """A .dat file packed by hand from the documented offsets."""
    ch, cw = counts.shape
    head = bytearray(size)
    struct.pack_into(">IHI", head, 0, magic, fmt, size)
    struct.pack_into(">hhHHH", head, 48, 0, 0, cw if nb else 0, ch if nb else 0, nb)
    struct.pack_into(">I", head, 60, 2 * cw * ch * nb if ac_n_bytes is None else ac_n_bytes)
    struct.pack_into(">hhHHI", head, 64, 3, 4, cw, ch, 4 * cw * ch)
    struct.pack_into(">ffff", head, 164, s, wl, 0.1, 1.0)
    struct.pack_into(">f", head, 184, lateral)
    struct.pack_into(">h", head, 218, phase_res)
    struct.pack_into(">h", head, 232, sign)
    intensity = np.full((nb, ch, cw), 777, ">u2").tobytes()
    path.write_bytes(bytes(head) + intensity + counts.astype(">i4").tobytes() + extra)
    return path


# ---------------------------------------------------------------- Measurement

def test_summary_rms_about_mean_of_valid_pixels():
    h = np.where(np.indices((4, 4)).sum(0) % 2, 3e-9, -1e-9) + 1e-6
    h[0, 0] = np.nan
    s = Measurement(h, 1e-6, {"comment": "x"}).summary()
    valid = h[np.isfinite(h)]
    assert s["kind"] == "measurement" and s["shape"] == [4, 4]
    assert s["invalid_fraction"] == pytest.approx(1 / 16)
    assert s["height_rms_m"] == pytest.approx(np.std(valid), rel=1e-12)
    assert s["height_rms_m"] == pytest.approx(2e-9, rel=0.01)  # +-2 nm about the mean
    assert s["height_min_m"] == pytest.approx(1e-6 - 1e-9)
    assert s["height_max_m"] == pytest.approx(1e-6 + 3e-9)
    json.dumps(s)


def test_measurement_rejects_bad_arrays():
    with pytest.raises(DoeError, match="2-D"):
        Measurement(np.zeros(5), 1e-6)
    with pytest.raises(DoeError, match="positive"):
        Measurement(np.zeros((2, 2)), 0.0)


# ---------------------------------------------------------------- MetroPro .dat

@pytest.mark.parametrize("phase_res", [0, 1, 2])
def test_hand_built_dat_matches_formula(tmp_path, phase_res):
    counts = np.array([[R[phase_res], -R[phase_res] // 2], [7, 2147483640]], dtype=np.int64)
    m = read_measurement(hand_dat(tmp_path / "a.dat", counts, phase_res))
    one_wave = 0.5 * float(np.float32(WL))  # R counts = S * wavelength of height
    assert m.height_m[0, 0] == pytest.approx(one_wave, rel=1e-12)
    assert m.height_m[0, 1] == pytest.approx(-one_wave / 2, rel=1e-12)
    assert m.height_m[1, 0] == pytest.approx(7 * one_wave / R[phase_res], rel=1e-12)
    assert np.isnan(m.height_m[1, 1])
    assert m.pixel_size_m == pytest.approx(2e-6, rel=1e-7)
    assert m.metadata["phase_origin"] == (3, 4)


def test_phase_res_1_is_32768_not_4096(tmp_path):
    """Regression: a public reader maps phase_res 1 to 4096 and reads heights 8x too large."""
    height = np.full((4, 4), 100e-9)
    write_dat(tmp_path / "a.dat", height, 1e-6, phase_res=1)
    raw = np.fromfile(tmp_path / "a.dat", ">i4", offset=834)
    assert raw[0] == round(100e-9 / step_m(1))  # 10357 counts for 100 nm
    m = read_measurement(tmp_path / "a.dat")
    assert m.height_m == pytest.approx(height, abs=step_m(1))
    assert m.metadata["phase_counts_per_wave"] == 32768


@pytest.mark.parametrize("header_format,size", [(1, 834), (2, 834), (3, 4096)])
@pytest.mark.parametrize("phase_res", [0, 1, 2])
def test_dat_round_trip_quantizes_to_one_count(tmp_path, surface, header_format, size, phase_res):
    path = write_dat(tmp_path / "s.dat", surface, 1.1e-6, header_format=header_format, phase_res=phase_res)
    assert path.stat().st_size == size + 4 * surface.size
    m = read_measurement(path)
    step = step_m(phase_res)
    assert m.metadata["height_step_m"] == pytest.approx(step, rel=1e-12)
    np.testing.assert_array_equal(np.isnan(m.height_m), np.isnan(surface))
    err = np.nanmax(np.abs(m.height_m - surface))
    assert err <= step / 2 * (1 + 1e-9)
    assert err > step / 4  # noise makes the rounding error reach ~step/2: real quantization
    counts = m.height_m / step
    assert np.nanmax(np.abs(counts - np.rint(counts))) < 1e-6
    assert m.metadata["header_format"] == header_format


def test_dat_sign_flag_negates(tmp_path, surface):
    write_dat(tmp_path / "s.dat", surface, 1e-6, sign_flip=True)
    raw = np.fromfile(tmp_path / "s.dat", ">i4", offset=834).reshape(surface.shape)
    ok = np.isfinite(surface)
    assert np.all(np.sign(raw[ok]) == -np.sign(np.rint(surface[ok] / step_m(1))))
    m = read_measurement(tmp_path / "s.dat")
    assert m.metadata["sign_flip"] is True
    assert np.nanmax(np.abs(m.height_m - surface)) <= step_m(1) / 2 * (1 + 1e-9)
    counts = np.array([[100]])
    assert read_measurement(hand_dat(tmp_path / "h.dat", counts, sign=1)).height_m[0, 0] == \
        pytest.approx(-100 * step_m(1))


def test_dat_intensity_frames_skipped(tmp_path, surface):
    frames = np.arange(3 * surface.size, dtype=np.uint16).reshape((3,) + surface.shape)
    path = write_dat(tmp_path / "s.dat", surface, 1e-6, intensity_frames=frames, phase_origin=(12, 34))
    assert path.stat().st_size == 834 + 2 * frames.size + 4 * surface.size
    m = read_measurement(path)
    assert m.metadata["intensity_frames"] == 3 and m.metadata["phase_origin"] == (12, 34)
    assert np.nanmax(np.abs(m.height_m - surface)) <= step_m(1) / 2 * (1 + 1e-9)
    counts = np.array([[5, 6]])
    assert read_measurement(hand_dat(tmp_path / "h.dat", counts, nb=2)).height_m[0, 1] == \
        pytest.approx(6 * step_m(1))


def test_dat_metadata(tmp_path):
    write_dat(tmp_path / "s.dat", np.zeros((2, 3)), 0.5e-6, header_format=2, wavelength_m=550e-9,
              comment="etch run 7", part_name="DOE-A", objective="50x", magnification=50,
              numerical_aperture=0.55, time_stamp=1700000000)
    meta = read_measurement(tmp_path / "s.dat").metadata
    assert meta["wavelength_m"] == pytest.approx(550e-9, rel=1e-7)
    assert meta["comment"] == "etch run 7" and meta["part_name"] == "DOE-A" and meta["objective"] == "50x"
    assert meta["magnification"] == 50 and meta["numerical_aperture"] == pytest.approx(0.55)
    assert meta["timestamp"] == "2023-11-14T22:13:20+00:00"
    assert meta["format"] == "metropro_dat" and meta["source_file"].endswith("s.dat")


def test_dat_invalid_threshold(tmp_path):
    counts = np.array([[2147483639, 2147483640, 2147483647]])
    h = read_measurement(hand_dat(tmp_path / "a.dat", counts)).height_m
    assert np.isfinite(h[0, 0]) and np.isnan(h[0, 1:]).all()


@pytest.mark.parametrize("kwargs,match", [
    ({"magic": 0x12345678}, "magic"),
    ({"magic": 0x881B0371}, "truncated"),  # format 3 magic needs 4096 header bytes
    ({"fmt": 2}, "header mismatch"),
    ({"size": 900}, "header mismatch"),
    ({"extra": b"\0\0"}, "too long"),
    ({"ac_n_bytes": 10}, "ac_n_bytes"),
    ({"wl": 0.0}, "wavelength"),
    ({"phase_res": 5}, "phase_res"),
    ({"lateral": 0.0}, "pixel_size_m"),
])
def test_bad_dat_files(tmp_path, kwargs, match):
    path = hand_dat(tmp_path / "bad.dat", np.zeros((4, 5)), **kwargs)
    with pytest.raises(MeasurementFileError, match=match) as info:
        read_measurement(path)
    assert "bad.dat" in str(info.value)


def test_truncated_and_missing_dat(tmp_path, surface):
    path = write_dat(tmp_path / "cut.dat", surface, 1e-6)
    data = path.read_bytes()
    path.write_bytes(data[:-10])
    with pytest.raises(MeasurementFileError, match="cut.dat: truncated: expected"):
        read_measurement(path)
    path.write_bytes(data[:500])
    with pytest.raises(MeasurementFileError, match="cut.dat: truncated"):
        read_measurement(path)
    path.write_bytes(data[:2])
    with pytest.raises(MeasurementFileError, match="cut.dat"):
        read_measurement(path, format="dat")
    with pytest.raises(MeasurementFileError, match="nothere.dat"):
        read_measurement(tmp_path / "nothere.dat")


def test_dat_pixel_override(tmp_path):
    m = read_measurement(hand_dat(tmp_path / "a.dat", np.zeros((2, 2)), lateral=0.0), pixel_size_m=3e-6)
    assert m.pixel_size_m == 3e-6


def test_writer_failure_leaves_no_file(tmp_path):
    with pytest.raises(DoeError, match="exceed"):
        write_dat(tmp_path / "big.dat", np.full((2, 2), 1.0), 1e-6, phase_res=2)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- Mx .datx

def hand_datx(path, values, unit=b"Fringes", where="/Data/Surface/{S}", wl=WL, s=0.5, o=1.0, no_data=1e300):
    with h5py.File(path, "w") as f:
        d = f.create_dataset(where, data=values)
        d.attrs["Unit"] = np.array([unit])
        d.attrs["No Data"] = np.array([no_data])
        d.attrs["Wavelength"] = np.array([wl])
        d.attrs["Interferometric Scale Factor"] = np.array([s])
        d.attrs["Obliquity Factor"] = np.array([o])
        conv = np.dtype([("Category", "S8"), ("BaseUnit", "S8"), ("HeightUnit", "S8"), ("Parameters", "<f8", (4,))])
        d.attrs["X Converter"] = np.array([(b"L", b"M", b"M", [0, 4e-7, 0, 0])], dtype=conv)
    return path


def test_hand_built_datx_fringes(tmp_path):
    path = hand_datx(tmp_path / "f.datx", np.array([[1.0, -0.25], [2e300, 0.0]]), o=1.1)
    m = read_measurement(path)
    assert m.height_m[0, 0] == pytest.approx(0.5 * 1.1 * WL, rel=1e-14)  # one fringe = S O wavelength
    assert m.height_m[0, 1] == pytest.approx(-0.25 * 0.5 * 1.1 * WL, rel=1e-14)
    assert np.isnan(m.height_m[1, 0]) and m.height_m[1, 1] == 0
    assert m.pixel_size_m == 4e-7 and m.metadata["surface_found_by"] == "data_surface"


@pytest.mark.parametrize("unit,scale", [(b"NanoMeters", 1e-9), (b"MicroMeters", 1e-6)])
def test_hand_built_datx_length_units(tmp_path, unit, scale):
    m = read_measurement(hand_datx(tmp_path / "u.datx", np.array([[3.0, 5.0]]), unit=unit,
                                   where="/Measurement/Surface"))
    assert m.height_m == pytest.approx(np.array([[3.0, 5.0]]) * scale, rel=1e-14)
    assert m.metadata["surface_found_by"] == "measurement_surface"


@pytest.mark.parametrize("layout", ["metadata", "data_surface", "measurement_surface"])
@pytest.mark.parametrize("unit", ["Fringes", "NanoMeters", "MicroMeters"])
def test_datx_round_trip(tmp_path, surface, layout, unit):
    path = write_datx(tmp_path / "s.datx", surface, 0.7e-6, unit=unit, layout=layout)
    m = read_measurement(path)
    np.testing.assert_array_equal(np.isnan(m.height_m), np.isnan(surface))
    np.testing.assert_allclose(m.height_m, surface, rtol=1e-12, atol=1e-22)
    assert m.pixel_size_m == 0.7e-6 and m.metadata["surface_found_by"] == layout
    assert m.metadata["unit"] == unit and m.metadata["coordinates"][2:] == [48, 36]


def test_datx_metadata_link_beats_first_surface(tmp_path, surface):
    path = write_datx(tmp_path / "s.datx", surface, 1e-6)
    with h5py.File(path, "a") as f:  # a decoy that sorts first under /Data/Surface
        decoy = f.create_dataset("Data/Surface/{00000000-DECOY}", data=np.zeros((2, 2)))
        decoy.attrs["Unit"] = np.array([b"NanoMeters"])
    m = read_measurement(path)
    assert m.shape == surface.shape and m.metadata["surface_found_by"] == "metadata"
    with h5py.File(path, "a") as f:  # break the link: the reader must fall back
        del f["MetaData"]
        f.create_dataset("MetaData", data=np.array([("Root", "Measurement", "{X}"), ("{X}", "Surface", "{Y}")],
                                                   dtype=[("Source", "S9"), ("Link", "S9"), ("Destination", "S9")]))
    with pytest.raises(MeasurementFileError, match="X Converter"):  # the decoy has no converter
        read_measurement(path)
    m = read_measurement(path, pixel_size_m=1e-6)
    assert m.metadata["surface_found_by"] == "data_surface" and m.shape == (2, 2)


def test_datx_converter_indexed_by_position_and_float32(tmp_path, surface):
    path = write_datx(tmp_path / "s.datx", surface, 2.5e-6, converter="extra_fields", dtype=np.float32,
                      no_data=np.finfo(np.float32).max)
    m = read_measurement(path)
    assert m.pixel_size_m == 2.5e-6
    np.testing.assert_array_equal(np.isnan(m.height_m), np.isnan(surface))
    np.testing.assert_allclose(m.height_m, surface, rtol=1e-6, atol=1e-15)


def test_datx_nounits_and_unknown_unit_refused(tmp_path, surface):
    write_datx(tmp_path / "n.datx", surface, 1e-6, unit="NoUnits")
    with pytest.raises(MeasurementFileError, match="n.datx.*NoUnits.*not a height map"):
        read_measurement(tmp_path / "n.datx")
    write_datx(tmp_path / "k.datx", surface, 1e-6, unit="Furlongs")
    with pytest.raises(MeasurementFileError, match="k.datx.*unknown unit 'Furlongs'"):
        read_measurement(tmp_path / "k.datx")


def test_bad_datx_files(tmp_path):
    with h5py.File(tmp_path / "empty.datx", "w") as f:
        f.create_group("Data/Intensity")
    with pytest.raises(MeasurementFileError, match="empty.datx: no surface dataset"):
        read_measurement(tmp_path / "empty.datx")
    hand_datx(tmp_path / "nowl.datx", np.ones((2, 2)), wl=0.0)
    with pytest.raises(MeasurementFileError, match="nowl.datx.*Wavelength"):
        read_measurement(tmp_path / "nowl.datx")
    good = hand_datx(tmp_path / "cut.datx", np.ones((64, 64)))
    good.write_bytes(good.read_bytes()[:3000])
    with pytest.raises(MeasurementFileError, match="cut.datx"):
        read_measurement(good)
    (tmp_path / "fake.datx").write_bytes(b"not hdf5 at all")
    with pytest.raises(MeasurementFileError, match="fake.datx"):
        read_measurement(tmp_path / "fake.datx")


# ---------------------------------------------------------------- ASCII exports

ASCII_HEADER = """Zygo XYZ Data File - Format 1
1 9 1 3 "Mon Jan 01 00:00:00 2024"
0 0 0 0 0 0
10 20 3 2
"a comment"
""
"part A"
0 0.5 6.328e-07 0.3 1 20 4.1e-06 1700000000
640 480 0 0 0 0 "20X"
#
"""


def test_hand_built_xyz(tmp_path):
    body = "10 20 0.5\n11 20 No Data\n12 20 -1.25\n10 21 0\n11 21 2\n12 21 3\n#\n"
    (tmp_path / "h.xyz").write_text(ASCII_HEADER + body)
    m = read_measurement(tmp_path / "h.xyz")
    expected = np.array([[0.5, np.nan, -1.25], [0, 2, 3]]) * 1e-6
    np.testing.assert_allclose(m.height_m, expected, rtol=1e-15)
    assert m.pixel_size_m == 4.1e-6 and m.metadata["phase_origin"] == (10, 20)
    assert m.metadata["part_name"] == "part A" and m.metadata["objective"] == "20X"
    assert m.metadata["wavelength_m"] == 6.328e-07


def test_xyz_round_trip_with_origin(tmp_path, surface):
    write_xyz(tmp_path / "s.xyz", surface, 1e-6, phase_origin=(100, 7), comment="hello")
    m = read_measurement(tmp_path / "s.xyz")
    np.testing.assert_array_equal(np.isnan(m.height_m), np.isnan(surface))
    assert np.nanmax(np.abs(m.height_m - surface)) <= 0.5e-13  # 7 decimals of a micrometre
    assert m.metadata["phase_origin"] == (100, 7) and m.metadata["comment"] == "hello"


@pytest.mark.parametrize("text,match", [
    (ASCII_HEADER.replace("#\n", "") + "10 20 0.5\n", "'#'"),
    (ASCII_HEADER + "10 20 abc\n", "unparseable"),
    (ASCII_HEADER + "10 20 1 2\n", "3 fields"),
    (ASCII_HEADER + "99 20 1\n", "outside the phase window"),
    (ASCII_HEADER + "10.5 20 1\n", "integers"),
    (ASCII_HEADER + "#\n", "no data lines"),
    (ASCII_HEADER.replace("0 0.5 6.328e-07", "0 x 6.328e-07"), "header line 8"),
    ("Not Zygo\n#\n1 2 3\n", "Zygo ASCII title"),
])
def test_bad_xyz(tmp_path, text, match):
    (tmp_path / "bad.xyz").write_text(text)
    with pytest.raises(MeasurementFileError, match=match) as info:
        read_measurement(tmp_path / "bad.xyz", format="xyz")
    assert "bad.xyz" in str(info.value)


@pytest.mark.parametrize("phase_res", [0, 1, 2])
@pytest.mark.parametrize("sign_flip", [False, True])
def test_asc_round_trip(tmp_path, surface, phase_res, sign_flip):
    write_asc(tmp_path / "s.asc", surface, 1e-6, phase_res=phase_res, sign_flip=sign_flip,
              intensity_frames=2, phase_origin=(3, 4))
    m = read_measurement(tmp_path / "s.asc")
    step = 0.5 * WL / R[phase_res]
    np.testing.assert_array_equal(np.isnan(m.height_m), np.isnan(surface))
    assert np.nanmax(np.abs(m.height_m - surface)) <= step / 2 * (1 + 1e-9)
    assert m.metadata["height_step_m"] == pytest.approx(step, rel=1e-12)
    assert m.metadata["intensity_frames"] == 2 and m.metadata["phase_origin"] == (3, 4)


def test_hand_built_asc_and_missing_phase_res(tmp_path):
    header = ASCII_HEADER.replace("XYZ Data File - Format 1", "ASCII Data File - Format 2").replace("#\n", "")
    line10 = "0 0 0 0 0 0 0 0 0 0\n"
    counts = "32768 -16384 2147483640\n0 1 2\n"
    (tmp_path / "h.asc").write_text(header + line10 + "1 0 0 0 0 0 0 0 0\n#\n#\n" + counts + "#\n")
    m = read_measurement(tmp_path / "h.asc")
    wave = 0.5 * 6.328e-07
    np.testing.assert_allclose(m.height_m, [[wave, -wave / 2, np.nan], [0, wave / 32768, 2 * wave / 32768]],
                               rtol=1e-14)
    (tmp_path / "short.asc").write_text(header + "#\n#\n" + counts + "#\n")
    with pytest.raises(MeasurementFileError, match="short.asc.*phase_res"):
        read_measurement(tmp_path / "short.asc")
    m = read_measurement(tmp_path / "short.asc", phase_res=0)  # R = 4096
    assert m.height_m[0, 0] == pytest.approx(8 * wave)
    (tmp_path / "cut.asc").write_text(header + line10 + "1 0 0 0 0 0 0 0 0\n#\n#\n32768 1\n")
    with pytest.raises(MeasurementFileError, match="cut.asc.*truncated"):
        read_measurement(tmp_path / "cut.asc")
    (tmp_path / "few.asc").write_text(header + line10 + "1 0 0 0 0 0 0 0 0\n#\n#\n32768 1\n#\n")
    with pytest.raises(MeasurementFileError, match="few.asc: phase block holds 2 values"):
        read_measurement(tmp_path / "few.asc")


# ---------------------------------------------------------------- CSV, npy, npz, TIFF

def test_profile_csv_round_trip_and_hand_built(tmp_path):
    z = np.array([0.0, -75e-9, np.nan, -150e-9, 12e-9])
    write_profile_csv(tmp_path / "p.csv", z, 0.25e-6, column="Slice", header={"Instrument": "Nexview"})
    m = read_measurement(tmp_path / "p.csv")
    assert m.shape == (1, 5) and m.pixel_size_m == pytest.approx(0.25e-6, rel=1e-12)
    np.testing.assert_allclose(m.height_m[0], z, rtol=1e-12, atol=1e-24)
    assert m.metadata["Instrument"] == "Nexview" and m.metadata["height_column"] == "Slice"
    (tmp_path / "h.csv").write_text("X,Y\n0,0.1\n2,\n4,-0.3\n")
    m = read_measurement(tmp_path / "h.csv")
    assert m.pixel_size_m == pytest.approx(2e-6)
    np.testing.assert_allclose(m.height_m, [[0.1e-6, np.nan, -0.3e-6]], rtol=1e-12)


@pytest.mark.parametrize("text,match", [
    ("a,b\n1,2\n", "no column-name row"),
    ("X,Q\n1,2\n2,3\n", "no Y / Slice"),
    ("X,Y\n1,2\n2,zz\n", "line 3 is not numeric"),
    ("X,Y\n1,2\n3,3\n4,1\n", "not uniformly"),
    ("X (furlong),Y\n1,2\n2,3\n", "unknown unit"),
])
def test_bad_csv(tmp_path, text, match):
    (tmp_path / "bad.csv").write_text(text)
    with pytest.raises(MeasurementFileError, match=f"bad.csv.*{match}"):
        read_measurement(tmp_path / "bad.csv")


def test_npy_npz_tiff_round_trips(tmp_path, surface):
    write_npy(tmp_path / "s.npy", surface)
    with pytest.raises(MeasurementFileError, match="s.npy.*pixel_size_m"):
        read_measurement(tmp_path / "s.npy")
    m = read_measurement(tmp_path / "s.npy", pixel_size_m=2e-6)
    np.testing.assert_array_equal(m.height_m, surface)
    write_npz(tmp_path / "s.npz", surface, 3e-6, metadata={"part_name": "P", "phase_origin": (1, 2)})
    m = read_measurement(tmp_path / "s.npz")
    np.testing.assert_array_equal(m.height_m, surface)
    assert m.pixel_size_m == 3e-6 and m.metadata["part_name"] == "P" and m.metadata["phase_origin"] == [1, 2]
    np.savez(tmp_path / "two.npz", a=surface, b=surface)
    with pytest.raises(MeasurementFileError, match="two.npz: no 'height_m'"):
        read_measurement(tmp_path / "two.npz", pixel_size_m=1e-6)
    np.savez(tmp_path / "one.npz", z=surface)
    assert read_measurement(tmp_path / "one.npz", pixel_size_m=1e-6).shape == surface.shape
    write_tiff(tmp_path / "s.tif", surface, 1.5e-6, z_unit_m=1e-9)
    m = read_measurement(tmp_path / "s.tif", z_unit_m=1e-9)
    assert m.pixel_size_m == pytest.approx(1.5e-6, rel=1e-6)
    np.testing.assert_allclose(m.height_m, surface, rtol=1e-6, atol=1e-15)


def test_write_measurement_dispatch_keeps_metadata(tmp_path, surface):
    meas = Measurement(surface, 1e-6, {"comment": "c"})
    for name in ("a.dat", "a.datx", "a.xyz", "a.asc", "a.npz", "a.tif"):
        back = read_measurement(write_measurement(tmp_path / name, meas))
        assert np.nanmax(np.abs(back.height_m - surface)) < 1e-11, name
        assert back.pixel_size_m == pytest.approx(1e-6, rel=1e-6)
    with pytest.raises(DoeError, match="pixel_size_m"):
        write_measurement(tmp_path / "b.dat", surface)
    with pytest.raises(DoeError, match="'.xls'"):
        write_measurement(tmp_path / "b.xls", meas)


def test_detect_format_prefers_magic(tmp_path, surface):
    write_dat(tmp_path / "s.dat", surface, 1e-6)
    (tmp_path / "s.bin").write_bytes((tmp_path / "s.dat").read_bytes())
    assert detect_format(tmp_path / "s.bin") == "dat"
    write_datx(tmp_path / "x.dat", surface, 1e-6)  # an HDF5 file with the wrong extension
    assert detect_format(tmp_path / "x.dat") == "datx"
    (tmp_path / "q.xyz2").write_text(ASCII_HEADER + "10 20 1\n")
    assert detect_format(tmp_path / "q.xyz2") == "xyz"
    (tmp_path / "u.foo").write_text("hello")
    with pytest.raises(MeasurementFileError, match="u.foo: unknown measurement format"):
        read_measurement(tmp_path / "u.foo")


# ---------------------------------------------------------------- CLI

def test_cli_inspect_json(tmp_path, surface, capsys):
    write_dat(tmp_path / "s.dat", surface, 1e-6, part_name="DOE-7")
    assert main(["inspect", str(tmp_path / "s.dat"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["kind"] == "measurement" and out["shape"] == [36, 48]
    assert out["invalid_fraction"] == pytest.approx(3 / surface.size)
    assert out["height_rms_m"] == pytest.approx(np.nanstd(surface), abs=step_m(1))
    assert out["metadata"]["part_name"] == "DOE-7" and out["metadata"]["phase_origin"] == [0, 0]


@pytest.mark.parametrize("name,content", [
    ("bad.dat", b"\x88\x1b\x03\x6f" + b"\0" * 40),
    ("bad.datx", b"\x89HDF\r\n\x1a\n" + b"\0" * 40),
    ("bad.xyz", b"Zygo XYZ Data File - Format 1\n1 2\n"),
    ("bad.npz", b"PK\x03\x04garbage"),
    ("bad.npy", b"\x93NUMPY garbage"),
    ("bad.tif", b"II*\0garbage"),
    ("bad.csv", b"\xff\xfe\x00"),
])
def test_cli_bad_files_exit_2_without_traceback(tmp_path, capsys, name, content):
    (tmp_path / name).write_bytes(content)
    assert main(["inspect", str(tmp_path / name), "--json"]) == 2
    err = capsys.readouterr().err
    assert name in err and "Traceback" not in err and err.count("\n") == 1
