"""The baked texture against synthetic ground truth, and the textured files as other tools read them.

A 60 mm box standing on the table carries a known smooth albedo ``albedo(X)``; its views are
ray-cast with known cameras (unlit: each pixel is the albedo where its ray meets the box), the texture
is baked from them, and texels are compared with the albedo at their own surface points.
"""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh

from calib.camera import make_T
from recon.export import export_mesh
from recon.texture import (
    TexturedMesh,
    bake_texture,
    render_albedo,
    srgb_decode_lut,
    srgb_encode,
    texture_mesh,
    texture_side,
    uv_atlas,
    uv_atlas_levels,
)
from recon.types import TableMesh

BOX_MM = 60.0
SIZE = (320, 240)
FOCAL_PX = 300.0
ALBEDO_TOL_DN = 2.0  # median |texel - truth| over the seen sides, 8-bit sRGB codes (measured 0.34)
ALBEDO_P90_TOL_DN = 4.0  # 90th percentile (edges of the box, sampling blur; measured 0.96)
REPO = Path(__file__).resolve().parents[1]


def albedo_srgb(X: np.ndarray) -> np.ndarray:
    """The box's true albedo (N, 3) in [0, 1], sRGB, at table points ``X`` (N, 3) mm: smooth in every direction."""
    r = 0.5 + 0.35 * np.sin(X[:, 0] / 9.0)
    g = 0.5 + 0.35 * np.cos(X[:, 2] / 11.0)
    b = 0.2 + 0.6 * X[:, 1] / BOX_MM
    return np.clip(np.column_stack([r, g, b]), 0.0, 1.0)


def _box() -> TableMesh:
    tm = trimesh.creation.box(extents=[BOX_MM] * 3)
    tm.apply_translation([0.0, BOX_MM / 2, 0.0])
    for _ in range(3):
        tm = tm.subdivide()
    V = np.asarray(tm.vertices, np.float64)
    colours = np.rint(albedo_srgb(V) * 255).astype(np.uint8)
    return TableMesh(V, np.asarray(tm.faces, np.int64), np.asarray(tm.vertex_normals, np.float64), colours)


def _look_at(azimuth_deg: float, elevation_deg: float, distance_mm: float = 260.0) -> np.ndarray:
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    L = np.array([0.0, BOX_MM / 2, 0.0])
    C = L + distance_mm * np.array([np.cos(e) * np.cos(a), np.sin(e), np.cos(e) * np.sin(a)])
    z = (L - C) / np.linalg.norm(L - C)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z]).T
    return make_T(R, -R @ C)


def _K() -> np.ndarray:
    return np.array([[FOCAL_PX, 0, (SIZE[0] - 1) / 2], [0, FOCAL_PX, (SIZE[1] - 1) / 2], [0, 0, 1.0]])


