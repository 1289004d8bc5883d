"""Open a reconstruction's GLB in a real renderer (three.js, headless Chromium) and its USDZ in usd-core; check both.

GLB: ``benchmarks/viewer_check.html`` is served from 127.0.0.1 (with three.js
and the model; every other host name is unresolvable in the browser) and loads
``model.glb`` with three.js's GLTFLoader into a PBR scene as a web/VR viewer
shows it: a white hemisphere light and a directional key light, sRGB output,
no tone mapping (three.js's default; a filmic or Khronos-neutral curve shifts
the hue of dark colours), 800x600, software WebGL (SwiftShader). The camera is
framed from the model's bounds (a sphere of the box's half diagonal) and aimed
the way an AR/VR viewer anchors an asset: at its origin (the table centre)
horizontally, at the model's mid-height vertically; from the front (+Z) and
three more azimuths, 15 degrees above the horizon. For every view the page
draws the viewer's picture and four code passes of the same geometry (texture
u, v and the height above the table, 16 bits each; the mesh's own x, y, z, 8
bits each), so every pixel of the screenshot is known: on the object or not,
which texel the viewer drew there, which point of the mesh, how high up. The
checks, computed from the screenshots:

- ``loads``: the page loaded the GLB without a JavaScript error;
- ``textured``: the material has a baseColorTexture whose image decodes (or
  vertex colours, COLOR_0);
- ``on table``: the model stands on the table plane at its origin, as the
  README promises (world bounds: min Y within 3 % of the height of 0, max Y
  above it, the bounds' horizontal centre within half the model's size of the
  origin);
- ``in frame``: no object pixel on the border, 2-80 % of the picture covered;
- ``lit``: the object is not dark (mean sRGB luminance >= 0.10) and lit as a
  viewer lights it: the median of rendered / texture albedo (linear luminance)
  is within 0.3-3;
- ``shading varies``: the 90th / 10th percentile of that ratio >= 1.2 (light
  depends on the surface's direction: not a flat, unlit fill);
- ``colour``: the chromaticity of the object's mean linear colour in the
  picture is within 0.02 of that of the texels the viewer drew there, plus at
  most 0.04 of white (the specular reflection of the white lights, at most a
  dielectric's F0 of 4 %, which desaturates dark colours; fitted per view);
  pixels with a channel at 250 or more (clipped highlights) are left out. This
  also rules out flat grey, the magenta of a missing texture, a swapped
  red/blue or a wrong colour space;
- ``texture detail``: per pixel, the drawn colour correlates (r >= 0.5) with
  the texel the GLB's UVs point to: the hue (chromaticity along the texture's
  main direction of hue variation, which shading leaves alone) where hues vary
  (std >= 0.01), else sRGB luminance (std >= 0.03), else not measured: the
  viewer samples the texture where the file says (sampler, flipY, UV set);
- ``photo colours`` (where ``model.ply`` lies next to the GLB, as the
  pipeline writes it: vertex colours taken from the photos, independent of the
  texture): the same chromaticity test (0.03) and per-pixel correlation
  against the nearest vertex's colour at the drawn point of the mesh. A
  texture consistent with its UVs but placed wrongly on the surface (v
  flipped) fails here only;
- ``upright``: the silhouette's top rows (5 % of its height) show the model's
  top (median height above the table plane >= 80 % of the model's height) and
  its bottom rows the part standing on the table (|median height| <= 15 %;
  the very base is hidden under overhangs, e.g. 8 mm of the real squirrel's
  238 mm): the GLB's +Y is screen up and the object stands on its base.

``--negatives`` also runs the checks on broken copies of the GLB (turned
upside down: 180 degrees about X; the texture removed; the texture black; the
texture flipped on the surface, v -> 1 - v; moved three model sizes along +X)
and reports whether each fails, as it must.

USDZ (needs ``usd-core``, the optional extra ``turntable[usd]``):
``usdchecker --arkit`` where the executable exists. usd-core's wheels ship no
usdchecker, and 26.x no longer has its engine (UsdUtils.ComplianceChecker):
``--usdchecker-python PY`` runs ComplianceChecker(arkit=True) -- what
usdchecker --arkit runs -- in another Python with an older usd-core (24.x).
Always: usd-core's validation framework (every registered validator,
usdchecker's rules incl. the usdz package rules) and the ARKit profile's rules
re-stated here (prim types, shader ids, file types in the package, a usdc
root layer first, nothing outside the package); stage up axis Y, metres per
unit 1; the mesh's material: a UsdPreviewSurface whose diffuseColor is fed by
a UsdUVTexture reading an sRGB PNG inside the package through a
UsdPrimvarReader_float2 of the mesh's ``st``, the same texture as the GLB's;
the surface: triangles wound outward (positive signed volume; AR Quick Look
culls back faces), the GLB's points and ``st`` = the GLB's (u, 1 - v), so the
texture sits where the GLB puts it; the mesh's bounds equal to the GLB's (1 mm).

three.js: ``--three DIR`` (its package folder), else ``$TURNTABLE_THREE``, else
``three`` under a ``$NODE_PATH`` folder, else
``~/.cache/turntable-viewer/node_modules/three``; ``--install-three`` puts it
there with npm. Chromium: ``/usr/bin/chromium`` (``--chromium``).

    .venv/bin/python benchmarks/viewer_check.py OUT_DIR_OR_MODEL [--screenshots DIR] [--negatives]

Prints a table (model, check, value, pass/fail); exit 0 when every check
passes (and every negative fails), 1 when not, 2 on bad input; where Chromium
or three.js is missing the GLB part is skipped (said so, exit 0) and the USDZ
checks still run. Without OUT_DIR_OR_MODEL it checks out/sample (make demo;
skipped if absent), so make bench can run it.
``tests/test_viewer_check.py`` runs it on a small synthetic reconstruction.

This file is the CLI and the browser side (the page server, three.js, the
screenshots); ``viewer_glb.py`` next to it reads the GLB, makes the broken
copies and computes the GLB checks from the screenshots, ``viewer_usd.py``
runs the USDZ checks.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import importlib.util
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # loaded by path, not run as a script: its sibling modules are imported by name
    sys.path.append(str(HERE))
from viewer_glb import (  # noqa: E402  (the GLB file and the checks of the screenshots)
    CheckError,
    Reference,
    Row,
    Views,
    glb_albedo,
    glb_rows,
    negative_models,
    photo_reference,
    read_glb,
)
from viewer_usd import usdz_rows  # noqa: E402  (the USDZ checks)

PAGE = HERE / "viewer_check.html"
CHROMIUM = "/usr/bin/chromium"
DEMO_OUT = HERE.parent / "out" / "sample"
THREE_CACHE = Path.home() / ".cache" / "turntable-viewer"
WINDOW = (800, 600)
AZIMUTHS_DEG = (0, 90, 180, 270)
PASSES = ("beauty", "u", "v", "y", "p")


# ---------------------------------------------------------------- the browser side

def find_three(explicit: str | None = None) -> Path | None:
    """three.js's package folder (with build/three.module.js), or None."""
    candidates = [explicit, os.environ.get("TURNTABLE_THREE")]
    candidates += [str(Path(p) / "three") for p in os.environ.get("NODE_PATH", "").split(os.pathsep) if p]
    candidates.append(str(THREE_CACHE / "node_modules" / "three"))
    for c in candidates:
        if c and (Path(c) / "build" / "three.module.js").is_file() and \
                (Path(c) / "examples" / "jsm" / "loaders" / "GLTFLoader.js").is_file():
            return Path(c)
    return None


