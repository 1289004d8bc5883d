"""Finished stages kept in ``OUT/.turntable/`` so a re-run reuses them.

Each stage's result is an ``.npz`` written atomically, stored with a key: the
hash of everything it was computed from (its options, and the bytes of every
file it read: :func:`file_digest`). A changed option or input file recomputes
that stage and every later one.

Each file also stores a checksum of its key and arrays. A file that cannot be
read (empty, truncated, not an archive, corrupt), whose checksum does not
match, or whose arrays lack a field or have the wrong shape or type is not
used: the stage is recomputed and a one-line note says why. A cache can make a
run faster, never wrong, and never stop it.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
import zlib
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from recon.fileio import atomic_path

__all__ = ["StageCache", "stage_key", "file_digest", "files_digest"]

_CHUNK = 1 << 20  # bytes read at a time when hashing a file


def stage_key(*parts) -> str:
    """Stable short hash of JSON-able parts (numpy arrays allowed)."""
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, np.ndarray):
            h.update(np.ascontiguousarray(p).tobytes())
            h.update(str(p.shape).encode())
            h.update(p.dtype.str.encode())
        else:
            h.update(json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def file_digest(path: str | Path | None) -> str | None:
    """BLAKE2b of a file's bytes, read in 1 MiB chunks (None: no path, or the file cannot be read).

    An unreadable file gets no digest: the stage that reads it reports the error.
    """
    if path is None:
        return None
    h = hashlib.blake2b(digest_size=16)
    try:
        with open(path, "rb") as fh:
            while chunk := fh.read(_CHUNK):
                h.update(chunk)
    except OSError:
        return None
    return h.hexdigest()


def files_digest(paths: Iterable[str | Path | None]) -> list:
    """``[name, digest]`` of each file, in order (a missing entry: None)."""
    return [None if p is None else [Path(p).name, file_digest(p)] for p in paths]


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    """BLAKE2b over every array's name, dtype, shape and bytes, in name order."""
    h = hashlib.blake2b(digest_size=16)
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(memoryview(a).cast("B"))  # no copy of the array (a 1024^3 hull is 4 GB)
    return h.hexdigest()


def _unreadable_reason(exc: BaseException) -> str:
    """A short reason for a cache file that could not be read."""
    if isinstance(exc, EOFError):
        return "empty"
    if isinstance(exc, zipfile.BadZipFile):
        return "truncated or not an archive" if "not a zip file" in str(exc) else f"corrupt: {exc}"
    if isinstance(exc, zlib.error):
        return "corrupt compressed data"
    if isinstance(exc, MemoryError):
        return "corrupt: implausible array size"
    return f"{type(exc).__name__}: {exc}"


Shape = tuple  # each entry: an int (that size), None (any size) or a str (the same size wherever it is named)
Fields = dict[str, tuple[str, Shape]]  # name -> (allowed dtype kinds, e.g. "biuf" or "U"; shape)


def _field_problem(arrays: dict[str, np.ndarray], fields: Fields) -> str | None:
    """What is wrong with ``arrays`` against ``fields`` (None: nothing)."""
    sizes: dict[str, int] = {}
    for name, (kinds, shape) in fields.items():
        a = arrays.get(name)
        if a is None:
            return f"no field {name!r}"
        if a.dtype.kind not in kinds or a.ndim != len(shape):
            return f"{name} is {a.dtype} {a.shape}, expected {len(shape)}-d of kind {kinds!r}"
        for got, want in zip(a.shape, shape, strict=True):
            if isinstance(want, str):
                want = sizes.setdefault(want, got)
            if want is not None and got != want:
                return f"{name} has shape {a.shape}, expected {tuple(shape)}"
    return None


class StageCache:
    """The stage files of ``OUT/.turntable``; ``note`` receives one line for each file that is not used."""

    def __init__(self, out_dir: Path, enabled: bool = True, note: Callable[[str], None] | None = None):
        self.dir = Path(out_dir) / ".turntable"
        self.enabled = enabled
        self.note = note or (lambda text: None)

    def clear(self) -> None:
        """Forget every finished stage (``--overwrite``); the lock and the published set's record stay."""
        for p in [*self.dir.glob("*.npz"), self.dir / "cameras.json"]:
            p.unlink(missing_ok=True)

    def path(self, name: str) -> Path:
        return self.dir / f"{name}.npz"

    def load(self, name: str, key: str, fields: Fields | None = None) -> dict | None:
        """The arrays saved under ``key``, or None: none, another key, or not usable (noted).

        ``fields`` lists what the caller reads: a missing field, another dtype
        kind or another shape makes the file unusable, as a failed read does.
        """
        p = self.path(name)
        if not self.enabled or not p.is_file():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}  # reads every member: zip CRCs and sizes are checked
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error, MemoryError) as exc:
            return self._unusable(p, f"unreadable ({_unreadable_reason(exc)})")
        stored = arrays.pop("_sum", None)
        if stored is None or stored.shape != () or stored.dtype.kind != "U":
            return self._unusable(p, "has no checksum (written by an older version)")
        if str(stored) != _checksum(arrays):
            return self._unusable(p, "checksum mismatch")
        stored_key = arrays.pop("_key", None)
        if stored_key is None or str(stored_key) != key:
            return None  # computed from other inputs or options: stale, not damaged
        problem = _field_problem(arrays, fields or {})
        if problem is not None:
            return self._unusable(p, f"unusable ({problem})")
        return arrays

    def _unusable(self, p: Path, why: str) -> None:
        self.note(f"cache: {p} {why}, recomputing")
        return None

    def save(self, name: str, key: str, **arrays) -> None:
        arrays = {k: np.asarray(v) for k, v in arrays.items()}
        arrays["_key"] = np.array(key)
        self.dir.mkdir(parents=True, exist_ok=True)
        with atomic_path(self.path(name), suffix=".npz") as tmp:
            np.savez_compressed(tmp, _sum=np.array(_checksum(arrays)), **arrays)
