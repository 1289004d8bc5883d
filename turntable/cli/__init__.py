"""turntable: calibrated, coloured 3D meshes from turntable photos.

Command line: a thin dispatcher over one module per subcommand.

Each command module ``turntable.cli.<name>`` defines ``add_arguments(parser)``
and ``run(args) -> int``. Modules are imported only when their command runs, so
``turntable pattern`` never pays for open3d.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import sys

from ..errors import (
    TERMINATION_SIGNALS,
    Terminated,
    UserError,
    check_terminated,
    note_termination,
    noted_termination,
)

# name -> (module, one-line help), in the order of the work: print the target, check the camera, calibrate a
# sequence, reconstruct, look at it; synth makes test sequences
COMMANDS: dict[str, tuple[str, str]] = {
    "pattern": ("turntable.cli.pattern", "write the printable target (PDF, SVG or PNG)"),
    "calibrate": ("turntable.cli.calibrate", "focal length and table pose from single photos of the two-ring target"),
    "calibrate-sequence": ("turntable.cli.sequence", "calibrate a whole turntable sequence into cameras.json"),
    "reconstruct": ("turntable.cli.reconstruct",
                    "photos of an object on the turntable -> coloured mesh + Rerun recording"),
    "batch": ("turntable.cli.batch", "reconstruct every object of a folder as Ray tasks (locally or on a cluster)"),
    "view": ("turntable.cli.view", "open a Rerun recording written by reconstruct"),
    "synth": ("turntable.cli.synth", "render a synthetic turntable sequence with ground truth"),
}

EPILOG = """example:
  turntable pattern target.pdf --r-outer 80 --r-inner 50
  turntable reconstruct photos/ --r-outer 80 --r-inner 50 --out scan/

exit codes:
  0    success
  1    finished, but some inputs failed (each named on stderr; the rest were used)
  2    bad input or an impossible request (one line naming the file and the reason)
  3    reconstruct finished and wrote everything, but the model failed a check (!! CHECK FAILED)
  4    internal error (a bug of ours; -vv shows the traceback)
  130  interrupted (Ctrl-C); 143 SIGTERM, 129 SIGHUP: outputs left as they were
"""


def _available() -> dict[str, tuple[str, str]]:
    out = {}
    for name, (mod, help_) in COMMANDS.items():
        if importlib.util.find_spec(mod) is not None:
            out[name] = (mod, help_)
    return out


_UNITS = {"deg": "DEG", "px": "PX", "mm": "MM", "s": "S", "pct": "PCT"}


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Every option shows its default (unless its help already says it), and no raw metavar
    (``STEP_DEG``): a unit where the name ends in one (``DEG``), else ``N`` (integers) or ``X``."""

    def _get_help_string(self, action):
        help_ = action.help or ""
        default = action.default
        if ("default" in help_ or default is None or default is False or default is argparse.SUPPRESS
                or not action.option_strings or isinstance(action, (argparse._HelpAction, argparse._VersionAction,
                                                                     argparse._CountAction))):
            return help_
        if isinstance(default, (list, tuple)):
            default = " ".join(str(v) for v in default)
        return f"{help_} (default {default})" if help_ else f"default {default}"

    def _get_default_metavar_for_optional(self, action):
        unit = _UNITS.get(action.dest.rsplit("_", 1)[-1]) if "_" in action.dest else None
        if unit:
            return unit
        if action.type is int:
            return "N"
        if action.type is float:
            return "X"
        return action.dest.rsplit("_", 1)[-1].upper()


def _threads_arg(value: str) -> int:
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number of threads >= 1, got {value!r}")
    return n


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
                "NUMEXPR_NUM_THREADS")


def _threads_from_argv(argv: list[str]) -> int | None:
    """``--threads N`` anywhere on the command line, read before numpy, OpenCV and open3d load (their
    thread pools size themselves from the environment when they start)."""
    for i, a in enumerate(argv):
        value = argv[i + 1] if a == "--threads" and i + 1 < len(argv) else a[10:] if a.startswith("--threads=") \
            else None
        if value is not None:
            try:
                return _threads_arg(value)
            except argparse.ArgumentTypeError:
                return None  # argparse reports it
    return None


