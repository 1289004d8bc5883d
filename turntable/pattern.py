"""The printable target: rasters for synthetic scenes and sheets for the printer.

Every drawing follows :func:`calib.target.ink_at` / :func:`calib.target.mark_cells`
(rings and angle marks from one :class:`~calib.target.TargetSpec`).

Raster layout (:func:`render_target_image`): a square raster centred on the
pattern centre. Seen from above (+Y towards the viewer), table +X is the
raster's column direction and table +Z its row direction (right-handed:
X x Y = Z). Pixel (row i, column j) has its centre at ``X = (j - c) / px_per_mm``,
``Z = (i - c) / px_per_mm`` with ``c = (N - 1) / 2``.

Sheet layout (:func:`write_pattern`): the same orientation on paper, text
upright: table +X to the right, +Z down the page, so the printed 0 deg mark is
to the right of the centre and angles grow clockwise. SVG and PDF are vector
drawings at true scale (SVG in mm units, PDF in points with a mm transform);
PNG is a raster at ``dpi`` with its resolution stored in the file. Each sheet
carries the radii and stroke as text, a 50 mm scale bar and a
"print at 100 % / actual size" note.

Ground colour (``background``): white paper by default; any other colour
fills the whole printable area (the sheet less ``SHEET_MARGIN_MM`` on every
side), under black rings, marks and text. A coloured ground lets the
silhouettes tell a white object from the target (README, "Scanning a white
object"). The ring and mark detectors work on grey levels, so a ground must
stay light: its relative luminance (sRGB, ``Y = 0.2126 R + 0.7152 G + 0.0722 B``
of the linearised channels) must be at least ``MIN_BACKGROUND_LUMINANCE``
(see ``benchmarks/target_background.py`` for the measurement behind it).
"""

from __future__ import annotations

import math
import os
import zlib
from dataclasses import dataclass

import numpy as np

from calib.target import TargetSpec, ink_at, mark_cells, turntable_angle

__all__ = ["render_target_image", "write_pattern", "sheet_layout", "SheetLayout", "paper_size_mm", "PAPER_SIZES_MM",
           "SHEET_MARGIN_MM", "BACKGROUND_COLOURS", "MIN_BACKGROUND_LUMINANCE", "parse_background",
           "relative_luminance"]

#: Paper sizes (width, height) in mm, portrait.
PAPER_SIZES_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4), "a3": (297.0, 420.0)}
#: Blank border (mm) kept on every side of the sheet: most printers cannot print there.
SHEET_MARGIN_MM = 5.0
MM_PER_INCH = 25.4
PT_PER_MM = 72.0 / MM_PER_INCH
#: Named ground colours (sRGB). ``green`` is the one README recommends for white objects.
BACKGROUND_COLOURS = {"white": (255, 255, 255), "green": (91, 200, 91), "blue": (110, 168, 255),
                      "grey": (166, 166, 166)}
#: Smallest relative luminance of a ground under black ink (measured: benchmarks/target_background.py).
MIN_BACKGROUND_LUMINANCE = 0.35


