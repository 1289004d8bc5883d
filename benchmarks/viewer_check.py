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
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import functools
import http.server
import importlib.util
import json
import os
import shutil
import struct
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
PAGE = HERE / "viewer_check.html"
CHROMIUM = "/usr/bin/chromium"
DEMO_OUT = HERE.parent / "out" / "sample"
THREE_CACHE = Path.home() / ".cache" / "turntable-viewer"
WINDOW = (800, 600)
AZIMUTHS_DEG = (0, 90, 180, 270)
PASSES = ("beauty", "u", "v", "y", "p")

# thresholds (see the module docstring)
MIN_COVERAGE, MAX_COVERAGE = 0.02, 0.80
MIN_LUMINANCE = 0.10  # mean sRGB luminance of the object's pixels, [0, 1]
LIGHT_RANGE = (0.3, 3.0)  # median rendered / albedo linear luminance
MIN_SHADING_SPREAD = 1.2  # 90th / 10th percentile of that ratio
MAX_CHROMA_DIFF = 0.02  # chromaticity (r, g, b) / (r + g + b) of the mean linear colours
MAX_PHOTO_CHROMA_DIFF = 0.03  # the same against the photos' vertex colours (model.ply)
MIN_HUE_STD = 0.01  # per-pixel chromaticity spread of the photo colours needed to correlate hues
MAX_SPECULAR = 0.04  # white added to the albedo by specular reflection, at most (albedo units): F0 of a dielectric
MIN_DETAIL_STD, MIN_DETAIL_R = 0.03, 0.5  # sRGB luminance std; correlation
EDGE_ROWS = 0.05  # the silhouette's top / bottom rows: this fraction of its height
TOP_BAND, BOTTOM_BAND = 0.80, 0.15  # their median height above the table plane, in model heights: >= / |.| <=
ON_PLANE_TOL = 0.03  # |min Y| / height


class CheckError(Exception):
    """Bad input: a file that is not there or not a GLB/USDZ."""


@dataclasses.dataclass
class Row:
    model: str
    check: str
    value: str
    ok: bool | None  # None: not a pass/fail row (information)


# ---------------------------------------------------------------- GLB files

