"""`doe masks` starts lean: only its own command is loaded, no matplotlib; Pillow preview."""

import json
import subprocess
import sys

import numpy as np

from doedesign.design import Design
from masks.element import LEVEL_COLOURS, PREVIEW_PX, preview

_PROBE = """
import json, sys
from doedesign.cli import main
code = main(sys.argv[1:])
print(json.dumps({"code": code, "modules": sorted(sys.modules)}))
"""


def _run(args, cwd):
    out = subprocess.run([sys.executable, "-c", _PROBE, *args], capture_output=True, text=True, cwd=cwd,
                         check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_doe_masks_loads_only_its_command_and_no_matplotlib(tmp_path):
    yy, xx = np.mgrid[:40, :50]
    levels = ((xx + yy) % 16).astype(np.int16)
    Design(-levels * 74.74e-9, 5.4e-6, levels=levels, metadata={"name": "s"}).save(tmp_path / "s.npz")
    got = _run(["masks", "s.npz", "--out", "out"], tmp_path)
    assert got["code"] == 0 and (tmp_path / "out" / "masks.png").is_file()
    loaded = set(got["modules"])
    assert "matplotlib" not in loaded
    assert not {m for m in loaded if m.startswith(("metrology", "masks.tolerance", "doedesign.engine.psf", "doedesign.bayer"))}
    # the plain `doe --help` still lists every command
    full = subprocess.run([sys.executable, "-c", "from doedesign.cli import main; main(['--help'])"],
                          capture_output=True, text=True, check=True).stdout
    assert all(name in full for name in ("design", "masks", "compare", "diagnose", "tolerance", "demo"))


def test_level_colours_are_viridis():
    from matplotlib import colormaps

    ref = np.round(np.asarray(colormaps["viridis"](np.linspace(0, 1, 16)))[:, :3] * 255)
    assert np.array_equal(LEVEL_COLOURS, ref.astype(np.uint8))


def test_preview_panels_show_the_levels_and_masks(tmp_path):
    from PIL import Image

    levels = np.repeat(np.arange(16, dtype=np.int16)[None, :], 8, axis=0).repeat(10, axis=1)  # 8 x 160
    masks = np.stack([(levels >> j) & 1 for j in range(4)]).astype(bool)
    preview(levels, masks, tmp_path / "p.png", "t")
    img = np.asarray(Image.open(tmp_path / "p.png").convert("RGB"))
    assert img.shape[1] > 5 * 160 and max(levels.shape) <= PREVIEW_PX
    # find the level panel: the row of pixels that runs through all 16 colours in order
    row = next(r for r in img if (r == LEVEL_COLOURS[7]).all(axis=1).any())
    first = [int(np.nonzero((row == c).all(axis=1))[0][0]) for c in LEVEL_COLOURS]
    assert first == sorted(first)  # level k lies left of level k + 1, as in the design
    # mask 4 (bit 3) is open (white) for levels 8..15: the right half of its panel
    x0 = first[0]
    # the panel's 8 rows come first, the colour key under it repeats the colours
    panel_rows = np.nonzero((img[:, first[7]] == LEVEL_COLOURS[7]).all(axis=1))[0][:8]
    assert panel_rows[-1] - panel_rows[0] == 7
    panel4 = img[panel_rows, x0 + 4 * (160 + 16):x0 + 4 * (160 + 16) + 160]
    assert (panel4[:, :80] == 0).all() and (panel4[:, 80:] == 255).all()
