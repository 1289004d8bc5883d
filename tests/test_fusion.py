"""Fusion of depth maps into points, and the hull+points surface, on a box with a dent."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from test_stereo import SIZE, box_mesh, hull_from_masks, intrinsics, noise_texture, render, turntable_poses

from recon.fusion import fuse_depths
from recon.stereo import depth_maps, hull_depth_range, hull_mesh
from recon.surface import compare_to_hull, fused_surface, splat_depth
from recon.types import DepthMap, FusedPoints

PIT_FLOOR_Y_MM = 30.0   # the dent's floor; the box top is at 50 mm
PIT_TOL_MM = 3.0        # fused surface at the dent's centre, 2 mm voxels
POINT_ACC_MM = 1.5      # 90 % of fused points within this of the GT (320x240, f=400 px, ~250 mm)


def pit_box(height: float, floor_y: float, pit_half: float, half: float = 40.0):
    """(2 half) x height x (2 half) mm box with a square pit (2 pit_half wide) from its top down to floor_y."""
    parts = [((-half, 0, -half), (half, floor_y, half)),
             ((-half, floor_y, -half), (half, height, -pit_half)), ((-half, floor_y, pit_half), (half, height, half)),
             ((-half, floor_y, -pit_half), (-pit_half, height, pit_half)),
             ((pit_half, floor_y, -pit_half), (half, height, pit_half))]
    V, F, n = [], [], 0
    for lo, hi in parts:
        v, f = box_mesh(lo, hi)
        V.append(v)
        F.append(f + n)
        n += len(v)
    return np.concatenate(V), np.concatenate(F)


def dent_box():
    """80 x 50 x 80 mm box with a 30 x 30 x 20 mm square pit in its top (union of boxes)."""
    return pit_box(50.0, 30.0, 15.0)


def pit_scene(v, f, seed: int, dist_mm: float, elev_deg: float, target_y: float, hull_top: float) -> dict:
    """24 turntable views of a textured mesh, its hull, depth maps and fused points."""
    rng = np.random.default_rng(seed)
    K = intrinsics()
    Ts = turntable_poses(24, 15.0, dist_mm, elev_deg, target_table=(0.0, target_y, 0.0))
    imgs, _, masks = render(v, f, K, Ts, SIZE, noise_texture(rng, extent_mm=300))
    hull = hull_from_masks(masks, K, Ts, (-50, -5, -50), (50, hull_top, 50), 2.0)
    near, far = hull_depth_range(hull, K, Ts, SIZE, margin_mm=2.0)
    dms = depth_maps(imgs, K, Ts, (near, far), masks=masks)
    pts = fuse_depths(dms, imgs, K, Ts)
    return dict(K=K, Ts=Ts, v=v, f=f, imgs=imgs, hull=hull, dms=dms, pts=pts)


@pytest.fixture(scope="module")
def dent_scene():
    v, f = dent_box()
    return pit_scene(v, f, seed=0, dist_mm=250.0, elev_deg=50.0, target_y=25.0, hull_top=60.0)


def _top_at_pit_centre(verts):
    sel = (np.abs(verts[:, 0]) < 5) & (np.abs(verts[:, 2]) < 5)
    return verts[sel, 1].max()


def test_fused_points_are_accurate_and_oriented(dent_scene):
    s = dent_scene
    pts = s["pts"]
    assert len(pts.pts_table) > 10000
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(s["v"].astype(np.float32)), o3d.core.Tensor(s["f"].astype(np.uint32)))
    dist = scene.compute_distance(o3d.core.Tensor(pts.pts_table.astype(np.float32))).numpy()
    assert np.percentile(dist, 90) < POINT_ACC_MM
    # points on the top rim face up, on the pit floor too
    top = np.abs(pts.pts_table[:, 1] - 50.0) < 0.5
    assert np.median(pts.normals_table[top, 1]) > 0.9
    np.testing.assert_allclose(np.linalg.norm(pts.normals_table, axis=1), 1.0, atol=1e-6)
    floor = (np.abs(pts.pts_table[:, 0]) < 10) & (np.abs(pts.pts_table[:, 2]) < 10)
    assert np.median(pts.pts_table[floor, 1]) == pytest.approx(PIT_FLOOR_Y_MM, abs=1.0)


def test_fused_surface_recovers_the_dent(dent_scene):
    s = dent_scene
    hv, hf = hull_mesh(s["hull"])
    assert _top_at_pit_centre(hv) > 49.0  # the hull cannot see the dent
    fv, ff = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"])
    assert _top_at_pit_centre(fv) == pytest.approx(PIT_FLOOR_Y_MM, abs=PIT_TOL_MM)
    # nothing outside the hull: every fused vertex within a voxel of the hull's inside
    lo, hi = hv.min(0) - 2.0, hv.max(0) + 2.0
    assert np.all((fv >= lo) & (fv <= hi))
    # the decision prefers the fused mesh here
    cmp = compare_to_hull((hv, hf), (fv, ff), s["dms"][1::2], s["K"], s["Ts"][1::2])
    assert cmp.use_fused and cmp.fused_err_mm < 0.5 * cmp.hull_err_mm


def test_fused_surface_without_points_is_the_hull(dent_scene):
    s = dent_scene
    empty = FusedPoints(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    fv, _ = fused_surface(empty, s["hull"], s["K"], s["Ts"], size=SIZE)
    hv, _ = hull_mesh(s["hull"])
    np.testing.assert_allclose(fv, hv)


def test_inconsistent_depths_are_rejected():
    rng = np.random.default_rng(3)
    K = intrinsics()
    Ts = turntable_poses(6, 10.0, 300.0, 20.0)
    H, W = SIZE[1], SIZE[0]
    dms = [DepthMap(i, rng.uniform(250, 350, (H, W)).astype(np.float32), np.ones((H, W), np.float32))
           for i in range(len(Ts))]
    imgs = [np.zeros((H, W, 3), np.uint8)] * len(Ts)
    pts = fuse_depths(dms, imgs, K, Ts, min_views=3, tol_mm=0.5)
    assert len(pts.pts_table) < 0.01 * H * W


def test_splat_keeps_the_nearest_facing_point():
    K = intrinsics()
    T = np.eye(4)
    pts = FusedPoints(np.array([[0.0, 0.0, 100.0], [0.0, 0.0, 50.0], [0.0, 0.0, 30.0]]),
                      np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]),  # last one faces away
                      np.zeros((3, 3), np.uint8))
    z = splat_depth(pts, K, T, SIZE, stride=2, fill_iters=0)
    cy, cx = int(round(K[1, 2] / 2)), int(round(K[0, 2] / 2))
    assert z[cy, cx] == pytest.approx(50.0)
    assert (z > 0).sum() == 1


def test_rejects_mismatched_inputs():
    K = intrinsics()
    with pytest.raises(ValueError):
        fuse_depths([], [], K, np.stack([np.eye(4)]))


# ------------------------------------------------------------ a pit too deep to see the floor of
WELL_FLOOR_Y_MM = 20.0   # 80 x 60 x 80 box, 40 x 40 pit from its top (60 mm) down to here; walls 20 mm
WELL_TOL_MM = 4.0        # 2 mm voxels; the floor kept as thick as the wall (20 mm), like the pit's


def well_box():
    """80 x 60 x 80 mm box with a 40 x 40 x 40 mm pit: from 30 deg elevation no ray reaches its floor."""
    return pit_box(60.0, WELL_FLOOR_Y_MM, 20.0)


@pytest.fixture(scope="module")
def well_scene():
    v, f = well_box()
    return pit_scene(v, f, seed=1, dist_mm=260.0, elev_deg=30.0, target_y=30.0, hull_top=70.0)


def _top_at(verts, x, z, r=4.0):
    sel = (np.abs(verts[:, 0] - x) < r) & (np.abs(verts[:, 2] - z) < r)
    return verts[sel, 1].max()


def test_unseen_floor_of_a_deep_pit_is_emptied_down_to_a_wall_thick_floor(well_scene):
    s = well_scene
    hv, _ = hull_mesh(s["hull"])
    assert _top_at(hv, 0, 0) > 58.0  # the hull roofs the pit over
    # without the prior the pit is carved only as deep as rays reach: a lid well above the floor
    fv0, _ = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"], cavity_prior=False)
    assert _top_at(fv0, 0, 0) > WELL_FLOOR_Y_MM + 3 * WELL_TOL_MM
    fv, _ = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"])
    assert _top_at(fv, 0, 0) == pytest.approx(WELL_FLOOR_Y_MM, abs=WELL_TOL_MM)
    # the walls keep their top: observed surface stops the descent
    for x, z in ((30, 0), (-30, 0), (0, 30), (0, -30)):
        assert _top_at(fv, x, z, r=3.0) == pytest.approx(60.0, abs=2.0)


def test_cavity_prior_leaves_a_visible_dent_alone(dent_scene):
    s = dent_scene
    a, _ = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"], cavity_prior=False)
    b, _ = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"])
    assert len(a) == len(b) and np.abs(a - b).max() < 1e-6