def install_three() -> Path | None:
    THREE_CACHE.mkdir(parents=True, exist_ok=True)
    subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--prefix", str(THREE_CACHE), "three"], check=True)
    return find_three()


@functools.lru_cache(maxsize=1)
def _web_view():
    """benchmarks/web_view.py, for its Chromium (headless, DevTools over a pipe, its own process group)."""
    spec = importlib.util.spec_from_file_location("web_view", HERE / "web_view.py")
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(module)
    return module


class _Handler(http.server.SimpleHTTPRequestHandler):
    """The page, three.js (read-only, under /three/) and the models (/models/NAME.glb); nothing else."""

    def __init__(self, *args, three: Path, models: dict[str, bytes], **kw):
        self.models = models
        super().__init__(*args, directory=str(three), **kw)

    def log_message(self, *args) -> None:
        pass

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        if path in ("/", "/index.html"):
            self._send(PAGE.read_bytes(), "text/html")
        elif path.startswith("/models/") and path.endswith(".glb") and path[8:-4] in self.models:
            self._send(self.models[path[8:-4]], "model/gltf-binary")
        elif path.startswith("/three/") and ".." not in path:
            self.path = path[len("/three"):]
            super().do_GET()
        else:
            self.send_error(404)

    def _send(self, body: bytes, kind: str) -> None:
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)