def read_glb(data: bytes, name: str = "model.glb") -> tuple[dict, bytes]:
    """A binary glTF's JSON and its BIN chunk."""
    if len(data) < 20 or data[:4] != b"glTF":
        raise CheckError(f"{name}: not a binary glTF file (no 'glTF' magic)")
    length = struct.unpack_from("<I", data, 8)[0]
    off, gltf, binary = 12, None, b""
    while off + 8 <= min(length, len(data)):
        size, kind = struct.unpack_from("<II", data, off)
        chunk = data[off + 8:off + 8 + size]
        if kind == 0x4E4F534A:
            gltf = json.loads(chunk)
        elif kind == 0x004E4942:
            binary = chunk
        off += 8 + size
    if gltf is None:
        raise CheckError(f"{name}: no JSON chunk")
    try:
        gltf["accessors"][gltf["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    except (KeyError, IndexError, TypeError):
        raise CheckError(f"{name}: no mesh with POSITION in its first primitive") from None
    return gltf, binary


def write_glb(gltf: dict, binary: bytes) -> bytes:
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(binary), 0x004E4942) + binary
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def _buffer_view(gltf: dict, binary: bytes, index: int) -> bytes:
    view = gltf["bufferViews"][index]
    start = view.get("byteOffset", 0)
    return binary[start:start + view["byteLength"]]


def _accessor(gltf: dict, binary: bytes, index: int) -> np.ndarray:
    acc = gltf["accessors"][index]
    dtype = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    view = gltf["bufferViews"][acc["bufferView"]]
    raw = binary[view.get("byteOffset", 0) + acc.get("byteOffset", 0):]
    a = np.frombuffer(raw, dtype, count=acc["count"] * width).reshape(-1, width).astype(np.float64)
    if acc.get("normalized"):
        a /= np.iinfo(dtype).max
    return a


@dataclasses.dataclass
class Albedo:
    """What the GLB says the object's colour is: a texture (sRGB RGB uint8) times a factor, or vertex colours."""

    factor: np.ndarray  # (4,) linear baseColorFactor
    texture: np.ndarray | None  # (H, W, 3) uint8 sRGB
    vertex_mean: np.ndarray | None  # (3,) linear mean of COLOR_0
    describe: str


def glb_albedo(gltf: dict, binary: bytes) -> Albedo:
    prim = gltf["meshes"][0]["primitives"][0]
    material = gltf.get("materials", [{}])[prim["material"]] if "material" in prim else {}
    pbr = material.get("pbrMetallicRoughness", {})
    factor = np.asarray(pbr.get("baseColorFactor", [1, 1, 1, 1]), np.float64)
    vertex_mean = None
    if "COLOR_0" in prim["attributes"]:
        vertex_mean = _accessor(gltf, binary, prim["attributes"]["COLOR_0"])[:, :3].mean(axis=0)
    if "baseColorTexture" not in pbr:
        what = "vertex colours (COLOR_0)" if vertex_mean is not None else "no baseColorTexture, no COLOR_0"
        return Albedo(factor, None, vertex_mean, what)
    image = gltf["images"][gltf["textures"][pbr["baseColorTexture"]["index"]]["source"]]
    data = _buffer_view(gltf, binary, image["bufferView"]) if "bufferView" in image else b""
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    if bgr is None:
        return Albedo(factor, None, vertex_mean, "baseColorTexture whose image does not decode")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    return Albedo(factor, rgb, vertex_mean, f"{rgb.shape[1]}x{rgb.shape[0]} {image.get('mimeType', '?')}")


def with_root(gltf: dict, **node: object) -> dict:
    """A copy of the glTF whose scene hangs below one new node with these properties (rotation, translation)."""
    g = copy.deepcopy(gltf)
    scene = g["scenes"][g.get("scene", 0)]
    g["nodes"].append({"name": "viewer_check_root", "children": scene["nodes"], **node})
    scene["nodes"] = [len(g["nodes"]) - 1]
    return g


def negative_models(glb: bytes) -> dict[str, bytes]:
    """Broken copies of a GLB that every check run must reject: upside down, untextured, out of frame."""
    gltf, binary = read_glb(glb)
    positions = _accessor(gltf, binary, gltf["meshes"][0]["primitives"][0]["attributes"]["POSITION"])
    size = float(np.max(positions.max(axis=0) - positions.min(axis=0)))
    untextured = copy.deepcopy(gltf)
    for material in untextured.get("materials", []):
        material.get("pbrMetallicRoughness", {}).pop("baseColorTexture", None)
    models = {
        "upside_down": write_glb(with_root(gltf, rotation=[1.0, 0.0, 0.0, 0.0]), binary),  # 180 degrees about X
        "no_texture": write_glb(untextured, binary),
        "out_of_frame": write_glb(with_root(gltf, translation=[3.0 * size, 0.0, 0.0]), binary),
    }
    albedo = glb_albedo(gltf, binary)
    if albedo.texture is not None:  # every image replaced by a black PNG of its size
        black, data = _appended(gltf, binary, cv2.imencode(".png", np.zeros_like(albedo.texture))[1].tobytes())
        for image in black["images"]:
            image.update(bufferView=len(black["bufferViews"]) - 1, mimeType="image/png")
        models["black_texture"] = write_glb(black, data)
    attributes = gltf["meshes"][0]["primitives"][0]["attributes"]
    if "TEXCOORD_0" in attributes:  # the texture upside down on the surface: v -> 1 - v (the classic flipY bug)
        uv = _accessor(gltf, binary, attributes["TEXCOORD_0"])
        flipped, data = _appended(gltf, binary, np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]).astype("<f4").tobytes())
        acc = flipped["accessors"][attributes["TEXCOORD_0"]]
        acc.update(bufferView=len(flipped["bufferViews"]) - 1, byteOffset=0)
        acc.pop("min", None), acc.pop("max", None)
        models["flipped_v"] = write_glb(flipped, data)
    return models


def _appended(gltf: dict, binary: bytes, blob: bytes) -> tuple[dict, bytes]:
    """A copy of the glTF with a new last bufferView holding ``blob``, appended to the BIN chunk."""
    g = copy.deepcopy(gltf)
    padded = binary + b"\0" * (-len(binary) % 4)
    g["bufferViews"].append({"buffer": 0, "byteOffset": len(padded), "byteLength": len(blob)})
    g["buffers"][0]["byteLength"] = len(padded) + len(blob)
    return g, padded + blob


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


