"""Moved to :mod:`turntable.cli.args` (kept until ``cmd_sequence`` moves into ``turntable.cli``)."""

from .cli.args import add_target_arguments, target_from_args  # noqa: F401