def relative_luminance(rgb) -> float:
    """Relative luminance in [0, 1] of an sRGB colour given as three 0-255 values (WCAG / ITU-R BT.709)."""
    c = np.asarray(rgb, dtype=np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return float(lin @ [0.2126, 0.7152, 0.0722])


def parse_background(text: str) -> tuple[int, int, int]:
    """sRGB (R, G, B), 0-255, of a ground colour: a name of ``BACKGROUND_COLOURS`` or ``#RRGGBB``.

    Raises
    ------
    ValueError
        Not a colour, or too dark for the ring and mark detectors (relative
        luminance below ``MIN_BACKGROUND_LUMINANCE``); the message says why.
    """
    key = str(text).strip().lower()
    if key in BACKGROUND_COLOURS:
        rgb = BACKGROUND_COLOURS[key]
    elif len(key) == 7 and key[0] == "#" and all(ch in "0123456789abcdef" for ch in key[1:]):
        rgb = tuple(int(key[i:i + 2], 16) for i in (1, 3, 5))
    else:
        raise ValueError(f"{text!r} is not a colour: use {', '.join(BACKGROUND_COLOURS)} or #RRGGBB (e.g. #5bc85b)")
    y = relative_luminance(rgb)
    if y < MIN_BACKGROUND_LUMINANCE:
        raise ValueError(f"{text!r} is too dark (relative luminance {y:.2f}, at least {MIN_BACKGROUND_LUMINANCE:.2f} "
                         "needed): black rings and marks must stand out from the ground; pick a lighter colour "
                         f"(e.g. {', '.join(k for k in BACKGROUND_COLOURS if k != 'white')})")
    return rgb


def _hex(rgb) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def render_target_image(spec: TargetSpec, px_per_mm: float, size_mm: float | None = None,
                        supersample: int = 4) -> np.ndarray:
    """Grey raster (N, N) uint8 of the target, white paper (255), black ink (0).

    Parameters
    ----------
    spec : TargetSpec
        Rings and, when ``spec.marks``, the angle marks.
    px_per_mm : float
        Raster resolution.
    size_mm : float, optional
        Side of the square; default: outer ring + 25 mm margin on every side
        (and at least 7 mm beyond the angle marks).
    supersample : int
        Anti-aliasing: ``supersample``² samples per pixel.

    Returns
    -------
    (N, N) uint8 with ``N = round(size_mm * px_per_mm)``; layout in the module docstring.
    """
    if not px_per_mm > 0:
        raise ValueError(f"px_per_mm must be positive, got {px_per_mm}")
    if size_mm is None:
        size_mm = 2.0 * max(spec.r_outer_mm + 25.0, spec.extent_mm + 7.0)
    n = int(round(size_mm * px_per_mm))
    c = (n - 1) / 2.0
    axis_mm = (np.arange(n) - c) / px_per_mm
    white = _coverage_white(spec, axis_mm, axis_mm, 1.0 / px_per_mm, int(supersample))
    return np.round(white * 255.0).astype(np.uint8)


def _coverage_white(spec: TargetSpec, x_mm: np.ndarray, z_mm: np.ndarray, pixel_mm: float,
                    supersample: int) -> np.ndarray:
    """Fraction of paper (not ink) in each pixel, (len(z_mm), len(x_mm)) float32.

    ``x_mm``/``z_mm`` are the table coordinates of the pixel centres of the
    columns/rows; pixels are ``pixel_mm`` square. Pixels that no ink boundary
    comes near take the value at their centre; the others average
    ``supersample``² samples of :func:`calib.target.ink_at`.
    """
    s = max(int(supersample), 1)
    X = x_mm[None, :]
    Z = z_mm[:, None]
    r = np.hypot(X, Z)
    out = (~ink_at(spec, X, Z)).astype(np.float32)
    # distance (mm) from each pixel centre to the nearest ink boundary, a lower bound
    h = spec.stroke_mm / 2.0
    radii = [spec.r_outer_mm - h, spec.r_outer_mm + h, spec.r_inner_mm - h, spec.r_inner_mm + h]
    if spec.marks:
        radii += [spec.mark_r0_mm, spec.mark_r1_mm]
    dist = np.abs(r - radii[0])
    for b in radii[1:]:
        np.minimum(dist, np.abs(r - b), out=dist)
    if spec.marks:
        step = np.pi / spec.n_sectors  # half-sector boundaries
        track = (r > spec.mark_r0_mm - pixel_mm) & (r < spec.mark_r1_mm + pixel_mm)
        rows, cols = np.nonzero(track)
        th = turntable_angle(x_mm[cols], z_mm[rows])
        frac = np.mod(th, step)
        d_edge = np.minimum(frac, step - frac) * r[rows, cols]
        dist[rows, cols] = np.minimum(dist[rows, cols], d_edge)
    mixed = dist < 0.75 * pixel_mm
    if s > 1 and np.any(mixed):
        rows, cols = np.nonzero(mixed)
        offs = ((np.arange(s) + 0.5) / s - 0.5) * pixel_mm
        xs = x_mm[cols][:, None, None] + offs[None, None, :]
        zs = z_mm[rows][:, None, None] + offs[None, :, None]
        out[rows, cols] = (~ink_at(spec, xs, zs)).mean(axis=(1, 2), dtype=np.float32)
    return out


# ----------------------------------------------------------------------------- sheet layout

@dataclass(frozen=True)
class SheetLayout:
    """What goes on the paper, in mm from the sheet's top-left corner, y down.

    Attributes
    ----------
    width_mm, height_mm : float
        Paper size.
    centre_mm : (float, float)
        Pattern centre (table origin); table +X is sheet +x, table +Z sheet +y.
    scale_bar_mm : (float, float, float)
        The 50 mm scale bar: left end x, top y, length.
    rects : tuple of (x, y, w, h)
        Filled black rectangles (the scale bar and its ticks).
    texts : tuple of (x, baseline_y, size, text)
        Left-aligned text lines, ``size`` = font size in mm.
    """

    width_mm: float
    height_mm: float
    centre_mm: tuple[float, float]
    scale_bar_mm: tuple[float, float, float]
    rects: tuple[tuple[float, float, float, float], ...]
    texts: tuple[tuple[float, float, float, str], ...]


def paper_size_mm(paper) -> tuple[float, float]:
    """(width, height) mm of ``"a4"``, ``"letter"``, ``"a3"``, ``"WxH"`` (mm) or a (W, H) pair."""
    if isinstance(paper, str):
        key = paper.strip().lower()
        if key in PAPER_SIZES_MM:
            return PAPER_SIZES_MM[key]
        parts = key.split("x")
        try:
            w, h = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"paper must be a4, letter, a3 or WxH in mm (e.g. 210x297), got {paper!r}") from None
    else:
        try:
            w, h = (float(p) for p in paper)
        except (TypeError, ValueError):
            raise ValueError(f"paper must be a name or a (width, height) pair in mm, got {paper!r}") from None
    if not (w > 0 and h > 0 and math.isfinite(w) and math.isfinite(h)):
        raise ValueError(f"paper size must be positive, got {w} x {h} mm")
    return w, h


