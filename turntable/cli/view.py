"""``turntable view OUT``: open the Rerun recording of a reconstruction."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from ..errors import UserError


def add_arguments(parser) -> None:
    parser.add_argument("target", metavar="OUT", help="an output folder of `reconstruct`, or a .rrd file")


def viewer_command(target: str | Path) -> list[str]:
    """The command that opens ``target`` (an OUT folder or a .rrd) in the Rerun viewer."""
    p = Path(target)
    rrd = p / "recording.rrd" if p.is_dir() else p
    if not rrd.is_file():
        raise UserError(f"{rrd}: no recording found (run `turntable reconstruct ... --out {p}` first)")
    viewer = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not Path(viewer).exists():
        raise UserError("the Rerun viewer is not installed (pip install rerun-sdk)")
    return [viewer, str(rrd)]


def run(args) -> int:
    return subprocess.call(viewer_command(args.target))
