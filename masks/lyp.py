"""KLayout layer-properties files (``.lyp``): each mask layer named with its etch depth and
drawn in its own colour, so a GDSII/OASIS file opens readable in KLayout (File > Load Layer
Properties, or ``klayout -l NAME.lyp NAME.gds``).

The file is the XML KLayout itself saves (``LayoutView.save_layer_props``): a
``<layer-properties>`` root with one ``<properties>`` entry per layer, ``<source>`` naming
``layer/datatype@1`` (the first layout loaded). It is written with the standard library's
ElementTree; KLayout is only a test dependency.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

from doedesign.fileio import atomic_path

from .grid import APERTURE_LAYER, DIE_LAYER, TEXT_LAYER

__all__ = ["LayerStyle", "MASK_COLOURS", "die_layer_styles", "layer_properties_xml", "write_lyp"]

#: Mask j's colour (frame and fill), j = 0, 1, ...: well apart in hue, none close to the grey
#: of the die outline or the yellow of the labels.
MASK_COLOURS = ("#ff3030", "#2f7fff", "#20b040", "#b040ff", "#ff8c00", "#00b8b8", "#c0a000", "#ff40a0")
# Stipples (KLayout's built-in dither patterns): each mask hatched its own way, so where
# masks overlap both stay visible.
MASK_PATTERNS = ("I5", "I9", "I13", "I17", "I6", "I10", "I14", "I18")


@dataclass(frozen=True)
class LayerStyle:
    """One ``<properties>`` entry: the layer's name and how KLayout draws it."""

    layer: int
    datatype: int
    name: str
    colour: str
    pattern: str = "I1"  # hollow
    width: int | None = None  # frame line width in pixels (None: KLayout's default)


def die_layer_styles(layers: Sequence[int], datatype: int, depths_m: Sequence[float],
                     etch_order: Sequence[int] | None = None, clear_aperture: bool = True,
                     extra: Sequence[LayerStyle] = ()) -> list[LayerStyle]:
    """Styles of a die's layers: the masks (named ``mask 3: 300.0 nm etch, step 3 (L3/0)``),
    the Cr aperture, die outline and labels, then ``extra`` (e.g. a plate's frame)."""
    order = list(range(len(layers)) if etch_order is None else etch_order)
    styles = [LayerStyle(layer, datatype, f"mask {j + 1}: {d * 1e9:.1f} nm etch, step {order.index(j) + 1} "
                                          f"(L{layer}/{datatype})",
                         MASK_COLOURS[j % len(MASK_COLOURS)], MASK_PATTERNS[j % len(MASK_PATTERNS)])
              for j, (layer, d) in enumerate(zip(layers, depths_m))]
    if clear_aperture:
        styles.append(LayerStyle(APERTURE_LAYER, 0, f"Cr aperture outside the clear circle (L{APERTURE_LAYER}/0)",
                                 "#808080", "I2"))
    styles += [LayerStyle(DIE_LAYER, 0, f"die outline (L{DIE_LAYER}/0)", "#404040", "I1", 2),
               LayerStyle(TEXT_LAYER, 0, f"text labels (L{TEXT_LAYER}/0)", "#e0e000", "I0")]
    return styles + list(extra)


def layer_properties_xml(styles: Sequence[LayerStyle]) -> str:
    """The ``.lyp`` XML of ``styles``, element for element as KLayout writes it."""
    root = ElementTree.Element("layer-properties")
    for s in styles:
        props = ElementTree.SubElement(root, "properties")
        for tag, text in (("expanded", "false"), ("frame-color", s.colour), ("fill-color", s.colour),
                          ("frame-brightness", "0"), ("fill-brightness", "0"), ("dither-pattern", s.pattern),
                          ("line-style", None), ("valid", "true"), ("visible", "true"),
                          ("transparent", "false"), ("width", None if s.width is None else str(s.width)),
                          ("marked", "false"), ("xfill", "false"), ("animation", "0"), ("name", s.name),
                          ("source", f"{s.layer}/{s.datatype}@1")):
            ElementTree.SubElement(props, tag).text = text
    ElementTree.SubElement(root, "name")
    ElementTree.indent(root, space=" ")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ElementTree.tostring(root, encoding="unicode") + "\n"


def write_lyp(path: str | Path, styles: Sequence[LayerStyle]) -> Path:
    """Write the ``.lyp`` of ``styles`` to ``path`` atomically; return the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(layer_properties_xml(styles), encoding="utf-8")
    return path
