"""Time and peak memory of ``turntable calibrate-sequence`` against the number of frames (issue 10).

One rendered turntable sequence (``turntable synth``) is calibrated with
``--frames N`` (N frames spread evenly over it) for each N, each run its own
``python -m turntable`` subprocess; its peak resident memory is that child's
``ru_maxrss`` (``os.wait4``). Per N it prints the wall time, the part of it
after the per-frame stage (the joint fit: the time after the progress line
``2N/2N``, i.e. the fit, the marks read again and writing cameras.json),
the peak memory, seconds per frame for both, and the focal length found.

Cost should be linear in N: seconds per frame about constant down the table.
``--tree DIR`` runs another checkout's code (e.g. ``git archive HEAD | tar -x
-C DIR``) to compare before and after a change.

    .venv/bin/turntable synth /tmp/seq500 --frames 500 --size 640x480 --focal-px 750 --step-deg 0.72 --seed 1
    nice .venv/bin/python benchmarks/sequence_scaling.py /tmp/seq500/images [--frames 60 120 250 500] [--tree DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_once(images: Path, n: int, tree: Path, timeout_s: float) -> dict:
    """One calibrate-sequence subprocess: wall s, per-frame stage s, peak MB, focal px (None on failure)."""
    with tempfile.TemporaryDirectory() as tmp:
        out, log = Path(tmp) / "cameras.json", Path(tmp) / "stderr.txt"
        cmd = [sys.executable, "-m", "turntable", "calibrate-sequence", str(images), "--r-outer", "80",
               "--r-inner", "50", "--stroke", "3", "--frames", str(n), "--out", str(out)]
        env = {**os.environ, "PYTHONPATH": str(tree)}
        t0 = time.perf_counter()
        with open(log, "w") as err:
            proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.DEVNULL, stderr=err)
            timed_out = False
            while True:  # os.wait4 reaps the child and gives its own peak memory
                pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                if pid:
                    break
                if time.perf_counter() - t0 > timeout_s:
                    proc.kill()
                    timed_out = True
                    _, status, usage = os.wait4(proc.pid, 0)
                    break
                time.sleep(0.1)
        wall = time.perf_counter() - t0
        text = log.read_text()
        per_frame = [float(m.group(1)) for m in re.finditer(rf"{2 * n}/{2 * n} \(([\d.]+) s\)", text)]
        focal = json.loads(out.read_text())["intrinsics"]["K"][0][0] if out.exists() else None
        return {"frames": n, "wall_s": wall, "per_frame_stage_s": per_frame[-1] if per_frame else float("nan"),
                "peak_mb": usage.ru_maxrss / 1024, "focal_px": focal, "timed_out": timed_out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", type=Path, help="folder of a rendered turntable sequence")
    ap.add_argument("--frames", type=int, nargs="+", default=[60, 120, 250, 500])
    ap.add_argument("--tree", type=Path, default=ROOT, help="checkout whose code runs (default: this one)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per run before it is stopped")
    args = ap.parse_args(argv)
    print(f"calibrate-sequence on {args.images} (code: {args.tree})")
    print(f"{'frames':>6} {'wall s':>8} {'s/frame':>8} {'frames s':>9} {'fit s':>8} {'fit s/frame':>11} "
          f"{'peak MB':>8} {'f px':>9}")
    for n in args.frames:
        r = run_once(args.images.resolve(), n, args.tree.resolve(), args.timeout)
        fit = r["wall_s"] - r["per_frame_stage_s"]
        focal = f"{r['focal_px']:9.3f}" if r["focal_px"] is not None else ("  timeout" if r["timed_out"] else "   failed")
        print(f"{n:>6} {r['wall_s']:8.1f} {r['wall_s'] / n:8.3f} {r['per_frame_stage_s']:9.1f} {fit:8.1f} "
              f"{fit / n:11.4f} {r['peak_mb']:8.0f} {focal}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
