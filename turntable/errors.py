"""User-facing errors: the CLI prints their message and exits non-zero, no traceback."""

from __future__ import annotations

__all__ = [
    "TERMINATION_SIGNALS", "Terminated", "UserError", "check_terminated", "note_termination", "noted_termination",
]

#: The signals a run ends on like Ctrl-C (names: Windows has no SIGHUP).
TERMINATION_SIGNALS = ("SIGTERM", "SIGHUP")


class UserError(Exception):
    """Bad input or an impossible request; the message names the file and reason."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP) received: unwound like Ctrl-C, so every run cleans up the same way."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


#: The termination signal this process received, if any. Kept beside the exception the handler raises
#: because a library can swallow that exception: trimesh, for one, wraps many small steps in
#: ``except BaseException: pass``, and a SIGTERM landing there would otherwise let the run go on and
#: publish as if nothing had happened.
_received: int | None = None


def note_termination(signum: int | None) -> None:
    """Remember (or, with ``None``, forget) a termination signal; the CLI's handler calls this."""
    global _received
    _received = signum


def noted_termination() -> int | None:
    """The termination signal noted, if any: what a plain KeyboardInterrupt really was where a library turned
    the :class:`Terminated` raised inside it into one (Ray's ``ray.wait`` does)."""
    return _received


def check_terminated() -> None:
    """Raise :class:`Terminated` again when a termination signal came in and its exception was swallowed."""
    if _received is not None:
        raise Terminated(_received)
