"""``turntable view OUT --web`` in a real browser: headless Chromium draws the recording's mesh.

It makes a small reconstruction (``turntable synth``: a vase of one magenta
albedo, 8 frames 640x480; ``turntable reconstruct`` with the true cameras and
masks, ``--resolution 32 --no-fusion``), serves it with ``turntable view R
--web``, opens the printed URL in headless Chromium (software WebGL:
``--use-angle=swiftshader --enable-unsafe-swiftshader``; every host name but
127.0.0.1 unresolvable, so a page that needed the internet would fail) and
takes a screenshot every few seconds until the mesh is drawn: pixels of the
mesh's magenta in the middle of the 3D view, where the default blueprint's eye
looks (the photos drawn in the camera frustums lie outside it). A blank or
still-loading page has none.

Chromium is driven over its DevTools pipe (``--remote-debugging-pipe``: JSON
messages on file descriptors 3 and 4), so nothing beyond the standard library
is needed; ``--screenshot`` alone cannot wait for the viewer's WebAssembly.

    .venv/bin/python benchmarks/web_view.py [--keep DIR] [--chromium PATH] [--timeout S]

Prints a table; exit 0 when the mesh is drawn, 1 when not, 0 with "skipped"
where Chromium is not installed (``apt-get install chromium``).
``tests/test_recording.py`` runs the same check where ``/usr/bin/chromium`` exists.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import fcntl
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
CHROMIUM = "/usr/bin/chromium"
#: The object's albedo (sRGB in [0, 1]): a magenta that nothing else in the viewer is drawn in.
ALBEDO = "0.85,0.15,0.75"
WINDOW = (1280, 800)
#: Mesh pixels needed in the middle of the 3D view (the vase covers some 4000 at this window size).
MIN_MESH_PIXELS = 300


class Chromium:
    """Headless Chromium driven over the DevTools pipe; one page."""

    def __init__(self, exe: str = CHROMIUM, size: tuple[int, int] = WINDOW):
        to_chrome_r, self._to_chrome_w = os.pipe()
        self._from_chrome_r, from_chrome_w = os.pipe()
        # Chromium reads commands on fd 3 and writes replies on fd 4: its ends go above those numbers first, and
        # bash puts them there (dash cannot redirect descriptors above 9)
        child_r, child_w = fcntl.fcntl(to_chrome_r, fcntl.F_DUPFD, 10), fcntl.fcntl(from_chrome_w, fcntl.F_DUPFD, 10)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self.profile = tempfile.mkdtemp(prefix="chromium-profile-")
        args = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--disable-quic", "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync",
                "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
                f"--user-data-dir={self.profile}", f"--window-size={size[0]},{size[1]}", "--remote-debugging-pipe",
                "about:blank"]
        shell = f'exec "$0" "$@" 3<&{child_r} 4>&{child_w} {child_r}<&- {child_w}>&-'
        self.proc = subprocess.Popen(["bash", "-c", shell, *args], pass_fds=(child_r, child_w),
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        os.close(child_r)
        os.close(child_w)
        self._id = 0
        self._buf = b""
        target = self.send("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.send("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        self.send("Emulation.setDeviceMetricsOverride", session=True, width=size[0], height=size[1],
                  deviceScaleFactor=1, mobile=False)

    def send(self, method: str, session: bool = False, **params) -> dict:
        """One DevTools command; its result (events that arrive meanwhile are dropped)."""
        self._id += 1
        msg: dict = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        os.write(self._to_chrome_w, json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in self._buf:
                chunk = os.read(self._from_chrome_r, 1 << 20)
                if not chunk:
                    raise RuntimeError(f"Chromium closed its DevTools pipe during {method}")
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def open(self, url: str) -> None:
        self.send("Page.navigate", session=True, url=url)

    def screenshot(self) -> np.ndarray:
        """The page as a BGR image."""
        data = base64.b64decode(self.send("Page.captureScreenshot", session=True, format="png")["data"])
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)

    def close(self) -> None:
        with contextlib.suppress(RuntimeError, OSError):
            self.send("Browser.close")
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        for fd in (self._to_chrome_w, self._from_chrome_r):
            os.close(fd)
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def mesh_pixels(bgr: np.ndarray) -> int:
    """Pixels of the mesh's magenta in the middle of the 3D view (the left 3/5 of the default layout)."""
    h, w = bgr.shape[:2]
    cx, cy = int(0.3 * w), int(0.5 * h)
    half = int(0.12 * min(w, h))
    hsv = cv2.cvtColor(bgr[cy - half:cy + half, cx - half:cx + half], cv2.COLOR_BGR2HSV)
    H, S, V = hsv[..., 0].astype(int), hsv[..., 1], hsv[..., 2]
    return int(np.count_nonzero((H >= 135) & (H <= 172) & (S >= 80) & (V >= 40)))


