"""Mesh and camera export: units, axes, colours, material and round trips."""

from __future__ import annotations

import json
import os
import shutil
import struct
import types
from pathlib import Path

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


# --- COLMAP tracks ---------------------------------------------------------------------------------

DIST = np.array([-0.08, 0.012, 0.0007, -0.0005, 0.002])  # k1 k2 p1 p2 k3: FULL_OPENCV
OBS_PIX_TOL = 1.0  # an observation against its point's independent reprojection, pixels
TEXT_PIX_TOL = 1e-4  # the same after the text round trip (6 decimals written)
BIG = (np.array([0.0, 50.0, 0.0]), 40.0)  # sphere centre (mm, table frame) and radius (mm)
SMALL = (np.array([0.0, 60.0, 110.0]), 18.0)  # in front of the big one, as seen from camera 0 (+Z)
SIZE = (800, 600)
K_TRACKS = np.array([[900.0, 0.0, 411.3], [0.0, 905.0, 296.8], [0.0, 0.0, 1.0]])


def two_spheres() -> TableMesh:
    """A big sphere and a small one occluding part of it from camera 0, both with grey vertices."""
    parts = [trimesh.creation.icosphere(subdivisions=4, radius=r).apply_translation(c) for c, r in (BIG, SMALL)]
    tm = trimesh.util.concatenate(parts)
    return TableMesh(np.asarray(tm.vertices), np.asarray(tm.faces, np.int64),
                     colors_rgb=np.full((len(tm.vertices), 3), 90, np.uint8))


def ring_cameras(n=8, distance_mm=420.0, elevation_deg=25.0) -> np.ndarray:
    from calib.camera import look_at

    Ts = []
    for k in range(n):
        a, e = np.radians(360.0 * k / n), np.radians(elevation_deg)
        centre = np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)]) * distance_mm
        Ts.append(look_at(centre, np.array([0.0, 50.0, 0.0])))
    return np.stack(Ts)


FACET_COS = 0.05  # the icosphere's facets turn up to ~3 degrees from the true sphere's normal


def sphere_visibility(X, C, margin_mm):
    """Ground truth for points X (P, 3) on the spheres seen from C (3,): faces C (cosine above
    ``-FACET_COS`` for a negative margin, above ``+FACET_COS`` for a positive one), and the segment
    C -> X passes more than ``margin_mm`` outside every sphere (the own one: from C to just before X)."""
    on = [np.abs(np.linalg.norm(X - c, axis=1) - r) < 0.5 for c, r in (BIG, SMALL)]
    seen = np.ones(len(X), bool)
    for (c, r), mine in zip((BIG, SMALL), on, strict=True):
        cos = np.einsum("pd,pd->p", X - c, C - X) / r / np.linalg.norm(C - X, axis=1)
        facing = cos > np.copysign(FACET_COS, margin_mm)
        seen &= ~mine | facing
        d = X - C
        s = np.clip(np.einsum("pd,d->p", d, c - C) / np.einsum("pd,pd->p", d, d), 0.0, 1.0)
        s = np.where(mine, np.minimum(s, 1.0 - 3.0 * margin_mm / np.linalg.norm(d, axis=1)), s)
        clear = np.linalg.norm(C + s[:, None] * d - c, axis=1) > r + margin_mm
        seen &= clear
    return seen


