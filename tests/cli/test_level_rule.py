"""One level rule: masks, compare and diagnose see the same levels of a design without levels.

The design carries heights only, some just outside the level range (15.6, -0.6, 17.2, -0.3
and 2.5 steps deep). The expected map is computed here independently, as the level nearest
in phase (circular distance modulo 16 steps), and compared pixel for pixel with the levels
the GDS masks print (read back with gdstk's own point-in-polygon test), the levels the
comparison labels the measurement with, and the levels the diagnosis models.
"""

import gdstk
import numpy as np
import pytest

from doedesign.cli import main
from doedesign.design import Design
from doedesign.levels import design_levels, level_step_m
from masks.process import ProcessParams
from metrology.formats.measurement import Measurement
from metrology.formats.writers import write_measurement
from metrology.matching import compare, register

PITCH = 5.4e-6
PIXEL = 1.1e-6
STEP = level_step_m("fused_silica", 550e-9)
EDGE_DEPTHS = np.array([15.6, -0.6, 17.2, -0.3, 2.5])


class _Seen(Exception):
    """Raised by the spy once the diagnosis has been handed its level map."""


def _nearest_in_phase(depth_steps):
    """Independent rule: the level with the smallest circular distance; a tie goes deeper."""
    k = np.arange(16)
    d = np.asarray(depth_steps)[..., None] + 1e-9
    dist = np.abs(np.mod(d - k + 8, 16) - 8)
    return np.argmin(dist, axis=-1)


def _design(shape=(60, 60), seed=4):
    rng = np.random.default_rng(seed)
    depth = rng.integers(0, 16, shape) + rng.uniform(-0.3, 0.3, shape)
    edge = rng.random(shape) < 0.25
    depth[edge] = rng.choice(EDGE_DEPTHS, int(edge.sum()))
    return Design(height_m=-depth * STEP, pitch_m=PITCH, metadata={"name": "nolevels"}), depth


def _printed_levels(gds_path, shape):
    """Levels recomposed from the four dark-tone mask layers, pixel centres tested by gdstk."""
    lib = gdstk.read_gds(str(gds_path))
    cell = next(c for c in lib.cells if c.name == "ELEMENT")
    rows, cols = shape
    pitch_um = PITCH * 1e6
    yy, xx = np.mgrid[:rows, :cols]
    centres = np.stack([(xx.ravel() - cols / 2 + 0.5) * pitch_um, (rows / 2 - yy.ravel() - 0.5) * pitch_um], 1)
    levels = np.zeros(shape, int)
    for bit in range(4):
        polys = [p for p in cell.get_polygons() if p.layer == bit + 1]
        inside = np.array(gdstk.inside(centres, polys)).reshape(shape) if polys else np.zeros(shape, bool)
        levels += inside.astype(int) << bit
    return levels


def test_edge_depths_follow_the_documented_rule():
    design = Design(height_m=-EDGE_DEPTHS[None, :] * STEP, pitch_m=PITCH)
    assert design_levels(design).tolist() == [[0, 15, 1, 0, 3]]
    assert _nearest_in_phase(EDGE_DEPTHS).tolist() == [0, 15, 1, 0, 3]


def test_masks_compare_and_diagnose_see_the_same_levels(tmp_path, monkeypatch):
    design, depth = _design()
    expected = _nearest_in_phase(depth)
    clipped = np.clip(np.rint(depth), 0, 15)
    assert np.count_nonzero(clipped != expected) > 100  # the old clipping rule would fail here
    path = tmp_path / "d.npz"
    design.save(path)
    assert Design.load(path).levels is None

    assert main(["masks", str(path), "--out", str(tmp_path / "m")]) == 0
    np.testing.assert_array_equal(_printed_levels(tmp_path / "m" / "nolevels.gds", depth.shape), expected)

    # A wafer made (by the process model) from the expected levels, seen by the comparison.
    truth = register.Registration.from_parameters(PIXEL / PITCH, 0.5, (False, False, False), (7.3, 6.6), PITCH,
                                                  depth.shape, (270, 270))
    params = ProcessParams(etch_depth=STEP * np.array([1, 2, 4, 8]))
    wafer = compare.process_on_measurement(expected, PITCH, params, truth)
    loaded = Design.load(path)
    comp = compare.compare_measurement(Measurement(wafer, PIXEL), loaded)
    seen = comp.labels >= 0
    old_rule_differs = register.design_on_measurement(clipped.astype(int), comp.registration) != comp.labels
    assert np.count_nonzero(seen & old_rule_differs) > 2000
    np.testing.assert_array_equal(comp.labels[seen],
                                  register.design_on_measurement(expected, comp.registration)[seen])

    # The diagnosis models the wafer on the levels of the same rule.
    import metrology.diagnosis.heights as heights

    got = {}

    def spy(levels, *args, **kwargs):
        got["levels"] = np.asarray(levels)
        raise _Seen

    monkeypatch.setattr(heights, "diagnose_heights", spy)
    meas_path = tmp_path / "wafer.npz"
    write_measurement(meas_path, wafer, pixel_size_m=PIXEL)
    with pytest.raises(_Seen):
        main(["diagnose", "--design", str(path), "--measured", str(meas_path), "--frame", "design",
              "--out", str(tmp_path / "g")])
    np.testing.assert_array_equal(got["levels"], expected)
