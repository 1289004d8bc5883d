"""User-facing errors: the CLI prints their message and exits non-zero, no traceback."""

from __future__ import annotations

__all__ = ["UserError"]


class UserError(Exception):
    """Bad input or an impossible request; the message names the file and reason."""
