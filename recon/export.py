"""Files for other tools: the mesh (GLB, PLY, OBJ, USDZ) and the cameras (COLMAP, nerfstudio).

Every file is in **metres** in the table frame (origin at the pattern centre on
the table plane, +Y up, right-handed), which is already glTF's frame, so the
only conversion is ``p_m = p_mm / 1000``. Files are written whole or not at
all (temporary file, then ``os.replace``).

Conversions at this edge:

* **glTF colours**: ``COLOR_0`` is a *linear* multiplier (glTF 2.0 §3.7.2.1)
  while photos are sRGB, so the GLB stores ``srgb_to_linear(rgb / 255)`` as
  float RGBA; PLY/OBJ keep the sRGB bytes (what MeshLab and Blender's PLY
  importer expect). The GLB carries one non-metallic material
  (``metallicFactor`` 0, ``roughnessFactor`` 0.9, white base colour) so the
  vertex colours show as they are instead of glTF's default metal.

The cameras' files and their conversions (pixels, poses, COLMAP's tracks) are
:mod:`recon.export_cameras`, whose public names are re-exported here; this
module writes the mesh: GLB (vertex colours, or a texture and its levels of
detail), PLY, OBJ (+ MTL and the PNG), USDZ, and samples points on it
(:func:`sample_surface`, COLMAP's points without fusion).
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from .export_cameras import (
    MAX_TRACK_POINTS,
    MM_PER_M,
    ColmapTracks,
    export_colmap,
    export_nerfstudio,
    project_photo_px,
    surface_tracks,
)
from .fileio import atomic_write_bytes
from .types import TableMesh

if TYPE_CHECKING:
    from .texture import TexturedMesh

__all__ = ["export_mesh", "png_bytes", "export_colmap", "export_nerfstudio", "glb_bytes", "srgb_to_linear",
           "ColmapTracks", "surface_tracks", "sample_surface", "project_photo_px", "MAX_TRACK_POINTS", "lod_stem"]

# glTF material of a scan: vertex colours times white, dielectric, matte.
SCAN_MATERIAL = {
    "name": "scan",
    "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.9},
    "doubleSided": False,
}


def export_mesh(mesh: TableMesh, out_dir: str | os.PathLike, *, stem: str = "model",
                textured: TexturedMesh | None = None) -> dict[str, Path]:
    """Write ``<stem>.glb``, ``<stem>.ply`` and ``<stem>.obj`` in metres.

    With ``textured`` (the same surface with a UV atlas and its texture,
    :mod:`recon.texture`), the GLB carries the texture as its material's
    ``baseColorTexture`` (no ``COLOR_0``) and the OBJ names ``<stem>.mtl``,
    whose ``map_Kd`` is ``<stem>_albedo.png``; the PLY keeps ``mesh``
    (watertight, vertex colours). Its levels of detail (``textured.lods``)
    are ``<stem>_lod1.glb``/``.obj``, ... sharing that texture and material.

    Parameters
    ----------
    mesh : TableMesh
        Vertices (N, 3) mm in the table frame, outward faces; normals are
        computed if missing, colours are optional.
    out_dir : path
        Created if missing.
    stem : str
        File name without extension.

    Returns
    -------
    dict
        ``{"glb": path, "ply": path, "obj": path}``, and ``"mtl"``, ``"texture"`` with ``textured``
        (and ``"glb_lod1"``, ``"obj_lod1"``, ... with its levels of detail).
    """
    V, F, N, C = _mesh_arrays(mesh)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {ext: out / f"{stem}.{ext}" for ext in ("glb", "ply", "obj")}
    tm = _trimesh_m(V, F, N, C)
    atomic_write_bytes(paths["ply"], trimesh.exchange.ply.export_ply(tm, encoding="binary", vertex_normal=True))
    if textured is not None:
        paths.update(_export_textured(textured, out, stem))
        return paths
    atomic_write_bytes(paths["glb"], glb_bytes(V / MM_PER_M, F, N, C))
    obj = trimesh.exchange.obj.export_obj(tm, include_normals=True, include_color=C is not None,
                                          include_texture=False, header=None)
    atomic_write_bytes(paths["obj"], obj.encode())
    return paths


def png_bytes(rgb: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 RGB image as a PNG file."""
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.asarray(rgb, np.uint8), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("could not encode the texture as PNG")
    return buf.tobytes()


