"""``doe masks``: design file -> verified GDSII of the binary etch masks, preview, report."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from doedesign.cli.common import Number
from doedesign.errors import DoeError
from doedesign.fileio import ensure_output_dir, output_run, save_figure, write_json

log = logging.getLogger(__name__)


def register(subparsers):
    p = subparsers.add_parser("masks", help="quantize, decompose into binary masks, write verified GDSII",
                              description="Write DIR/<name>.gds (one layer per mask), DIR/masks.png and "
                                          "DIR/report.json; the GDS is read back and verified pixel by pixel.")
    p.add_argument("design", help="design .npz")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--tone", choices=("dark", "clear"), default="dark",
                   help="dark: draw the etched (open) areas (default); clear: draw the chrome")
    p.add_argument("--mirror", action="store_true", help="mirror x -> -x (contact printing)")
    p.add_argument("--depths-nm", default=None,
                   help="etch depth per mask, comma separated (default 2**j times the level step)")
    p.add_argument("--layers", default="1,2,3,4", help="GDS layer per mask")
    p.add_argument("--etch-order", default=None, help="mask index etched in each step, e.g. 3,2,1,0")
    p.add_argument("--clear-aperture-mm", type=Number(float, 0, 1000, lo_open=True, unit="mm"), default=None,
                   help="clear circle diameter (default: camera aperture from the metadata)")
    p.add_argument("--oasis", action="store_true", help="also write <name>.oas")
    p.set_defaults(func=run_masks)


def _int_list(text, what):
    try:
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise DoeError(f"--{what} must be comma-separated integers, got {text!r}") from None


def _float_list(text, what):
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise DoeError(f"--{what} must be comma-separated numbers, got {text!r}") from None
    if not all(np.isfinite(vals)) or min(vals) <= 0:
        raise DoeError(f"--{what} must be positive, got {text!r}")
    return vals


def clear_aperture_m(design):
    """Clear circle diameter: the camera's aperture from the metadata, else the aperture mask."""
    cam = design.metadata.get("camera") if isinstance(design.metadata, dict) else None
    if isinstance(cam, dict) and cam.get("aperture_diameter_m"):
        return float(cam["aperture_diameter_m"])
    if design.aperture is not None and design.aperture.any():
        rows, cols = np.nonzero(design.aperture)
        extent = max(rows.max() - rows.min(), cols.max() - cols.min()) + 1
        return float(extent * design.pitch_m)
    return None


def preview(levels, masks, path, title):
    """Figure of the level map and every mask (row 0 at the top, white = open/etched)."""
    import matplotlib.pyplot as plt

    n = masks.shape[0]
    fig, axes = plt.subplots(1, n + 1, figsize=(3 * (n + 1), 3.2))
    im = axes[0].imshow(levels, cmap="viridis", interpolation="nearest", vmin=0, vmax=2 ** n - 1)
    axes[0].set_title(f"{title}: levels")
    fig.colorbar(im, ax=axes[0], fraction=0.046)
    for j in range(n):
        axes[j + 1].imshow(masks[j], cmap="gray", interpolation="nearest", vmin=0, vmax=1)
        axes[j + 1].set_title(f"mask {j + 1} (bit {j}, open = white)")
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    save_figure(fig, path)


def run_masks(args):
    from doedesign.design import Design
    from doedesign.levels import N_LEVELS, quantize_design

    from .decompose import binary_depths_m, levels_to_masks
    from .gds import export_masks

    out = ensure_output_dir(args.out)
    design = Design.load(args.design)
    source = str(args.design)
    levels, quantization = quantize_design(design, N_LEVELS, source)
    step = design.level_step_m(N_LEVELS)
    masks = levels_to_masks(levels, 4)
    depths = (binary_depths_m(step, 4) if args.depths_nm is None
              else [d * 1e-9 for d in _float_list(args.depths_nm, "depths-nm")])
    layers = _int_list(args.layers, "layers")
    order = None if args.etch_order is None else _int_list(args.etch_order, "etch-order")
    aperture = (args.clear_aperture_mm * 1e-3 if args.clear_aperture_mm is not None
                else clear_aperture_m(design))
    die = 10e-3
    if aperture is not None and aperture >= die:
        log.warning("%s: clear aperture %.2f mm does not fit the die; no Cr aperture drawn", source, aperture * 1e3)
        aperture = None
    name = design.name
    gds_path = out / f"{Path(name).name or 'design'}.gds"
    with output_run(out, f"doe masks {source}"):
        report = export_masks(gds_path, masks, design.pitch_m, layers=layers, tone=args.tone,
                              mirrored=args.mirror, depths_m=depths, etch_order=order, name=name,
                              clear_aperture_m=aperture, die_size_m=die, oasis=args.oasis)
        report["design"] = source
        report["level_step_nm"] = step * 1e9
        report["quantization"] = None if quantization is None else quantization.summary()
        preview(levels, masks, out / "masks.png", name)
        write_json(out / "report.json", report)
    from doedesign.cli.common import print_json

    print_json({k: report[k] for k in ("file", "file_size_bytes", "seconds", "verification")})
    return 0
