"""OUT as a transaction: one run at a time, the new files built beside the old ones, switched in whole.

A run never changes what OUT shows until it has finished every file. It builds
its outputs in a staging folder inside ``OUT/.turntable``; when the last one is
written, one ``rename`` of that folder commits the run, and its files are moved
into OUT (replacing the previous ones, removing those the new run does not
write, such as an old ``colmap/``). A run that fails, is interrupted or is
killed before the commit leaves OUT exactly as it was; one killed during the
moves (milliseconds) is finished by the next run, which rolls the commit
forward before doing anything else. ``OUT/.turntable/published.json`` names the
files of the one consistent set in OUT.

Layout of ``OUT/.turntable`` (beside the stage cache's ``*.npz``)::

    lock             held (``flock``) by the run using OUT; holds its pid
    published.json   the names of the files in OUT that belong to the last finished run
    staging.<pid>/   the files a running run has written so far
    commit/          a finished run's files on their way into OUT (only mid-switch)
    trash/           the previous run's files on their way out (only mid-switch)

Two runs into one OUT: the second is refused at once ("OUT is in use by pid
N"); the lock is the kernel's, so a killed run never leaves a stale one.
Temporary files of a killed run (staging folders, ``.name.*`` temp files of
atomic writes) are removed by the next run.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import time
from pathlib import Path

from recon.fileio import atomic_write_bytes

from .errors import UserError, check_terminated

__all__ = ["OutputFolder", "KNOWN_OUTPUTS", "DISK_FULL_ERRNOS", "leftovers", "write_error"]

#: Everything ``reconstruct`` has ever published in OUT. Without a ``published.json`` (OUT written
#: by an older version) these are the names a new run replaces or removes.
KNOWN_OUTPUTS = ("model.glb", "model.ply", "model.obj", "model.mtl", "points.ply", "cameras.json",
                 "summary.json", "recording.rrd", "colmap", "transforms.json")

DISK_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}

_MANIFEST = ".manifest.json"

#: A run never writes less than this (model files of the smallest mesh, cameras, summary, recording).
MIN_ROOM = 64 << 10


def _files(p: Path) -> list[Path]:
    try:
        return [p] if p.is_file() else [q for q in p.rglob("*") if q.is_file()]
    except OSError:
        return []


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 100_000 else f"{n / 1e3:.0f} kB"


def write_error(exc: OSError, out: Path, staging: Path | None = None) -> UserError:
    """A one-line error for a failed write under ``out``: the file, the reason, and that OUT is unchanged.

    A file in ``staging`` is named as it would have been published (``OUT/model.glb``).
    """
    where = Path(os.fsdecode(exc.filename)) if exc.filename else out
    if staging is not None and where.is_relative_to(staging):
        where = out / where.relative_to(staging)
    if exc.errno in DISK_FULL_ERRNOS:
        why = "no space left on the device" if exc.errno != errno.EFBIG else "file too large for this system"
    else:
        why = exc.strerror or str(exc)
    return UserError(f"cannot write {where}: {why}; {out} was left as it was (nothing of this run was published)")


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


def leftovers(out: str | os.PathLike) -> list[Path]:
    """What interrupted runs left in OUT: staging folders, a half-done switch (``commit/``,
    ``trash/``), temporary files of atomic writes (ours and older versions'). Empty after any
    run has started there (it removes them, or finishes the switch)."""
    out = Path(out)
    meta = out / ".turntable"
    left = [p for p in (meta / "commit", meta / "trash") if p.exists()]
    left += list(meta.glob("staging.*"))
    left += [p for p in meta.glob(".*") if p.is_file()]  # atomic writes' temp files (cache)
    left += list(out.glob(".recording.*.rrd"))  # older versions' recording temp files
    left += [p for n in KNOWN_OUTPUTS for p in out.glob(f".{n}.*")]  # atomic writes' temp files (outputs)
    return sorted(left)


class _Lock:
    """An exclusive, non-blocking lock on a file (``flock``; ``msvcrt.locking`` on Windows)."""

    def __init__(self, path: Path):
        self.path = path
        self.fd: int | None = None

    def acquire(self, what: str) -> None:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            _lock_fd(fd)
        except OSError:
            os.close(fd)
            try:
                holder = self.path.read_text().split()[0]
            except (OSError, IndexError):
                holder = "?"
            raise UserError(f"{what} is in use by pid {holder} (another turntable run writing there); wait for "
                            f"it to finish, or choose another --out") from None
        try:  # who holds it, for the message another run prints (the lock itself is the flock)
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()} {time.strftime('%Y-%m-%dT%H:%M:%S')}\n".encode())
        except OSError:
            pass  # a full disk: the run will say so at its first real write
        self.fd = fd

    def release(self) -> None:
        if self.fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self.fd, 0)
            os.close(self.fd)  # closing the descriptor releases the lock
            self.fd = None


def _lock_fd(fd: int) -> None:
    try:
        import fcntl
    except ImportError:  # Windows
        import msvcrt

        msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        return
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)


class OutputFolder:
    """OUT for one run: ``with OutputFolder(out) as o:`` write into ``o.staging``, then ``o.publish()``.

    Leaving the block without ``publish()`` (an error, Ctrl-C, SIGTERM) removes
    the staging folder and leaves OUT as it was. ``files()`` maps each staged
    file to the path it will have in OUT.
    """

    def __init__(self, out: str | os.PathLike):
        self.out = Path(out)
        self.meta = self.out / ".turntable"
        self.staging = self.meta / f"staging.{os.getpid()}"
        self.created = False
        self.published = False
        self.cleaned: list[str] = []  # what the start-up found and removed or finished (for a note)
        self._lock = _Lock(self.meta / "lock")

    # -- lifetime -----------------------------------------------------------------------
    def __enter__(self) -> OutputFolder:
        if self.out.exists() and not self.out.is_dir():
            raise UserError(f"--out {self.out}: exists and is a file, not a folder")
        self.created = not self.out.exists()
        try:
            self.meta.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise write_error(exc, self.out) from None
        self._lock.acquire(str(self.out))
        try:
            self._recover()
            self._check_room()
            self.staging.mkdir()
        except OSError as exc:
            _remove(self.staging)
            self._lock.release()
            raise write_error(exc, self.out) from None
        except BaseException:  # Ctrl-C or SIGTERM right as the run starts
            _remove(self.staging)
            self._lock.release()
            raise
        return self

    def _check_room(self) -> None:
        """Refuse at once when OUT's disk cannot hold even half the last run's files (a full disk).

        A run writes its whole set beside the old one; a disk that fills later in
        the run fails at that write (naming the file) — this only spares the
        wait for a disk that is already full.
        """
        try:
            free = shutil.disk_usage(self.out).free
        except OSError:
            return
        last = sum(p.stat().st_size for n in self.published_names() for p in _files(self.out / n))
        need = max(MIN_ROOM, last // 2)
        if free < need:
            raise UserError(f"cannot write {self.out}: no space left on the device ({_mb(free)} free; a run writes "
                            f"at least {_mb(need)}" + (f", the last one wrote {_mb(last)}" if last else "") +
                            f"); {self.out} was left as it was")

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if not self.published:
                _remove(self.staging)
        finally:
            self._lock.release()

    # -- publishing ---------------------------------------------------------------------
    def publish(self) -> None:
        """Switch the staged files into OUT: all of them, replacing the previous run's set."""
        check_terminated()  # a SIGTERM whose exception a library swallowed: never publish after it
        names = sorted(p.name for p in self.staging.iterdir())
        manifest = {"files": names, "pid": os.getpid(), "time": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        atomic_write_bytes(self.staging / _MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode())
        commit = self.meta / "commit"
        _remove(commit)  # none after _recover; defensive
        os.replace(self.staging, commit)  # the commit point
        self.published = True
        self._roll_forward()

    def published_names(self) -> set[str]:
        """The files in OUT that belong to the last finished run."""
        try:
            return set(json.loads((self.meta / "published.json").read_text())["files"])
        except (OSError, ValueError, KeyError, TypeError):
            return {n for n in KNOWN_OUTPUTS if (self.out / n).exists()}

    def _roll_forward(self) -> None:
        """Move a committed set into OUT; safe to repeat after an interruption at any point."""
        commit, trash = self.meta / "commit", self.meta / "trash"
        manifest = commit / _MANIFEST
        if manifest.is_file():
            try:
                new = json.loads(manifest.read_text())["files"]
            except (OSError, ValueError, KeyError, TypeError):
                new = None  # cannot happen (written atomically before the commit); drop the commit
            if new is not None:
                old = self.published_names()
                trash.mkdir(exist_ok=True)
                for name in new:
                    src, dst = commit / name, self.out / name
                    if not (src.exists() or src.is_symlink()):
                        continue  # moved before an interruption
                    if dst.exists() or dst.is_symlink():
                        _remove(trash / name)
                        os.replace(dst, trash / name)
                    os.replace(src, dst)
                for name in sorted(old - set(new)):
                    dst = self.out / name
                    if dst.exists() or dst.is_symlink():
                        _remove(trash / name)
                        os.replace(dst, trash / name)
                os.replace(manifest, self.meta / "published.json")
        _remove(commit)
        _remove(trash)

    def _recover(self) -> None:
        """Finish a commit a killed run left mid-switch; remove what killed runs left behind."""
        if (self.meta / "commit").exists():
            self._roll_forward()
            self.cleaned.append("finished publishing an interrupted run's outputs")
        left = leftovers(self.out)
        for p in left:
            _remove(p)
        if left:
            self.cleaned.append(f"removed {len(left)} temporary file(s) of an interrupted run")
