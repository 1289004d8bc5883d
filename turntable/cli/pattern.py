"""``turntable pattern``: write the printable target (PDF, SVG or PNG) at true scale.

The sheet carries the two rings, the angle marks (unless ``--no-marks``), the
printed radii and stroke, a 50 mm scale bar and a "print at 100 %" note, in
black on white paper or, with ``--background COLOUR``, on a coloured ground
(for white objects: README, "Scanning a white object").
"""

from __future__ import annotations

import logging
from pathlib import Path

from calib.target import TargetSpec

from ..errors import UserError

log = logging.getLogger(__name__)

FORMATS = (".pdf", ".svg", ".png")


def add_arguments(parser) -> None:
    parser.add_argument("out", metavar="OUT", help="output file: .pdf, .svg or .png")
    g = parser.add_argument_group("target (millimetres, stroke centre lines)")
    g.add_argument("--r-outer", type=float, default=80.0, metavar="MM", help="outer ring radius (default 80)")
    g.add_argument("--r-inner", type=float, default=50.0, metavar="MM", help="inner ring radius (default 50)")
    g.add_argument("--stroke", type=float, default=3.0, metavar="MM", help="stroke width (default 3)")
    g.add_argument("--no-marks", action="store_true", help="rings only, without the angle marks")
    parser.add_argument("--paper", default="a4", metavar="SIZE",
                        help="a4 (default), letter, a3, or WxH in millimetres (e.g. 300x300)")
    parser.add_argument("--dpi", type=float, default=300.0, help="PNG resolution (default 300)")
    parser.add_argument("--background", default="white", metavar="COLOUR",
                        help="ground colour of the printable area under the black ink: white (default), "
                             "green (recommended for white objects), blue, grey, or #RRGGBB with a relative "
                             "luminance of at least 0.35")


def run(args) -> int:
    from ..pattern import paper_size_mm, parse_background, write_pattern

    out = Path(args.out)
    if out.suffix.lower() not in FORMATS:
        raise UserError(f"{out}: unsupported format {out.suffix or '(no extension)'!r}; use .pdf, .svg or .png")
    try:
        spec = TargetSpec(r_outer_mm=args.r_outer, r_inner_mm=args.r_inner, stroke_mm=args.stroke,
                          marks=not args.no_marks)
        paper = paper_size_mm(args.paper)
    except ValueError as exc:
        raise UserError(f"{out}: {exc}") from None
    try:
        ground = parse_background(args.background)
    except ValueError as exc:
        raise UserError(f"{out}: --background {exc}") from None
    if not args.dpi > 0:
        raise UserError(f"{out}: --dpi must be positive, got {args.dpi:g}")
    if not out.parent.is_dir():
        raise UserError(f"{out}: folder {out.parent} does not exist")
    try:
        write_pattern(out, spec, paper=paper, dpi=args.dpi, background=ground)
    except ValueError as exc:
        raise UserError(f"{out}: {exc}") from None
    except OSError as exc:
        raise UserError(f"{out}: cannot write: {exc.strerror or exc}") from None
    log.info("wrote %s", out)
    print(f"wrote {out} ({paper[0]:g} x {paper[1]:g} mm): print it at 100 % / actual size and check the 50 mm bar")
    return 0