def parse_colmap_text(folder):
    """cameras.txt, images.txt and points3D.txt as plain data, read as COLMAP's text format defines them."""
    cam = [ln.split() for ln in (folder / "cameras.txt").read_text().splitlines() if not ln.startswith("#")][0]
    lines = [ln for ln in (folder / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    images = {}
    for head, obs in zip(lines[0::2], lines[1::2], strict=True):
        e = head.split()
        qw, qx, qy, qz, tx, ty, tz = map(float, e[1:8])
        o = np.array(obs.split(), float).reshape(-1, 3)
        images[int(e[0])] = {"name": e[9], "R": Rotation.from_quat([qx, qy, qz, qw]).as_matrix(),
                             "t_m": np.array([tx, ty, tz]), "xy": o[:, :2], "pid": o[:, 2].astype(int)}
    points = {}
    for ln in (folder / "points3D.txt").read_text().splitlines():
        if ln.startswith("#") or not ln.strip():
            continue
        e = ln.split()
        track = np.array(e[8:], int).reshape(-1, 2)
        points[int(e[0])] = {"xyz_m": np.array(e[1:4], float), "rgb": np.array(e[4:7], int), "track": track}
    return cam, images, points


def test_colmap_tracks_reproject_their_points_and_respect_occlusion(tmp_path):
    import cv2

    from recon.export import sample_surface, surface_tracks

    mesh, Ts = two_spheres(), ring_cameras()
    pts, cols = sample_surface(mesh, 6000, seed=1)
    tracks = surface_tracks(mesh.vertices_table, mesh.faces, pts, cols, K_TRACKS, DIST, SIZE, Ts)
    frames = [(f"frame_{k:03d}.jpg", T) for k, T in enumerate(Ts)]
    export_colmap(K_TRACKS, *SIZE, frames, tmp_path, dist=DIST, tracks=tracks)
    cam, images, points = parse_colmap_text(tmp_path)
    assert cam[1] == "FULL_OPENCV" and len(points) == len(tracks.points_table) > 3000

    n_obs = 0
    for image_id, im in images.items():
        assert len(im["pid"]) > 500, im["name"]  # every image observes points
        X_m = np.array([points[p]["xyz_m"] for p in im["pid"]])
        # OpenCV's own projection (pixel centres at integers) + 0.5 = COLMAP's pixels
        rvec = cv2.Rodrigues(im["R"])[0]
        uv = cv2.projectPoints(X_m * 1000.0, rvec, im["t_m"] * 1000.0, K_TRACKS, DIST)[0].reshape(-1, 2) + 0.5
        assert np.abs(uv - im["xy"]).max() < TEXT_PIX_TOL
        assert np.all((im["xy"] >= 0) & (im["xy"] < SIZE))
        # the observed points are those the true geometry lets this camera see
        T = Ts[image_id - 1]
        C = -T[:3, :3].T @ T[:3, 3]
        assert sphere_visibility(X_m * 1000.0, C, margin_mm=-1.0).all(), im["name"]
        n_obs += len(im["pid"])
        # each observation's index is where the point's track says it is
        for idx, p in enumerate(im["pid"]):
            assert [image_id, idx] in points[p]["track"].tolist()
    assert n_obs == sum(len(p["track"]) for p in points.values())

    # recall: points clearly visible (1 mm clear of every occluder, inside the image) are observed
    X_all = np.array([p["xyz_m"] for p in points.values()]) * 1000.0
    observed = {(i, p) for i, im in images.items() for p in im["pid"]}
    pids = list(points)
    for image_id in images:
        T = Ts[image_id - 1]
        C = -T[:3, :3].T @ T[:3, 3]
        uv = cv2.projectPoints(X_all, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K_TRACKS, DIST)[0].reshape(-1, 2)
        inside = np.all((uv > 1) & (uv < np.array(SIZE) - 2), axis=1)
        clear = sphere_visibility(X_all, C, margin_mm=1.0) & inside
        hits = sum((image_id, pids[k]) in observed for k in np.flatnonzero(clear))
        assert hits >= 0.99 * clear.sum(), (image_id, hits, clear.sum())
    # camera 0 looks at the big sphere past the small one: a shadow of points it does not observe
    C0 = -Ts[0][:3, :3].T @ Ts[0][:3, 3]
    (c, r), (c_small, r_small) = BIG, SMALL
    on_big = np.abs(np.linalg.norm(X_all - c, axis=1) - r) < 0.5
    d = X_all - C0
    s = np.clip(np.einsum("pd,d->p", d, c_small - C0) / np.einsum("pd,pd->p", d, d), 0.0, 1.0)
    shadow = on_big & (np.linalg.norm(C0 + s[:, None] * d - c_small, axis=1) < r_small - 1.0)
    assert shadow.sum() > 50 and not any((1, pids[k]) in observed for k in np.flatnonzero(shadow))


def test_points_off_the_mesh_or_seen_once_are_dropped():
    from recon.export import surface_tracks

    mesh, Ts = two_spheres(), ring_cameras()
    c, r = BIG
    on_top = c + np.array([0.0, r, 0.0])  # every camera (25 deg up) sees the sphere's top
    off = c + np.array([0.0, r + 3.0, 0.0])  # 3 mm above the surface
    pts = np.array([on_top, off])
    tracks = surface_tracks(mesh.vertices_table, mesh.faces, pts, np.zeros((2, 3), np.uint8), K_TRACKS, DIST,
                            SIZE, Ts, surface_tol_mm=1.0)
    assert np.allclose(tracks.points_table, [on_top]) and tracks.visible.all()
    one_view = surface_tracks(mesh.vertices_table, mesh.faces, pts[:1], np.zeros((1, 3), np.uint8), K_TRACKS,
                              DIST, SIZE, Ts[:1])
    assert len(one_view.points_table) == 0  # a track of one view is no track


def test_sample_surface_lies_on_the_mesh_with_interpolated_colours():
    from recon.export import sample_surface

    tm = trimesh.creation.box(extents=(40.0, 100.0, 20.0))
    colors = np.where(tm.vertices[:, 1:2] > 0, [200, 10, 10], [10, 10, 200]).astype(np.uint8)  # top red, bottom blue
    pts, cols = sample_surface(TableMesh(np.asarray(tm.vertices), np.asarray(tm.faces, np.int64),
                                         colors_rgb=colors), 4000, seed=2)
    half = np.abs(pts) - np.array([20.0, 50.0, 10.0])
    assert np.all(half < 1e-9) and np.all(np.isclose(half.max(axis=1), 0.0, atol=1e-9))  # on a face
    top = pts[:, 1] > 49.999
    assert np.all(cols[top] == [200, 10, 10])
    assert 0.25 < np.mean(pts[:, 1] > 0) < 0.75  # area-weighted: as many above the middle as below


@pytest.mark.parametrize("model_dist", [None, DIST[:4], DIST])
def test_pycolmap_reads_the_tracks_and_reprojects_them(tmp_path, model_dist):
    pycolmap = pytest.importorskip("pycolmap")
    from recon.export import sample_surface, surface_tracks

    mesh, Ts = two_spheres(), ring_cameras()
    tracks = surface_tracks(mesh.vertices_table, mesh.faces, *sample_surface(mesh, 3000, seed=3), K_TRACKS,
                            model_dist, SIZE, Ts)
    export_colmap(K_TRACKS, *SIZE, [(f"f{k}.png", T) for k, T in enumerate(Ts)], tmp_path, dist=model_dist,
                  tracks=tracks)
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert rec.num_points3D() == len(tracks.points_table)
    assert rec.compute_num_observations() == tracks.visible.sum()
    cam = rec.cameras[1]
    for image_id, im in rec.images.items():
        obs = [p for p in im.points2D if p.has_point3D()]
        assert len(obs) == tracks.visible[:, image_id - 1].sum() > 0
        for p in obs[::25]:
            xyz = rec.points3D[p.point3D_id].xyz
            uv = cam.img_from_cam(im.cam_from_world() * xyz)  # COLMAP's own camera model
            assert np.linalg.norm(uv - p.xy) < TEXT_PIX_TOL
    assert min(pt.track.length() for pt in rec.points3D.values()) >= 2


# --- the exports as `turntable reconstruct` writes them: self-contained OUT, video frames, nerfstudio ----


@pytest.fixture(scope="module")
def lens_scene(tmp_path_factory):
    """8 views 45 degrees apart of the vase through a lens with barrel distortion, ground-truth cameras."""
    from turntable.synth import SynthOptions, make_sequence

    root = tmp_path_factory.mktemp("lens") / "seq"
    make_sequence(root, SynthOptions(object="vase", frames=8, step_deg=45.0, width=480, height=360, focal_px=560.0,
                                     elevation_deg=35.0, distance_mm=430.0, k1=-0.06, jpeg=92, supersample=1))
    return root


def reconstruct_args(inp, cameras, masks, out, *extra) -> list[str]:
    return ["reconstruct", str(inp), "--cameras", str(cameras), "--masks", str(masks), "--out", str(out),
            "--resolution", "32", "--max-faces", "5000", "--no-fusion", "--quiet", "--export-colmap",
            "--export-nerfstudio", *extra]


def exported_image_paths(out) -> list:
    """Every image path the COLMAP model (relative to OUT/images) and transforms.json (relative to OUT) name."""
    names = [ln.split()[9] for ln in (out / "colmap" / "images.txt").read_text().splitlines()[4::2]]
    doc = json.loads((out / "transforms.json").read_text())
    return [out / "images" / n for n in names] + [out / fr["file_path"] for fr in doc["frames"]]


@pytest.fixture(scope="module")
def moved_export(lens_scene, tmp_path_factory):
    """A reconstruction with both exports, then its OUT moved elsewhere (``mv OUT elsewhere``)."""
    from turntable.cli import main

    root = tmp_path_factory.mktemp("export")
    out = root / "scan"
    assert main(reconstruct_args(lens_scene / "images", lens_scene / "cameras_gt.json", lens_scene / "masks",
                                 out)) == 0
    moved = root / "elsewhere" / "scan_moved"
    moved.parent.mkdir()
    shutil.move(str(out), str(moved))
    return moved


def test_out_moved_elsewhere_still_finds_every_exported_photo(moved_export, lens_scene):
    paths = exported_image_paths(moved_export)
    assert len(paths) == 16 and all(p.is_file() for p in paths), [p for p in paths if not p.is_file()]
    for p in paths:  # the photos themselves, hard-linked (OUT and the photos share this filesystem)
        assert os.path.samefile(p, lens_scene / "images" / p.name)
    summary = json.loads((moved_export / "summary.json").read_text())
    assert Path(summary["files"]["images"]).name == "images"
    assert "images" in json.loads((moved_export / ".turntable" / "published.json").read_text())["files"]


def test_export_of_a_real_run_has_tracks_on_every_image_that_reproject(moved_export, lens_scene):
    import cv2

    from turntable.cameras_io import read_cameras

    cam, images, points = parse_colmap_text(moved_export / "colmap")
    seq = read_cameras(moved_export / "cameras.json")
    intr, T_by_name = seq.intrinsics, {fp.image: fp.T_cam_table for fp in seq.frames}
    assert cam[1] == "OPENCV" and np.isclose(float(cam[8]), -0.06, atol=1e-9)  # k1 of the photos
    assert len(points) > 2000 and min(len(p["track"]) for p in points.values()) >= 2
    for im in images.values():
        assert len(im["pid"]) > 300, im["name"]
        T = T_by_name[im["name"]]
        X_mm = np.array([points[p]["xyz_m"] for p in im["pid"]]) * 1000.0
        uv = cv2.projectPoints(X_mm, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], intr.K, intr.dist)[0].reshape(-1, 2)
        assert np.abs(uv + 0.5 - im["xy"]).max() < OBS_PIX_TOL
        # depths COLMAP's undistorter takes its depth range from: in front, about the camera's distance
        depth = X_mm @ T[2, :3] + T[2, 3]
        assert depth.min() > 300.0 and depth.max() < 560.0


def test_copy_images_copies_and_says_so(lens_scene, tmp_path, capsys):
    from turntable.cli import main

    out = tmp_path / "scan"
    args = reconstruct_args(lens_scene / "images", lens_scene / "cameras_gt.json", lens_scene / "masks", out,
                            "--copy-images")
    args.remove("--quiet")
    assert main(args) == 0
    printed = capsys.readouterr()
    assert "photos for the exports in OUT/images: 8 copied" in printed.out + printed.err
    for p in exported_image_paths(out):
        src = lens_scene / "images" / p.name
        assert not os.path.samefile(p, src) and p.read_bytes() == src.read_bytes()


def test_photos_already_in_out_images_are_used_in_place_and_never_removed(lens_scene, tmp_path):
    from turntable.cli import main

    out = tmp_path / "dataset"
    shutil.copytree(lens_scene / "images", out / "images")
    (out / "images" / "notes.txt").write_text("mine")
    before = sorted(p.name for p in (out / "images").iterdir())
    for _ in range(2):
        assert main(reconstruct_args(out / "images", lens_scene / "cameras_gt.json", lens_scene / "masks",
                                     out)) == 0
        assert sorted(p.name for p in (out / "images").iterdir()) == before
    assert all(p.is_file() for p in exported_image_paths(out))
    assert "images" not in json.loads((out / ".turntable" / "published.json").read_text())["files"]


def test_video_input_writes_the_frames_it_names(lens_scene, tmp_path):
    import cv2

    from turntable.cli import main

    video = tmp_path / "turn.avi"
    frames = sorted((lens_scene / "images").iterdir())
    h, w = cv2.imread(str(frames[0])).shape[:2]
    vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 5, (w, h))
    if not vw.isOpened():
        pytest.skip("no video writer in this OpenCV build")
    for f in frames:
        vw.write(cv2.imread(str(f)))
    vw.release()
    # the ground-truth cameras and masks under the video frames' names
    cams = json.loads((lens_scene / "cameras_gt.json").read_text())
    masks = tmp_path / "masks"
    masks.mkdir()
    for i, fr in enumerate(cams["frames"]):
        shutil.copy(lens_scene / "masks" / f"{Path(fr['image']).stem}.png", masks / f"turn_{i:05d}.png")
        fr["image"] = f"turn_{i:05d}.png"
    (tmp_path / "cams.json").write_text(json.dumps(cams))
    out = tmp_path / "scan"
    assert main(reconstruct_args(video, tmp_path / "cams.json", masks, out)) == 0
    paths = exported_image_paths(out)
    assert sorted({p.name for p in paths}) == [f"turn_{i:05d}.png" for i in range(8)]
    cap = cv2.VideoCapture(str(video))
    for p in paths[:8]:  # the frames as decoded (lossless PNG of what was calibrated)
        ok, img = cap.read()
        assert ok and np.array_equal(cv2.imread(str(p)), img), p.name


