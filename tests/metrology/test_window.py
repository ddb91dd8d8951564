"""Where the profilometer field and the diagnosis window go (metrology.matching.window)."""

import numpy as np
import pytest

from doedesign.errors import DoeError
from metrology.matching.window import busiest_window


def _stripes_without_top(n=120):
    """A busy striped left half on levels 1..15 only, a calmer right half that is partly unetched."""
    cols = np.arange(n)
    levels = np.tile(1 + (cols // 2) % 15, (n, 1))
    right = cols >= n // 2
    levels[:, right] = np.where((cols[right] // 10) % 2 == 1, 0, 5)
    return levels


def test_busiest_window_prefers_edges():
    levels = _stripes_without_top()
    r0, r1, c0, c1 = busiest_window(levels, 40, need_flat=False)
    assert c1 <= 62 and not (levels[r0:r1, c0:c1] == 0).any()


def test_a_field_must_hold_unetched_surface_when_asked():
    levels = _stripes_without_top()
    r0, r1, c0, c1 = busiest_window(levels, 40, need_flat=False, min_level0_px=50)
    window = levels[r0:r1, c0:c1]
    assert (window == 0).sum() >= 50
    # Still the busiest of the allowed windows: it reaches into the striped half.
    assert c0 < 60


def test_no_unetched_surface_anywhere_is_a_clear_error():
    levels = np.tile(1 + (np.arange(64) // 2) % 15, (64, 1))
    with pytest.raises(DoeError, match="unetched"):
        busiest_window(levels, 32, need_flat=False, min_level0_px=10)
