"""Many objects at once: one ``reconstruct`` per object, each a Ray task (``turntable batch``).

ROOT holds one folder (or video) per object, or a manifest lists them
(:mod:`turntable.batch_jobs`: the objects, their settings, the digests). Each
object becomes a :class:`Job`: the same :class:`ReconstructOptions` ``turntable
reconstruct`` would build (the command line, overridden by the object's
``turntable.toml``/``turntable.json``), writing ``OUT/<object>/`` through the
same OUT transaction, so a batch output is a set of separate runs. Each job is
one Ray task (:func:`run_job`) declaring ``num_cpus`` and a memory estimate, so
Ray's scheduler packs them on one machine or a cluster; :func:`run_batch` is the
driver.

Failure isolation: a job's bad input (``UserError``) is its result, with the
message as the reason, never retried; a worker that dies (killed, out of memory,
a node lost) is retried by Ray up to ``retries`` times. Every finished job is
recorded in ``OUT/.batch/<object>.json`` with a digest of its inputs (file
names, sizes, mtimes) and options; ``resume`` skips an object whose record
matches and whose output is in place. While a job runs,
``OUT/.batch/<object>.running`` holds one line per attempt (pid, host, node).

At the end: ``OUT/batch.json``, ``OUT/batch.csv`` (one row per object) and
``OUT/index.html`` (a thumbnail per object, ``OUT/thumbnails/<object>.png``,
rendered from its model by ray casting on the CPU): :mod:`turntable.batch_report`.

The public names of those two modules that callers use are importable from here too.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from .batch_jobs import (
    MANIFEST_SUFFIXES,
    PATH_SETTINGS,
    SETTINGS_FILES,
    ManifestEntry,
    check_name,
    check_settings,
    find_objects,
    inputs_digest,
    memory_estimate,
    object_input,
    read_manifest,
    read_settings,
)
from .batch_report import (
    BATCH_DIR,
    STATUSES,
    THUMB_DIR,
    THUMB_PX,
    BatchResult,
    render_thumbnail,
    write_reports,
    write_thumbnail,
)
from .cameras_io import atomic_write_text
from .errors import TERMINATION_SIGNALS, UserError
from .stages.options import ReconstructOptions

__all__ = ["Job", "find_objects", "read_settings", "check_settings", "read_manifest", "ManifestEntry", "check_name",
           "object_input", "inputs_digest", "memory_estimate", "run_batch", "render_thumbnail", "STATUSES",
           "SETTINGS_FILES", "MANIFEST_SUFFIXES", "PATH_SETTINGS", "THUMB_PX"]

FINISHED = ("ok", "warning", "check_failed")  # of STATUSES: the object's OUT holds this run's model


@dataclass(frozen=True)
class Job:
    """One object: its options (None when they could not be built: ``error`` says why)."""

    name: str
    path: Path  # the object's folder or video in ROOT
    opts: ReconstructOptions | None
    error: str | None = None
    digest: str = ""
    memory_bytes: int = 0


# --------------------------------------------------------------------------- one job (runs in a Ray worker)


def _node_id() -> str:
    try:
        import ray

        return ray.get_runtime_context().get_node_id()
    except Exception:  # noqa: BLE001  (outside Ray)
        return ""


def run_job(opts: ReconstructOptions, name: str, out_root: str, threads: int) -> dict:
    """Reconstruct one object into ``OUT/<name>`` and render its thumbnail; a user error is a result.

    Appends ``pid host node`` to ``OUT/.batch/<name>.running`` first (one line per attempt).
    """
    import cv2  # noqa: F401  (loaded before apply_threads, which sets its threads)

    from .cli import apply_threads
    from .reconstruct import reconstruct
    from .recording import Recorder

    apply_threads(threads)  # else OpenCV, loaded later, would run a thread per core of the node, not the job's
    marker = Path(out_root) / BATCH_DIR / f"{name}.running"
    node = _node_id()
    with open(marker, "a") as fh:
        fh.write(f"{os.getpid()} {socket.gethostname()} {node}\n")
    t0 = time.perf_counter()
    rec = Recorder()
    try:
        res = reconstruct(opts, recorder=rec)
    except UserError as exc:
        return {"exit_code": 2, "reason": str(exc), "node": node, "wall_s": time.perf_counter() - t0}
    finally:
        rec.close()
    reason = "; ".join(res.failed_checks) if res.failed_checks else (
        f"unreadable frames: {', '.join(res.unreadable)}" if res.unreadable else "")
    result = {"exit_code": res.exit_code, "reason": reason, "node": node, "wall_s": time.perf_counter() - t0}
    try:
        thumb = write_thumbnail(Path(opts.out), Path(out_root) / THUMB_DIR / f"{name}.png")
        result["thumbnail"] = str(thumb.relative_to(out_root))
    except Exception as exc:  # noqa: BLE001  (the model is there; the overview only lacks its picture)
        result["thumbnail_error"] = f"{type(exc).__name__}: {exc}"
    return result


# --------------------------------------------------------------------------- the batch (the driver)


def _connect(address: str | None) -> bool:
    """Start (or join) Ray; True when this call started the connection (and must shut it down)."""
    import logging

    import ray

    if ray.is_initialized():
        return False
    kw: dict = {"log_to_driver": False, "logging_level": logging.WARNING}
    with _signal_handlers_kept():
        if address is None:
            ray.init(include_dashboard=False, **kw)
        else:
            try:
                ray.init(address=address, **kw)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise UserError(f"--address {address}: cannot connect to a Ray cluster there: {exc}") from None
    return True


@contextlib.contextmanager
def _signal_handlers_kept():
    """Put the termination signals' Python handlers back after the block (main thread only).

    ``ray.init`` installs its own SIGTERM handler (``sys.exit(15)``): a batch sent SIGTERM ended with exit
    15 and no message, where the CLI's handler ends it like Ctrl-C (jobs stopped, the report written, 143).
    """
    import signal
    import threading

    names = [n for n in TERMINATION_SIGNALS if hasattr(signal, n)]
    main = threading.current_thread() is threading.main_thread()
    saved = {getattr(signal, n): signal.getsignal(getattr(signal, n)) for n in names} if main else {}
    try:
        yield
    finally:
        for sig, handler in saved.items():
            if handler is not None:
                signal.signal(sig, handler)


def _record_path(out: Path, name: str) -> Path:
    return out / BATCH_DIR / f"{name}.json"


def _resumable(out: Path, job: Job) -> dict | None:
    """The row of the last run of ``job`` when it finished with the same inputs and options and its output is
    in place; else None."""
    try:
        rec = json.loads(_record_path(out, job.name).read_text())
    except (OSError, ValueError):
        return None
    row = rec.get("row") or {}
    if rec.get("digest") != job.digest or row.get("status") not in FINISHED:
        return None
    if not (out / job.name / "summary.json").is_file():
        return None
    return row


def _row(job: Job, out: Path, result: dict | None, status: str | None = None, reason: str = "") -> dict:
    """One report row: the job's outcome and, for a finished model, what its ``summary.json`` says."""
    row: dict = {"object": job.name, "status": status, "reason": reason, "attempts": 0, "node": "",
                 "frames_used": None, "focal_px": None, "focal_std_px": None, "rms_px": None, "mesh_faces": None,
                 "volume_cm3": None, "watertight": None, "wall_s": None, "time_s": {}, "thumbnail": "",
                 "output": job.name}
    if result is not None:
        code = result.get("exit_code")
        row["status"] = {0: "ok", 1: "warning", 3: "check_failed"}.get(code, "failed")
        row["reason"] = result.get("reason", "")
        row["node"] = result.get("node", "")
        row["wall_s"] = round(result["wall_s"], 2) if result.get("wall_s") is not None else None
        row["thumbnail"] = result.get("thumbnail", "")
    if row["status"] in FINISHED:
        try:
            s = json.loads((out / job.name / "summary.json").read_text())
        except (OSError, ValueError) as exc:
            row["status"], row["reason"] = "failed", f"no readable summary.json: {exc}"
            return row
        mesh = s.get("mesh") or {}
        row.update(frames_used=s.get("frames_used"), focal_px=s.get("focal_px"), focal_std_px=s.get("focal_std_px"),
                   rms_px=s.get("rms_px"), mesh_faces=mesh.get("faces"), volume_cm3=mesh.get("volume_cm3"),
                   watertight=mesh.get("watertight"), time_s=s.get("time_s") or {})
    return row


