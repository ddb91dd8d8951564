"""Camera geometry against the lens equation and the area of a disc."""

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.errors import DoeError


def test_seed_camera_focal_length_and_f_number():
    cam = Camera()
    # 1/f = 1/5 m + 1/50 mm
    assert cam.focal_length_m == pytest.approx(1 / (1 / 5.0 + 1 / 50e-3))
    assert cam.focal_length_m * 1e3 == pytest.approx(49.50, abs=0.01)
    assert cam.f_number == pytest.approx(cam.focal_length_m / 8.64e-3)
    assert Camera(focus_distance_m=np.inf).focal_length_m == pytest.approx(50e-3)


@pytest.mark.parametrize("side", ["left", "right", "full"])
def test_view_weights_hold_the_disc_area(side):
    pitch = 5.4e-6
    cam = Camera(aperture_diameter_m=100 * pitch, doe_side=side)
    w = cam.view_weights(cam.pupil_grid_shape((100, 100), pitch), pitch)
    disc = np.pi * 50 ** 2
    if side == "full":
        assert w[0].sum() == pytest.approx(disc, rel=2e-3)
        np.testing.assert_array_equal(w[0], w[1])
    else:
        assert w[0].sum() == pytest.approx(disc / 2, rel=2e-3)
        assert w[0].sum() + w[1].sum() == pytest.approx(disc, rel=2e-3)
        coded_cols = np.nonzero(w[0].sum(axis=0))[0]
        assert (coded_cols.max() < 50) == (side == "left")


def test_bad_cameras_and_oversized_design():
    with pytest.raises(DoeError, match="doe_side"):
        Camera(doe_side="top")
    with pytest.raises(DoeError, match="sensor_distance_m"):
        Camera(sensor_distance_m=0)
    with pytest.raises(DoeError, match="larger than the aperture"):
        Camera(aperture_diameter_m=10 * 5.4e-6).pupil_grid_shape((20, 20), 5.4e-6)
    assert Camera.from_dict(Camera(window_shape=(64, 32)).to_dict()) == Camera(window_shape=(64, 32))
