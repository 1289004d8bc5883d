"""Plane-sweep stereo on ray-cast synthetic scenes with a known depth."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy import ndimage

from calib.camera import look_at
from recon.stereo import depth_maps, hull_depth_range, select_neighbours
from recon.types import VoxelHull

# ---------------------------------------------------------------- synthetic scenes (shared with test_fusion)
FOCAL_PX = 400.0
SIZE = (320, 240)


look_at_T = look_at  # T_cam_table of a camera at eye_table looking at target_table (+Y up)


def turntable_poses(n_views: int, step_deg: float, dist_mm: float, elev_deg: float,
                    target_table=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(V, 4, 4) poses of a fixed camera while the table turns by ``step_deg``."""
    e = np.radians(elev_deg)
    eye = np.array([0.0, dist_mm * np.sin(e), -dist_mm * np.cos(e)]) + target_table
    T0 = look_at_T(eye, np.asarray(target_table, float))
    out = []
    for i in range(n_views):
        a = np.radians(step_deg * (i - (n_views - 1) / 2))
        Ry = np.array([[np.cos(a), 0, np.sin(a), 0], [0, 1, 0, 0], [-np.sin(a), 0, np.cos(a), 0], [0, 0, 0, 1]])
        out.append(T0 @ Ry)
    return np.stack(out)


def intrinsics(size=SIZE, focal_px=FOCAL_PX) -> np.ndarray:
    W, H = size
    return np.array([[focal_px, 0, (W - 1) / 2], [0, focal_px, (H - 1) / 2], [0, 0, 1.0]])


def noise_texture(rng: np.random.Generator, cell_mm: float = 1.5, extent_mm: float = 200.0):
    """Smooth random grey texture of 3-D position (value noise), 0..255."""
    n = int(extent_mm / cell_mm) + 3
    grid = ndimage.gaussian_filter(rng.random((n, n, n)), 0.7)
    grid = (grid - grid.mean()) / grid.std()

    def tex(pts_table: np.ndarray) -> np.ndarray:
        idx = (pts_table + extent_mm / 2) / cell_mm
        v = ndimage.map_coordinates(grid, idx.T, order=1, mode="nearest")
        return np.clip(128 + 45 * v, 0, 255)
    return tex


def render(verts, faces, K, Ts, size, tex, flat_faces=None):
    """Ray-cast images (V, H, W, 3) uint8, depth (V, H, W) and masks of a textured mesh.

    Faces listed in ``flat_faces`` get a constant grey (no texture).
    """
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(verts, np.float32)), o3d.core.Tensor(np.asarray(faces, np.uint32)))
    W, H = size
    imgs, depths = [], []
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    pix = np.stack([u, v, np.ones_like(u)], -1)
    for T in Ts:
        R, t = T[:3, :3], T[:3, 3]
        d = pix @ np.linalg.inv(K).T @ R
        c = -R.T @ t
        rays = np.concatenate([np.broadcast_to(c, d.shape), d], -1).astype(np.float32)
        ans = scene.cast_rays(o3d.core.Tensor(rays))
        th = ans["t_hit"].numpy()
        hit = np.isfinite(th)
        pts = c + d * np.where(hit, th, 0)[..., None]
        g = np.full((H, W), 30.0)
        g[hit] = tex(pts[hit])
        if flat_faces is not None:
            prim = ans["primitive_ids"].numpy()
            g[hit & np.isin(prim, flat_faces)] = 200.0
        imgs.append(np.repeat(g[..., None], 3, -1).astype(np.uint8))
        depths.append(np.where(hit, th, 0.0))
    return np.stack(imgs), np.stack(depths), np.stack(depths) > 0


def box_mesh(lo, hi):
    """Axis-aligned box (8 vertices, 12 faces, outward)."""
    import trimesh
    m = trimesh.creation.box(bounds=np.array([lo, hi], float))
    return np.asarray(m.vertices), np.asarray(m.faces)


