"""Finished stages kept in ``OUT/.turntable/`` so a re-run reuses them.

Each stage's result is an ``.npz`` written atomically, stored with a key: the
hash of everything it was computed from (its options and its inputs' keys).
A changed option recomputes that stage and every later one.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from recon.fileio import atomic_path

__all__ = ["StageCache", "stage_key"]


def stage_key(*parts) -> str:
    """Stable short hash of JSON-able parts (numpy arrays allowed)."""
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, np.ndarray):
            h.update(np.ascontiguousarray(p).tobytes())
            h.update(str(p.shape).encode())
        else:
            h.update(json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


class StageCache:
    def __init__(self, out_dir: Path, enabled: bool = True):
        self.dir = Path(out_dir) / ".turntable"
        self.enabled = enabled

    def load(self, name: str, key: str) -> dict | None:
        p = self.dir / f"{name}.npz"
        if not self.enabled or not p.is_file():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                if str(z["_key"]) != key:
                    return None
                return {k: z[k] for k in z.files if k != "_key"}
        except (OSError, ValueError, KeyError):
            return None

    def save(self, name: str, key: str, **arrays) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)
        with atomic_path(self.dir / f"{name}.npz", suffix=".npz") as tmp:
            np.savez_compressed(tmp, _key=np.array(key), **arrays)