@dataclasses.dataclass
class Views:
    """What the viewer drew: per azimuth the picture (RGB uint8) and the decoded code passes."""

    info: dict
    errors: list[str]
    beauty: dict[int, np.ndarray]
    mask: dict[int, np.ndarray]  # bool (H, W): object pixel in every code pass
    u: dict[int, np.ndarray]
    v: dict[int, np.ndarray]
    height: dict[int, np.ndarray]  # [0, 1] of the model's world bounds
    local: dict[int, np.ndarray]  # (H, W, 3) the mesh's own coordinates (metres; 8 bits of its bounds per axis)


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


# ---------------------------------------------------------------- the checks

def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


LUMA = np.array([0.2126, 0.7152, 0.0722])


def expected_albedo(albedo: Albedo, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Linear RGB albedo the GLB asks for at each pixel (texels sampled bilinearly at the drawn UVs)."""
    if albedo.texture is not None:
        h, w = albedo.texture.shape[:2]
        texel = cv2.remap(albedo.texture, (u * w - 0.5).astype(np.float32), (v * h - 0.5).astype(np.float32),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return srgb_to_linear(texel / 255.0) * albedo.factor[:3]
    base = albedo.vertex_mean if albedo.vertex_mean is not None else np.ones(3)
    return np.broadcast_to(base * albedo.factor[:3], u.shape + (3,)).copy()


def _chroma(rgb: np.ndarray) -> np.ndarray:
    return rgb / max(float(np.sum(rgb)), 1e-9)


def _chroma_fit(shot: np.ndarray, want: np.ndarray) -> tuple[float, float]:
    """(chromaticity difference, white added) of mean linear colours: drawn ~ light x (albedo + white).

    Specular reflection (at most a dielectric's F0 of 4 %) adds the white lights, which desaturates dark
    colours; up to MAX_SPECULAR of white (albedo units) is allowed and the best fit kept.
    """
    fits = [(float(np.abs(_chroma(shot) - _chroma(want + s)).max()), float(s))
            for s in np.linspace(0.0, MAX_SPECULAR, 21)]
    return min(fits)


@dataclasses.dataclass
class Reference:
    """Colours from the photos, independent of the texture: the vertex colours of the pipeline's model.ply."""

    path: Path
    vertices: np.ndarray  # (N, 3) metres, the GLB's frame
    colours: np.ndarray  # (N, 3) linear RGB

    @functools.cached_property
    def tree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self.vertices)


def photo_reference(glb: Path) -> Reference | None:
    """NAME.ply, else model.ply, next to the GLB, if it has vertex colours (the pipeline writes them from the photos).

    A level of detail (model_lod1.glb) has no PLY of its own; the full model's surface stands for it.
    """
    ply = glb.with_suffix(".ply")
    if not ply.is_file():
        ply = glb.parent / "model.ply"
    if not ply.is_file():
        return None
    import trimesh

    mesh = trimesh.load(ply, process=False)
    colours = getattr(mesh.visual, "vertex_colors", None) if getattr(mesh.visual, "kind", None) == "vertex" else None
    if colours is None or len(colours) != len(mesh.vertices):
        return None
    return Reference(ply, np.asarray(mesh.vertices, np.float64), srgb_to_linear(colours[:, :3] / 255.0))


def _detail(shot: np.ndarray, want: np.ndarray) -> tuple[float | None, str]:
    """Per-pixel correlation of drawn and expected colours (linear RGB rows): (r, what was correlated).

    Hue where the expected hues vary: chromaticity along its main direction of variation, which the
    viewer's shading leaves alone (the photos' colours carry the photographed shading, which a viewer's
    light imitates, so brightness alone would correlate even where the texture is wrong); else sRGB
    luminance where that varies; else (None, why not).
    """
    lit = (shot @ LUMA > 0.005) & (want @ LUMA > 0.005)
    if lit.sum() < 50:
        return None, "too few lit pixels"
    c_shot = shot[lit] / shot[lit].sum(axis=1, keepdims=True)
    c_want = want[lit] / want[lit].sum(axis=1, keepdims=True)
    centred = c_want - c_want.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    if (centred @ axis).std() >= MIN_HUE_STD:
        return float(np.corrcoef(c_shot @ axis, c_want @ axis)[0, 1]), "hue"
    l_shot, l_want = shot[lit] ** (1 / 2.2) @ LUMA, want[lit] ** (1 / 2.2) @ LUMA
    if l_want.std() >= MIN_DETAIL_STD:
        return float(np.corrcoef(l_shot, l_want)[0, 1]), "luminance"
    return None, "uniform"


def view_measures(views: Views, albedo: Albedo, az: int, reference: Reference | None = None) -> dict:
    """The figures the checks compare, for one azimuth."""
    mask = views.mask[az]
    h, w = mask.shape
    border = int(mask[0].sum() + mask[-1].sum() + mask[:, 0].sum() + mask[:, -1].sum())
    m = {"coverage": float(mask.mean()), "border": border}
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)  # edges blend
    if inner.sum() < 50:
        return m
    shot = srgb_to_linear(views.beauty[az][inner] / 255.0)
    want = expected_albedo(albedo, views.u[az], views.v[az])[inner]
    m["luminance"] = float(np.mean(views.beauty[az][inner] / 255.0 @ LUMA))
    lum_shot, lum_want = shot @ LUMA, want @ LUMA
    ratio = lum_shot[lum_want > 0.01] / lum_want[lum_want > 0.01]
    if ratio.size > 50:
        m["light"] = float(np.median(ratio))
        p10, p90 = np.percentile(ratio, [10, 90])
        m["spread"] = float(p90 / max(p10, 1e-9))
    # a channel at 255 has lost the colour's proportions (no tone mapping: highlights clip)
    unclipped = views.beauty[az][inner].max(axis=1) < 250
    m["clipped"] = float(1.0 - unclipped.mean())
    keep = unclipped if unclipped.sum() >= 50 else np.ones_like(unclipped)
    m["rgb_shot"], m["rgb_want"] = shot[keep].mean(axis=0), want[keep].mean(axis=0)
    m["chroma"], m["specular"] = _chroma_fit(m["rgb_shot"], m["rgb_want"])
    m["detail_r"], m["detail_kind"] = _detail(shot, want)
    if reference is not None:
        ref = reference.colours[reference.tree.query(views.local[az][inner])[1]]
        m["photo_chroma"], _ = _chroma_fit(m["rgb_shot"], ref.mean(axis=0))
        m["photo_r"], m["photo_kind"] = _detail(shot, ref)
    rows_px = np.nonzero(mask)[0]
    top, bottom = rows_px.min(), rows_px.max()
    band = max(1, round(EDGE_ROWS * (bottom - top)))
    ymin, ymax = views.info["min"][1], views.info["max"][1]
    above_table = (ymin + views.height[az] * (ymax - ymin)) / max(ymax - ymin, 1e-12)  # in model heights
    row = np.arange(h)[:, None]
    m["top_height"] = float(np.median(above_table[mask & (row <= top + band)]))
    m["bottom_height"] = float(np.median(above_table[mask & (row >= bottom - band)]))
    return m


