"""Progress bars and stage timing on stderr (the CLI's, never the libraries')."""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager

from .errors import check_terminated

__all__ = ["Progress", "fit_reporter"]


class Progress:
    """One line per stage; a live bar on a terminal, start/end lines otherwise.

    ``with progress.stage("carving") as tick: ... tick(done, total)``; the time
    of each stage is kept in ``times_s``. Stages that cannot count towards a
    total (an iterative fit) report through :meth:`status`.
    """

    def __init__(self, stream=None, enabled: bool = True):
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.times_s: dict[str, float] = {}
        self._started: dict[str, float] = {}  # status stages under way: their start

    def _write(self, text: str) -> None:
        if self.enabled:
            self.stream.write(text)
            self.stream.flush()

    @contextmanager
    def stage(self, name: str):
        check_terminated()  # a SIGTERM a library swallowed in the last stage ends the run here
        t0 = time.perf_counter()
        last = [0.0, 0]  # time of the last live update; last quarter logged

        def tick(done: int, total: int) -> None:
            check_terminated()
            now = time.perf_counter()
            if not self.tty:  # a log: a line at each quarter of a long count, nothing else
                quarter = 4 * done // max(total, 1)
                if total >= 8 and 0 < quarter < 4 and quarter != last[1]:
                    last[1] = quarter
                    self._write(f"  {name} {done}/{total} ({now - t0:.1f} s)\n")
                return
            if now - last[0] < 0.1 and done < total:
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
            # off a terminal no carriage return and no padding: one clean line per stage in a log
            self._write(f"\r  {name:<14} done in {dt:6.1f} s{' ' * 30}\n" if self.tty else
                        f"  {name} done in {dt:.1f} s\n")

    def status(self, name: str, text: str, done: bool = False) -> None:
        """A stage that reports what it is at (an iteration, a cost) rather than a count.

        On a terminal ``text`` replaces the stage's live line; otherwise nothing
        is written until ``done``, then one line: ``name: text (time)``. The
        stage's time runs from its first call to the one with ``done``; it is printed, not kept in
        ``times_s`` (a status stage is part of the counted stage around it).
        """
        now = time.perf_counter()
        t0 = self._started.setdefault(name, now)
        if done:
            del self._started[name]  # a part of the stage around it: its time is that stage's, not listed apart
            end = f" ({now - t0:.1f} s)"
            self._write(f"\r  {name}: {text}{end}{' ' * 10}\n" if self.tty else f"  {name}: {text}{end}\n")
        elif self.tty:
            self._write(f"\r  {name}: {text}{' ' * 10}")

    def note(self, text: str) -> None:
        self._write(f"  {text}\n")


def fit_reporter(progress: Progress, label: str = "joint fit"):
    """``report(step)`` for the ``fit_progress`` of :func:`calib.sequence.calibrate_sequence`.

    Each least-squares stage of the joint fit is a :meth:`Progress.status`
    stage named ``label stage``: its iterations and cost (first -> current)
    live on a terminal, one line when it ends otherwise.
    """
    first: dict[str, float] = {}

    def report(step) -> None:
        c0 = first.setdefault(step.stage, step.cost)
        if step.done:
            del first[step.stage]
        progress.status(f"{label} {step.stage}", f"{step.iteration} iterations, cost {c0:.6g} -> {step.cost:.6g} "
                        f"px^2 (rms {step.rms_px:.3f} px)", done=step.done)

    return report