class Server:
    """An HTTP server on 127.0.0.1 only, in a thread."""

    def __init__(self, three: Path, models: dict[str, bytes]):
        handler = functools.partial(_Handler, three=three, models=models)
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def _evaluate(browser, expression: str, timeout: float = 60.0):
    reply = browser.send("Runtime.evaluate", session=True, expression=expression, awaitPromise=True,
                         returnByValue=True, timeout=int(timeout * 1000))
    if "exceptionDetails" in reply:
        raise RuntimeError(f"{expression}: {reply['exceptionDetails'].get('text')}")
    return reply["result"].get("value")

def render(browser, url: str, name: str, azimuths: tuple[int, ...] = AZIMUTHS_DEG, timeout: float = 120.0) -> Views:
    """Load model ``name`` in the page and draw every pass from each azimuth."""
    query = f"?model={name}&t={time.monotonic_ns()}"  # until the new page answers, window.* is the last one
    browser.send("Page.navigate", session=True, url=url + query)
    t0 = time.monotonic()
    state = "loading"
    while time.monotonic() - t0 < timeout:
        time.sleep(0.3)
        try:
            state = _evaluate(browser, f"location.search === {json.dumps(query)} ? (window.viewerState || 'loading')"
                              " : 'loading'")
        except RuntimeError:
            continue
        if state != "loading":
            break
    errors = _evaluate(browser, "window.viewerErrors || []") or []
    if state != "ready":
        return Views({"state": state}, errors + [state], {}, {}, {}, {}, {}, {})
    info = _evaluate(browser, "window.viewerInfo")
    views = Views(info, errors, {}, {}, {}, {}, {}, {})
    lo, hi = np.asarray(info["localMin"]), np.asarray(info["localMax"])
    for az in azimuths:
        codes = {}
        for p in PASSES:
            _evaluate(browser, f"window.show({az}, '{p}')")
            rgb = cv2.cvtColor(browser.screenshot(), cv2.COLOR_BGR2RGB)
            if p == "beauty":
                views.beauty[az] = rgb
            else:
                codes[p] = rgb
        views.mask[az] = np.all([codes[p][..., 2] > 127 for p in ("u", "v", "y")], axis=0)
        decode = {p: (codes[p][..., 0].astype(np.float64) * 256 + codes[p][..., 1]) / 65535.0 for p in "uvy"}
        views.u[az], views.v[az], views.height[az] = decode["u"], decode["v"], decode["y"]
        views.local[az] = lo + codes["p"] / 255.0 * (hi - lo)
    return views


# ---------------------------------------------------------------- driver

