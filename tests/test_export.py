"""Mesh and camera export: units, axes, colours, material and round trips."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from calib.camera import invert_T, make_T, project_points
from recon.export import export_colmap, export_mesh, export_nerfstudio, srgb_to_linear
from recon.types import TableMesh

POS_TOL_M = 1e-6  # float32 positions of a 0.1 m object
POSE_TOL = 1e-9  # rotation entries / mm after a text round trip
PIX_TOL = 1e-6  # reprojection through the exported convention, pixels


def tall_box(rng) -> TableMesh:
    """A 40 x 100 x 20 mm box standing on the table (Y from 0 to 100 mm), random colours."""
    tm = trimesh.creation.box(extents=(40.0, 100.0, 20.0))
    tm.apply_translation((5.0, 50.0, -3.0))
    colors = rng.integers(0, 256, (len(tm.vertices), 3)).astype(np.uint8)
    return TableMesh(np.asarray(tm.vertices, float), np.asarray(tm.faces, np.int64),
                     np.asarray(tm.vertex_normals, float), colors)


def glb_json(path) -> dict:
    data = path.read_bytes()
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, total) == (b"glTF", 2, len(data))
    length, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    return json.loads(data[20:20 + length])


def test_glb_is_metres_y_up_with_linear_vertex_colours_and_matte_material(tmp_path):
    mesh = tall_box(np.random.default_rng(0))
    paths = export_mesh(mesh, tmp_path)
    assert set(paths) == {"glb", "ply", "obj"} and all(p.exists() for p in paths.values())
    assert not list(tmp_path.glob(".*.tmp"))  # no temp files left behind

    loaded = trimesh.load(paths["glb"], force="mesh", skip_materials=True)
    assert np.allclose(loaded.bounds, np.array([[-15.0, 0.0, -13.0], [25.0, 100.0, 7.0]]) / 1000, atol=POS_TOL_M)
    assert np.allclose(loaded.extents, [0.040, 0.100, 0.020], atol=POS_TOL_M)  # tallest along +Y
    assert loaded.is_watertight and loaded.volume > 0  # faces still counter-clockwise from outside
    expected = np.rint(srgb_to_linear(mesh.colors_rgb / 255.0) * 255).astype(int)
    assert np.abs(loaded.visual.vertex_colors[:, :3].astype(int) - expected).max() <= 1

    gltf = glb_json(paths["glb"])
    prim = gltf["meshes"][0]["primitives"][0]
    assert {"POSITION", "NORMAL", "COLOR_0"} <= set(prim["attributes"])
    pbr = gltf["materials"][prim["material"]]["pbrMetallicRoughness"]
    assert pbr["metallicFactor"] == 0.0 and 0.8 <= pbr["roughnessFactor"] <= 1.0
    assert pbr["baseColorFactor"] == [1.0, 1.0, 1.0, 1.0]
    pos = gltf["accessors"][prim["attributes"]["POSITION"]]
    assert np.allclose(pos["max"], [0.025, 0.100, 0.007], atol=POS_TOL_M)


def test_srgb_to_linear_matches_the_standard_at_known_points():
    assert np.allclose(srgb_to_linear(np.array([0.0, 0.04045, 0.5, 1.0])),
                       [0.0, 0.04045 / 12.92, 0.21404114, 1.0], atol=1e-7)


@pytest.mark.parametrize("ext", ["ply", "obj"])
def test_ply_and_obj_round_trip_in_metres_with_colours(tmp_path, ext):
    mesh = tall_box(np.random.default_rng(1))
    path = export_mesh(mesh, tmp_path)[ext]
    loaded = trimesh.load(path, process=False)
    assert np.allclose(loaded.vertices, mesh.vertices_table / 1000, atol=POS_TOL_M)
    assert np.array_equal(loaded.faces, mesh.faces)
    assert np.abs(loaded.visual.vertex_colors[:, :3].astype(int) - mesh.colors_rgb).max() <= 1
    assert np.allclose(loaded.vertex_normals, mesh.normals_table, atol=1e-4)


def test_mesh_without_colours_or_normals_exports(tmp_path):
    tm = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    paths = export_mesh(TableMesh(np.asarray(tm.vertices), np.asarray(tm.faces)), tmp_path, stem="bare")
    assert paths["glb"].name == "bare.glb"
    assert "COLOR_0" not in glb_json(paths["glb"])["meshes"][0]["primitives"][0]["attributes"]
    assert trimesh.load(paths["glb"], force="mesh").is_watertight


def test_export_mesh_rejects_mismatched_colours(tmp_path):
    tm = trimesh.creation.icosphere(subdivisions=1)
    bad = TableMesh(np.asarray(tm.vertices), np.asarray(tm.faces), colors_rgb=np.zeros((3, 3), np.uint8))
    with pytest.raises(ValueError, match="colors_rgb"):
        export_mesh(bad, tmp_path)


# --- cameras ---------------------------------------------------------------------------------------


def random_frames(rng, n=5):
    frames = []
    for k in range(n):
        R = Rotation.from_rotvec(rng.normal(0, 1.0, 3)).as_matrix()
        t = np.array([0.0, 0.0, 600.0]) + rng.normal(0, 50.0, 3)
        frames.append((f"images/frame_{k:03d}.jpg", make_T(R, t)))
    return frames


K_CAM = np.array([[1400.0, 0.0, 639.5], [0.0, 1390.0, 481.25], [0.0, 0.0, 1.0]])


def read_colmap(folder):
    cam = [ln.split() for ln in (folder / "cameras.txt").read_text().splitlines() if not ln.startswith("#")][0]
    model, w, h, params = cam[1], int(cam[2]), int(cam[3]), np.array(cam[4:], float)
    lines = [ln for ln in (folder / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    poses = {}
    for ln in lines[0::2]:  # every image line is followed by its (empty) POINTS2D line
        e = ln.split()
        qw, qx, qy, qz, tx, ty, tz = map(float, e[1:8])
        poses[e[9]] = (Rotation.from_quat([qx, qy, qz, qw]).as_matrix(), np.array([tx, ty, tz]))
    return model, w, h, params, poses


@pytest.mark.parametrize("dist, model", [(None, "PINHOLE"), ([0.05, -0.01, 0.001, -0.002], "OPENCV"),
                                         ([0.05, -0.01, 0.001, -0.002, 0.003], "FULL_OPENCV")])
def test_colmap_round_trip_and_projection(tmp_path, dist, model):
    rng = np.random.default_rng(2)
    frames = random_frames(rng)
    pts = rng.uniform(-50, 50, (7, 3))
    paths = export_colmap(K_CAM, 1280, 960, frames, tmp_path, dist=dist, points_table=pts)
    written_model, w, h, params, poses = read_colmap(tmp_path)
    assert (w, h) == (1280, 960)
    assert written_model == model
    fx, fy, cx, cy = params[:4]
    if dist is not None:
        assert np.allclose(params[4:4 + len(dist)], dist) and not np.any(params[4 + len(dist):])
    for name, T in frames:
        R, t_m = poses[name]
        assert np.allclose(R, T[:3, :3], atol=POSE_TOL)
        assert np.allclose(t_m * 1000, T[:3, 3], atol=POSE_TOL)
        # COLMAP's pinhole in its own pixel convention, shifted back to ours
        X = pts / 1000 @ R.T + t_m
        uv_colmap = np.column_stack([fx * X[:, 0] / X[:, 2] + cx, fy * X[:, 1] / X[:, 2] + cy])
        assert np.allclose(uv_colmap - 0.5, project_points(K_CAM, T, pts), atol=PIX_TOL)
    rows = [ln.split() for ln in paths["points3D"].read_text().splitlines() if not ln.startswith("#")]
    assert np.allclose(np.array([r[1:4] for r in rows], float) * 1000, pts, atol=1e-5)


def test_colmap_rejects_names_with_spaces(tmp_path):
    with pytest.raises(ValueError, match="whitespace"):
        export_colmap(K_CAM, 1280, 960, [("my photo.jpg", np.eye(4))], tmp_path)


def test_nerfstudio_round_trip_and_projection(tmp_path):
    rng = np.random.default_rng(3)
    frames = random_frames(rng)
    pts = rng.uniform(-50, 50, (7, 3))
    path = export_nerfstudio(K_CAM, 1280, 960, frames, tmp_path, dist=[0.1, 0.0, 0.0, 0.0],
                             ply_file_path="model.ply")
    doc = json.loads(path.read_text())
    assert doc["w"] == 1280 and doc["h"] == 960 and doc["k1"] == 0.1 and doc["ply_file_path"] == "model.ply"
    for (name, T), fr in zip(frames, doc["frames"], strict=True):
        assert fr["file_path"] == name
        c2w = np.array(fr["transform_matrix"])
        # back to T_cam_table: undo OpenGL axes, metres -> mm, invert
        T_table_cam = c2w @ np.diag([1.0, -1.0, -1.0, 1.0])
        T_table_cam[:3, 3] *= 1000
        assert np.allclose(invert_T(T_table_cam), T, atol=POSE_TOL)
        # nerfstudio's own projection: OpenGL camera looks down -z, y up, pixel centres at +0.5
        P = (pts / 1000 - c2w[:3, 3]) @ c2w[:3, :3]
        u = doc["fl_x"] * P[:, 0] / -P[:, 2] + doc["cx"]
        v = doc["cy"] - doc["fl_y"] * P[:, 1] / -P[:, 2]
        assert np.all(P[:, 2] < 0)
        assert np.allclose(np.column_stack([u, v]) - 0.5, project_points(K_CAM, T, pts), atol=PIX_TOL)