def _attempts(out: Path, name: str) -> tuple[int, str]:
    """How many attempts the running marker saw, and the last one's node; the marker is removed."""
    marker = out / BATCH_DIR / f"{name}.running"
    try:
        lines = [ln.split() for ln in marker.read_text().splitlines() if ln.strip()]
        marker.unlink()
    except OSError:
        return 0, ""
    return len(lines), (lines[-1][2] if lines and len(lines[-1]) > 2 else "")


def _line(i: int, n: int, row: dict) -> str:
    what = [row["status"] + (" (unchanged since the last run, not redone)" if row.get("resumed") else "")]
    if row["status"] in FINISHED:
        what.append(f"{row['frames_used']} frames, {row['mesh_faces']} faces")
    if row.get("wall_s") is not None:
        what.append(f"{row['wall_s']:.1f} s")
    if row.get("attempts", 0) > 1:
        what.append(f"{row['attempts']} attempts")
    if row.get("reason"):
        what.append(row["reason"])
    return f"[{i}/{n}] {row['object']}: " + ", ".join(what)


def run_batch(jobs: list[Job], out: Path, *, address: str | None = None, cpus_per_job: int = 1, retries: int = 2,
              resume: bool = False, stream=None) -> BatchResult:
    """Run every job as a Ray task and write the report; see the module docstring.

    Progress: one line per finished object on ``stream`` (stderr). Ctrl-C (or SIGTERM) cancels the
    running jobs (their OUT/<object> stay as they were), writes the report with them ``not_run``
    and re-raises. Uses a Ray connection the caller has already made (``ray.init``); otherwise starts
    a local Ray with this machine's cores, or joins the cluster at ``address``.
    """
    stream = stream or sys.stderr
    out = Path(out)
    (out / BATCH_DIR).mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows: dict[str, dict] = {}
    todo: list[Job] = []
    n, finished = len(jobs), 0

    def done(job: Job, row: dict, record: bool = True) -> None:
        nonlocal finished
        rows[job.name] = row
        finished += 1
        if record:
            atomic_write_text(_record_path(out, job.name), json.dumps({"digest": job.digest, "row": row}) + "\n")
        stream.write(_line(finished, n, row) + "\n")
        stream.flush()

    for job in jobs:
        prev = _resumable(out, job) if resume and job.opts is not None else None
        if job.opts is None:
            done(job, _row(job, out, None, "failed", job.error or "bad settings"))
        elif prev is not None:
            prev = {**prev, "resumed": True}
            if not (out / THUMB_DIR / f"{job.name}.png").is_file():
                with contextlib.suppress(Exception):  # the overview shows no picture; the model is there
                    write_thumbnail(out / job.name, out / THUMB_DIR / f"{job.name}.png")
            done(job, prev, record=False)
        else:
            todo.append(job)
    if todo:
        _run_ray(todo, out, address, cpus_per_job, retries, done, rows)
    ordered = [rows[j.name] for j in jobs]
    for r in ordered:
        r.setdefault("resumed", False)
    res = BatchResult(rows=ordered, wall_s=time.perf_counter() - t0)
    res.files = write_reports(out, res)
    return res