def _span(values: list[float], fmt: str) -> str:
    return format(min(values), fmt) if min(values) == max(values) else f"{min(values):{fmt}}-{max(values):{fmt}}"


def _detail_row(name: str, check: str, what: str, rs: list, kinds: list) -> Row:
    measured = [(r, k) for r, k in zip(rs, kinds, strict=True) if r is not None]
    if not measured:
        return Row(name, check, f"not measured {what} ({', '.join(sorted(set(map(str, kinds))))})".strip(), None)
    r = [x for x, _ in measured]
    return Row(name, check, f"per-pixel r = {_span(r, '.2f')} {what} ({', '.join(sorted({k for _, k in measured}))}, "
               f"{len(r)} of {len(rs)} views)".replace("  ", " "), min(r) >= MIN_DETAIL_R)


def _colour_rows(name: str, ms: dict[int, dict], reference: Reference | None) -> list[Row]:
    """colour, texture detail and photo colours, from every view's measures."""
    rows: list[Row] = []

    def each(key: str) -> list:
        return [m.get(key) for m in ms.values()]

    chroma = each("chroma")
    if None in chroma:
        rows.append(Row(name, "colour", "no measurable object pixels", False))
    else:
        worst = int(np.argmax(chroma))
        shot, want = (np.clip(ms[list(ms)[worst]][k], 0, 1) ** (1 / 2.2) * 255 for k in ("rgb_shot", "rgb_want"))
        spec = _span(each("specular"), ".3f")
        rows.append(Row(name, "colour", f"chromaticity off by {_span(chroma, '.3f')}, white specular {spec}, "
                        f"{_span([100 * c for c in each('clipped')], '.1f')} % clipped pixels left out "
                        f"(worst view: drawn sRGB "
                        f"{np.round(shot).astype(int).tolist()}, texture {np.round(want).astype(int).tolist()})",
                        max(chroma) <= MAX_CHROMA_DIFF))
    rows.append(_detail_row(name, "texture detail", "vs the drawn texels", each("detail_r"), each("detail_kind")))
    if reference is not None:
        pc = each("photo_chroma")
        if None in pc:
            rows.append(Row(name, "photo colours", "no measurable object pixels", False))
        else:
            detail = _detail_row(name, "", "", each("photo_r"), each("photo_kind"))
            rows.append(Row(name, "photo colours", f"vs {reference.path.name}'s vertex colours at the drawn points: "
                            f"chromaticity off by {_span(pc, '.3f')}; {detail.value}",
                            max(pc) <= MAX_PHOTO_CHROMA_DIFF and detail.ok is not False))
    return rows


