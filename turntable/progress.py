"""Progress bars and stage timing on stderr (the CLI's, never the libraries')."""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager

__all__ = ["Progress"]


class Progress:
    """One line per stage; a live bar on a terminal, start/end lines otherwise.

    ``with progress.stage("carving") as tick: ... tick(done, total)``; the time
    of each stage is kept in ``times_s``.
    """

    def __init__(self, stream=None, enabled: bool = True):
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.times_s: dict[str, float] = {}

    def _write(self, text: str) -> None:
        if self.enabled:
            self.stream.write(text)
            self.stream.flush()

    @contextmanager
    def stage(self, name: str):
        t0 = time.perf_counter()
        last = [0.0]

        def tick(done: int, total: int) -> None:
            now = time.perf_counter()
            if not self.tty or (now - last[0] < 0.1 and done < total):
                return
            last[0] = now
            width = 30
            fill = int(width * done / max(total, 1))
            self._write(f"\r  {name:<14} [{'#' * fill}{'.' * (width - fill)}] {done}/{total} {now - t0:6.1f} s")

        if not self.tty:
            self._write(f"  {name} ...\n")
        try:
            yield tick
        finally:
            dt = time.perf_counter() - t0
            self.times_s[name] = self.times_s.get(name, 0.0) + dt
            self._write(f"\r  {name:<14} done in {dt:6.1f} s{' ' * 30}\n")

    def note(self, text: str) -> None:
        self._write(f"  {text}\n")
