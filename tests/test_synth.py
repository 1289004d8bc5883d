"""Synthetic scenes: ground truth agrees with the pixels (turntable.synth)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.camera import circle_conic
from calib.conics import conic_to_ellipse, ellipse_points, sampson_distance
from calib.target import TargetSpec
from turntable.cameras_io import read_cameras
from turntable.cli import main
from turntable.synth.objects import OBJECT_NAMES, make_object
from turntable.synth.render import build_scene, pixel_rays_cam, render_view
from turntable.synth.sequence import SynthOptions, look_at, make_sequence, rot_y

W, H, F = 240, 180, 280.0
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
SPEC = TargetSpec(80.0, 50.0, 3.0)
IOU_MIN = 0.97  # silhouette from rays vs. filled projected triangles (different rasterisers)


def _pose(elevation_deg=35.0, distance_mm=450.0, aim_y=30.0):
    el = np.radians(elevation_deg)
    return look_at(distance_mm * np.array([0.0, np.sin(el), np.cos(el)]), [0.0, aim_y, 0.0])


@pytest.fixture(scope="module")
def vase_scene():
    rng = np.random.default_rng(1)
    mesh = make_object("vase", rng)
    return mesh, build_scene(mesh, SPEC, "dark", rng=rng, target_px_per_mm=3.0)


def _projected_silhouette(mesh, K_, T, w, h, up=8):
    """Independent check: fill every projected triangle (cv2.fillPoly) at up x resolution."""
    V = np.asarray(mesh.vertices, float)
    pc = V @ T[:3, :3].T + T[:3, 3]
    uv = pc[:, :2] / pc[:, 2:3] * [K_[0, 0], K_[1, 1]] + K_[:2, 2]
    shift = 4
    # fine pixel centre c_f = up * c + (up - 1) / 2
    fine = np.round((uv * up + (up - 1) / 2) * (1 << shift)).astype(np.int32)
    canvas = np.zeros((h * up, w * up), np.uint8)
    cv2.fillPoly(canvas, list(fine[np.asarray(mesh.faces)]), 1, lineType=cv2.LINE_8, shift=shift)
    return canvas.reshape(h, up, w, up).mean(axis=(1, 3)) >= 0.5


@pytest.fixture(scope="module")
def chair_scene():
    rng = np.random.default_rng(2)
    mesh = make_object("chair", rng)
    return mesh, build_scene(mesh, SPEC, "clutter", rng=rng, target_px_per_mm=3.0, backdrop_distance_mm=240.0)


@pytest.mark.parametrize("which", ["vase_scene", "chair_scene"])
def test_object_mask_matches_mesh_projection(which, request):
    mesh, scene = request.getfixturevalue(which)
    T0 = _pose()
    for angle in (0.0, 73.0):
        T = T0 @ rot_y(np.radians(angle))
        rgb, mask = render_view(scene, K, T, (W, H), supersample=3, T_world_table=rot_y(np.radians(angle)))
        ref = _projected_silhouette(mesh, K, T, W, H)
        iou = (mask & ref).sum() / (mask | ref).sum()
        assert mask.sum() > 1000, "object too small to test"
        assert iou > IOU_MIN, f"angle {angle}: IoU {iou:.4f}"
        assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8


def test_outer_ring_is_where_circle_conic_says(vase_scene):
    mesh, scene = vase_scene
    T = _pose()
    rgb, mask = render_view(scene, K, T, (W, H), supersample=3)
    grey = rgb.astype(float).mean(axis=2)
    for r_mm in (SPEC.r_outer_mm, SPEC.r_inner_mm):
        ellipse = conic_to_ellipse(circle_conic(K, T, r_mm))
        uv = ellipse_points(ellipse, 400)
        assert np.abs(sampson_distance(circle_conic(K, T, r_mm), uv)).max() < 1e-6
        # centre line of the stroke: dark; 3 mm either side on the plane: bright paper
        uv_in = ellipse_points(conic_to_ellipse(circle_conic(K, T, r_mm - 3.0)), 400)
        uv_out = ellipse_points(conic_to_ellipse(circle_conic(K, T, r_mm + 3.0)), 400)
        px = np.round(uv).astype(int)
        visible = ~cv2.dilate(mask.astype(np.uint8), np.ones((9, 9), np.uint8))[px[:, 1], px[:, 0]].astype(bool)
        assert visible.mean() > 0.6
        ink = cv2.remap(grey.astype(np.float32), *uv.T[:, None, :].astype(np.float32), cv2.INTER_LINEAR).ravel()
        paper_in = cv2.remap(grey.astype(np.float32), *uv_in.T[:, None, :].astype(np.float32), cv2.INTER_LINEAR).ravel()
        paper_out = cv2.remap(grey.astype(np.float32), *uv_out.T[:, None, :].astype(np.float32),
                              cv2.INTER_LINEAR).ravel()
        contrast = np.minimum(paper_in, paper_out)[visible] - ink[visible]
        # the object's shadow darkens some paper; the stroke must still be darker there
        assert np.median(ink[visible]) < 60, f"r={r_mm}: ring not dark along its projected centre line"
        assert np.mean(contrast > 40) > 0.9, f"r={r_mm}: no paper either side of the projected ring"


def test_distortion_rays_reproject_with_cv2():
    rng = np.random.default_rng(3)
    dist = np.array([-0.12, 0.05, 0.001, -0.0005, 0.01])
    uv = rng.uniform([0, 0], [W - 1, H - 1], (500, 2))
    d = pixel_rays_cam(K, uv, dist)
    pts = d * rng.uniform(100, 900, (500, 1))
    back, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    assert np.abs(back.reshape(-1, 2) - uv).max() < 1e-6  # pixels


def test_distorted_render_puts_ring_where_cv2_projects_it(vase_scene):
    _, scene = vase_scene
    T = _pose(elevation_deg=45.0, distance_mm=420.0)
    dist = np.array([-0.25, 0.08, 0.0, 0.0, 0.0])
    rgb, mask = render_view(scene, K, T, (W, H), dist=dist, supersample=2)
    grey = rgb.astype(np.float32).mean(axis=2)
    near_object = cv2.dilate(mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(np.float32)
    pts = np.column_stack([np.cos(t := np.linspace(0, 2 * np.pi, 300, endpoint=False)), np.zeros(300), np.sin(t)])
    def sample(r):
        uv, _ = cv2.projectPoints(pts * r, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, dist)
        uv = uv.reshape(-1, 2).astype(np.float32)
        return (cv2.remap(grey, uv[:, 0:1], uv[:, 1:2], cv2.INTER_LINEAR).ravel(),
                cv2.remap(near_object, uv[:, 0:1], uv[:, 1:2], cv2.INTER_NEAREST).ravel() > 0)
    (ink, hidden_a), (paper, hidden_b) = sample(SPEC.r_outer_mm), sample(SPEC.r_outer_mm - 3.0)
    visible = ~(hidden_a | hidden_b)
    assert visible.mean() > 0.6
    assert np.mean(ink[visible] < 90) > 0.9
    assert np.mean(paper[visible] - ink[visible] > 40) > 0.9
    # the same ring without distortion handling would be elsewhere near the image border
    undist, _ = render_view(scene, K, T, (W, H), supersample=1)
    assert np.abs(undist.astype(float) - rgb.astype(float)).mean() > 5.0


def _small_options(**kw):
    base = dict(frames=3, width=96, height=72, focal_px=110.0, step_deg=30.0, jitter_deg=2.0, supersample=2,
                noise=2.0)
    base.update(kw)
    return SynthOptions(**base)


def test_sequence_files_and_cameras_round_trip(tmp_path):
    opts = _small_options(k1=-0.05, k2=0.01, principal_point=(50.0, 33.0))
    out = make_sequence(tmp_path / "seq", opts)
    seq = read_cameras(out / "cameras_gt.json")
    scene = json.loads((out / "scene.json").read_text())
    assert seq.mode == "turntable" and len(seq.frames) == 3
    np.testing.assert_allclose(seq.intrinsics.dist, [-0.05, 0.01, 0, 0, 0])
    np.testing.assert_allclose(seq.intrinsics.principal_point_px, [50.0, 33.0])
    np.testing.assert_allclose(seq.intrinsics.focal_px, 110.0)
    T0 = seq.frames[0].T_cam_table
    for f, a in zip(seq.frames, scene["angles_deg"], strict=True):
        assert f.ok and np.isnan(f.rms_px) and f.angle_deg == pytest.approx(a)
        np.testing.assert_allclose(f.T_cam_table, T0 @ rot_y(np.radians(f.angle_deg)), atol=1e-9)
        img = cv2.imread(str(out / f.image))
        mask = cv2.imread(str(out / "masks" / Path(f.image).with_suffix(".png").name), cv2.IMREAD_UNCHANGED)
        assert img.shape == (72, 96, 3) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
        assert mask.any()
    assert seq.frames[0].angle_deg == 0.0 and seq.frames[1].angle_deg != 30.0  # jittered
    assert seq.extra["object"] == "vase" and seq.extra["target"]["r_outer_mm"] == 80.0
    import trimesh
    gt = trimesh.load_mesh(out / "object_gt.ply")
    assert gt.visual.kind == "vertex" and len(gt.vertices) > 1000
    assert abs(gt.vertices[:, 1].min()) < 1e-6
    assert not list(tmp_path.glob(".seq*")), "temporary folder left behind"


def test_sequence_is_deterministic_per_seed(tmp_path):
    opts = _small_options(frames=2, handheld=True, backdrop="clutter")
    a = make_sequence(tmp_path / "a", opts)
    b = make_sequence(tmp_path / "b", opts)
    c = make_sequence(tmp_path / "c", _small_options(frames=2, handheld=True, backdrop="clutter", seed=1))
    for name in ("images/frame_001.jpg", "masks/frame_001.png", "cameras_gt.json", "object_gt.ply"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert (a / "images/frame_001.jpg").read_bytes() != (c / "images/frame_001.jpg").read_bytes()
    seq = read_cameras(a / "cameras_gt.json")
    assert seq.mode == "handheld"
    Ta, Tb = seq.frames[0].T_cam_table, seq.frames[1].T_cam_table
    assert np.abs(Ta - Tb).max() > 1.0, "hand-held camera did not move"


@pytest.mark.parametrize("argv, message", [
    (["--r-inner", "90"], "smaller than --r-outer"),
    (["--frames", "0"], "--frames"),
    (["--jpeg", "101"], "--jpeg"),
    (["--elevation-deg", "95"], "--elevation-deg"),
    (["--object", "no_such_mesh.obj"], "neither a built-in"),
    (["--k1", "-0.5", "--focal-px", "40"], "folds over"),
])
def test_bad_options_are_user_errors(tmp_path, capsys, argv, message):
    rc = main(["synth", str(tmp_path / "out"), "--frames", "1", "--size", "64x48", *argv])
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_existing_output_needs_overwrite(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    args = ["synth", str(out), "--frames", "1", "--size", "64x48", "--focal-px", "80", "--supersample", "1"]
    assert main(args) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "keep.txt").exists()
    assert main(args + ["--overwrite"]) == 0
    assert not (out / "keep.txt").exists() and (out / "images" / "frame_000.jpg").exists()


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_objects_fit_inside_inner_ring(name):
    rng = np.random.default_rng(0)
    mesh = make_object(name, rng)
    V = np.asarray(mesh.vertices)
    assert abs(V[:, 1].min()) < 1e-9 and 60.0 <= V[:, 1].max() <= 120.0
    assert np.hypot(V[:, 0], V[:, 2]).max() < SPEC.r_inner_mm - SPEC.stroke_mm / 2 - 5.0
    assert 50.0 <= np.ptp(V[:, 0]) <= 90.0
    colors = np.asarray(mesh.visual.vertex_colors)
    assert colors.shape == (len(V), 4) and colors[:, :3].std() > 5.0


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_objects_are_one_body(name):
    """A real object on a turntable is one body resting on it, and the pipeline drops hull pieces that float
    above the table: every built-in object is one solid at 0.5 mm (the figure's head once floated 1 mm above
    its torso, and its staff 4 mm above the table)."""
    from scipy import ndimage

    mesh = make_object(name, np.random.default_rng(0))
    solid = mesh.voxelized(0.5).fill().matrix
    _, n = ndimage.label(solid, structure=np.ones((3, 3, 3), bool))
    assert n == 1


def test_cup_has_a_concavity_silhouettes_cannot_see():
    mesh = make_object("cup", np.random.default_rng(0))
    assert mesh.is_watertight
    assert mesh.volume < 0.5 * mesh.convex_hull.volume


def test_object_from_mesh_file_is_scaled_to_fit(tmp_path):
    import trimesh
    box = trimesh.creation.box(extents=[300.0, 500.0, 200.0])  # far too big, centred on the origin
    path = tmp_path / "box.ply"
    box.export(path)
    out = make_sequence(tmp_path / "seq", _small_options(object=str(path), frames=1))
    gt = trimesh.load_mesh(out / "object_gt.ply")
    V = np.asarray(gt.vertices)
    assert abs(V[:, 1].min()) < 1e-6 and V[:, 1].max() <= 120.0 + 1e-6
    assert np.hypot(V[:, 0], V[:, 2]).max() <= 0.85 * (SPEC.r_inner_mm - SPEC.stroke_mm / 2) + 1e-6
    np.testing.assert_allclose(np.ptp(V, axis=0) / np.ptp(V, axis=0)[1], [0.6, 1.0, 0.4], rtol=1e-6)
    assert gt.visual.kind == "vertex"


def test_angle_convention_matches_the_mark_reader(tmp_path):
    """GT poses put the printed 0 deg mark on table +X; frame k = frame 0 turned by +angle_deg about +Y."""
    marks = pytest.importorskip("calib.marks")
    opts = _small_options(frames=2, width=480, height=360, focal_px=560.0, step_deg=40.0, jitter_deg=3.0,
                          supersample=2, noise=1.0)
    out = make_sequence(tmp_path / "seq", opts)
    seq = read_cameras(out / "cameras_gt.json")
    T0 = seq.frames[0].T_cam_table
    for f in seq.frames:
        img = cv2.imread(str(out / f.image))
        own = marks.read_turntable_angle(img, seq.intrinsics.K, f.T_cam_table, opts.target_spec())
        assert abs((own.angle_deg + 180.0) % 360.0 - 180.0) < 0.2  # deg
        first = marks.read_turntable_angle(img, seq.intrinsics.K, T0, opts.target_spec())
        assert abs((first.angle_deg + f.angle_deg + 180.0) % 360.0 - 180.0) < 0.2  # reads -angle_deg


@pytest.mark.parametrize("handheld", [False, True])
def test_far_camera_still_sees_the_table(tmp_path, handheld):
    """The room grows with the camera distance: a far camera is never walled off."""
    opts = _small_options(frames=2, distance_mm=1100.0, focal_px=260.0, handheld=handheld)
    out = make_sequence(tmp_path / "far", opts)
    for k in range(2):
        mask = cv2.imread(str(out / "masks" / f"frame_{k:03d}.png"), cv2.IMREAD_UNCHANGED)
        assert 20 < (mask > 0).sum() < mask.size // 4


def test_failed_render_leaves_nothing_behind(tmp_path, monkeypatch):
    import turntable.synth.sequence as sequence

    calls = []

    def failing_render(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("disk on fire")
        return render_view(*args, **kwargs)

    monkeypatch.setattr(sequence, "render_view", failing_render)
    with pytest.raises(RuntimeError, match="disk on fire"):
        make_sequence(tmp_path / "seq", _small_options(frames=3, supersample=1))
    assert len(calls) == 2
    assert list(tmp_path.iterdir()) == [], "partial output or temporary folder left behind"


@pytest.mark.parametrize("text", ["0.9,0.9", "1.2,0.9,0.9", "ivory"])
def test_bad_albedo_is_refused(tmp_path, capsys, text):
    with pytest.raises(SystemExit) as exc:
        main(["synth", str(tmp_path / "out"), "--frames", "1", "--size", "64x48", "--albedo", text])
    assert exc.value.code == 2 and "--albedo" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--albedo"):
        _small_options(albedo=(0.5, 1.5, 0.5))


def test_uniform_albedo_renders_one_colour(tmp_path):
    """--albedo: every object pixel is the same colour up to shading (channel ratios of the albedo)."""
    rgb = (0.85, 0.5, 0.2)
    out = make_sequence(tmp_path / "seq", _small_options(frames=1, noise=0.0, albedo=rgb))
    img = cv2.imread(str(out / "images/frame_000.jpg"))[..., ::-1].astype(float)
    mask = cv2.imread(str(out / "masks/frame_000.png"), cv2.IMREAD_GRAYSCALE) > 0
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    px = img[inner]
    lit = px[px[:, 0] > np.percentile(px[:, 0], 50)]
    # sRGB ratios survive shading (a common factor in linear light): G/R and B/R of the albedo
    tol = 0.08  # JPEG and highlights
    assert abs(np.median(lit[:, 1] / lit[:, 0]) - rgb[1] / rgb[0]) < tol
    assert abs(np.median(lit[:, 2] / lit[:, 0]) - rgb[2] / rgb[0]) < tol
    import trimesh
    gt = trimesh.load_mesh(out / "object_gt.ply")
    assert (np.asarray(gt.visual.vertex_colors)[:, :3] == np.round(np.array(rgb) * 255)).all()


def test_pixel_rays_reject_wrong_point_shapes():
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    with pytest.raises(ValueError, match=r"uv_px must be \(N, 2\), got \(2, 5\)"):
        pixel_rays_cam(K, np.zeros((2, 5)))