def _fmt(x: float) -> str:
    return f"{x:g}"


def sheet_layout(spec: TargetSpec, paper) -> SheetLayout:
    """Where the pattern, scale bar and text go on ``paper``; ValueError if it does not fit."""
    W, H = paper_size_mm(paper)
    m = SHEET_MARGIN_MM
    R = spec.extent_mm
    head, foot = 14.0, 40.0  # heights of the text blocks above and below the pattern
    need_w, need_h = 2 * R + 2 * m, 2 * R + 2 * m + head + foot + 6.0
    if need_w > W or need_h > H:
        raise ValueError(f"the pattern ({_fmt(2 * R)} mm across, {_fmt(need_w)} x {_fmt(need_h)} mm with "
                         f"margins and text) does not fit on {_fmt(W)} x {_fmt(H)} mm paper; "
                         f"use smaller radii or larger paper (e.g. a3)")
    spare = H - need_h
    top = m + spare / 3.0
    cx, cy = W / 2.0, top + head + 3.0 + R
    x0 = max(m, cx - R)
    texts = [(x0, top + 5.0, 4.2, "PRINT AT 100 % / ACTUAL SIZE - no 'fit to page', no scaling"),
             (x0, top + 10.5, 3.0, "Check with a ruler: the bar below the target must measure exactly 50 mm.")]
    y = cy + R + 6.0
    bar = [(x0, y, 50.0, 1.5)]  # the 50 mm scale bar, with 0.2 mm ticks every 10 mm inside its ends
    bar += [(min(max(x0 + 10.0 * k - 0.1, x0), x0 + 49.8), y - 1.5, 0.2, 3.0) for k in range(6)]
    texts.append((x0 + 53.0, y + 1.5, 3.5, "50 mm"))
    lines = [f"Rings (stroke centre lines): outer radius {_fmt(spec.r_outer_mm)} mm, inner radius "
             f"{_fmt(spec.r_inner_mm)} mm, stroke {_fmt(spec.stroke_mm)} mm "
             f"(diameters {_fmt(2 * spec.r_outer_mm)} / {_fmt(2 * spec.r_inner_mm)} mm)."]
    if spec.marks:
        lines.append(f"Angle marks: {spec.n_sectors} sectors of {_fmt(360.0 / spec.n_sectors)}\u00b0 between radius "
                     f"{_fmt(spec.mark_r0_mm)} and {_fmt(spec.mark_r1_mm)} mm; 0\u00b0 points right, angles clockwise.")
    lines.append(f"turntable calibrate IMAGE... --r-outer {_fmt(spec.r_outer_mm)} --r-inner "
                 f"{_fmt(spec.r_inner_mm)} --stroke {_fmt(spec.stroke_mm)}")
    lines.append("Lay the sheet flat on the turntable with the centre on the axis; keep the rings and marks clean.")
    for i, line in enumerate(lines):
        texts.append((x0, y + 10.0 + 5.5 * i, 2.8, line))
    return SheetLayout(W, H, (cx, cy), (x0, y, 50.0), tuple(bar), tuple(texts))


# ----------------------------------------------------------------------------- writers