def make_reconstruction(work: Path) -> tuple[Path, float]:
    """A small synthetic reconstruction in ``work/R``; (its folder, seconds)."""
    t0 = time.perf_counter()
    seq, out = work / "S", work / "R"
    subprocess.run([PY, "-m", "turntable", "synth", str(seq), "--object", "vase", "--frames", "8", "--size",
                    "640x480", "--focal-px", "760", "--elevation-deg", "35", "--distance-mm", "430", "--albedo",
                    ALBEDO, "--overwrite"], check=True, stdout=subprocess.DEVNULL, cwd=ROOT)
    subprocess.run([PY, "-m", "turntable", "reconstruct", str(seq / "images"), "--cameras",
                    str(seq / "cameras_gt.json"), "--masks", str(seq / "masks"), "--r-outer", "80", "--r-inner", "50",
                    "--resolution", "32", "--no-fusion", "--out", str(out), "--quiet"], check=True,
                   stdout=subprocess.DEVNULL, cwd=ROOT)
    return out, time.perf_counter() - t0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_view(out: Path, port: int, timeout: float = 60.0) -> tuple[subprocess.Popen, str]:
    """``turntable view OUT --web --port PORT``: the process and the URL it printed."""
    # its own process group, like a command in a terminal: Ctrl-C (stop_view) and a kill reach the Rerun server
    # too, which otherwise could outlive it holding our pipes open
    # and with Ctrl-C's default action, even when this process was started as `cmd &` by a script (a
    # non-interactive shell ignores SIGINT there, and children inherit that: stop_view then had to kill it)
    proc = subprocess.Popen([PY, "-m", "turntable", "view", str(out), "--web", "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            start_new_session=True, preexec_fn=_default_sigint)
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    for line in proc.stdout:  # the URL is printed before the server is waited on
        if line.strip().startswith("http://"):
            url = line.strip()
            break
        if time.monotonic() > deadline:
            break
    else:
        url = ""
    if not url:
        _kill_group(proc)
        raise RuntimeError(f"turntable view --web printed no URL (exit {proc.wait()}): {proc.stderr.read()[-500:]}")
    while time.monotonic() < deadline:  # the page is up when its port answers
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1):
                return proc, url
        except OSError:
            time.sleep(0.2)
    _kill_group(proc)
    raise RuntimeError(f"nothing listens on 127.0.0.1:{port} after {timeout:.0f} s")


def _kill_group(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def stop_view(proc: subprocess.Popen) -> tuple[int, str]:
    """Ctrl-C, as a terminal sends it to the command's process group: (exit code, what it wrote on stderr)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        _kill_group(proc)
        try:
            _, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            err = "(no answer to SIGKILL)"
    return proc.returncode, err


def shoot_until_drawn(url: str, png: Path, timeout: float = 240.0, every: float = 5.0,
                      chromium: str = CHROMIUM) -> tuple[int, float]:
    """Open ``url``; screenshot every ``every`` s until the mesh is drawn and the page has settled, or ``timeout``.

    Settled: less than 0.5 % of the pixels changed since the last screenshot
    (the photos and plots stream in after the mesh). Writes the last screenshot
    to ``png``; returns (mesh pixels in it, seconds until they first appeared,
    NaN if never).
    """
    t0 = time.perf_counter()
    first = float("nan")
    count = 0
    previous = None
    with Chromium(chromium) as browser:
        browser.open(url)
        while time.perf_counter() - t0 < timeout:
            time.sleep(every)
            img = browser.screenshot()
            count = mesh_pixels(img)
            cv2.imwrite(str(png), img)
            if count >= MIN_MESH_PIXELS:
                if math.isnan(first):
                    first = time.perf_counter() - t0
                elif previous is not None and np.mean(np.any(img != previous, axis=2)) < 0.005:
                    break
            previous = img
    return count, first


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, help="work in this folder and keep it (default: a temporary one)")
    ap.add_argument("--chromium", default=CHROMIUM, help=f"the browser (default {CHROMIUM})")
    ap.add_argument("--timeout", type=float, default=240.0, help="seconds to wait for the mesh (default 240)")
    args = ap.parse_args(argv)
    if not Path(args.chromium).exists():
        print(f"web_view: skipped: {args.chromium} not found (apt-get install chromium)")
        return 0
    work = args.keep or Path(tempfile.mkdtemp(prefix="web_view-"))
    work.mkdir(parents=True, exist_ok=True)
    out, t_recon = make_reconstruction(work)
    port = free_port()
    proc, url = start_view(out, port)
    png = work / "web_view.png"
    try:
        count, t_mesh = shoot_until_drawn(url, png, timeout=args.timeout, chromium=args.chromium)
    finally:
        code, err = stop_view(proc)
    drawn = count >= MIN_MESH_PIXELS
    print(f"\nweb view: turntable view R --web, headless Chromium {WINDOW[0]}x{WINDOW[1]}, software WebGL\n")
    print(f"| reconstruction s | mesh drawn after s | mesh pixels (>= {MIN_MESH_PIXELS}) | Ctrl-C exit | traceback "
          "| screenshot |")
    print("|---|---|---|---|---|---|")
    print(f"| {t_recon:.0f} | {t_mesh:.0f} | {count} | {code} | {'yes' if 'Traceback' in err else 'no'} | {png} |")
    ok = drawn and code == 130 and "Traceback" not in err
    print("\nweb_view: " + ("ok: the mesh is drawn" if ok else "FAILED"))
    if args.keep is None:  # the screenshot stays
        for d in (work / "S", work / "R"):
            shutil.rmtree(d, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
