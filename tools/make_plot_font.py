#!/usr/bin/env python3
"""Makes DejaVuSans-subset.ttf, the font `kfmap plot` embeds (not run by the build).

    pip install fonttools
    python3 tools/make_plot_font.py /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf \
        plot/src/DejaVuSans-subset.ttf

1. Subset DejaVu Sans to the characters the pictures use, without hinting or OpenType
   layout tables (the legacy `kern` table is kept).
2. Work around plotters 0.3.7's ab_glyph text drawing, which places each glyph's ink at
   the pen position and so drops its left side bearing: every outline is moved so its
   ink starts at x = 0 (advance reduced by as much), and the bearing comes back as
   kerning before the glyph (a class-based `kern` subtable: any glyph, then glyph h ->
   h's old bearing; the font's own pairs, plus the bearing, in a first subtable). Text
   is then spaced as the original font spaces it, both when drawn and when measured.
"""

import struct
import sys

from fontTools import subset
from fontTools.pens.recordingPen import DecomposingRecordingPen
from fontTools.pens.ttGlyphPen import TTGlyphPen
from fontTools.ttLib import TTFont
from fontTools.ttLib.tables._k_e_r_n import KernTable_format_0, KernTable_format_unkown

UNICODES = "U+0020-007E,U+00A0-00FF,U+0394,U+03C3,U+2013,U+2014,U+2026,U+2192,U+2212,U+2248,U+2264,U+2265"


def main(source: str, target: str) -> None:
    options = subset.Options()
    options.hinting = False
    options.layout_features = []
    options.legacy_kern = True
    options.drop_tables += ["MATH", "GSUB", "GPOS", "GDEF", "FFTM"]
    font = subset.load_font(source, options)
    subsetter = subset.Subsetter(options)
    subsetter.populate(unicodes=subset.parse_unicodes(UNICODES))
    subsetter.subset(font)

    glyf, hmtx = font["glyf"], font["hmtx"]
    order = font.getGlyphOrder()
    # Composites reference other glyphs' outlines: make every glyph simple first.
    glyph_set = font.getGlyphSet()
    simple = {}
    for name in order:
        if glyf[name].isComposite():
            recording = DecomposingRecordingPen(glyph_set)
            glyph_set[name].draw(recording)
            pen = TTGlyphPen(None)
            recording.replay(pen)
            simple[name] = pen.glyph()
    for name, glyph in simple.items():
        glyf[name] = glyph
    bearing = {}
    for name in order:
        glyph = glyf[name]
        advance, _ = hmtx[name]
        if glyph.numberOfContours == 0:
            bearing[name] = 0
            continue
        glyph.recalcBounds(glyf)
        x_min = glyph.xMin
        coords = glyph.coordinates
        for i in range(len(coords)):
            x, y = coords[i]
            coords[i] = (x - x_min, y)
        glyph.recalcBounds(glyf)
        hmtx[name] = (advance - x_min, 0)
        bearing[name] = x_min

    pairs = {}
    if "kern" in font:
        for table in font["kern"].kernTables:
            for (left, right), value in getattr(table, "kernTable", {}).items():
                pairs.setdefault((left, right), value)
    first = KernTable_format_0()
    first.version, first.format, first.coverage, first.tupleIndex = 0, 0, 1, None
    first.kernTable = {
        (left, right): value + bearing[right] for (left, right), value in pairs.items()
    }

    columns = sorted(set(bearing.values()))
    column = {b: i for i, b in enumerate(columns)}
    n = len(order)
    header = 6
    left_at = header + 8
    right_at = left_at + 4 + 2 * n
    array_at = right_at + 4 + 2 * n
    body = struct.pack(">HHHH", 2 * len(columns), left_at, right_at, array_at)
    body += struct.pack(">HH", 0, n) + struct.pack(f">{n}H", *([array_at] * n))
    body += struct.pack(">HH", 0, n) + struct.pack(
        f">{n}H", *(2 * column[bearing[name]] for name in order)
    )
    body += struct.pack(f">{len(columns)}h", *columns)
    second = KernTable_format_unkown(2)
    second.data = struct.pack(">HHBB", 0, header + len(body), 2, 1) + body

    kern = font["kern"] if "kern" in font else None
    if kern is None:
        from fontTools.ttLib import newTable

        kern = font["kern"] = newTable("kern")
    kern.version = 0
    kern.kernTables = [first, second]
    font.save(target)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