def write_pattern(path, spec: TargetSpec, paper="a4", dpi: float = 300, background="white") -> str:
    """Write the printable target sheet to ``path`` (.pdf, .svg or .png), true scale.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; the extension picks the format.
    spec : TargetSpec
    paper : str or (float, float)
        ``"a4"``, ``"letter"``, ``"a3"``, ``"WxH"`` or ``(W, H)``, mm, portrait.
    dpi : float
        Resolution of a PNG (stored in its pHYs chunk); ignored for vector formats.
    background : str or (int, int, int)
        Ground colour of the printable area: a name of ``BACKGROUND_COLOURS``,
        ``#RRGGBB`` or sRGB 0-255 values (checked by :func:`parse_background`).

    Returns
    -------
    str
        The path written.

    Raises
    ------
    ValueError
        Unknown extension or paper, bad dpi, a pattern that does not fit the
        paper, or a ground colour that is not one or is too dark.
    """
    path = os.fspath(path)
    ground = parse_background(background if isinstance(background, str) else _hex(background))
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".pdf", ".svg", ".png"):
        raise ValueError(f"unsupported output format {ext or '(none)'!r}: use .pdf, .svg or .png")
    sheet = sheet_layout(spec, paper)
    if ext == ".svg":
        data = _svg(spec, sheet, ground).encode("utf-8")
    elif ext == ".pdf":
        data = _pdf(spec, sheet, ground)
    else:
        if not (dpi > 0 and math.isfinite(dpi)):
            raise ValueError(f"dpi must be positive, got {dpi}")
        data = _png(spec, sheet, float(dpi), ground)
    with open(path, "wb") as f:
        f.write(data)
    return path


def _sector_points(cx, cy, t0, t1, r0, r1):
    """End points of an annulus sector: outer start/end, inner end/start (mm, y down)."""
    c0, s0, c1, s1 = math.cos(t0), math.sin(t0), math.cos(t1), math.sin(t1)
    return ((cx + r1 * c0, cy + r1 * s0), (cx + r1 * c1, cy + r1 * s1),
            (cx + r0 * c1, cy + r0 * s1), (cx + r0 * c0, cy + r0 * s0))


def _printable_mm(sheet: SheetLayout) -> tuple[float, float, float, float]:
    """The printable area (x, y, w, h), mm: the sheet less ``SHEET_MARGIN_MM`` on every side."""
    m = SHEET_MARGIN_MM
    return m, m, sheet.width_mm - 2 * m, sheet.height_mm - 2 * m