def glb_rows(name: str, views: Views, albedo: Albedo, reference: Reference | None = None) -> list[Row]:
    rows = [Row(name, "loads", f"three.js r{views.info.get('three', '?')}, {views.info.get('triangles', 0):.0f} "
                f"triangles" + (f"; errors: {'; '.join(views.errors)[:200]}" if views.errors else ""),
                not views.errors and views.info.get("state", "ready") == "ready")]
    textured = albedo.texture is not None or albedo.vertex_mean is not None
    rows.append(Row(name, "textured", albedo.describe, textured and (albedo.texture is None or
                                                                    views.info.get("texturedMeshes", 0) > 0)))
    if not views.beauty:
        return rows
    lo, hi = np.asarray(views.info["min"]), np.asarray(views.info["max"])
    height, size = hi[1] - lo[1], float(np.max(hi - lo))
    centre = 0.5 * (lo + hi)
    on_table = abs(lo[1]) <= ON_PLANE_TOL * height and hi[1] > 0 and np.hypot(centre[0], centre[2]) <= 0.5 * size
    rows.append(Row(name, "on table", f"Y {lo[1]:.3f}..{hi[1]:.3f} m, centre XZ ({centre[0]:.3f}, {centre[2]:.3f}) m",
                    bool(on_table)))
    ms = {az: view_measures(views, albedo, az, reference) for az in views.beauty}

    def each(key: str) -> list:
        return [m.get(key) for m in ms.values()]

    cov, border = each("coverage"), each("border")
    rows.append(Row(name, "in frame", f"covers {_span([100 * c for c in cov], '.1f')} %, border px {max(border)}",
                    all(MIN_COVERAGE <= c <= MAX_COVERAGE for c in cov) and max(border) == 0))
    lum, light, spread = each("luminance"), each("light"), each("spread")
    if None in lum or None in light:
        rows.append(Row(name, "lit", "no measurable object pixels in some view", False))
    else:
        rows.append(Row(name, "lit", f"mean sRGB luminance {_span(lum, '.2f')}, rendered/albedo {_span(light, '.2f')}",
                        min(lum) >= MIN_LUMINANCE and all(LIGHT_RANGE[0] <= x <= LIGHT_RANGE[1] for x in light)))
    if None in spread:
        rows.append(Row(name, "shading varies", "no measurable albedo", False))
    else:
        rows.append(Row(name, "shading varies", f"p90/p10 of rendered/albedo {_span(spread, '.2f')}",
                        min(spread) >= MIN_SHADING_SPREAD))
    rows += _colour_rows(name, ms, reference)
    bottom, top = each("bottom_height"), each("top_height")
    if None in bottom or None in top:
        rows.append(Row(name, "upright", "no measurable object pixels in some view", False))
    else:
        rows.append(Row(name, "upright", f"height above the table plane (model heights) of the silhouette's top rows "
                        f"{_span(top, '.2f')}, bottom rows {_span(bottom, '.2f')}",
                        min(top) >= TOP_BAND and max(abs(b) for b in bottom) <= BOTTOM_BAND))
    return rows


