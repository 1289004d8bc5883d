"""``turntable view OUT``: open the Rerun recording of a reconstruction.

In the native Rerun viewer, or with ``--web`` in a browser: Rerun's web viewer
(bundled with rerun-sdk, nothing fetched from the internet) served on
127.0.0.1 with a gRPC server holding the recording, until Ctrl-C.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path
from urllib.parse import quote

from ..errors import UserError

#: Where ``--web`` serves the page by default (Rerun's own default web viewer port).
DEFAULT_WEB_PORT = 9090
HOST = "127.0.0.1"


def add_arguments(parser) -> None:
    parser.add_argument("target", metavar="OUT", help="an output folder of `reconstruct`, or a .rrd file")
    parser.add_argument("--web", action="store_true",
                        help=f"serve Rerun's web viewer on {HOST} and print its URL instead of opening a window "
                             "(for machines without a display, or a browser elsewhere through an SSH tunnel); "
                             "Ctrl-C stops it")
    parser.add_argument("--port", type=int, default=DEFAULT_WEB_PORT, metavar="N",
                        help=f"with --web: the page's port (default {DEFAULT_WEB_PORT}); the recording is served "
                             "over gRPC on a free port next to it")


def recording_path(target: str | Path) -> Path:
    """``OUT/recording.rrd`` for an OUT folder, the file itself for a .rrd."""
    p = Path(target)
    rrd = p / "recording.rrd" if p.is_dir() else p
    if not rrd.is_file():
        raise UserError(f"{rrd}: no recording found (run `turntable reconstruct ... --out {p}` first)")
    return rrd


def rerun_executable() -> str:
    """The Rerun binary itself (not the pip wrapper script, which would leave it running when killed)."""
    try:
        import rerun_cli

        binary = Path(rerun_cli.__file__).with_name("rerun.exe" if sys.platform.startswith("win") else "rerun")
        if binary.is_file():
            return str(binary)
    except ImportError:
        pass
    viewer = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not Path(viewer).exists():
        raise UserError("the Rerun viewer is not installed (pip install rerun-sdk)")
    return viewer


def viewer_command(target: str | Path) -> list[str]:
    """The command that opens ``target`` (an OUT folder or a .rrd) in the native Rerun viewer."""
    return [rerun_executable(), str(recording_path(target))]


def no_display_reason(environ=None, platform: str | None = None) -> str | None:
    """Why a native window cannot open here (Linux without DISPLAY or WAYLAND_DISPLAY), or None."""
    environ = os.environ if environ is None else environ
    platform = sys.platform if platform is None else platform
    if platform.startswith("linux") and not (environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY")):
        return "no display found (DISPLAY and WAYLAND_DISPLAY are not set)"
    return None


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((HOST, port))
        except OSError:
            return False
    return True


def _free_port(avoid: int) -> int:
    for port in (avoid + 1, 0):  # next to the page's port, else whatever the system gives
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((HOST, port))
            except OSError:
                continue
            return int(s.getsockname()[1])
    raise UserError(f"no free port on {HOST} for the recording's gRPC server")


def web_url(web_port: int, grpc_port: int) -> str:
    """The page that opens the recording: the web viewer with the gRPC server as its data source."""
    return f"http://{HOST}:{web_port}/?url={quote(f'rerun+http://{HOST}:{grpc_port}/proxy', safe='')}"


def web_command(rrd: Path, web_port: int, grpc_port: int) -> list[str]:
    """Rerun serving ``rrd``: the web viewer over HTTP on ``web_port``, the data over gRPC on ``grpc_port``."""
    # the server buffers the recording for every browser that connects; by default it keeps 1 GiB and drops
    # the oldest data beyond it, so give it room for the whole file
    limit_mib = max(1024, 2 * (rrd.stat().st_size >> 20) + 64)
    return [rerun_executable(), "--serve-web", "--bind", HOST, "--port", str(grpc_port),
            "--web-viewer-port", str(web_port), "--server-memory-limit", f"{limit_mib}MiB", str(rrd)]


def serve_web(rrd: Path, web_port: int) -> int:
    """Serve ``rrd`` to browsers until Ctrl-C (KeyboardInterrupt: the caller's exit 130) or the server ends."""
    if not 0 < web_port < 65536:
        raise UserError(f"--port {web_port}: expected 1..65535")
    if not _port_free(web_port):
        raise UserError(f"--port {web_port}: {HOST}:{web_port} is in use; choose another port with --port N")
    grpc_port = _free_port(web_port)
    env = {**os.environ, "RUST_LOG": os.environ.get("RUST_LOG", "warn")}  # Rerun's info lines repeat our URL
    proc = subprocess.Popen(web_command(rrd, web_port, grpc_port), env=env)
    try:
        print(f"Rerun web viewer for {rrd}:\n  {web_url(web_port, grpc_port)}\n"
              "open it in a browser on this machine (or through an SSH tunnel of both ports: "
              f"ssh -L {web_port}:{HOST}:{web_port} -L {grpc_port}:{HOST}:{grpc_port}); Ctrl-C stops it",
              flush=True)
        code = proc.wait()
    finally:
        if proc.poll() is None:  # Ctrl-C reached it too; SIGTERM or an error of ours did not
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    if code != 0:
        raise UserError(f"the Rerun web viewer stopped with exit code {code} (see its message above)")
    return 0


def run(args) -> int:
    rrd = recording_path(args.target)
    if args.web:
        return serve_web(rrd, args.port)
    why = no_display_reason()
    if why is not None:
        raise UserError(f"{why}: the Rerun viewer needs a window. Use `turntable view {args.target} --web` to "
                        "open the recording in a browser instead")
    return subprocess.call(viewer_command(rrd))
