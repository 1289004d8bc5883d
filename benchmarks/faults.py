"""Fault classes against a whole default run (issue 10): a markdown table of what each did to OUT.

``tests/test_faults.py`` runs the same classes quickly (known cameras and
masks, no fusion). This runs them as a user does — automatic calibration and
silhouettes, fusion — on one rendered sequence (``turntable synth``, 12 frames
640x480), each case in a fresh copy of a finished OUT:

* ``disk full <budget>``: OUT on a tmpfs with that much room left (root, or
  ``unshare -rm`` where user namespaces are allowed; otherwise skipped),
  ``--overwrite`` so every stage writes: exit code, seconds, file named;
* ``SIGKILL at t``: the run killed t seconds in, then a plain re-run: is the
  model byte-identical to the first run's, are temporary files left;
* ``SIGTERM at t``: exit code, OUT unchanged, nothing left behind;
* ``two at once``: a second run started while the first runs: refused or
  waits, never mixed;
* ``cache <file> <damage>``: a stage file truncated / emptied / one byte
  flipped: recomputed (with a note), model identical;
* ``edited <input>``: a mask, one frame's pixels: recomputed (volume changes).

"previous intact" compares every published file byte for byte with the copy's.

Usage: ``python benchmarks/faults.py [--keep DIR] [--quick]`` (``--quick``: 8 frames, fewer cases).
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from disk_full import model_digests, published_digests, run_leftovers, tmpfs_prefix  # noqa: E402

PY = sys.executable


def _cmd(seq: Path, out: Path, *extra: str) -> list[str]:
    return [PY, "-m", "turntable", "reconstruct", str(seq / "images"), "--r-outer", "80", "--r-inner", "50",
            "--stroke", "3", "--out", str(out), "--quiet", *extra]


def _run(cmd: list[str], timeout: float = 900) -> tuple[int, float, str]:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT)
    last = [line for line in r.stderr.strip().splitlines() if line][-1:] or [""]
    return r.returncode, time.perf_counter() - t0, last[0]


def _volume(out: Path) -> float:
    return json.loads((out / "summary.json").read_text())["mesh"]["volume_cm3"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, help="work here (kept) instead of a temporary folder")
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    work = a.keep or Path(tempfile.mkdtemp(prefix="turntable-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    seq = work / "seq"
    frames = 8 if a.quick else 12
    if not (seq / "images").is_dir():
        subprocess.run([PY, "-m", "turntable", "synth", str(seq), "--object", "vase", "--frames", str(frames),
                        "--step-deg", str(360 / frames), "--size", "640x480", "--focal-px", "760",
                        "--elevation-deg", "35", "--distance-mm", "430", "--seed", "3", "--overwrite"],
                       check=True, capture_output=True, cwd=ROOT)
    good = work / "good"
    if not (good / "summary.json").is_file():
        code, secs, _ = _run(_cmd(seq, good, "--overwrite"))
        assert code == 0, code
    else:
        secs = json.loads((good / "summary.json").read_text())["time_s"]["total"]
    ref = published_digests(good)
    rows = []

    def copy(name: str) -> Path:
        out = work / "cases" / name
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(good, out)
        return out

    def row(case, code, seconds, intact, model_same, left, said):
        rows.append((case, code, f"{seconds:.1f}", intact, model_same, ", ".join(left) or "none", said[:110]))

    # -- disk full
    mount = tmpfs_prefix()
    if mount is None:
        rows.append(("disk full", "skipped: cannot mount a tmpfs here", "", "", "", "", ""))
    else:
        pub = sum(p.stat().st_size for p in good.rglob("*") if p.is_file() and ".turntable" not in p.parts)
        budgets = [0, 1 << 20, pub // 2] if a.quick else [0, 256 << 10, 1 << 20, pub // 2, pub - (64 << 10)]
        args = _cmd(seq, Path("OUT"), "--overwrite")[3:]
        r = subprocess.run([*mount, PY, str(ROOT / "tests" / "disk_full.py"), str(good), json.dumps(budgets), "--",
                            *args], capture_output=True, text=True, timeout=3600, cwd=ROOT)
        for res in json.loads(r.stdout)["results"]:
            row(f"disk full, {res['budget'] >> 10} KiB free", res["exit"], res["seconds"], res["previous_intact"],
                "-", res["leftovers"], res["stderr"][0].replace(str(good), "OUT"))

    # -- SIGKILL / SIGTERM at points of a run
    points = [0.2, 0.6] if a.quick else [0.1, 0.3, 0.5, 0.7, 0.9, 0.97]
    for sig in (signal.SIGKILL, signal.SIGTERM):
        for f in points if sig == signal.SIGKILL else points[1:2]:
            out = copy(f"{sig.name}_{f}")
            p = subprocess.Popen(_cmd(seq, out, "--overwrite"), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                 text=True, cwd=ROOT)
            time.sleep(f * secs)
            p.send_signal(sig)
            _, err = p.communicate()
            intact = published_digests(out) == ref
            whole = intact or model_digests(out) == model_digests(good)
            t0 = time.perf_counter()
            code, s2, said = _run(_cmd(seq, out))  # the user runs it again
            row(f"{sig.name} at {f * secs:.0f} s, then re-run", f"{p.returncode} then {code}",
                time.perf_counter() - t0, f"{'yes' if intact else 'new set, whole' if whole else 'NO'}",
                model_digests(out) == model_digests(good), run_leftovers(out),
                (err.strip().splitlines() or [""])[-1] if sig == signal.SIGTERM else said)

    # -- two runs at once
    out = copy("two")
    p1 = subprocess.Popen(_cmd(seq, out, "--overwrite"), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          text=True, cwd=ROOT)
    time.sleep(2.0)
    code2, s2, said2 = _run(_cmd(seq, out, "--overwrite", "--max-faces", "5000"))
    _, err1 = p1.communicate()
    row("two runs into one OUT", f"{p1.returncode} and {code2}", s2, "-", model_digests(out) == model_digests(good),
        run_leftovers(out), said2.replace(str(out), "OUT"))

    # -- damaged cache files
    for name in ("silhouettes", "hull", "detections"):
        for how in ("truncated", "empty", "flipped byte"):
            out = copy(f"cache_{name}_{how}")
            f = out / ".turntable" / f"{name}.npz"
            data = bytearray(f.read_bytes())
            if how == "truncated":
                data = data[: len(data) // 2]
            elif how == "empty":
                data = bytearray()
            else:
                data[len(data) // 3] ^= 0xFF
            f.write_bytes(bytes(data))
            code, s, said = _run(_cmd(seq, out))
            row(f"cache {name}.npz {how}", code, s, "-", model_digests(out) == model_digests(good), run_leftovers(out),
                said)
            if a.quick:
                break

    # -- edited inputs (a copy of the sequence, edited in place between runs)
    import cv2

    eseq = work / "seq_edit"
    shutil.rmtree(eseq, ignore_errors=True)
    shutil.copytree(seq, eseq)
    out = work / "cases" / "edited"
    shutil.rmtree(out, ignore_errors=True)
    code, s, _ = _run(_cmd(eseq, out))
    v0 = _volume(out)
    frame = sorted((eseq / "images").iterdir())[2]
    img = cv2.imread(str(frame))
    h, w = img.shape[:2]
    img[h // 4: h // 2, w // 2 - 40: w // 2 + 40] = 20  # a dark block where the object stands
    cv2.imwrite(str(frame), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    code, s, said = _run(_cmd(eseq, out))
    summary = json.loads((out / "summary.json").read_text())
    rows.append(("edited: a block of one frame's pixels", code, f"{s:.1f}", "-",
                 f"volume {v0:.1f} -> {_volume(out):.1f} cm³", ", ".join(run_leftovers(out)) or "none",
                 "stages recomputed: " + ", ".join(k for k in summary["time_s"] if k not in ("total", "recording"))))

    print(f"\nfaults: {frames} frames 640x480, automatic cameras and silhouettes, fusion; one clean run {secs:.0f} s\n")
    print("| case | exit | s | previous intact | model = first run | left behind | said |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(str(x) for x in r) + " |")
    if not a.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