# ---------------------------------------------------------------- USDZ

ARKIT_PRIM_TYPES = {"", "Scope", "Xform", "Camera", "Shader", "Material", "Mesh", "Sphere", "Cube", "Cylinder",
                    "Cone", "Capsule", "GeomSubset", "Points", "SkelRoot", "Skeleton", "SkelAnimation",
                    "BlendShape", "SpatialAudio"}
ARKIT_SHADER_IDS = {"UsdPreviewSurface", "UsdUVTexture", "UsdTransform2d"} | {
    f"UsdPrimvarReader_{t}" for t in ("float", "float2", "float3", "float4", "int", "string", "normal", "point",
                                      "vector", "matrix")}
ARKIT_EXTENSIONS = {"usdc", "usd", "usda", "png", "jpg", "jpeg", "m4a", "mp3", "wav"}


#: What ``usdchecker --arkit`` runs (USD <= 25.x: UsdUtils.ComplianceChecker), for an interpreter whose usd-core has it.
_LEGACY_USDCHECKER = """
import json, sys
from pxr import Sdr, Tf, UsdUtils
if not hasattr(UsdUtils, "ComplianceChecker"):
    print(json.dumps(None)); sys.exit()
missing = []
for sid in ("UsdPreviewSurface", "UsdUVTexture", "UsdPrimvarReader_float2"):
    try:  # usd-core wheels lack the usdShaders plugin: no Sdr definitions of the preview shaders
        node = Sdr.Registry().GetShaderNodeByIdentifier(sid)
    except Tf.ErrorException:
        node = None
    if node is None:
        missing.append(sid)
c = UsdUtils.ComplianceChecker(arkit=True, skipARKitRootLayerCheck=False, rootPackageOnly=False, skipVariants=False,
                               verbose=False)
c.CheckCompliance(sys.argv[1])
from pxr import Usd
print(json.dumps({"version": ".".join(map(str, Usd.GetVersion()[1:])), "errors": c.GetErrors(),
                  "failed": c.GetFailedChecks(), "warnings": c.GetWarnings(), "rules": len(c._rules),
                  "no_definition": missing}))
"""