def _svg(spec: TargetSpec, sheet: SheetLayout, ground=(255, 255, 255)) -> str:
    from xml.sax.saxutils import escape

    W, H = sheet.width_mm, sheet.height_mm
    cx, cy = sheet.centre_mm
    f = "{:.4f}".format
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<svg xmlns="http://www.w3.org/2000/svg" width="{_fmt(W)}mm" height="{_fmt(H)}mm" '
           f'viewBox="0 0 {_fmt(W)} {_fmt(H)}">',
           f'<title>turntable target r_outer={_fmt(spec.r_outer_mm)} r_inner={_fmt(spec.r_inner_mm)} '
           f'stroke={_fmt(spec.stroke_mm)} mm</title>',
           f'<rect x="0" y="0" width="{_fmt(W)}" height="{_fmt(H)}" fill="#ffffff"/>']
    if tuple(ground) != (255, 255, 255):
        gx, gy, gw, gh = _printable_mm(sheet)
        out.append(f'<rect id="ground" x="{_fmt(gx)}" y="{_fmt(gy)}" width="{_fmt(gw)}" height="{_fmt(gh)}" '
                   f'fill="{_hex(ground)}"/>')
    for R in (spec.r_outer_mm, spec.r_inner_mm):
        out.append(f'<circle cx="{f(cx)}" cy="{f(cy)}" r="{f(R)}" fill="none" stroke="#000000" '
                   f'stroke-width="{f(spec.stroke_mm)}"/>')
    for t0, t1, r0, r1 in mark_cells(spec):
        a, b, c, d = _sector_points(cx, cy, t0, t1, r0, r1)
        large = 1 if t1 - t0 > math.pi else 0
        out.append(f'<path fill="#000000" d="M{f(a[0])},{f(a[1])} A{f(r1)},{f(r1)} 0 {large} 1 {f(b[0])},{f(b[1])} '
                   f'L{f(c[0])},{f(c[1])} A{f(r0)},{f(r0)} 0 {large} 0 {f(d[0])},{f(d[1])} Z"/>')
    for x, y, w, h in sheet.rects:
        out.append(f'<rect x="{f(x)}" y="{f(y)}" width="{f(w)}" height="{f(h)}" fill="#000000"/>')
    for x, y, size, text in sheet.texts:
        out.append(f'<text x="{f(x)}" y="{f(y)}" font-size="{f(size)}" '
                   f'font-family="Helvetica, Arial, sans-serif" fill="#000000">{escape(text)}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def _bezier_arc(cx, cy, r, t0, t1):
    """Cubic Bézier segments (each ≤ 90 deg) of the arc from t0 to t1: [(p1, p2, p3)], mm."""
    n = max(1, int(math.ceil(abs(t1 - t0) / (math.pi / 2) - 1e-9)))
    segs = []
    for i in range(n):
        a0 = t0 + (t1 - t0) * i / n
        a1 = t0 + (t1 - t0) * (i + 1) / n
        k = 4.0 / 3.0 * math.tan((a1 - a0) / 4.0)
        p0 = (math.cos(a0), math.sin(a0))
        p3 = (math.cos(a1), math.sin(a1))
        p1 = (p0[0] - k * p0[1], p0[1] + k * p0[0])
        p2 = (p3[0] + k * p3[1], p3[1] - k * p3[0])
        segs.append(tuple((cx + r * p[0], cy + r * p[1]) for p in (p1, p2, p3)))
    return segs


def _pdf_text(s: str) -> str:
    raw = s.encode("cp1252", errors="replace")
    return "".join(f"\\{chr(b)}" if b in b"()\\" else (chr(b) if 32 <= b < 127 else f"\\{b:03o}") for b in raw)


def _pdf(spec: TargetSpec, sheet: SheetLayout, ground=(255, 255, 255)) -> bytes:
    W, H = sheet.width_mm, sheet.height_mm
    cx, cy = sheet.centre_mm
    f = "{:.4f}".format
    ops = [f"{PT_PER_MM:.9f} 0 0 {-PT_PER_MM:.9f} 0 {H * PT_PER_MM:.4f} cm"]  # mm, y down
    if tuple(ground) != (255, 255, 255):  # the ground first, the ink over it
        r, g, b = (v / 255.0 for v in ground)
        ops.append(f"{r:.4f} {g:.4f} {b:.4f} rg " + " ".join(f(v) for v in _printable_mm(sheet)) + " re f")
    ops.append(f"0 g 0 G {f(spec.stroke_mm)} w")
    for R in (spec.r_outer_mm, spec.r_inner_mm):
        ops.append(f"{f(cx + R)} {f(cy)} m")
        ops += [" ".join(f"{f(x)} {f(y)}" for x, y in seg) + " c" for seg in _bezier_arc(cx, cy, R, 0, 2 * math.pi)]
        ops.append("h S")
    for t0, t1, r0, r1 in mark_cells(spec):
        a, _, c, _ = _sector_points(cx, cy, t0, t1, r0, r1)
        ops.append(f"{f(a[0])} {f(a[1])} m")
        ops += [" ".join(f"{f(x)} {f(y)}" for x, y in seg) + " c" for seg in _bezier_arc(cx, cy, r1, t0, t1)]
        ops.append(f"{f(c[0])} {f(c[1])} l")
        ops += [" ".join(f"{f(x)} {f(y)}" for x, y in seg) + " c" for seg in _bezier_arc(cx, cy, r0, t1, t0)]
        ops.append("h f")
    for x, y, w, h in sheet.rects:
        ops.append(f"{f(x)} {f(y)} {f(w)} {f(h)} re f")
    for x, y, size, text in sheet.texts:  # flip the text matrix back so glyphs stand upright
        ops.append(f"BT /F1 {f(size)} Tf 1 0 0 -1 {f(x)} {f(y)} Tm ({_pdf_text(text)}) Tj ET")
    content = zlib.compress("\n".join(ops).encode("latin-1"))
    wpt, hpt = W * PT_PER_MM, H * PT_PER_MM
    objs = [b"<< /Type /Catalog /Pages 2 0 R >>",
            b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
            (f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {wpt:.2f} {hpt:.2f}] "
             f"/Resources << /Font << /F1 5 0 R >> >> /Contents 4 0 R >>").encode(),
            b"<< /Length %d /Filter /FlateDecode >>\nstream\n" % len(content) + content + b"\nendstream",
            b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>",
            (f"<< /Title (turntable target r_outer {_fmt(spec.r_outer_mm)} mm r_inner {_fmt(spec.r_inner_mm)} mm "
             f"stroke {_fmt(spec.stroke_mm)} mm) /Producer (turntable pattern) >>").encode()]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for i, body in enumerate(objs, start=1):
        offsets.append(len(out))
        out += b"%d 0 obj\n" % i + body + b"\nendobj\n"
    xref = len(out)
    out += b"xref\n0 %d\n0000000000 65535 f \n" % (len(objs) + 1)
    out += b"".join(b"%010d 00000 n \n" % o for o in offsets)
    out += b"trailer\n<< /Size %d /Root 1 0 R /Info 6 0 R >>\nstartxref\n%d\n%%%%EOF\n" % (len(objs) + 1, xref)
    return bytes(out)