def hull_from_masks(masks, K, Ts, lo, hi, voxel_mm) -> VoxelHull:
    """Silhouette carving on a grid (test helper): +voxel inside all masks, -voxel outside."""
    axes = [np.arange(a, b + 1e-9, voxel_mm) for a, b in zip(lo, hi, strict=True)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([X, Y, Z], -1).reshape(-1, 3)
    inside = np.ones(len(pts), bool)
    for m, T in zip(masks, Ts, strict=True):
        pc = pts @ T[:3, :3].T + T[:3, 3]
        uv = pc @ K.T
        u = np.round(uv[:, 0] / uv[:, 2]).astype(int)
        v = np.round(uv[:, 1] / uv[:, 2]).astype(int)
        ok = (u >= 0) & (v >= 0) & (u < m.shape[1]) & (v < m.shape[0])
        inside &= ok & m[np.clip(v, 0, m.shape[0] - 1), np.clip(u, 0, m.shape[1] - 1)]
    occ = inside.reshape(X.shape).astype(np.float32)
    vals = (ndimage.gaussian_filter(occ, 0.8) - 0.5) * 2 * voxel_mm
    return VoxelHull(values=vals.astype(np.float32), origin_table=np.array(lo, float), voxel_mm=float(voxel_mm))


# ---------------------------------------------------------------- tests
DEPTH_TOL_MM = 1.0     # plane at ~300 mm, half-resolution sweep, 0.75 px/sample before refinement
CONF_TEXTURED = 0.5    # median confidence on the textured plane


def _plane_scene(rng, flat_half=False):
    """A textured slab facing the camera at ~240 mm, 60 mm in front of the turntable's axis (a face through
    the axis barely moves in the image as the table turns: see ``test_a_pattern_that_does_not_move_...``);
    optionally its left half untextured."""
    K = intrinsics()
    Ts = turntable_poses(5, 4.0, 300.0, 0.0, target_table=(0.0, 0.0, 0.0))
    import trimesh
    m = trimesh.creation.box(bounds=np.array([(-80, -60, -60), (80, 60, -50)], float)).subdivide().subdivide()
    verts, faces = np.asarray(m.vertices), np.asarray(m.faces)
    flat = np.nonzero(verts[faces].mean(1)[:, 0] > 0)[0] if flat_half else None
    imgs, depth, masks = render(verts, faces, K, Ts, SIZE, noise_texture(rng), flat)
    return K, Ts, imgs, depth, masks


def test_textured_plane_depth_and_confidence():
    rng = np.random.default_rng(0)
    K, Ts, imgs, depth_gt, masks = _plane_scene(rng)
    near = np.where(masks, depth_gt - 15.0, 0.0)
    far = np.where(masks, depth_gt + 15.0, 0.0)
    dms = depth_maps(imgs, K, Ts, (near, far), masks=masks, neighbours=2)
    r = 2
    dm = dms[r]
    core = ndimage.binary_erosion(masks[r], iterations=8)
    good = core & (dm.confidence > 0.3)
    assert good.sum() > 0.8 * core.sum()
    err = np.abs(dm.depth_mm[good] - depth_gt[r][good])
    assert np.percentile(err, 90) < DEPTH_TOL_MM
    assert np.median(dm.confidence[core]) > CONF_TEXTURED
    assert np.all(dm.depth_mm[~masks[r]] == 0)


def test_untextured_region_gets_low_confidence():
    rng = np.random.default_rng(1)
    K, Ts, imgs, depth_gt, masks = _plane_scene(rng, flat_half=True)
    near = np.where(masks, depth_gt - 15.0, 0.0)
    far = np.where(masks, depth_gt + 15.0, 0.0)
    dm = depth_maps(imgs, K, Ts, (near, far), masks=masks, neighbours=2)[2]
    core = ndimage.binary_erosion(masks[2], iterations=8)
    flat = core & (imgs[2][..., 0] == 200)
    textured = core & (imgs[2][..., 0] != 200)
    assert flat.sum() > 1000 and textured.sum() > 1000
    assert np.percentile(dm.confidence[flat], 95) < 0.1
    assert np.median(dm.confidence[textured]) > CONF_TEXTURED


def test_a_pattern_that_does_not_move_with_the_table_is_no_evidence_of_depth():
    """Shading under a fixed light on a turning body of revolution, or a shadow, stays put in the image
    while the table turns. Matched between views it looks like a surface where the warp is the identity
    (near the axis, far behind the object's front): a confident wrong depth that carved a white snowman
    (1.6 % of its diagonal). The sweep's peak must beat the unmoved image by the uniqueness gap."""
    rng = np.random.default_rng(2)
    K, Ts, imgs, depth_gt, masks = _plane_scene(rng)
    static = np.repeat(imgs[2:3], len(imgs), axis=0)  # the middle view's image in every frame
    near = np.where(masks[2], depth_gt[2] - 15.0, 0.0)[None].repeat(len(imgs), 0)
    far = np.where(masks[2], depth_gt[2] + 80.0, 0.0)[None].repeat(len(imgs), 0)  # the axis is 60 mm behind
    core = ndimage.binary_erosion(masks[2], iterations=8)
    dm = depth_maps(static, K, Ts, (near, far), masks=masks[2][None].repeat(len(imgs), 0), neighbours=2)[2]
    assert np.percentile(dm.confidence[core], 95) < 0.05
    moving = depth_maps(imgs, K, Ts, (near, far), masks=masks, neighbours=2)[2]  # the same range, true images
    assert np.median(moving.confidence[core]) > CONF_TEXTURED


def test_hull_depth_range_brackets_a_box():
    K = intrinsics()
    Ts = turntable_poses(3, 10.0, 300.0, 20.0)
    verts, faces = box_mesh((-30, 0, -30), (30, 40, 30))
    _, depth_gt, masks = render(verts, faces, K, Ts, SIZE, lambda p: np.full(len(p), 100.0))
    near, far = hull_depth_range((verts, faces), K, Ts, SIZE)
    hit = near > 0
    assert np.array_equal(hit[:, 5:-5, 5:-5], masks[:, 5:-5, 5:-5])
    np.testing.assert_allclose(near[masks], depth_gt[masks], atol=1e-2)
    core = ndimage.binary_erosion(masks, structure=np.ones((1, 7, 7)))
    assert np.all(far[core] > near[core] + 1.0)
    assert far[masks].max() < 300.0 + 60.0


def test_select_neighbours_by_angle():
    Ts = turntable_poses(12, 30.0, 300.0, 20.0)
    nb = select_neighbours(Ts, 2)
    assert sorted(nb[5]) == [3, 4, 6, 7]
    assert sorted(nb[0]) == [1, 2, 10, 11]  # 12 x 30 deg wraps around


def test_rejects_bad_arguments():
    K = intrinsics()
    with pytest.raises(ValueError):
        depth_maps([np.zeros((240, 320, 3), np.uint8)] * 2, K, np.stack([np.eye(4)] * 3), (1.0, 2.0))


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6])
def test_best_half_mean_is_the_mean_of_the_best_half(n):
    from recon.stereo import _best_half_mean

    rng = np.random.default_rng(n)
    scores = rng.uniform(-1.0, 1.0, (n, 23, 17)).astype(np.float32)
    scores[:, :4] = 0.25  # ties
    k = (n + 1) // 2
    want = np.sort(scores, axis=0)[::-1][:k].mean(axis=0)
    got = _best_half_mean(scores)
    assert got.shape == (23, 17) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.array_equal(scores[:, :4], np.full((n, 4, 17), 0.25, np.float32))  # the input is left as it was


def test_pick_peak_finds_the_peak_and_the_second_local_maximum():
    from recon.stereo import _pick_peak

    rng = np.random.default_rng(7)
    D, h, w = 12, 9, 8
    vol = rng.uniform(-1.0, 1.0, (D, h, w)).astype(np.float32)
    pos, c1, c2 = _pick_peak(vol)
    best = vol.argmax(axis=0)
    np.testing.assert_array_equal(c1, vol.max(axis=0))
    assert np.all(np.abs(pos - best) <= 0.5)
    for i in range(h):  # the second local maximum by its definition, pixel by pixel
        for j in range(w):
            col = vol[:, i, j]
            maxima = [col[d] for d in range(D) if abs(d - best[i, j]) > 1
                      and (d == 0 or col[d] >= col[d - 1]) and (d == D - 1 or col[d] >= col[d + 1])]
            assert c2[i, j] == (max(maxima) if maxima else -1.0)