def _views(mesh: TableMesh, n: int, gains=None) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Unlit ray-cast photos of the box (sRGB of the true albedo times each view's gain), masks, poses."""
    from recon.raycast import raycasting_scene

    Ts = np.stack([_look_at(360.0 * k / n + 7.0, 35.0 if k % 2 else 20.0) for k in range(n)])
    scene = raycasting_scene(mesh.vertices_table, mesh.faces)
    K = _K()
    u, v = np.meshgrid(np.arange(SIZE[0], dtype=float), np.arange(SIZE[1], dtype=float))
    d_cam = np.stack([(u - K[0, 2]) / FOCAL_PX, (v - K[1, 2]) / FOCAL_PX, np.ones_like(u)], -1)
    images, masks = [], []
    lut = srgb_decode_lut()
    for k, T in enumerate(Ts):
        R, t = T[:3, :3], T[:3, 3]
        C = -R.T @ t
        rays = np.concatenate([np.broadcast_to(C, d_cam.shape), d_cam @ R], -1).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        hit = np.isfinite(t_hit)
        X = C + (d_cam @ R)[hit] * t_hit[hit][:, None]
        lin = lut[np.rint(albedo_srgb(X) * 255).astype(np.uint8)] * (1.0 if gains is None else gains[k])
        img = np.full((SIZE[1], SIZE[0], 3), 12, np.uint8)  # a dark background the bake must not pull in
        img[hit] = srgb_encode(lin)
        images.append(img)
        masks.append(hit.astype(np.uint8) * 255)
    return images, masks, Ts


def _texel_errors(textured: TexturedMesh, rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    """|texture - truth| (n, 3) in 8-bit codes at random points of the box's sides and top (not the bottom)."""
    m = textured.mesh
    V, F = m.vertices_table, m.faces
    up = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])[:, 1]
    faces = np.flatnonzero(up >= -1e-9)  # not the underside (no view sees it)
    f = rng.choice(faces, n)
    b = rng.dirichlet([1.0, 1.0, 1.0], n)
    X = np.einsum("nk,nkd->nd", b, V[F[f]])
    uv = np.einsum("nk,nkd->nd", b, textured.texcoords[F[f]].astype(np.float64))
    S = textured.texture_rgb.shape[0]
    col = np.clip(np.floor(uv[:, 0] * S).astype(int), 0, S - 1)
    row = np.clip(np.floor(uv[:, 1] * S).astype(int), 0, S - 1)
    texel = textured.texture_rgb[row, col].astype(np.float64)
    return np.abs(texel - albedo_srgb(X) * 255.0)


@pytest.fixture(scope="module")
def box_views():
    mesh = _box()
    return mesh, *_views(mesh, 10)


@pytest.fixture(scope="module")
def baked(box_views):
    mesh, images, masks, Ts = box_views
    return texture_mesh(mesh, images, _K(), Ts, masks=masks, size=512)


def test_atlas_keeps_faces_and_splits_only_at_seams(box_views):
    mesh = box_views[0]
    src, faces, uv = uv_atlas(mesh.vertices_table, mesh.faces, 512)
    assert faces.shape == mesh.faces.shape
    np.testing.assert_array_equal(src[faces], mesh.faces)  # same triangles, same order
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    assert len(mesh.vertices_table) <= len(src) < 1.5 * len(mesh.vertices_table)


def test_baked_texels_match_the_true_albedo(baked):
    err = _texel_errors(baked, np.random.default_rng(0))
    assert np.median(err) < ALBEDO_TOL_DN, np.median(err)
    assert np.percentile(err, 90) < ALBEDO_P90_TOL_DN, np.percentile(err, 90)


def test_exposure_differences_between_views_are_balanced(box_views):
    mesh, _, _, _ = box_views
    gains = np.array([0.75, 1.0 / 0.75] * 5)  # geometric mean 1: the true albedo's level (unbalanced: median 4.9 DN)
    images, masks, Ts = _views(mesh, 10, gains)
    textured = texture_mesh(mesh, images, _K(), Ts, masks=masks, size=512)
    err = _texel_errors(textured, np.random.default_rng(1))
    assert np.median(err) < ALBEDO_TOL_DN, np.median(err)


def test_no_background_bleeds_into_the_charts_or_the_gutter(baked):
    tex = baked.texture_rgb.astype(float)
    assert tex.min() > 25  # the dark background (12) never reaches a texel; the gutter holds chart colours


def test_render_of_the_baked_model_matches_a_view(box_views, baked):
    mesh, images, masks, Ts = box_views
    img, hit = render_albedo(baked.mesh, _K(), Ts[3], SIZE, texcoords=baked.texcoords,
                             texture_rgb=baked.texture_rgb)
    inner = hit & (masks[3] > 0)
    diff = np.abs(img[inner].astype(float) - images[3][inner].astype(float))
    assert np.median(diff) < ALBEDO_TOL_DN, np.median(diff)


