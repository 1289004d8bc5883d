"""Command-line arguments shared by the commands that see the printed target."""

from __future__ import annotations

import math

from calib.target import TargetSpec

from ..errors import UserError

__all__ = ["add_target_arguments", "target_from_args"]


def add_target_arguments(parser, required: bool = True, optional_note: str = "") -> None:
    """``--r-outer``, ``--r-inner``, ``--stroke``: shared by every command that sees the target.

    ``required=False`` leaves the check to the command (``optional_note`` says when they may be left out).
    """
    g = parser.add_argument_group(f"target (millimetres, stroke centre lines{optional_note})")
    g.add_argument("--r-outer", type=float, required=required, metavar="MM", help="outer ring radius")
    g.add_argument("--r-inner", type=float, required=required, metavar="MM", help="inner ring radius")
    g.add_argument("--stroke", type=float, default=3.0, metavar="MM", help="nominal stroke width (default 3)")


def target_from_args(args) -> TargetSpec:
    for flag, value in (("--r-outer", args.r_outer), ("--r-inner", args.r_inner), ("--stroke", args.stroke)):
        if not (value is not None and math.isfinite(value) and value > 0):
            raise UserError(f"{flag} must be a positive number of millimetres, got {value}")
    pp = getattr(args, "principal_point", None)
    if pp is not None and not all(math.isfinite(v) for v in pp):
        raise UserError(f"--principal-point must be two finite pixel coordinates, got {pp[0]} {pp[1]}")
    try:
        return TargetSpec(r_outer_mm=args.r_outer, r_inner_mm=args.r_inner, stroke_mm=args.stroke)
    except ValueError as exc:
        raise UserError(str(exc)) from None