def lod_stem(stem: str, level: int) -> str:
    """File stem of a level of detail: ``stem`` itself for level 0, ``<stem>_lod<level>`` for coarser ones."""
    return stem if level == 0 else f"{stem}_lod{level}"


def _export_textured(textured: TexturedMesh, out: Path, stem: str) -> dict[str, Path]:
    """``<stem>.glb`` with the texture embedded, ``<stem>.obj`` + ``.mtl`` + ``<stem>_albedo.png``; each level
    of detail ``textured.lods[i - 1]`` as ``<stem>_lod<i>.glb`` (the same PNG embedded) and ``.obj`` (naming
    ``<stem>.mtl``: one material, one texture file for every level)."""
    png = png_bytes(textured.texture_rgb)
    paths = {"mtl": out / f"{stem}.mtl", "texture": out / f"{stem}_albedo.png"}
    atomic_write_bytes(paths["texture"], png)
    atomic_write_bytes(paths["mtl"], (f"# turntable: matte, the photo texture (sRGB)\nnewmtl scan\n"
                                      f"Ka 0 0 0\nKd 1 1 1\nKs 0 0 0\nNs 1\nillum 1\nd 1\n"
                                      f"map_Kd {paths['texture'].name}\n").encode())
    for i, level in enumerate((textured, *textured.lods)):
        V, F, N, _ = _mesh_arrays(level.mesh)
        uv = np.asarray(level.texcoords, np.float64)
        if uv.shape != (len(V), 2):
            raise ValueError(f"texcoords of level {i}: expected {(len(V), 2)}, got {uv.shape}")
        name, suffix = lod_stem(stem, i), "" if i == 0 else f"_lod{i}"
        glb, obj = out / f"{name}.glb", out / f"{name}.obj"
        atomic_write_bytes(glb, glb_bytes(V / MM_PER_M, F, N, texcoords=uv, texture_png=png))
        lines = [f"# turntable: metres, +Y up, table frame\nmtllib {paths['mtl'].name}\no {name}\n",
                 _rows("v", V / MM_PER_M, "{:.7g}"),
                 _rows("vt", np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]), "{:.7g}"),  # OBJ: v up from the bottom row
                 _rows("vn", N, "{:.6g}"), "usemtl scan\n"]
        f1 = np.asarray(F, np.int64) + 1
        lines.append("".join(f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}\n" for a, b, c in f1.tolist()))
        atomic_write_bytes(obj, "".join(lines).encode())
        paths[f"glb{suffix}"], paths[f"obj{suffix}"] = glb, obj
    return paths


def _rows(tag: str, a: np.ndarray, fmt: str) -> str:
    line = tag + (" " + fmt) * a.shape[1] + "\n"
    return "".join(line.format(*row) for row in a.tolist())


def _mesh_arrays(mesh: TableMesh):
    V = np.asarray(mesh.vertices_table, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise ValueError(f"vertices_table: expected (N, 3) with N > 0, got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0 or F.min() < 0 or F.max() >= len(V):
        raise ValueError(f"faces: expected (M, 3) indices into {len(V)} vertices, got {F.shape}")
    if mesh.normals_table is None:
        N = np.asarray(trimesh.Trimesh(V, F, process=False).vertex_normals, dtype=np.float64)
    else:
        N = np.asarray(mesh.normals_table, dtype=np.float64)
    C = None if mesh.colors_rgb is None else np.asarray(mesh.colors_rgb, dtype=np.uint8)
    for name, a in (("normals_table", N), ("colors_rgb", C)):
        if a is not None and a.shape != V.shape:
            raise ValueError(f"{name}: expected {V.shape}, got {a.shape}")
    return V, F, N, C


def _trimesh_m(V, F, N, C) -> trimesh.Trimesh:
    """trimesh in metres, vertex order kept (``process=False``)."""
    colors = None if C is None else np.hstack([C, np.full((len(C), 1), 255, np.uint8)])
    return trimesh.Trimesh(V / MM_PER_M, F, vertex_normals=N, vertex_colors=colors, process=False)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light (IEC 61966-2-1)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def glb_bytes(vertices_m: np.ndarray, faces: np.ndarray, normals: np.ndarray,
              colors_rgb: np.ndarray | None = None, *, texcoords: np.ndarray | None = None,
              texture_png: bytes | None = None) -> bytes:
    """A binary glTF 2.0 file of one triangle mesh with one non-metallic material.

    Parameters
    ----------
    vertices_m : (N, 3) float
        Positions in metres, glTF frame (+Y up, right-handed).
    faces : (M, 3) int
        Counter-clockwise seen from outside (glTF's front faces).
    normals : (N, 3) float
        Unit vertex normals.
    colors_rgb : (N, 3) uint8, optional
        sRGB vertex colours; stored as linear float RGBA ``COLOR_0``. Not with a texture
        (``COLOR_0`` would multiply it).
    texcoords : (N, 2) float, optional
        ``TEXCOORD_0`` (glTF: origin at the image's top-left corner, v down), with ``texture_png``.
    texture_png : bytes, optional
        The sRGB base-colour texture as a PNG file, embedded in the binary chunk.
    """
    if (texcoords is None) != (texture_png is None) or (texture_png is not None and colors_rgb is not None):
        raise ValueError("give texcoords with texture_png, and no colors_rgb with a texture")
    n = np.asarray(normals, np.float64)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 1e-12, n / np.maximum(length, 1e-12), (0.0, 1.0, 0.0))  # glTF: NORMAL must be unit
    arrays: list[np.ndarray] = [np.asarray(vertices_m, np.float32), n.astype(np.float32)]
    attributes = {"POSITION": 0, "NORMAL": 1}
    if colors_rgb is not None:
        lin = srgb_to_linear(np.asarray(colors_rgb, np.float64) / 255.0)
        arrays.append(np.hstack([lin, np.ones((len(lin), 1))]).astype(np.float32))
        attributes["COLOR_0"] = 2
    if texcoords is not None:
        arrays.append(np.asarray(texcoords, np.float32).reshape(-1, 2))
        attributes["TEXCOORD_0"] = len(arrays) - 1
    arrays.append(np.asarray(faces, np.uint32).ravel())

    views, accessors, offset = [], [], 0
    for i, a in enumerate(arrays):
        is_index = i == len(arrays) - 1
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": a.nbytes,
                      "target": 34963 if is_index else 34962})
        acc = {"bufferView": i, "componentType": 5125 if is_index else 5126,
               "count": int(a.size if is_index else len(a)),
               "type": "SCALAR" if is_index else f"VEC{a.shape[1]}"}
        if i == 0:  # POSITION requires bounds
            acc["min"], acc["max"] = a.min(axis=0).tolist(), a.max(axis=0).tolist()
        accessors.append(acc)
        offset += a.nbytes  # every array is a multiple of 4 bytes long
    material = dict(SCAN_MATERIAL)
    blobs = [a.tobytes() for a in arrays]
    extra: dict = {}
    if texture_png is not None:  # the image's own buffer view (no target), padded to 4 bytes
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(texture_png)})
        blobs.append(texture_png + b"\0" * (-len(texture_png) % 4))
        offset += len(blobs[-1])
        extra = {"images": [{"bufferView": len(views) - 1, "mimeType": "image/png"}],
                 "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
                 "textures": [{"sampler": 0, "source": 0}]}
        material["pbrMetallicRoughness"] = {**SCAN_MATERIAL["pbrMetallicRoughness"],  # type: ignore[dict-item]
                                            "baseColorTexture": {"index": 0}}
    gltf = {
        "asset": {"version": "2.0", "generator": "turntable recon.export",
                  "extras": {"units": "m", "frame": "table: origin at the pattern centre, +Y up"}},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "model"}],
        "meshes": [{"name": "model", "primitives": [
            {"attributes": attributes, "indices": len(arrays) - 1, "material": 0, "mode": 4}]}],
        "materials": [material],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": offset}],
        **extra,
    }
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    binary = b"".join(blobs)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return b"".join([struct.pack("<4sII", b"glTF", 2, total),
                     struct.pack("<I4s", len(js), b"JSON"), js,
                     struct.pack("<I4s", len(binary), b"BIN\0"), binary])