def apply_threads(n: int) -> None:
    """Use at most ``n`` threads: BLAS/OpenMP pools (open3d, numpy), OpenCV, and our own worker threads
    (``recon.silhouettes`` sizes its pool by ``OMP_NUM_THREADS``)."""
    import os

    for var in _THREAD_VARS:
        os.environ[var] = str(n)
    if "cv2" in sys.modules:
        sys.modules["cv2"].setNumThreads(n)


def build_parser(commands: dict[str, tuple[str, str]]) -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(prog="turntable", description=__doc__.splitlines()[0], epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"turntable {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv: debug, tracebacks)")
    parser.add_argument("--threads", type=_threads_arg, metavar="N", default=None,
                        help="use at most N threads (default: every core)")
    # the same flags after the command (turntable reconstruct ... -v): counted into the same total
    after = argparse.ArgumentParser(add_help=False)
    after.add_argument("-v", "--verbose", action="count", dest="verbose_after", default=0,
                       help="more logging (-vv: debug, tracebacks)")
    after.add_argument("--threads", type=_threads_arg, metavar="N", dest="threads_after", default=None,
                       help="use at most N threads (default: every core)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (mod, help_) in commands.items():
        p = sub.add_parser(name, help=help_, description=help_, parents=[after], formatter_class=HelpFormatter)
        importlib.import_module(mod).add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


#: Exit code of a failure of ours (a bug), distinct from 1 (finished, some inputs failed), 2 (bad input)
#: and 3 (reconstruct: a model that failed a check).
INTERNAL_ERROR = 4


def _raise_terminated(signum, frame) -> None:
    note_termination(signum)  # sticky: checked again before publishing and at the end of the run
    raise Terminated(signum)


def _handle_termination() -> dict:
    """Turn SIGTERM/SIGHUP into :class:`Terminated` (main thread only); returns the previous handlers."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}
    previous = {}
    for name in TERMINATION_SIGNALS:
        sig = getattr(signal, name, None)
        if sig is not None and signal.getsignal(sig) in (signal.SIG_DFL, None):
            previous[sig] = signal.signal(sig, _raise_terminated)
    return previous


def main(argv: list[str] | None = None) -> int:
    import signal

    threads = _threads_from_argv(sys.argv[1:] if argv is None else list(argv))
    if threads is not None:
        apply_threads(threads)  # before the command modules load numpy, OpenCV, open3d
    parser = build_parser(_available())
    args = parser.parse_args(argv)
    args.verbose += getattr(args, "verbose_after", 0)
    threads = getattr(args, "threads_after", None) or args.threads
    if threads is not None:
        apply_threads(threads)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    # force: rebind to the current stderr on every call (tests, or a host program, may swap it)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", force=True)
    note_termination(None)
    previous = _handle_termination()
    for stream in (sys.stdout, sys.stderr):  # odd file names (undecodable bytes) print as \xNN, never fail
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")
    try:
        code = int(importlib.import_module(args._module).run(args) or 0)
        check_terminated()  # a signal whose exception a library swallowed still ends the run as one
        return code
    except UserError as exc:
        print(f"turntable {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C, or Terminated (or the plain one a library made of it)
        signum = exc.signum if isinstance(exc, Terminated) else noted_termination()
        if signum is not None:
            print(f"turntable {args.command}: terminated (signal {signum})", file=sys.stderr)
            return 128 + signum
        print(f"turntable {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # last resort: a message, not a traceback
        if args.verbose >= 2:
            raise
        print(f"turntable {args.command}: internal error: {type(exc).__name__}: {exc} "
              "(run with -vv for the traceback)", file=sys.stderr)
        return INTERNAL_ERROR
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == "__main__":
    sys.exit(main())