def test_bake_rejects_inconsistent_inputs(box_views):
    mesh, images, masks, Ts = box_views
    with pytest.raises(ValueError, match="texcoords"):
        bake_texture(mesh, np.zeros((3, 2)), images, _K(), Ts)
    with pytest.raises(ValueError, match="pose"):
        bake_texture(mesh, np.zeros((len(mesh.vertices_table), 2)), images[:2], _K(), Ts)


def test_texture_side_follows_the_photos_resolution(box_views):
    mesh, _, _, Ts = box_views
    small = texture_side(mesh.vertices_table, mesh.faces, _K(), Ts, 4096)
    big = texture_side(mesh.vertices_table, mesh.faces, _K() * [[4], [4], [1]], Ts, 4096)
    assert 256 <= small < big <= 4096 and big == 4 * small  # 4x the focal length: 4x the texture side
    assert texture_side(mesh.vertices_table, mesh.faces, _K() * [[4], [4], [1]], Ts, 512) == 512


@pytest.fixture(scope="module")
def baked_lods(box_views):
    mesh, images, masks, Ts = box_views
    return texture_mesh(mesh, images, _K(), Ts, masks=masks, size=512, lods=(200, 60))


def test_lods_share_the_one_texture_and_keep_its_detail(baked_lods):
    """Every level of detail maps into the one atlas: its texels are the true albedo at its own points."""
    faces = [len(lv.mesh.faces) for lv in baked_lods.lods]
    assert len(faces) == 2 and faces[1] <= 60 and faces[1] < faces[0] <= 200, faces
    for i, level in enumerate((baked_lods, *baked_lods.lods)):
        assert level.texture_rgb is baked_lods.texture_rgb
        assert level.texcoords.min() >= 0.0 and level.texcoords.max() <= 1.0
        err = _texel_errors(level, np.random.default_rng(2 + i))
        assert np.median(err) < ALBEDO_TOL_DN, (i, np.median(err))
        assert np.percentile(err, 90) < ALBEDO_P90_TOL_DN, (i, np.percentile(err, 90))


def test_a_level_not_below_the_finer_one_is_left_out(box_views):
    mesh, images, masks, Ts = box_views
    textured = texture_mesh(mesh, images[:4], _K(), Ts[:4], masks=masks[:4], size=256,
                            lods=(len(mesh.faces) + 10, 100))
    assert [len(lv.mesh.faces) <= 100 for lv in textured.lods] == [True]


def test_lod_renders_match_a_view(box_views, baked_lods):
    mesh, images, masks, Ts = box_views
    for level in baked_lods.lods:
        img, hit = render_albedo(level.mesh, _K(), Ts[4], SIZE, texcoords=level.texcoords,
                                 texture_rgb=level.texture_rgb)
        inner = hit & (masks[4] > 0)
        diff = np.abs(img[inner].astype(float) - images[4][inner].astype(float))
        assert inner.sum() > 0.5 * (masks[4] > 0).sum() and np.median(diff) < ALBEDO_TOL_DN, np.median(diff)


def test_atlas_levels_put_every_level_in_one_chart_set(box_views):
    mesh = box_views[0]
    from recon.texture import decimate

    coarse = decimate(mesh, 48)
    (src0, f0, uv0), (src1, f1, uv1) = uv_atlas_levels([(mesh.vertices_table, mesh.faces),
                                                       (coarse.vertices_table, coarse.faces)], 512)
    np.testing.assert_array_equal(src0[f0], mesh.faces)
    np.testing.assert_array_equal(src1[f1], coarse.faces)
    # the same table point has the same texture coordinates on both levels (the box's corners are on both)
    corners = np.array([[-30.0, 0.0, -30.0], [30.0, 60.0, 30.0], [30.0, 0.0, 30.0]])
    for c in corners:
        a = np.flatnonzero(np.linalg.norm(mesh.vertices_table[src0] - c, axis=1) < 1e-6)
        b = np.flatnonzero(np.linalg.norm(coarse.vertices_table[src1] - c, axis=1) < 1e-6)
        assert len(a) and len(b)
        ua = {tuple(np.round(u, 5)) for u in uv0[a]}
        assert all(tuple(np.round(u, 5)) in ua for u in uv1[b]), (ua, uv1[b])