def _png(spec: TargetSpec, sheet: SheetLayout, dpi: float, ground=(255, 255, 255)) -> bytes:
    import io

    from PIL import Image, ImageDraw, ImageFont

    mm_per_px = MM_PER_INCH / dpi
    w_px = int(round(sheet.width_mm / mm_per_px))
    h_px = int(round(sheet.height_mm / mm_per_px))
    img = np.full((h_px, w_px), 255, dtype=np.uint8)
    cx, cy = sheet.centre_mm
    R = spec.extent_mm + 1.0
    # pixel (i, j) has its centre at ((j + 0.5), (i + 0.5)) * mm_per_px on the sheet
    j0, j1 = max(int((cx - R) / mm_per_px), 0), min(int(math.ceil((cx + R) / mm_per_px)), w_px)
    i0, i1 = max(int((cy - R) / mm_per_px), 0), min(int(math.ceil((cy + R) / mm_per_px)), h_px)
    x_mm = (np.arange(j0, j1) + 0.5) * mm_per_px - cx
    z_mm = (np.arange(i0, i1) + 0.5) * mm_per_px - cy
    white = _coverage_white(spec, x_mm, z_mm, mm_per_px, 3)
    img[i0:i1, j0:j1] = np.round(white * 255.0).astype(np.uint8)
    for x, y, w, h in sheet.rects:  # area coverage, so sub-pixel widths keep their ink
        _fill_rect(img, x / mm_per_px - 0.5, y / mm_per_px - 0.5, w / mm_per_px, h / mm_per_px)
    pil = Image.fromarray(img, mode="L")
    draw = ImageDraw.Draw(pil)
    for x, y, size, text in sheet.texts:
        try:
            font = ImageFont.load_default(size=max(size / mm_per_px, 4.0))
        except TypeError:  # Pillow < 10.1: fixed bitmap font
            font = ImageFont.load_default()
        draw.text((x / mm_per_px, y / mm_per_px), text, fill=0, font=font, anchor="ls")
    if tuple(ground) != (255, 255, 255):  # ink over the ground: the grey sheet's paper fraction times the ground
        gx, gy, gw, gh = _printable_mm(sheet)
        rgb = np.full((h_px, w_px, 3), 255.0, np.float32)
        rows = slice(int(round(gy / mm_per_px)), int(round((gy + gh) / mm_per_px)))
        cols = slice(int(round(gx / mm_per_px)), int(round((gx + gw) / mm_per_px)))
        rgb[rows, cols] = np.asarray(ground, np.float32)
        paper = np.asarray(pil, dtype=np.float32) / 255.0
        pil = Image.fromarray(np.round(paper[..., None] * rgb).astype(np.uint8), mode="RGB")
    buf = io.BytesIO()
    pil.save(buf, format="PNG", dpi=(dpi, dpi))
    return buf.getvalue()


def _fill_rect(img: np.ndarray, x0: float, y0: float, w: float, h: float) -> None:
    """Darken ``img`` by the ink coverage of the rectangle; pixel centres at integers."""
    i0, j0 = max(int(math.floor(y0)), 0), max(int(math.floor(x0)), 0)
    i1, j1 = min(int(math.ceil(y0 + h)) + 1, img.shape[0]), min(int(math.ceil(x0 + w)) + 1, img.shape[1])

    def cover(a0, length, k):
        return np.clip(np.minimum(k + 0.5, a0 + length) - np.maximum(k - 0.5, a0), 0.0, 1.0)

    cov = cover(y0, h, np.arange(i0, i1))[:, None] * cover(x0, w, np.arange(j0, j1))[None, :]
    img[i0:i1, j0:j1] = np.round(img[i0:i1, j0:j1] * (1.0 - cov)).astype(np.uint8)