# --- points on the surface -------------------------------------------------------------------------


def sample_surface(mesh: TableMesh, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points spread evenly over a mesh's surface (area-weighted) with their interpolated colours.

    Returns
    -------
    points_table : (n, 3) float64
        mm, on the surface.
    colors_rgb : (n, 3) uint8
        Barycentric mix of the face's vertex colours (grey without colours).
    """
    V, F, _, C = _mesh_arrays(mesh)
    rng = np.random.default_rng(seed)
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(F), size=int(n), p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(int(n))), rng.random(int(n))
    bary = np.column_stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2])  # uniform on each triangle
    pts = np.einsum("nk,nkd->nd", bary, tri[face])
    if C is None:
        return pts, np.full((len(pts), 3), 128, np.uint8)
    cols = np.einsum("nk,nkd->nd", bary, C[F[face]].astype(np.float64))
    return pts, np.clip(np.rint(cols), 0, 255).astype(np.uint8)


# --- USDZ ------------------------------------------------------------------------------------------


def usd_available() -> bool:
    """Whether ``usd-core`` (``pxr``) is installed: the optional extra ``turntable[usd]``."""
    try:
        import pxr  # noqa: F401
    except ImportError:
        return False
    return True


def export_usdz(textured: TexturedMesh, path: str | os.PathLike) -> Path:
    """Write a USDZ (AR Quick Look, Apple Vision Pro) of a textured mesh: metres, +Y up, UsdPreviewSurface.

    The package holds one ``.usdc`` layer (``metersPerUnit`` 1, ``upAxis`` Y; the mesh counter-clockwise
    seen from outside, USD's right-handed default) with ``primvars:st`` (USD's t runs up: ``1 - v``), a
    matte, non-metallic ``UsdPreviewSurface`` whose ``diffuseColor`` reads the sRGB PNG texture, and the
    texture itself. Needs ``usd-core`` (:func:`usd_available`).
    """
    import tempfile

    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdUtils, Vt

    V, F, N, _ = _mesh_arrays(textured.mesh)
    uv = np.asarray(textured.texcoords, np.float64)
    with tempfile.TemporaryDirectory(prefix="usdz") as tmp:
        layer, tex = Path(tmp) / "model.usdc", Path(tmp) / "model_albedo.png"
        tex.write_bytes(png_bytes(textured.texture_rgb))
        stage = Usd.Stage.CreateNew(str(layer))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        root = UsdGeom.Xform.Define(stage, "/model")
        stage.SetDefaultPrim(root.GetPrim())
        mesh = UsdGeom.Mesh.Define(stage, "/model/scan")
        pts = V / MM_PER_M
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*pts.min(axis=0).tolist()), Gf.Vec3f(*pts.max(axis=0).tolist())]))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(F), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(F.astype(np.int32).ravel()))
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(N.astype(np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]).astype(np.float32)))
        material = UsdShade.Material.Define(stage, "/model/scan_material")
        surface = UsdShade.Shader.Define(stage, "/model/scan_material/surface")
        surface.CreateIdAttr("UsdPreviewSurface")
        surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
        surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.9)
        reader = UsdShade.Shader.Define(stage, "/model/scan_material/st_reader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        image = UsdShade.Shader.Define(stage, "/model/scan_material/albedo")
        image.CreateIdAttr("UsdUVTexture")
        image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(tex.name)
        image.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
        image.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        image.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(image.ConnectableAPI(), "rgb")
        material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
        stage.GetRootLayer().Save()
        packed = Path(tmp) / "model.usdz"
        if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(layer)), str(packed)):
            raise ValueError("usd-core could not package the USDZ")
        out = Path(path)
        atomic_write_bytes(out, _zip_times_fixed(packed.read_bytes()))
    return out


def _zip_times_fixed(data: bytes) -> bytes:
    """A zip (USDZ) with every entry's DOS time stamp set to 1980-01-01 00:00: the same model, the same bytes."""
    import io
    import zipfile

    buf = bytearray(data)
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        infos = z.infolist()
        start = z.start_dir  # the central directory's offset (CPython keeps it on the ZipFile)
    fixed = struct.pack("<HH", 0, (0 << 9) | (1 << 5) | 1)  # time 00:00:00, date 1980-01-01
    for info in infos:
        if buf[info.header_offset:info.header_offset + 4] == b"PK\x03\x04":
            buf[info.header_offset + 10:info.header_offset + 14] = fixed
    pos = start
    while buf[pos:pos + 4] == b"PK\x01\x02":
        buf[pos + 12:pos + 16] = fixed
        n, m, k = struct.unpack("<HHH", buf[pos + 28:pos + 34])
        pos += 46 + n + m + k
    return bytes(buf)