def legacy_usdchecker_row(name: str, usdz: Path, python: str) -> Row | None:
    """``usdchecker --arkit``'s checks (ComplianceChecker, arkit=True) run by ``python``; None if it has none.

    A failure of ShaderPropertyTypeConformanceChecker ("has invalid shader node") for a shader whose
    Sdr definition that usd-core lacks is the wheel's gap, not the asset's: it is listed, not counted.
    """
    r = subprocess.run([python, "-c", _LEGACY_USDCHECKER, str(usdz)], capture_output=True, text=True, timeout=300)
    try:
        out = json.loads(r.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        return Row(name, "usdchecker --arkit", f"{python} failed: {r.stderr.strip()[-160:]}", False)
    if out is None:
        return None
    excused = [f for f in out["failed"] if "invalid shader node" in f and "ShaderPropertyTypeConformance" in f
               and out["no_definition"]]
    real = [f for f in out["failed"] if f not in excused] + out["errors"]
    value = (f"ComplianceChecker(arkit=True) of usd-core {out['version']}: {out['rules']} rules, "
             f"{len(out['errors'])} errors, {len(out['failed'])} failed checks, {len(out['warnings'])} warnings")
    if excused:
        value += (f"; {len(excused)} 'invalid shader node' not counted: that usd-core has no Sdr definition of "
                  f"{', '.join(out['no_definition'])}")
    if real:
        value += "; " + "; ".join(real)[:200]
    return Row(name, "usdchecker --arkit", value, not real)


def usdchecker_rows(name: str, usdz: Path, legacy_python: str | None = None) -> list[Row]:
    """usdchecker --arkit where it exists; usd-core's validators and the ARKit profile's rules always."""
    exe = shutil.which("usdchecker") or shutil.which("usdchecker", path=str(Path(sys.executable).parent))
    rows = []
    if exe:
        r = subprocess.run([exe, "--arkit", str(usdz)], capture_output=True, text=True, timeout=120)
        text = (r.stdout + r.stderr).strip().splitlines()
        rows.append(Row(name, "usdchecker --arkit", f"exit {r.returncode}: {(text[-1] if text else '')[:120]}",
                        r.returncode == 0))
    else:
        row = legacy_usdchecker_row(name, usdz, legacy_python or sys.executable)
        if row is not None:
            rows.append(row)
    from pxr import Usd, UsdValidation

    stage = Usd.Stage.Open(str(usdz))
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = [e for e in UsdValidation.ValidationContext(validators).Validate(stage)
              if e.GetType() == UsdValidation.ValidationErrorType.Error]
    rows.append(Row(name, "usd validators", f"{len(validators)} validators of usd-core "
                    f"{'.'.join(map(str, Usd.GetVersion()[1:]))} (usdchecker's rules): {len(errors)} errors"
                    + (f": {errors[0].GetMessage()[:120]}" if errors else ""), not errors))
    problems = []
    with zipfile.ZipFile(usdz) as z:
        names = z.namelist()
    if not names or not names[0].endswith(".usdc"):
        problems.append(f"first file {names[:1]} is not a usdc layer")
    problems += [f"{n}: file type not allowed" for n in names if n.rsplit(".", 1)[-1].lower() not in ARKIT_EXTENSIONS]
    for prim in stage.Traverse():
        if prim.GetTypeName() not in ARKIT_PRIM_TYPES:
            problems.append(f"{prim.GetPath()}: prim type {prim.GetTypeName()}")
        if prim.GetTypeName() == "Shader":
            sid = prim.GetAttribute("info:id").Get()
            if sid not in ARKIT_SHADER_IDS:
                problems.append(f"{prim.GetPath()}: shader {sid}")
    layers = stage.GetUsedLayers()
    problems += [f"layer {ly.identifier} outside the package" for ly in layers
                 if "[" not in ly.identifier and not ly.anonymous and ly.identifier != str(usdz)]
    rows.append(Row(name, "ARKit rules", f"{len(names)} files {names}; " + ("; ".join(problems)[:160] or "no problem"),
                    not problems))
    return rows


def usdz_rows(name: str, usdz: Path, glb: bytes | None = None, legacy_python: str | None = None) -> list[Row]:
    """The USDZ checks; with the GLB of the same reconstruction, also its texture, UVs and bounds against that."""
    if importlib.util.find_spec("pxr") is None:
        return [Row(name, "usd-core", "not installed (pip install usd-core): USDZ not checked", None)]
    from pxr import Usd, UsdGeom

    albedo, glb_bounds, glb_mesh = None, None, None
    if glb is not None:
        gltf, binary = read_glb(glb)
        attributes = gltf["meshes"][0]["primitives"][0]["attributes"]
        acc = gltf["accessors"][attributes["POSITION"]]
        glb_bounds = np.array([acc["min"], acc["max"]], np.float64)
        albedo = glb_albedo(gltf, binary)
        uv = _accessor(gltf, binary, attributes["TEXCOORD_0"]) if "TEXCOORD_0" in attributes else None
        glb_mesh = (_accessor(gltf, binary, attributes["POSITION"]), uv)

    rows = usdchecker_rows(name, usdz, legacy_python)
    stage = Usd.Stage.Open(str(usdz))
    up = UsdGeom.GetStageUpAxis(stage)
    rows.append(Row(name, "up axis", str(up), up == UsdGeom.Tokens.y))
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    rows.append(Row(name, "metres per unit", f"{mpu:g}", abs(mpu - 1.0) < 1e-9))
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    rows.append(Row(name, "texture binding", *_texture_binding(stage, meshes, usdz, albedo)))
    if len(meshes) == 1:
        rows.append(Row(name, "surface", *_usd_surface(UsdGeom.Mesh(meshes[0]), glb_mesh)))
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_])
    rng = cache.ComputeWorldBound(stage.GetPseudoRoot()).ComputeAlignedRange()
    lo, hi = np.array(rng.GetMin()), np.array(rng.GetMax())
    value = f"min {np.round(lo, 4).tolist()} max {np.round(hi, 4).tolist()} m"
    if glb_bounds is not None:
        diff = float(np.abs(np.concatenate([lo, hi]) - glb_bounds.ravel()).max())
        rows.append(Row(name, "bounds", value + f"; vs GLB {1000 * diff:.2f} mm", diff <= 1e-3))
    else:
        rows.append(Row(name, "bounds", value, None))
    return rows


