"""The one strict JSON encoder and the camera's JSON round trip."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.errors import DesignFileError
from doedesign.fileio import dumps_json, json_ready, write_json


def _strict(text):
    def reject(name):
        raise ValueError(name)

    return json.loads(text, parse_constant=reject)


def test_nan_and_infinity_become_null_numpy_becomes_plain(tmp_path):
    obj = {"a": np.float32(1.5), "b": np.array([[1, 2], [3, 4]], np.int16), "c": (np.nan, -np.inf, 2.0),
           "d": np.array([np.inf, 0.25]), 3: Path("x/y"), "e": np.bool_(True), "f": math.nan}
    back = _strict(write_json(tmp_path / "r.json", obj).read_text())
    assert back == {"a": 1.5, "b": [[1, 2], [3, 4]], "c": [None, None, 2.0], "d": [None, 0.25], "3": "x/y",
                    "e": True, "f": None}
    assert isinstance(json_ready(np.int64(7)), int) and type(json_ready(np.float64(0.1))) is float
    with pytest.raises(TypeError):
        dumps_json({"x": object()})


def test_camera_at_infinity_round_trips_through_the_design_file(tmp_path):
    cam = Camera(focus_distance_m=np.inf, window_shape=(64, 64), axis_pixel=(32, 32))
    design = Design(height_m=np.zeros((4, 4)), pitch_m=5.4e-6, metadata={"camera": cam.to_dict()})
    design.save(tmp_path / "d.npz")
    with np.load(tmp_path / "d.npz") as npz:
        _strict(str(npz["metadata"]))
    back = Design.load(tmp_path / "d.npz").camera()
    assert back == cam and np.isinf(back.focus_distance_m)
    # The focal length of a lens focused at infinity is its sensor distance.
    assert back.focal_length_m == pytest.approx(cam.sensor_distance_m)


def test_design_camera_missing_and_broken():
    d = Design(height_m=np.zeros((2, 2)), pitch_m=5.4e-6)
    assert d.camera() == Camera() and d.camera(missing="none") is None
    bad = Design(height_m=np.zeros((2, 2)), pitch_m=5.4e-6, metadata={"name": "b", "camera": {"doe_side": "up"}})
    with pytest.raises(DesignFileError, match="b: metadata camera"):
        bad.camera()
    with pytest.raises(DesignFileError, match="JSON object"):
        Design(height_m=np.zeros((2, 2)), pitch_m=5.4e-6, metadata={"camera": 3}).camera()


def test_progress_switch_and_counts(monkeypatch):
    import io

    from doedesign.progress import Progress

    stream = io.StringIO()
    monkeypatch.setenv("DOE_PROGRESS", "1")
    with Progress(4, desc="work", stream=stream) as bar:
        for i in range(6):
            bar.update(1, status=f"loss {i}")
    assert bar.count == 4 and "work" in stream.getvalue() and "4/4" in stream.getvalue()
    monkeypatch.setenv("DOE_PROGRESS", "0")
    quiet = io.StringIO()
    with Progress(3, desc="quiet", stream=quiet) as bar:
        bar.update(3)
    assert quiet.getvalue() == "" and bar.count == 3