def check_models(models: dict[str, bytes], three: Path, chromium: str = CHROMIUM, screenshots: Path | None = None,
                 azimuths: tuple[int, ...] = AZIMUTHS_DEG, reference: Reference | None = None,
                 window: tuple[int, int] = WINDOW) -> list[Row]:
    """Every GLB (name: bytes) drawn from these azimuths in one browser; the check rows of all."""
    rows: list[Row] = []
    server = Server(three, models)
    try:
        with _web_view().Chromium(chromium, window) as browser:
            for name, data in models.items():
                views = render(browser, server.url, name, azimuths)
                rows += glb_rows(name, views, glb_albedo(*read_glb(data, name)), reference)
                if screenshots is not None:
                    screenshots.mkdir(parents=True, exist_ok=True)
                    for az, rgb in views.beauty.items():
                        cv2.imwrite(str(screenshots / f"{name}_az{az:03d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    finally:
        server.close()
    return rows


def print_table(rows: list[Row]) -> None:
    print("| model | check | value | result |")
    print("|---|---|---|---|")
    for r in rows:
        result = "-" if r.ok is None else ("pass" if r.ok else "FAIL")
        print(f"| {r.model} | {r.check} | {r.value} | {result} |")


def _inputs(target: Path) -> tuple[Path | None, Path | None]:
    if target.is_dir():
        glb, usdz = target / "model.glb", target / "model.usdz"
        if not glb.is_file() and not usdz.is_file():
            raise CheckError(f"{target}: no model.glb or model.usdz in it")
        return (glb if glb.is_file() else None), (usdz if usdz.is_file() else None)
    if not target.is_file():
        raise CheckError(f"{target}: no such file or folder")
    if target.suffix.lower() == ".glb":
        sibling = target.with_suffix(".usdz")
        return target, (sibling if sibling.is_file() else None)
    if target.suffix.lower() == ".usdz":
        return None, target
    raise CheckError(f"{target}: expected a .glb, a .usdz or a reconstruction folder")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("target", type=Path, nargs="?",
                    help=f"a reconstruction folder (model.glb, model.usdz) or a .glb/.usdz (default: {DEMO_OUT}, "
                    "what make demo writes)")
    ap.add_argument("--screenshots", type=Path, help="write the viewer's pictures here (NAME_azDDD.png)")
    ap.add_argument("--negatives", action="store_true",
                    help="also check broken copies of the GLB (upside down, no texture, black texture, flipped "
                    "v, out of frame): each must fail")
    ap.add_argument("--three", help="three.js's package folder (default: see the module docstring)")
    ap.add_argument("--install-three", action="store_true", help=f"npm install three into {THREE_CACHE} if missing")
    ap.add_argument("--chromium", default=CHROMIUM, help=f"the browser (default {CHROMIUM})")
    ap.add_argument("--usdchecker-python", metavar="PY",
                    help="a Python whose usd-core (<= 25.x) has UsdUtils.ComplianceChecker: run usdchecker --arkit's "
                    "checks with it (usd-core's wheels ship no usdchecker executable)")
    args = ap.parse_args(argv)
    if args.target is None:
        if not DEMO_OUT.is_dir():
            print(f"viewer_check: skipped: {DEMO_OUT} not found (make demo, or name a reconstruction folder)")
            return 0
        args.target = DEMO_OUT
    try:
        glb, usdz = _inputs(args.target)
        glb_data = glb.read_bytes() if glb else None
        if glb_data is not None:
            read_glb(glb_data, str(glb))  # bad input is said here, not as a traceback later
    except (CheckError, OSError, ValueError) as e:
        print(f"viewer_check: error: {e}", file=sys.stderr)
        return 2
    rows: list[Row] = []
    missing = ""
    negatives_ok = True
    if glb_data is not None:
        three = find_three(args.three) or (install_three() if args.install_three else None)
        if three is None:
            missing = "three.js not found (--install-three, --three DIR or $TURNTABLE_THREE)"
        elif not Path(args.chromium).exists():
            missing = f"{args.chromium} not found (apt-get install chromium)"
        else:
            label = glb.name if glb is not None else "model"
            models = {label: glb_data}
            if args.negatives:
                models.update(negative_models(glb_data))
            t0 = time.perf_counter()
            reference = photo_reference(glb) if glb is not None else None
            all_rows = check_models(models, three, args.chromium, args.screenshots, reference=reference)
            print(f"viewer_check: {len(models)} model(s) x {len(AZIMUTHS_DEG)} views x {len(PASSES)} passes in "
                  f"{time.perf_counter() - t0:.1f} s, {WINDOW[0]}x{WINDOW[1]}, headless Chromium (SwiftShader)\n")
            rows += [r for r in all_rows if r.model == label]
            for name in models:
                if name == label:
                    continue
                failed = [r.check for r in all_rows if r.model == name and r.ok is False]
                negatives_ok &= bool(failed)
                rows.append(Row(name, "must fail", "fails: " + (", ".join(failed) or "nothing"), bool(failed)))
    if usdz is not None:
        rows += usdz_rows(usdz.name, usdz, glb_data, args.usdchecker_python)
    print_table(rows)
    if missing:
        print(f"\nviewer_check: GLB skipped: {missing}")
    failed = [r for r in rows if r.ok is False]
    print("\nviewer_check: " + ("ok" if not failed and negatives_ok else f"FAILED: {len(failed)} check(s)"))
    return 1 if failed or not negatives_ok else 0


if __name__ == "__main__":
    sys.exit(main())