def _usd_surface(mesh, glb_mesh: tuple[np.ndarray, np.ndarray | None] | None) -> tuple[str, bool]:
    """Faces wound outward (positive signed volume: AR Quick Look culls back faces); st = the GLB's (u, 1 - v)."""
    from pxr import UsdGeom

    pts = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    if len(counts) == 0 or np.any(counts != 3):
        return "not a triangle mesh", False
    tri = pts[np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)]
    volume = float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        volume = -volume
    problems = [] if volume > 0 else ["faces wound inward"]
    value = f"{len(tri)} triangles, signed volume {1e6 * volume:.1f} cm3"
    if glb_mesh is not None:
        positions, uv = glb_mesh
        st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
        st_v = np.asarray(st.Get(), np.float64) if st and st.HasValue() else None
        if len(positions) != len(pts) or uv is None or st_v is None or len(st_v) != len(uv):
            value += "; vertices or UVs not one to one with the GLB's: st not compared"
        else:
            d_pos = float(np.abs(positions - pts).max())
            d_st = float(np.abs(st_v - np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])).max())
            value += f"; vs GLB: points {1000 * d_pos:.3f} mm, st vs (u, 1 - v) {d_st:.1e}"
            if d_pos > 1e-6 or d_st > 1e-5:
                problems.append("not the GLB's points/UVs")
    return value + ("; " + "; ".join(problems) if problems else ""), not problems


def _texture_binding(stage, meshes: list, usdz: Path, albedo: Albedo | None) -> tuple[str, bool]:
    from pxr import UsdGeom, UsdShade

    if len(meshes) != 1:
        return f"{len(meshes)} meshes (expected 1)", False
    mesh = meshes[0]
    material, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
    if not material:
        return f"{mesh.GetPath()} has no bound material", False
    surface = material.ComputeSurfaceSource()[0]
    if not surface or surface.GetIdAttr().Get() != "UsdPreviewSurface":
        return "the material's surface is not a UsdPreviewSurface", False
    diffuse = surface.GetInput("diffuseColor")
    src = diffuse.GetConnectedSources()[0] if diffuse and diffuse.HasConnectedSource() else []
    if not src or UsdShade.Shader(src[0].source.GetPrim()).GetIdAttr().Get() != "UsdUVTexture":
        return "diffuseColor is not fed by a UsdUVTexture", False
    tex = UsdShade.Shader(src[0].source.GetPrim())
    asset = tex.GetInput("file").Get()
    space = tex.GetInput("sourceColorSpace").Get() if tex.GetInput("sourceColorSpace") else None
    st_in = tex.GetInput("st")
    reader = st_in.GetConnectedSources()[0] if st_in and st_in.HasConnectedSource() else []
    varname = UsdShade.Shader(reader[0].source.GetPrim()).GetInput("varname").Get() if reader else None
    primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar(str(varname)) if varname else None
    with zipfile.ZipFile(usdz) as z:
        inside = asset.path in z.namelist()
        data = z.read(asset.path) if inside else b""
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    problems = []
    if bgr is None:
        problems.append(f"texture {asset.path!r} not a PNG/JPEG inside the package")
    if space != "sRGB":
        problems.append(f"sourceColorSpace {space}")
    if not primvar or not primvar.IsDefined() or str(primvar.GetTypeName()) != "texCoord2f[]":
        problems.append(f"st reader's varname {varname!r} is no texCoord2f[] primvar of the mesh")
    same = ""
    if bgr is not None and albedo is not None and albedo.texture is not None:
        usd_mean = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).reshape(-1, 3).mean(axis=0)
        d = float(np.abs(usd_mean - albedo.texture.reshape(-1, 3).mean(axis=0)).max()) \
            if bgr.shape == albedo.texture.shape else float("inf")
        same = f", mean colour vs the GLB's texture {d:.2f} DN"
        if d > 1.0:
            problems.append("not the GLB's texture")
    value = (f"UsdPreviewSurface.diffuseColor <- UsdUVTexture({asset.path}, {space}) <- primvar {varname}"
             + (f" {bgr.shape[1]}x{bgr.shape[0]}" if bgr is not None else "") + same)
    return value + ("; " + "; ".join(problems) if problems else ""), not problems


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
