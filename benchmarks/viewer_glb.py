"""The GLB side of benchmarks/viewer_check.py: the file, its broken copies, and the checks of what three.js drew.

``read_glb``/``write_glb`` read and write a binary glTF; ``glb_albedo`` is the
colour the file asks for (texture or vertex colours); ``negative_models`` are
the broken copies ``--negatives`` checks. ``glb_rows`` turns a viewer's
screenshots and code passes (``Views``) into the check rows; the checks and
their thresholds are described in ``benchmarks/viewer_check.py``'s docstring.
``Row`` (one line of the table) and ``CheckError`` (bad input) are shared with
``viewer_usd.py``.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import struct
from pathlib import Path

import cv2
import numpy as np

# thresholds (see benchmarks/viewer_check.py's docstring)
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


def accessor(gltf: dict, binary: bytes, index: int) -> np.ndarray:
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
        vertex_mean = accessor(gltf, binary, prim["attributes"]["COLOR_0"])[:, :3].mean(axis=0)
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
    positions = accessor(gltf, binary, gltf["meshes"][0]["primitives"][0]["attributes"]["POSITION"])
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
        uv = accessor(gltf, binary, attributes["TEXCOORD_0"])
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