# --------------------------------------------------------------------------- files


def _glb_json(data: bytes) -> dict:
    n, kind = struct.unpack("<I4s", data[12:20])
    assert data[:4] == b"glTF" and kind == b"JSON"
    return json.loads(data[20:20 + n])


def test_glb_round_trip_keeps_uvs_and_texture(baked, tmp_path):
    paths = export_mesh(baked.mesh, tmp_path, textured=baked)
    doc = _glb_json(paths["glb"].read_bytes())
    prim = doc["meshes"][0]["primitives"][0]
    assert "TEXCOORD_0" in prim["attributes"] and "COLOR_0" not in prim["attributes"]
    pbr = doc["materials"][0]["pbrMetallicRoughness"]
    assert pbr["metallicFactor"] == 0 and pbr["roughnessFactor"] >= 0.9 and pbr["baseColorTexture"]["index"] == 0
    assert doc["images"][0]["mimeType"] == "image/png"
    loaded = trimesh.load(paths["glb"], force="mesh", process=False)
    assert isinstance(loaded.visual, trimesh.visual.TextureVisuals)
    np.testing.assert_allclose(loaded.vertices * 1000.0, baked.mesh.vertices_table, atol=1e-3)  # metres
    uv = loaded.visual.uv.copy()
    uv[:, 1] = 1.0 - uv[:, 1]  # trimesh keeps OBJ's v-up convention
    np.testing.assert_allclose(uv, baked.texcoords, atol=1e-6)
    img = np.asarray(loaded.visual.material.baseColorTexture.convert("RGB"))
    np.testing.assert_array_equal(img, baked.texture_rgb)  # PNG: lossless
    merged = trimesh.load(paths["glb"], force="mesh")
    merged.merge_vertices(merge_tex=True, merge_norm=True)
    assert merged.is_watertight  # the seams split vertices, not the surface


def test_lod_files_share_the_texture_and_material(baked_lods, tmp_path):
    paths = export_mesh(baked_lods.mesh, tmp_path, textured=baked_lods)
    assert {"glb_lod1", "obj_lod1", "glb_lod2", "obj_lod2"} <= set(paths)
    assert paths["glb_lod2"].name == "model_lod2.glb" and paths["obj_lod1"].name == "model_lod1.obj"
    assert "mtllib model.mtl" in paths["obj_lod1"].read_text()  # one material, one PNG for all levels
    for i, level in enumerate(baked_lods.lods, start=1):
        loaded = trimesh.load(paths[f"glb_lod{i}"], force="mesh", process=False)
        assert len(loaded.faces) == len(level.mesh.faces)
        np.testing.assert_array_equal(np.asarray(loaded.visual.material.baseColorTexture.convert("RGB")),
                                      baked_lods.texture_rgb)
        obj = trimesh.load(paths[f"obj_lod{i}"], force="mesh", process=False)
        np.testing.assert_allclose(obj.visual.uv[:, 1], 1.0 - level.texcoords[:, 1], atol=1e-6)


def test_obj_mtl_png_load_with_the_texture(baked, tmp_path):
    paths = export_mesh(baked.mesh, tmp_path, textured=baked)
    assert {"obj", "mtl", "texture", "ply"} <= set(paths)
    assert f"map_Kd {paths['texture'].name}" in paths["mtl"].read_text()
    loaded = trimesh.load(paths["obj"], force="mesh", process=False)
    assert isinstance(loaded.visual, trimesh.visual.TextureVisuals)
    assert len(loaded.vertices) == len(baked.mesh.vertices_table)
    img = np.asarray(loaded.visual.material.image.convert("RGB"))
    np.testing.assert_array_equal(img, baked.texture_rgb)
    # the same texel through OBJ's v-up coordinates
    np.testing.assert_allclose(loaded.visual.uv[:, 1], 1.0 - baked.texcoords[:, 1], atol=1e-6)