def _run_ray(todo: list[Job], out: Path, address: str | None, cpus: int, retries: int, done, rows) -> None:
    import ray

    started = _connect(address)
    interrupted = False
    pending: list = []
    by_ref: dict = {}
    try:
        largest = max((nd["Resources"].get("memory", 0) for nd in ray.nodes() if nd.get("Alive")), default=0)
        task = ray.remote(run_job)
        (out / THUMB_DIR).mkdir(exist_ok=True)
        for job in todo:
            (out / BATCH_DIR / f"{job.name}.running").unlink(missing_ok=True)
            mem = job.memory_bytes if not largest else min(job.memory_bytes, int(0.8 * largest))
            ref = task.options(num_cpus=cpus, memory=mem or None, max_retries=retries, retry_exceptions=False,
                               name=f"turntable:{job.name}").remote(job.opts, job.name, str(out.resolve()), cpus)
            by_ref[ref] = job
        pending = list(by_ref)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for ref in ready:
                job = by_ref[ref]
                try:
                    result = ray.get(ref)
                    reason = ""
                except ray.exceptions.RayError as exc:
                    result, reason = None, _ray_reason(exc, retries)
                attempts, node = _attempts(out, job.name)
                row = _row(job, out, result, None if result else "failed", reason)
                row["attempts"] = attempts
                row["node"] = row["node"] or node
                done(job, row)
    except BaseException:  # Ctrl-C, SIGTERM: stop every job, report what finished, then let it end the run
        interrupted = True
        # A Ray this call started stops its jobs' workers at shutdown (below), and a cluster kills the tasks
        # of a driver that leaves; ray.cancel(force=True) is left to a caller's own Ray: racing a finishing
        # task's reply it can crash the driver (RAY_CHECK in TaskManager, seen with Ray 2.60)
        if not started:
            for ref in pending:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)
        raise
    finally:
        if started:
            ray.shutdown()
        if interrupted:  # after the shutdown: no job can start (and leave its marker) any more
            for job in todo:
                if job.name not in rows:
                    _attempts(out, job.name)
                    rows[job.name] = _row(job, out, None, "not_run", "interrupted (a re-run with --resume continues)")
            write_reports(out, BatchResult(rows=list(rows.values()), wall_s=0.0, interrupted=True))


def _ray_reason(exc, retries: int) -> str:
    import ray

    if isinstance(exc, (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError)):
        return f"the worker died in each of {retries + 1} attempts ({type(exc).__name__})"
    if isinstance(exc, ray.exceptions.OutOfMemoryError):
        return f"out of memory in each of {retries + 1} attempts"
    if isinstance(exc, ray.exceptions.TaskCancelledError):
        return "cancelled"
    if isinstance(exc, ray.exceptions.RayTaskError):
        cause = exc.cause if getattr(exc, "cause", None) is not None else exc
        return f"internal error: {type(cause).__name__}: {str(cause).splitlines()[0] if str(cause) else ''}"
    return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
