"""Run ``turntable reconstruct`` into an OUT whose disk fills up, and say what happened (JSON on stdout).

    python tests/disk_full.py [--rlimit] GOOD_OUT BUDGETS_JSON -- RECONSTRUCT_ARGS...

For each budget (bytes of free space), a copy of ``GOOD_OUT`` (a finished
run's output folder) is put on a disk with that much room left, and the
reconstruct command (``RECONSTRUCT_ARGS``, which must contain ``--out OUT``;
OUT is replaced by the copy) runs there. Reported per budget: exit code,
seconds, the last line of stderr, whether every file of the previous output is
still byte-identical (or the run finished and published a whole new set), and
what temporary files were left.

The disk is a tmpfs of the right size where this process may mount one (root,
or inside ``unshare -rm``), otherwise every file written is limited to the
budget (``RLIMIT_FSIZE``: a write past it fails with EFBIG, as a full disk
fails with ENOSPC). ``"mode"`` in the output says which.
"""

from __future__ import annotations

import hashlib
import json
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from turntable.outdir import leftovers

FILLER = "filler.bin"


def published_digests(out: Path) -> dict[str, str]:
    """Relative path -> BLAKE2b of every published file in OUT (the stage cache left out)."""
    return {str(p.relative_to(out)): hashlib.blake2b(p.read_bytes(), digest_size=16).hexdigest()
            for p in sorted(out.rglob("*")) if p.is_file() and p.relative_to(out).parts[0] != ".turntable"}


def model_digests(out: Path) -> dict[str, str]:
    """:func:`published_digests` of the model files only (model.glb, .ply, .obj)."""
    return {k: v for k, v in published_digests(out).items() if k.startswith("model.")}


def run_leftovers(out: Path) -> list[str]:
    """What a run left behind (turntable.outdir.leftovers), and any other hidden file in OUT or its cache."""
    left = {*leftovers(out), *(p for p in out.glob(".*") if p.is_file()), *(out / ".turntable").glob(".*")}
    return sorted(str(p.relative_to(out)) for p in left)


def tmpfs_prefix() -> list[str] | None:
    """The command prefix under which ``mount -t tmpfs`` works here: [] (root), ["unshare", "-rm"], or None."""
    probe = "d=$(mktemp -d) && mount -t tmpfs -o size=1m tmpfs $d && umount $d; r=$?; rmdir $d; exit $r"
    for prefix in ([], ["unshare", "-rm"]):
        if prefix and shutil.which("unshare") is None:
            continue
        try:
            if subprocess.run([*prefix, "sh", "-c", probe], capture_output=True, timeout=20).returncode == 0:
                return prefix
        except (OSError, subprocess.SubprocessError):
            pass
    return None


def _mount_tmpfs(where: Path, size: int) -> bool:
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)], capture_output=True)
    return r.returncode == 0


def _fill(disk: Path, leave: int) -> None:
    """Write a filler file so that ``leave`` bytes stay free (to tmpfs's page granularity)."""
    free = shutil.disk_usage(disk).free
    with open(disk / FILLER, "wb") as fh:
        fh.write(b"\0" * max(0, free - leave))


def _limit_files(budget: int):
    def pre() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG) instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (budget, budget))
    return pre


def main(argv: list[str]) -> int:
    force_rlimit = argv[:1] == ["--rlimit"]  # use RLIMIT_FSIZE even where a tmpfs could be mounted
    argv = argv[force_rlimit:]
    good, budgets, args = Path(argv[0]), json.loads(argv[1]), argv[3:]
    i = args.index("--out")
    before = published_digests(good)
    size = sum(p.stat().st_size for p in good.rglob("*") if p.is_file())
    results, mode = [], None
    for budget in budgets:
        scratch = Path(tempfile.mkdtemp(prefix="turntable-disk-"))
        disk = scratch / "disk"
        disk.mkdir()
        # the copy of OUT, its stage cache, the new run's outputs (up to twice the old) and the budget
        mounted = not force_rlimit and _mount_tmpfs(disk, 4 * size + budget + (8 << 20))
        mode = "tmpfs" if mounted else "RLIMIT_FSIZE"
        out = disk / "scan"
        shutil.copytree(good, out)
        if mounted:
            _fill(disk, budget)
        cmd = [sys.executable, "-m", "turntable", *args[:i + 1], str(out), *args[i + 2:]]
        t0 = time.perf_counter()
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=120,
                               preexec_fn=None if mounted else _limit_files(budget))
            code, err = r.returncode, r.stderr
        except subprocess.TimeoutExpired as exc:
            code, err = "timeout", (exc.stderr or b"").decode(errors="replace") if isinstance(exc.stderr, bytes) \
                else (exc.stderr or "")
        seconds = time.perf_counter() - t0
        after = published_digests(out)
        published = json.loads((out / ".turntable" / "published.json").read_text())["files"] \
            if (out / ".turntable" / "published.json").is_file() else None
        results.append({
            "budget": budget, "exit": code, "seconds": round(seconds, 2),
            "stderr": [line for line in err.strip().splitlines() if line][-1:] or [""],
            "previous_intact": after == before,
            "new_set_whole": published is not None and sorted(after) == sorted(
                str(p.relative_to(out)) for n in published for p in
                ([out / n] if (out / n).is_file() else (out / n).rglob("*")) if p.is_file()),
            "leftovers": run_leftovers(out),
        })
        if mounted:
            subprocess.run(["umount", str(disk)], capture_output=True)
        shutil.rmtree(scratch, ignore_errors=True)
    print(json.dumps({"mode": mode, "results": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
