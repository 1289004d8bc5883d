"""Many objects at once: one ``reconstruct`` per object, each a Ray task (``turntable batch``).

ROOT holds one folder (or video) per object. Each object becomes a :class:`Job`:
the same :class:`ReconstructOptions` ``turntable reconstruct`` would build (the
command line, overridden by the object's ``turntable.toml``/``turntable.json``),
writing ``OUT/<object>/`` through the same OUT transaction, so a batch output is
a set of separate runs. Each job is one Ray task declaring ``num_cpus`` and a
memory estimate, so Ray's scheduler packs them on one machine or a cluster.

Failure isolation: a job's bad input (``UserError``) is its result, with the
message as the reason, never retried; a worker that dies (killed, out of memory,
a node lost) is retried by Ray up to ``retries`` times. Every finished job is
recorded in ``OUT/.batch/<object>.json`` with a digest of its inputs (file
names, sizes, mtimes) and options; ``resume`` skips an object whose record
matches and whose output is in place. While a job runs,
``OUT/.batch/<object>.running`` holds one line per attempt (pid, host, node).

At the end: ``OUT/batch.json``, ``OUT/batch.csv`` (one row per object) and
``OUT/index.html`` (a thumbnail per object, ``OUT/thumbnails/<object>.png``,
rendered from its model by ray casting on the CPU).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import hashlib
import html
import io
import json
import os
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .cameras_io import atomic_write_text
from .errors import UserError
from .frames import VIDEO_SUFFIXES
from .images import IMAGE_SUFFIXES, natural_key
from .stages.options import ReconstructOptions

__all__ = ["Job", "find_objects", "read_settings", "check_settings", "read_manifest", "ManifestEntry", "check_name",
           "object_input", "inputs_digest", "memory_estimate", "run_batch", "render_thumbnail", "STATUSES",
           "SETTINGS_FILES", "MANIFEST_SUFFIXES"]

SETTINGS_FILES = ("turntable.toml", "turntable.json")

#: What a job ended as. ``ok``: exit 0; ``warning``: finished, some frames unreadable (reconstruct's 1);
#: ``check_failed``: finished, the model failed a check (3); ``failed``: no model (bad input, a worker
#: that died every attempt, an internal error); ``not_run``: the batch was interrupted first.
STATUSES = ("ok", "warning", "check_failed", "failed", "not_run")
FINISHED = ("ok", "warning", "check_failed")  # the object's OUT holds this run's model

#: Settings that name files: relative to the object's folder in its settings file
PATH_SETTINGS = ("input", "masks", "cameras", "intrinsics")

BATCH_DIR = ".batch"  # OUT/.batch: one record per finished object, the running markers
THUMB_DIR = "thumbnails"
THUMB_PX = 192


@dataclass(frozen=True)
class Job:
    """One object: its options (None when they could not be built: ``error`` says why)."""

    name: str
    path: Path  # the object's folder or video in ROOT
    opts: ReconstructOptions | None
    error: str | None = None
    digest: str = ""
    memory_bytes: int = 0


# --------------------------------------------------------------------------- objects and their settings


def find_objects(root: Path, out: Path | None = None) -> list[tuple[str, Path]]:
    """``(name, path)`` of every object in ROOT: its folders (not hidden, not OUT) and videos, natural order."""
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: not a folder (ROOT holds one folder or video per object)")
    skip = out.resolve() if out is not None else None
    found = []
    for p in root.iterdir():
        if p.name.startswith(".") or (skip is not None and p.resolve() == skip):
            continue
        if p.is_dir():
            found.append((p.name, p))
        elif p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES:
            found.append((p.stem, p))
    names = [n for n, _ in found]
    for n, p in found:
        if n.casefold() in RESERVED_NAMES:
            check_name(n, str(p))  # not one of OUT's report files (other names: as the filesystem has them)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UserError(f"{root}: two objects would write OUT/{dup[0]} (a folder and a video of one name)")
    return sorted(found, key=lambda t: natural_key(t[0]))


def read_settings(path: Path, types: dict[str, tuple[type, ...]]) -> dict:
    """The object's own settings (``turntable.toml`` or ``turntable.json`` in its folder), keys with ``_``.

    ``types``: the settings allowed (``reconstruct``'s option names, ``-`` or ``_``) and their types; a
    ``no_X`` switch may also be given as ``X = false``. Paths (:data:`PATH_SETTINGS`) are made relative to
    the object's folder, other strings and numbers are returned as given. Raises ``UserError`` naming the
    file for a file that does not parse, an unknown key or a wrong type.
    """
    if not path.is_dir():
        return {}
    for fname in SETTINGS_FILES:
        f = path / fname
        if not f.is_file():
            continue
        raw = _load_table_file(f, "settings")
        if not isinstance(raw, dict):
            raise UserError(f"{f}: expected a table of settings")
        return check_settings(raw, types, base=path, where=str(f))
    return {}


def _load_table_file(f: Path, what: str):
    try:
        if f.suffix.lower() == ".toml":
            import tomllib

            return tomllib.loads(f.read_text())
        return json.loads(f.read_text())
    except (ValueError, OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{f}: cannot read the {what}: {exc}") from None


def check_settings(raw: dict, types: dict[str, tuple[type, ...]], *, base: Path, where: str,
                   text: bool = False) -> dict:
    """``raw`` settings checked against ``types`` (see :func:`read_settings`), keys with ``_``, paths made
    relative to ``base``. ``text``: the values are strings to convert (a CSV's cells; empty: not set).
    ``where`` starts every error message (a file, a manifest's row)."""
    settings = {}
    for key, value in raw.items():
        k = str(key).strip().replace("-", "_")
        if text:
            value = value.strip() if isinstance(value, str) else value
            if value in ("", None):
                continue
        if k not in types and types.get(f"no_{k}") == (bool,):  # fusion = false -> no_fusion = true
            if text:
                value = _from_text(value, (bool,), where, key)
            k, value = f"no_{k}", (not value) if isinstance(value, bool) else value
        if k not in types:
            raise UserError(f"{where}: unknown setting {key!r} (known: {', '.join(sorted(types))})")
        ok = types[k]
        if text:
            value = _from_text(value, ok, where, key)
        if not isinstance(value, ok) or (isinstance(value, bool) and bool not in ok):
            raise UserError(f"{where}: {key} = {value!r}: expected {' or '.join(t.__name__ for t in ok)}")
        if k in PATH_SETTINGS and not Path(value).is_absolute():
            value = str(base / value)
        settings[k] = str(value) if str in ok else value
    return settings


_TRUE, _FALSE = ("true", "yes", "1", "on"), ("false", "no", "0", "off")


def _from_text(value, ok: tuple[type, ...], where: str, key) -> object:
    """A CSV cell as the type a setting takes (a bool, an int, a float, or the text itself)."""
    if not isinstance(value, str) or str in ok:
        return value
    if bool in ok:
        if value.lower() in _TRUE + _FALSE:
            return value.lower() in _TRUE
        raise UserError(f"{where}: {key} = {value!r}: expected true or false")
    for t in (int, float):
        if t in ok:
            try:
                return t(value)
            except ValueError:
                pass
    raise UserError(f"{where}: {key} = {value!r}: expected {' or '.join(t.__name__ for t in ok)}")


# --------------------------------------------------------------------------- a manifest: the jobs listed in a file

MANIFEST_SUFFIXES = (".csv", ".toml", ".json")
#: What OUT holds besides the objects' folders: no object may be named so
RESERVED_NAMES = ("batch.json", "batch.csv", "index.html", THUMB_DIR, BATCH_DIR)


@dataclass(frozen=True)
class ManifestEntry:
    """One job of a manifest: the object's name (``OUT/<name>``), its folder or video, its own settings
    (checked, keys with ``_``, paths absolute), and where it is written (for messages)."""

    name: str
    path: Path
    settings: dict
    where: str


def check_name(name: str, where: str) -> None:
    """``UserError`` unless ``name`` can be a folder of OUT of its own (one path component, not hidden, not
    one of OUT's report files)."""
    if not name or name != name.strip() or any(c in name for c in "/\\\0") or name.startswith("."):
        raise UserError(f"{where}: name {name!r}: must be a folder name (no '/', not empty, not starting with '.')")
    if name.casefold() in RESERVED_NAMES:
        raise UserError(f"{where}: name {name!r}: OUT/{name} is the batch's own (report files: "
                        f"{', '.join(RESERVED_NAMES)})")


def read_manifest(manifest: Path, types: dict[str, tuple[type, ...]]) -> list[ManifestEntry]:
    """The jobs a manifest lists (``.csv``, ``.toml`` or ``.json``); ``UserError`` naming the file, the row
    and the reason for the first bad row.

    - CSV: a header row (``name``, ``input``, then any settings, named as the options are), one row per
      object; an empty cell leaves the command line's value; booleans ``true``/``false``; a row whose
      first cell starts with ``#`` is a comment.
    - TOML: one ``[[jobs]]`` table per object; JSON: ``{"jobs": [{...}, ...]}`` (or the list alone).

    ``input`` (the object's folder or video) and every path setting are relative to the manifest's folder;
    ``name`` (``OUT/<name>``) defaults to the input's name (a video's without its suffix). Names must
    differ (also in case: OUT may be on a case-insensitive filesystem).
    """
    manifest = Path(manifest)
    if not manifest.is_file():
        raise UserError(f"--manifest {manifest}: file not found")
    suffix = manifest.suffix.lower()
    if suffix not in MANIFEST_SUFFIXES:
        raise UserError(f"--manifest {manifest}: expected a .csv, .toml or .json file")
    base = manifest.parent
    rows: list[tuple[str, dict]] = []
    if suffix == ".csv":
        try:
            text = manifest.read_text(encoding="utf-8-sig")
        except (OSError, UnicodeDecodeError) as exc:
            raise UserError(f"{manifest}: cannot read the manifest: {exc}") from None
        lines = [(i, ln) for i, ln in enumerate(text.splitlines(), 1) if ln.strip() and not ln.lstrip().startswith("#")]
        if not lines:
            raise UserError(f"{manifest}: empty (expected a header row: name,input,...)")
        try:
            table = list(csv.reader([ln for _, ln in lines], strict=True))
        except csv.Error as exc:
            raise UserError(f"{manifest}: not a CSV table: {exc}") from None
        header = [h.strip() for h in table[0]]
        if "input" not in header:
            raise UserError(f"{manifest}: line {lines[0][0]}: the header has no 'input' column (got {header})")
        dup = sorted({h for h in header if header.count(h) > 1})
        if dup or "" in header:
            raise UserError(f"{manifest}: line {lines[0][0]}: " + (f"column {dup[0]!r} twice" if dup else
                                                                  "a column without a name"))
        for (lineno, _), cells in zip(lines[1:], table[1:], strict=True):
            if len(cells) != len(header):
                raise UserError(f"{manifest}: line {lineno}: {len(cells)} cells, the header has {len(header)}")
            rows.append((f"line {lineno}", dict(zip(header, cells, strict=True))))
    else:
        raw = _load_table_file(manifest, "manifest")
        entries = raw.get("jobs") if isinstance(raw, dict) and set(raw) == {"jobs"} else raw
        if not isinstance(entries, list) or not entries:
            what = "[[jobs]] tables" if suffix == ".toml" else '{"jobs": [...]} or a list'
            raise UserError(f"{manifest}: expected {what}, one per object")
        for i, e in enumerate(entries, 1):
            if not isinstance(e, dict):
                raise UserError(f"{manifest}: job {i}: expected a table of settings, got {e!r}")
            rows.append((f"job {i}", e))
    jobs: list[ManifestEntry] = []
    seen: dict[str, str] = {}
    for row, entry in rows:
        where = f"{manifest}: {row}"
        entry = dict(entry)
        text = suffix == ".csv"
        name = entry.pop("name", None)
        inp = entry.pop("input", None)
        if inp is None or (isinstance(inp, str) and not inp.strip()):
            raise UserError(f"{where}: no input (the object's folder or video, relative to the manifest's folder)")
        if not isinstance(inp, str):
            raise UserError(f"{where}: input = {inp!r}: expected a path (a string)")
        path = base / inp.strip()
        if not (path.is_dir() or (path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES)):
            raise UserError(f"{where}: input {inp!r}: " + (f"not a folder or a video ({', '.join(VIDEO_SUFFIXES)})"
                                                          if path.exists() else f"{path}: not found"))
        if name is None or (isinstance(name, str) and not name.strip()):
            name = path.name if path.is_dir() else path.stem
        if not isinstance(name, str):
            raise UserError(f"{where}: name = {name!r}: expected a string")
        name = name.strip() if text else name
        check_name(name, where)
        where = f"{where} ({name})"
        if name.casefold() in seen:
            raise UserError(f"{where}: name {name!r} already used by {seen[name.casefold()]}: two jobs would "
                            f"write OUT/{name}")
        seen[name.casefold()] = row
        settings = check_settings(entry, {k: v for k, v in types.items() if k != "input"}, base=base,
                                  where=where, text=text)
        jobs.append(ManifestEntry(name=name, path=path, settings=settings, where=where))
    return jobs


def object_input(path: Path) -> Path:
    """What ``reconstruct`` reads for an object: a video as it is; a folder's ``images/`` if it has one
    (the layout ``turntable synth`` writes), else the folder itself."""
    return path / "images" if path.is_dir() and (path / "images").is_dir() else path


def _stat_rows(p: Path | None) -> list:
    if p is None:
        return []
    try:
        if p.is_dir():
            return [[q.name, q.stat().st_size, q.stat().st_mtime_ns] for q in sorted(p.iterdir()) if q.is_file()]
        st = p.stat()
        return [[str(p.resolve()), st.st_size, st.st_mtime_ns]]
    except OSError:
        return [[str(p), None, None]]


def inputs_digest(opts: ReconstructOptions) -> str:
    """What a finished output depends on: the turntable version, the options (not OUT, ``overwrite``,
    ``spawn``) and the names, sizes and mtimes of the files read (frames, masks, cameras, intrinsics)."""
    from . import __version__

    d = dataclasses.asdict(opts)
    for k in ("out", "overwrite", "spawn"):
        d.pop(k)
    files = {k: _stat_rows(v) for k, v in (("input", opts.input), ("masks", opts.masks_dir),
                                            ("cameras", opts.cameras), ("intrinsics", opts.intrinsics))}
    text = json.dumps({"version": __version__, "options": d, "files": files}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


#: Memory of a reconstruct process before its data (Python, numpy, OpenCV, open3d, Rerun), bytes
BASE_MEMORY = 600 << 20


def memory_estimate(opts: ReconstructOptions) -> int:
    """A rough peak (bytes) of one ``reconstruct``, for Ray's scheduler: the process, the work images and
    their silhouettes/distance maps (~24 bytes a pixel), the carving grid (~12 bytes a voxel) and, with
    fusion, the depth maps. Read from the first photo's header only."""
    n, full = 36, 1_300_000
    p = Path(opts.input)
    if p.is_dir():
        files = [q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES]
        n = len(files) // max(opts.every, 1) if opts.frames is None else min(opts.frames, len(files))
        if files:
            try:
                from PIL import Image

                with Image.open(min(files)) as im:
                    full = im.width * im.height
            except Exception:  # noqa: BLE001  (an estimate; the job itself says what is wrong with the photo)
                pass
    # the work images: at most ~1.3 MP by default, the photos with work_size 0 ('full'), else N x 3N/4
    px = min(full, 1_300_000) if opts.work_size is None else full if opts.work_size == 0 else \
        min(full, opts.work_size ** 2 * 3 // 4)
    per_px = 24 + (16 if opts.fusion else 0)
    return int(BASE_MEMORY + n * px * per_px + 12 * opts.resolution ** 3)


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


@dataclass
class BatchResult:
    rows: list[dict]
    wall_s: float
    interrupted: bool = False
    files: dict[str, Path] = field(default_factory=dict)

    @property
    def not_ok(self) -> list[dict]:
        return [r for r in self.rows if r["status"] != "ok"]


def _connect(address: str | None) -> bool:
    """Start (or join) Ray; True when this call started the connection (and must shut it down)."""
    import logging

    import ray

    if ray.is_initialized():
        return False
    kw: dict = {"log_to_driver": False, "logging_level": logging.WARNING}
    if address is None:
        ray.init(include_dashboard=False, **kw)
    else:
        try:
            ray.init(address=address, **kw)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise UserError(f"--address {address}: cannot connect to a Ray cluster there: {exc}") from None
    return True


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


# --------------------------------------------------------------------------- the report

CSV_COLUMNS = ("object", "status", "reason", "attempts", "resumed", "node", "frames_used", "focal_px",
               "focal_std_px", "rms_px", "mesh_faces", "volume_cm3", "watertight", "wall_s")


def write_reports(out: Path, res: BatchResult) -> dict[str, Path]:
    """``OUT/batch.json``, ``OUT/batch.csv`` (stage times as ``time_<stage>_s`` columns) and ``OUT/index.html``."""
    counts = {s: sum(r["status"] == s for r in res.rows) for s in STATUSES}
    doc = {"objects": len(res.rows), "counts": counts, "wall_s": round(res.wall_s, 2), "interrupted": res.interrupted,
           "rows": res.rows}
    atomic_write_text(out / "batch.json", json.dumps(doc, indent=1, default=str) + "\n")
    stages: list[str] = []
    for r in res.rows:
        stages += [k for k in r.get("time_s") or {} if k not in stages]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*CSV_COLUMNS, *(f"time_{s.replace(' ', '_')}_s" for s in stages)])
    for r in res.rows:
        w.writerow([("" if r.get(c) is None else r.get(c)) for c in CSV_COLUMNS] +
                   [(r.get("time_s") or {}).get(s, "") for s in stages])
    atomic_write_text(out / "batch.csv", buf.getvalue())
    atomic_write_text(out / "index.html", overview_html(res.rows, counts))
    return {"json": out / "batch.json", "csv": out / "batch.csv", "html": out / "index.html"}


_COLOURS = {"ok": "#2e7d32", "warning": "#b26a00", "check_failed": "#c62828", "failed": "#c62828",
            "not_run": "#616161"}


_CARD = {"warning": "warn", "check_failed": "bad", "failed": "bad", "not_run": "idle"}  # a card's frame


def _fmt(v, spec: str = "") -> str:
    return "–" if v is None else format(v, spec)


def overview_html(rows: list[dict], counts: dict) -> str:
    """One self-contained page: a card per object (thumbnail, status, reason, the main figures)."""
    e = html.escape
    cards = []
    for r in rows:
        img = (f'<img src="{e(r["thumbnail"])}" alt="{e(r["object"])}">' if r.get("thumbnail")
               else '<div class="none">no model</div>')
        f = "" if r.get("focal_px") is None else (
            f"f {r['focal_px']:.1f}" + (f" ± {r['focal_std_px']:.2f}" if r.get("focal_std_px") is not None else "")
            + " px")
        facts = " · ".join(x for x in (f"{r['frames_used']} frames" if r.get("frames_used") is not None else "", f,
                                       f"edge RMS {r['rms_px']:.3f} px" if r.get("rms_px") is not None else "",
                                       f"{_fmt(r.get('mesh_faces'))} faces" if r.get("mesh_faces") else "",
                                       f"{r['volume_cm3']:.1f} cm³" if r.get("volume_cm3") is not None else "",
                                       f"{r['wall_s']:.1f} s" if r.get("wall_s") is not None else "") if x)
        kind = _CARD.get(r["status"], "")
        link = f'<a href="{e(r["output"])}/">{img}</a>' if r.get("thumbnail") else img  # no model: nothing to open
        cards.append(f'<div class="card {kind}" id="{e(r["object"])}">{link}'
                     f'<h2>{e(r["object"])}</h2>'
                     f'<p class="st" style="color:{_COLOURS.get(r["status"], "#000")}">{e(r["status"])}'
                     f'{" (resumed)" if r.get("resumed") else ""}</p><p>{e(facts)}</p>'
                     f'<p class="why">{e(r.get("reason") or "")}</p></div>')
    summary = e(", ".join(f"{v} {k}" for k, v in counts.items() if v))
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:  # the objects to look at, first: a link to each card
        summary += "<br>not ok: " + ", ".join(f'<a href="#{e(r["object"])}" style="color:'
                                               f'{_COLOURS.get(r["status"], "#000")}">{e(r["object"])}</a>'
                                               for r in bad)
    return ("<!doctype html><html><head><meta charset=\"utf-8\"><title>turntable batch</title><style>"
            "body{font:14px sans-serif;margin:1em}.card{display:inline-block;vertical-align:top;width:"
            f"{THUMB_PX + 24}px;margin:6px;padding:6px;border:1px solid #ccc;border-radius:4px}}"
            ".card.bad{border:4px solid #c62828;padding:3px;background:#fdecea}"
            ".card.warn{border:4px solid #b26a00;padding:3px;background:#fff3e0}"
            ".card.idle{border:4px dashed #9e9e9e;padding:3px;background:#f5f5f5}"
            "h2{font-size:14px;margin:4px 0}p{margin:2px 0}.st{font-weight:bold}.why{color:#c62828;font-size:12px}"
            f".none{{width:{THUMB_PX}px;height:{THUMB_PX}px;background:#eee;text-align:center;line-height:"
            f"{THUMB_PX}px;color:#888}}</style></head><body><h1>turntable batch: {len(rows)} objects</h1>"
            f"<p>{summary}</p>{''.join(cards)}</body></html>\n")


# --------------------------------------------------------------------------- thumbnails


def load_model(out_dir: Path):
    """What an object's OUT shows: ``(TableMesh, texcoords, texture_rgb)``, mm in the table frame. A textured
    model (``model.glb`` next to ``model_albedo.png``) is read from the GLB, its UVs in the pipeline's
    convention (``v`` down from the texture's top row); otherwise ``model.ply`` with its vertex colours and
    ``None, None``."""
    import trimesh

    from recon.types import TableMesh

    out_dir = Path(out_dir)
    glb, ply = out_dir / "model.glb", out_dir / "model.ply"
    if glb.is_file() and (out_dir / "model_albedo.png").is_file():
        m = trimesh.load(glb, force="mesh", process=False)
        tex = getattr(getattr(m.visual, "material", None), "baseColorTexture", None)
        uv = getattr(m.visual, "uv", None)
        if tex is not None and uv is not None and len(uv) == len(m.vertices):
            uv = np.asarray(uv, np.float64).copy()
            uv[:, 1] = 1.0 - uv[:, 1]  # trimesh turns glTF's v (down) into OpenGL's (up): back
            mesh = TableMesh(vertices_table=np.asarray(m.vertices, np.float64) * 1000.0,  # GLB: metres
                             faces=np.asarray(m.faces, np.int64))
            return mesh, uv, np.asarray(tex.convert("RGB"), np.uint8)
    m = trimesh.load(ply, process=False)
    colours = getattr(m.visual, "vertex_colors", None)
    mesh = TableMesh(vertices_table=np.asarray(m.vertices, np.float64) * 1000.0,  # PLY: metres, as the GLB
                     faces=np.asarray(m.faces, np.int64),
                     colors_rgb=None if colours is None else np.asarray(colours, np.uint8)[:, :3])
    return mesh, None, None


def thumbnail_camera(vertices: np.ndarray, size: int, elevation_deg: float = 25.0, azimuth_deg: float = 35.0,
                     fov_deg: float = 35.0) -> tuple[np.ndarray, np.ndarray]:
    """``K, T_cam_table`` of a square ``size`` view (OpenCV camera, pixel centres at integers) that looks at
    the bounding box's centre from ``elevation_deg`` above the table (+Y up), far enough for the box's
    sphere to fit ``fov_deg``."""
    V = np.asarray(vertices, np.float64)
    lo, hi = V.min(0), V.max(0)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    view = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    eye = centre + view * radius / np.sin(np.radians(fov_deg / 2)) * 1.05
    z = (centre - eye) / np.linalg.norm(centre - eye)
    x = np.cross([0.0, -1.0, 0.0], z)  # image y runs down the table's +Y
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ eye
    f = (size / 2) / np.tan(np.radians(fov_deg / 2))
    K = np.array([[f, 0.0, (size - 1) / 2], [0.0, f, (size - 1) / 2], [0.0, 0.0, 1.0]])
    return K, T


def render_thumbnail(out_dir: Path, size: int = THUMB_PX) -> np.ndarray:
    """A small picture of an object's model as its GLB shows it: the photo texture when the model is
    textured, else the vertex colours (:func:`load_model`), looked up by ray casting on the CPU
    (:func:`recon.texture.render_albedo`), shaded by the surface's angle to the eye so the shape reads.
    ``(size, size, 3)`` uint8 RGB on a light grey background."""
    import open3d as o3d

    from recon.raycast import raycasting_scene
    from recon.texture import render_albedo

    mesh, uv, tex = load_model(Path(out_dir))
    V, F = mesh.vertices_table, mesh.faces
    if len(F) == 0:
        raise ValueError(f"{out_dir}: the model has no faces")
    K, T = thumbnail_camera(V, size)
    rgb, hit = render_albedo(mesh, K, T, (size, size), texcoords=uv, texture_rgb=tex)
    img = np.full((size, size, 3), 245.0)
    if hit.any():
        # the same rays as render_albedo's: the hit face's normal against the ray gives a Lambert shade
        u, v = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64))
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T[:3, :3]
        rays = np.concatenate([np.broadcast_to(-T[:3, :3].T @ T[:3, 3], d.shape), d], -1).astype(np.float32)
        ans = raycasting_scene(V, F).cast_rays(o3d.core.Tensor(rays))  # type: ignore[call-overload]
        n = ans["primitive_normals"].numpy()[hit].astype(np.float64)
        d = d[hit] / np.linalg.norm(d[hit], axis=1, keepdims=True)
        shade = 0.45 + 0.55 * np.abs((n * d).sum(1))
        img[hit] = rgb[hit] * shade[:, None]
    return np.round(np.clip(img, 0, 255)).astype(np.uint8)


def write_thumbnail(out_dir: Path, png: Path) -> Path:
    """:func:`render_thumbnail` of the model in ``out_dir`` written (atomically) to ``png``."""
    import cv2

    from recon.fileio import atomic_write_bytes

    rgb = render_thumbnail(out_dir)
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"{png}: PNG encoding failed")
    png.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(png, data.tobytes())
    return png
