"""``turntable batch``: one ``reconstruct`` per object of ROOT, as Ray tasks (locally or on a cluster)."""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from ..errors import UserError
from .args import add_target_arguments
from .reconstruct import add_job_arguments, options_from_args

#: Options whose paths name something inside each object's folder when given on the batch command line
PER_OBJECT_PATHS = ("masks", "cameras")


def add_arguments(parser) -> None:
    parser.add_argument("root", metavar="ROOT", nargs="?",
                        help="folder with one folder (or video) per object; an object's folder may hold a "
                             "turntable.toml (or turntable.json) whose settings override the command line")
    parser.add_argument("--manifest", metavar="FILE",
                        help="instead of ROOT: a .csv, .toml or .json file listing the jobs (name, input "
                             "folder or video relative to the file's folder, the object's own settings)")
    add_target_arguments(parser, required=False,
                         optional_note="; per object in turntable.toml; optional with --cameras")
    parser.add_argument("--out", required=True, metavar="OUT",
                        help="output folder: OUT/<object>/ as reconstruct writes it, OUT/batch.csv, "
                             "OUT/batch.json, OUT/index.html")
    parser.add_argument("--address", metavar="ADDRESS",
                        help="run on an existing Ray cluster: 'auto' (the one `ray start` runs on this machine) "
                             "or ray://HOST:PORT (default: a local Ray on this machine's cores)")
    parser.add_argument("--cpus-per-job", type=int, default=1, metavar="N",
                        help="CPU cores each object's job declares (and its threads)")
    parser.add_argument("--retries", type=int, default=2, metavar="K",
                        help="run a job again up to K times when its worker dies (killed, out of memory, node "
                             "lost); bad input is not retried")
    parser.add_argument("--resume", action="store_true",
                        help="skip objects whose finished output matches their inputs (names, sizes, times) and "
                             "options")
    add_job_arguments(parser)
    parser.add_argument("--overwrite", action="store_true", help="recompute every stage of every object")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    for action in parser._actions:  # these name a path inside each object's folder here
        if action.dest in PER_OBJECT_PATHS:
            action.help = f"{action.help}; a path inside each object's folder"


_ADDRESS = re.compile(r"^(auto|ray://[^\s:/]+:\d+|[^\s:/]+:\d+)$")


def _check(args) -> None:
    if (args.root is None) == (args.manifest is None):
        raise UserError("give ROOT (one folder or video per object) or --manifest FILE (the jobs listed)"
                        + (", not both" if args.root else ""))
    if args.cpus_per_job < 1:
        raise UserError(f"--cpus-per-job must be 1 or more, got {args.cpus_per_job}")
    if args.retries < 0:
        raise UserError(f"--retries must be 0 or more, got {args.retries}")
    if args.address is not None and not _ADDRESS.match(args.address):
        raise UserError(f"--address must be 'auto', ray://HOST:PORT or HOST:PORT, got {args.address!r}")
    # the shared options' own checks, once for the whole batch (an object's turntable.toml is checked with it)
    probe = argparse.Namespace(**{**vars(args), "input": args.root or args.manifest, "out": args.out, "masks": None,
                                  "cameras": None, "spawn": False})
    if probe.r_outer is None and probe.r_inner is None:
        probe.cameras = __file__  # the radii may come from each object's settings, or --cameras
    options_from_args(probe)


def settings_types() -> dict[str, tuple[type, ...]]:
    """What an object's ``turntable.toml`` may set: ``input`` and every reconstruct option ``batch`` takes (the
    target, :func:`add_job_arguments`), by its argparse name, with the types its value may have."""
    from ..batch import PATH_SETTINGS

    p = argparse.ArgumentParser(add_help=False)
    add_target_arguments(p, required=False)
    add_job_arguments(p)
    types: dict[str, tuple[type, ...]] = {"input": (str,)}
    for a in p._actions:
        if isinstance(a, argparse._StoreTrueAction):
            types[a.dest] = (bool,)
        elif a.type in (int, float):
            types[a.dest] = (int,) if a.type is int else (int, float)
        elif a.dest in PATH_SETTINGS:
            types[a.dest] = (str,)
        elif a.dest != "help":
            types[a.dest] = (str, int)  # --work-size 1600 or 'full'
    return types


def job_namespace(args, name: str, path: Path, out: Path, row: dict | None = None) -> argparse.Namespace:
    """The ``reconstruct`` arguments of one object: the command line, then its own settings file on top,
    then (``row``) its manifest entry's settings."""
    from ..batch import object_input, read_settings

    ns = argparse.Namespace(**vars(args))
    ns.input, ns.out, ns.spawn = str(object_input(path)), str(out / name), False
    for key in PER_OBJECT_PATHS:
        value = getattr(args, key)
        if value is not None and not Path(value).is_absolute() and path.is_dir():
            setattr(ns, key, str(path / value))
    for key, value in {**read_settings(path, settings_types()), **(row or {})}.items():
        setattr(ns, key, value)
    return ns


def build_jobs(args, out: Path) -> list:
    """One :class:`~turntable.batch.Job` per object. ROOT: an object whose settings are bad is a failed job;
    a manifest: every row is checked first, a bad one is a ``UserError`` naming the file and the row."""
    from ..batch import Job, find_objects, inputs_digest, memory_estimate, read_manifest

    if args.manifest is not None:
        entries = read_manifest(Path(args.manifest), settings_types())
        objects = [(e.name, e.path, e.settings, e.where) for e in entries]
    else:
        objects = [(name, path, None, None) for name, path in find_objects(Path(args.root), out)]
        if not objects:
            raise UserError(f"{args.root}: no objects (expected one folder or video per object)")
    jobs = []
    for name, path, row, where in objects:
        try:
            opts = options_from_args(job_namespace(args, name, path, out, row))
        except UserError as exc:
            if where is not None:  # a manifest's row: nothing runs until every row is right
                raise UserError(f"{where}: {exc}") from None
            jobs.append(Job(name=name, path=path, opts=None, error=str(exc)))
            continue
        jobs.append(Job(name=name, path=path, opts=opts, digest=inputs_digest(opts),
                        memory_bytes=memory_estimate(opts)))
    return jobs


def run(args) -> int:
    from ..batch import run_batch

    _check(args)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: exists and is a file, not a folder")
    jobs = build_jobs(args, out)
    stream = open(os.devnull, "w") if args.quiet else sys.stderr  # noqa: SIM115
    try:
        res = run_batch(jobs, out, address=args.address, cpus_per_job=args.cpus_per_job, retries=args.retries,
                        resume=args.resume, stream=stream)
    finally:
        if args.quiet:
            stream.close()
    counts = {}
    for r in res.rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    resumed = sum(bool(r.get("resumed")) for r in res.rows)
    print(f"turntable batch: {len(res.rows)} objects in {res.wall_s:.1f} s: "
          + ", ".join(f"{v} {k}" for k, v in counts.items())
          + (f" ({resumed} unchanged since the last run, not redone)" if resumed else ""))
    for k, p in res.files.items():
        print(f"  {k:<6} {p}")
    if res.not_ok:
        for r in res.not_ok:
            print(f"turntable batch: {r['object']}: {r['status']}: {r['reason']}", file=sys.stderr)
        return 1
    return 0
