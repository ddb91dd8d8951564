"""Measurement writers read back by independent parsers (plain text, numpy, tifffile), not ours."""

import json

import numpy as np
import pytest
import tifffile

from metrology.formats.writers import write_npz, write_profile_csv, write_tiff, write_xyz

SURFACE = np.array([[0.0, -75e-9, -150e-9], [-300e-9, np.nan, -600e-9]])


def test_xyz_lists_col_row_z_in_micrometres(tmp_path):
    path = write_xyz(tmp_path / "s.xyz", SURFACE, 1e-6, phase_origin=(10, 20))
    lines = path.read_text(encoding="latin-1").splitlines()
    assert lines[-1] == "#"
    start = len(lines) - 2 - lines[-2::-1].index("#")  # the data block sits between the last two "#"
    data = [line.split(maxsplit=2) for line in lines[start + 1:-1]]
    assert len(data) == SURFACE.size
    for col, row, z in data:
        h = SURFACE[int(row) - 20, int(col) - 10]
        if np.isfinite(h):
            assert float(z) == pytest.approx(h * 1e6, abs=1e-7)
        else:
            assert z == "No Data"


def test_profile_csv_is_micrometres_with_blank_for_no_data(tmp_path):
    z = np.array([0.0, -0.5e-6, np.nan, -1.25e-6])
    lines = write_profile_csv(tmp_path / "p.csv", z, 2e-6, x0_m=1e-6).read_text().splitlines()
    assert lines[0] == "X,Y"
    rows = [line.split(",") for line in lines[1:]]
    assert [float(x) for x, _ in rows] == pytest.approx([1.0, 3.0, 5.0, 7.0])
    assert rows[2][1] == ""
    assert [float(v) for _, v in rows if v] == pytest.approx([0.0, -0.5, -1.25])


def test_tiff_holds_heights_and_pixel_size(tmp_path):
    path = write_tiff(tmp_path / "s.tif", SURFACE, 0.5e-6, z_unit_m=1e-9)
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        data = page.asarray()
        num, den = page.tags["XResolution"].value
        assert page.tags["ResolutionUnit"].value == 3  # centimetre
    np.testing.assert_allclose(data, SURFACE * 1e9, rtol=1e-6)
    assert 0.01 / (num / den) == pytest.approx(0.5e-6, rel=1e-6)


def test_npz_is_plain_numpy_with_strict_json_metadata(tmp_path):
    path = write_npz(tmp_path / "s.npz", SURFACE, 1.1e-6, metadata={"gain": np.float32(2.0), "bad": np.inf})
    with np.load(path) as npz:
        np.testing.assert_array_equal(npz["height_m"], SURFACE)
        assert float(npz["pixel_size_m"]) == 1.1e-6
        assert json.loads(str(npz["metadata"])) == {"gain": 2.0, "bad": None}