def _validator_env():
    node = shutil.which("node")
    if node is None:
        return None
    probe = subprocess.run([node, "-e", "require.resolve('gltf-validator')"], capture_output=True, cwd=REPO)
    return node if probe.returncode == 0 else None


def test_textured_glb_passes_the_khronos_validator(baked_lods, tmp_path):
    node = _validator_env()
    if node is None:
        pytest.skip("node or the npm package gltf-validator not found (NODE_PATH)")
    paths = export_mesh(baked_lods.mesh, tmp_path, textured=baked_lods)
    for key in ("glb", "glb_lod1", "glb_lod2"):
        res = subprocess.run([node, str(REPO / "benchmarks" / "gltf_validate.mjs"), str(paths[key])],
                             capture_output=True, text=True, timeout=120)
        report = json.loads(res.stdout.splitlines()[-1])
        assert res.returncode == 0 and report["errors"] == 0 and report["warnings"] == 0, (key, report)


# --------------------------------------------------------------------------- the command


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    from turntable.synth import SynthOptions, make_sequence

    root = tmp_path_factory.mktemp("texscene") / "seq"
    make_sequence(root, SynthOptions(object="vase", frames=6, step_deg=60.0, width=320, height=240, focal_px=380.0,
                                     elevation_deg=35.0, distance_mm=430.0, jpeg=95, seed=4))
    return root


def _reconstruct(scene: Path, out: Path, *extra: str) -> int:
    from turntable.cli import main

    return main(["reconstruct", str(scene / "images"), "--cameras", str(scene / "cameras_gt.json"), "--masks",
                 str(scene / "masks"), "--resolution", "32", "--no-fusion", "--quiet", "--out", str(out), *extra])