# nerfstudio's dataparser, step by step without torch: nerfstudio/data/dataparsers/nerfstudio_dataparser.py
# (Nerfstudio._generate_dataparser_outputs, _get_fname, _load_3D_points) and the ray model of
# nerfstudio/cameras/cameras.py (Cameras.generate_rays: pixel centres at +0.5, camera looking down -z, y up).
def load_like_nerfstudio(data_dir):
    from PIL import Image

    meta = json.loads((data_dir / "transforms.json").read_text())
    fnames = [data_dir / fr["file_path"] for fr in meta["frames"]]
    order = np.argsort([str(f) for f in fnames])  # "sort the frames by fname"
    frames = [meta["frames"][i] for i in order]
    fnames = [fnames[i] for i in order]
    sizes = []
    for f in fnames:  # _get_fname opens each image (PIL) to choose the downscale factor
        with Image.open(f) as im:
            sizes.append(im.size)
    assert meta["camera_model"] in {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"}
    K = np.array([[meta["fl_x"], 0, meta["cx"]], [0, meta["fl_y"], meta["cy"]], [0, 0, 1]], float)
    # camera_utils.get_distortion_params order: k1, k2, k3, k4, p1, p2
    distortion = [float(meta.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "p1", "p2")]
    c2w = np.array([fr["transform_matrix"] for fr in frames], float)[:, :3, :4]
    applied = np.eye(4)
    if "applied_transform" in meta:
        applied[:3] = np.array(meta["applied_transform"], float)
    points = None
    if "ply_file_path" in meta:  # _load_3D_points: open3d point cloud, then transform_matrix @ applied_transform
        import open3d as o3d

        pcd = o3d.io.read_point_cloud(str(data_dir / meta["ply_file_path"]))
        points = np.asarray(pcd.points) @ applied[:3, :3].T + applied[:3, 3]
    return {"names": [f.name for f in fnames], "sizes": sizes, "K": K, "wh": (meta["w"], meta["h"]),
            "distortion": distortion, "c2w": c2w, "points": points}


NS_CENTRE_TOL_M = 1e-9
NS_DIR_TOL = 1e-9


def test_transforms_json_loads_like_nerfstudio_and_matches_cameras_json(moved_export):
    from turntable.cameras_io import read_cameras

    ns = load_like_nerfstudio(moved_export)
    seq = read_cameras(moved_export / "cameras.json")
    intr, by_name = seq.intrinsics, {fp.image: fp.T_cam_table for fp in seq.frames}
    assert all(s == ns["wh"] == (intr.width, intr.height) for s in ns["sizes"])
    assert np.allclose(ns["K"][:2, 2] - 0.5, intr.K[:2, 2]) and np.isclose(ns["K"][0, 0], intr.K[0, 0])
    assert np.allclose(ns["distortion"], [intr.dist[0], intr.dist[1], 0.0, 0.0, intr.dist[2], intr.dist[3]])
    for name, c2w in zip(ns["names"], ns["c2w"], strict=True):
        T = by_name[name]
        R, t = T[:3, :3], T[:3, 3]
        assert np.allclose(c2w[:3, 3], -R.T @ t / 1000.0, atol=NS_CENTRE_TOL_M)  # camera centre, metres
        assert np.allclose(-c2w[:3, 2], R.T @ [0.0, 0.0, 1.0], atol=NS_DIR_TOL)  # looks down its -z
        assert np.allclose(c2w[:3, 1], R.T @ [0.0, -1.0, 0.0], atol=NS_DIR_TOL)  # its +y is image up
        # nerfstudio's ray through the pixel where we project the model's points passes through them
        P = ns["points"][::50]
        p_cam = (P - c2w[:3, 3]) @ c2w[:3, :3]
        x = ns["K"][0, 0] * p_cam[:, 0] / -p_cam[:, 2] + ns["K"][0, 2]
        y = ns["K"][1, 2] - ns["K"][1, 1] * p_cam[:, 1] / -p_cam[:, 2]
        assert np.allclose(np.column_stack([x, y]) - 0.5, project_points(intr.K, T, P * 1000.0), atol=PIX_TOL)
    # the point cloud is the model, in the cameras' frame and unit: metres, in front of every camera
    assert ns["points"] is not None and 0.05 < np.ptp(ns["points"][:, 1]) < 0.2


def test_photos_other_tools_would_read_differently_are_written_upright_as_png(tmp_path):
    import cv2
    from PIL import Image

    from turntable.images import read_image
    from turntable.stages.export import place_images

    rng = np.random.default_rng(4)
    src = tmp_path / "photos"
    src.mkdir()
    pixels = rng.integers(0, 256, (40, 60, 3)).astype(np.uint8)
    Image.fromarray(pixels).save(src / "a plain.jpg", quality=95)
    exif = Image.Exif()
    exif[0x0112] = 6  # stored landscape, shown rotated 90 degrees clockwise (a portrait phone photo)
    Image.fromarray(pixels).save(src / "b_rotated.jpg", quality=95, exif=exif.tobytes())
    Image.fromarray(pixels[:, :, 0]).save(src / "c_grey.png")
    names = ["a plain.jpg", "b_rotated.jpg", "c_grey.png"]
    staging = tmp_path / "out" / ".turntable" / "staging.1"
    staging.mkdir(parents=True)
    opts = types.SimpleNamespace(input=src, out=tmp_path / "out", copy_images=False, every=1, frames=None)
    placed = place_images(opts, names, staging)
    assert placed.folder == "images" and placed.staged
    assert placed.file_names == {"a plain.jpg": "a_plain.jpg", "b_rotated.jpg": "b_rotated.jpg.png",
                                 "c_grey.png": "c_grey.png"}  # no whitespace: COLMAP's text format
    assert placed.counts == {"hard-linked": 1, "copied": 0, "written as PNG": 2}
    out = staging / "images"
    assert os.path.samefile(out / "a_plain.jpg", src / "a plain.jpg")
    for name in names[1:]:  # as calibrated: upright, 3 channels, 8 bit, and PIL (nerfstudio) sees the same
        written = out / placed.file_names[name]
        assert np.array_equal(cv2.imread(str(written), cv2.IMREAD_UNCHANGED), read_image(src / name))
        with Image.open(written) as im:
            assert im.mode == "RGB" and im.size == read_image(src / name).shape[1::-1]
    assert read_image(src / "b_rotated.jpg").shape[:2] == (60, 40)  # the rotation was applied


def test_pycolmap_undistorts_the_moved_export_and_every_image_gets_a_depth_range(moved_export, lens_scene, tmp_path):
    """What COLMAP's dense stage reads: image_undistorter on the export as it is, then each image's depth
    range as patch-match computes it (mvs::Model::ComputeDepthRanges: 1st/99th percentile of its tracks'
    depths, x0.75 / x1.25) must hold the true object's depths."""
    pycolmap = pytest.importorskip("pycolmap")

    pycolmap.undistort_images(str(tmp_path / "dense"), str(moved_export / "colmap"), str(moved_export / "images"))
    rec = pycolmap.Reconstruction(str(tmp_path / "dense" / "sparse"))
    assert rec.num_images() == 8 and all((tmp_path / "dense" / "images" / im.name).is_file()
                                         for im in rec.images.values())
    truth_m = trimesh.load(lens_scene / "object_gt.ply", process=False).vertices / 1000.0
    for image_id, im in rec.images.items():
        T = im.cam_from_world().matrix()
        depth = np.sort([T[2, :3] @ rec.points3D[p.point3D_id].xyz + T[2, 3]
                         for p in im.points2D if p.has_point3D()])
        assert len(depth) > 300 and depth[0] > 0, image_id
        lo, hi = depth[int(len(depth) * 0.01)] * 0.75, depth[int(len(depth) * 0.99)] * 1.25
        true = truth_m @ T[2, :3] + T[2, 3]
        assert lo <= true.min() and true.max() <= hi, (image_id, lo, hi, true.min(), true.max())
