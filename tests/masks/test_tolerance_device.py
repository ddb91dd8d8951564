"""doe tolerance's samples on any array namespace: a seeded sample gives the same metrics on
array_api_strict (CPU) and on CuPy (``gpu``) as on NumPy (the ``namespace_backend`` fixture)."""

import numpy as np
import pytest

from doedesign.camera import Camera

PITCH = 5.4e-6


def test_seeded_tolerance_sample_same_metrics_on_either_device(namespace_backend):
    # doe tolerance's sample k (its process draw, fabricated heights, PSF and metrics) on the
    # namespace under test against NumPy: the same metrics to 1e-9.
    import math

    from doedesign.design import Design
    from doedesign.levels import level_step_m
    from masks.tolerance.analysis import build_evaluator, nominal_depths
    from masks.tolerance.spec import default_spec

    n = 24
    levels = np.random.default_rng(3).integers(0, 16, (n, n)).astype(np.int16)
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=math.inf, window_shape=(24, 24), axis_pixel=(12, 12))
    meta = {"camera": cam.to_dict(), "n_levels": 16,
            "target": {"kind": "bayer", "wavelengths_nm": [656.0, 589.0, 486.0], "depths_m": ["inf"], "rggb": False}}
    design = Design(height_m=-levels * level_step_m("fused_silica", 550e-9, 16), pitch_m=PITCH, levels=levels,
                    metadata=meta)
    spec = default_spec(nominal_depths(design))
    values, seed = spec.draw(11, 3)
    job = {"id": 3, "values": values, "seed": seed}
    ref = build_evaluator(design, spec, device="cpu")[0](job)["metrics"]
    got = build_evaluator(design, spec, device=namespace_backend)[0](job)["metrics"]
    assert set(got) == set(ref) and ref
    for k, v in ref.items():
        assert got[k] == pytest.approx(v, rel=1e-9, abs=1e-12), k