def test_reconstruct_writes_the_textured_model(small_scene, tmp_path):
    out = tmp_path / "scan"
    assert _reconstruct(small_scene, out, "--texture-size", "512") == 0
    for name in ("model.glb", "model.obj", "model.mtl", "model_albedo.png", "model.ply"):
        assert (out / name).is_file(), name
    doc = _glb_json((out / "model.glb").read_bytes())
    assert "baseColorTexture" in doc["materials"][0]["pbrMetallicRoughness"]
    assert "COLOR_0" not in doc["meshes"][0]["primitives"][0]["attributes"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["files"]["texture"].endswith("model_albedo.png")
    from recon.export import usd_available

    assert (out / "model.usdz").is_file() == usd_available()  # with the extra turntable[usd] only


def test_no_texture_keeps_the_vertex_coloured_model(small_scene, tmp_path):
    out = tmp_path / "scan"
    assert _reconstruct(small_scene, out, "--no-texture") == 0
    assert not (out / "model_albedo.png").exists() and not (out / "model.mtl").exists()
    doc = _glb_json((out / "model.glb").read_bytes())
    assert "COLOR_0" in doc["meshes"][0]["primitives"][0]["attributes"]
    assert "images" not in doc and "baseColorTexture" not in doc["materials"][0]["pbrMetallicRoughness"]


def test_reconstruct_lods_summary_and_cached_texture(small_scene, tmp_path, capsys):
    """--lods writes model_lod1/2 sharing model_albedo.png; summary.json and the screen name the texture and
    the levels; a re-run with the same inputs reuses the cached bake and writes the same files."""
    out = tmp_path / "scan"
    args = ["--texture-size", "512", "--max-faces", "3000", "--lods", "1000,300"]
    assert _reconstruct(small_scene, out, *args) == 0
    first_out = capsys.readouterr().out
    for name in ("model_lod1.glb", "model_lod1.obj", "model_lod2.glb", "model_lod2.obj"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    tex = summary["texture"]
    assert tex["size_px"] == 512 and tex["file"] == "model_albedo.png"
    assert [lv["file"] for lv in tex["levels"]] == ["model.glb", "model_lod1.glb", "model_lod2.glb"]
    faces = [lv["faces"] for lv in tex["levels"]]
    assert faces[0] == summary["mesh"]["faces"] and faces[2] <= 300 and faces[2] < faces[1] <= 1000
    assert "texture         512 x 512 px, model_albedo.png" in first_out
    assert f"LOD 2           model_lod2.glb: {faces[2]} faces" in first_out
    assert summary["files"]["glb_lod2"].endswith("model_lod2.glb")
    before = {p.name: p.read_bytes() for p in out.glob("model*")}
    from turntable.cli import main

    again = ["reconstruct", str(small_scene / "images"), "--cameras", str(small_scene / "cameras_gt.json"),
             "--masks", str(small_scene / "masks"), "--resolution", "32", "--no-fusion", "--out", str(out), *args]
    assert main(again) == 0
    captured = capsys.readouterr()
    assert "texture: reused" in captured.err
    assert "texture" not in json.loads((out / "summary.json").read_text())["time_s"]  # not baked again
    assert {p.name: p.read_bytes() for p in out.glob("model*")} == before
    smaller = [a if a != "512" else "256" for a in again]  # another option: baked again, at that size
    assert main(smaller) == 0
    assert "texture: reused" not in capsys.readouterr().err
    assert json.loads((out / "summary.json").read_text())["texture"]["size_px"] == 256


def test_no_texture_summary_says_vertex_colours(small_scene, tmp_path, capsys):
    out = tmp_path / "scan"
    from turntable.cli import main

    assert main(["reconstruct", str(small_scene / "images"), "--cameras", str(small_scene / "cameras_gt.json"),
                 "--masks", str(small_scene / "masks"), "--resolution", "32", "--no-fusion", "--no-texture",
                 "--out", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text())["texture"] is None
    assert "texture         none (--no-texture)" in capsys.readouterr().out


@pytest.mark.parametrize("value, message", [("60000", "fewer than --max-faces 50000"), ("abc", "face counts"),
                                            ("50", "at least 100")])
def test_lods_are_checked(small_scene, tmp_path, capsys, value, message):
    assert _reconstruct(small_scene, tmp_path / "scan", "--lods", value) == 2
    assert message in capsys.readouterr().err


def test_lods_need_the_texture(small_scene, tmp_path, capsys):
    assert _reconstruct(small_scene, tmp_path / "scan", "--lods", "2000", "--no-texture") == 2
    assert "--lods needs the texture" in capsys.readouterr().err


def test_texture_size_must_be_a_power_of_two(small_scene, tmp_path, capsys):
    assert _reconstruct(small_scene, tmp_path / "scan", "--texture-size", "1000") == 2
    assert "--texture-size" in capsys.readouterr().err


def test_usdz_is_metres_y_up_textured_and_valid(baked, tmp_path):
    pytest.importorskip("pxr", reason="usd-core not installed (pip install '.[usd]')")
    from pxr import Usd, UsdGeom, UsdShade, UsdValidation

    from recon.export import export_usdz

    path = export_usdz(baked, tmp_path / "model.usdz")
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/model/scan"))
    pts = np.asarray(mesh.GetPointsAttr().Get())
    np.testing.assert_allclose(pts * 1000.0, baked.mesh.vertices_table, atol=1e-3)
    st = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").Get())
    np.testing.assert_allclose(st[:, 1], 1.0 - baked.texcoords[:, 1], atol=1e-6)  # USD's t runs up
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert material and "model_albedo.png" in str(
        stage.GetPrimAtPath("/model/scan_material/albedo").GetAttribute("inputs:file").Get())
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()  # usdchecker's rules, usdz included
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    assert not errors, [e.GetMessage() for e in errors]
