"""Fusion of depth maps into points, and the hull+points surface, on a box with a dent."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from test_stereo import SIZE, box_mesh, hull_from_masks, intrinsics, noise_texture, render, turntable_poses

from recon.fusion import FusionOptions, fuse_depths
from recon.meshing import clip_to_hull, hull_excess_mm, mesh_from_hull, mesh_stats
from recon.regions import choose_regions, supported_field
from recon.stereo import depth_maps, hull_depth_range, hull_mesh
from recon.surface import SurfaceOptions, _unseen_cavity, compare_to_hull, fused_field, fused_surface, splat_depth
from recon.types import DepthMap, FusedPoints, TableMesh, VoxelHull

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
    return dict(K=K, Ts=Ts, v=v, f=f, imgs=imgs, masks=np.asarray(masks, bool), hull=hull, dms=dms, pts=pts)


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
    fused = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"])
    fv, ff = fused.vertices_table, fused.faces
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
    fv = fused_surface(empty, s["hull"], s["K"], s["Ts"], size=SIZE).vertices_table
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


def test_options_objects_and_keyword_overrides_are_the_same_settings(dent_scene):
    s = dent_scene
    kw = fuse_depths(s["dms"], s["imgs"], s["K"], s["Ts"], min_views=4, voxel_mm=1.0)
    opt = fuse_depths(s["dms"], s["imgs"], s["K"], s["Ts"], options=FusionOptions(min_views=4, voxel_mm=1.0))
    np.testing.assert_array_equal(kw.pts_table, opt.pts_table)
    assert 0 < len(kw.pts_table) < len(s["pts"].pts_table)  # the settings took effect
    # a misspelt setting is refused, as a misspelt keyword argument was
    with pytest.raises(TypeError):
        fuse_depths(s["dms"], s["imgs"], s["K"], s["Ts"], min_view=4)
    with pytest.raises(TypeError):
        depth_maps(s["imgs"], s["K"], s["Ts"], (1.0, 2.0), neighbors=2)
    with pytest.raises(TypeError):
        fused_field(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"], cavity=False)
    with pytest.raises(TypeError):
        choose_regions(s["hull"], s["hull"].values, s["dms"], s["K"], s["Ts"], min_pixel=3)


def test_fused_surface_is_a_table_mesh(dent_scene):
    s = dent_scene
    mesh = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"], options=SurfaceOptions(cavity_prior=False))
    assert isinstance(mesh, TableMesh) and mesh.faces.shape[1] == 3 and mesh.vertices_table.shape[1] == 3
    np.testing.assert_array_equal(mesh.vertices_table, fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"],
                                                                     cavity_prior=False).vertices_table)


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
    fv0 = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"], cavity_prior=False).vertices_table
    assert _top_at(fv0, 0, 0) > WELL_FLOOR_Y_MM + 3 * WELL_TOL_MM
    fv = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"]).vertices_table
    assert _top_at(fv, 0, 0) == pytest.approx(WELL_FLOOR_Y_MM, abs=WELL_TOL_MM)
    # the walls keep their top: observed surface stops the descent
    for x, z in ((30, 0), (-30, 0), (0, 30), (0, -30)):
        assert _top_at(fv, x, z, r=3.0) == pytest.approx(60.0, abs=2.0)


def test_cavity_prior_leaves_a_visible_dent_alone(dent_scene):
    s = dent_scene
    a = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"], cavity_prior=False).vertices_table
    b = fused_surface(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"]).vertices_table
    assert len(a) == len(b) and np.abs(a - b).max() < 1e-6


# ------------------------------------------------------------ carve only on evidence
def test_cavity_prior_needs_an_opening_seen_from_above():
    """A thin layer of free space at the top of a solid block starts no cavity; a deep observed pit does."""
    vox = 1.0
    h = np.full((30, 30, 30), -5.0, np.float32)
    h[3:27, 2:26, 3:27] = 5.0                      # a solid block, top layer j = 25
    D = h.copy()
    C = np.zeros(h.shape, np.float32)
    down = np.zeros(h.shape, np.int16)
    # noise: one voxel of free space at the top, seen only by cameras below it
    D[8:22, 25, 8:22] = -1.0
    C[8:22, 25, 8:22] = 3.0
    E = _unseen_cavity(h, D, C, down, vox, min_area_mm2=100.0, min_views=2, min_opening_mm=5.0)
    assert not E.any()
    # the same layer seen from above is still too shallow to be an opening
    down[8:22, 25, 8:22] = 3
    assert not _unseen_cavity(h, D, C, down, vox, 100.0, 2, 5.0).any()
    # an observed pit 8 voxels deep, looked into from above: the unseen space below it empties
    D[8:22, 18:26, 8:22] = -1.0
    C[8:22, 18:26, 8:22] = 3.0
    down[8:22, 18:26, 8:22] = 3
    E = _unseen_cavity(h, D, C, down, vox, 100.0, 2, 5.0)
    assert E[15, 17, 15] and E[15, 10, 15]
    assert not E[15, 2, 15]                          # a floor stays
    assert not E[3, 17, 15] and not E[26, 17, 15]    # walls stay
    # the pit's lowest voxel lies within the depth noise of the unseen space under it: one view saw it free
    # (at 0.8 mm voxels the rendered cup's cavity stayed full so); the pit above it was looked into
    down[8:22, 18, 8:22] = 1
    E2 = _unseen_cavity(h, D, C, down, vox, 100.0, 2, 5.0)
    assert (E2 == E).all()
    # a pit seen free only from below all the way up (the top of a head above every camera) starts nothing
    down[8:22, 18:26, 8:22] = 0
    assert not _unseen_cavity(h, D, C, down, vox, 100.0, 2, 5.0).any()


def test_fused_field_never_leaves_the_hull(dent_scene):
    s = dent_scene
    F = fused_field(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"])
    assert np.all(s["hull"].values >= F)
    # points far outside the hull (a speck of bad stereo) change nothing outside it
    rng = np.random.default_rng(5)
    speck = FusedPoints(rng.normal((0.0, 120.0, 0.0), 2.0, (200, 3)), np.tile([0.0, 1.0, 0.0], (200, 1)),
                        np.zeros((200, 3), np.uint8))
    both = FusedPoints(np.vstack([s["pts"].pts_table, speck.pts_table]),
                       np.vstack([s["pts"].normals_table, speck.normals_table]),
                       np.vstack([s["pts"].colors_rgb, speck.colors_rgb]))
    F2 = fused_field(both, s["hull"], s["K"], s["Ts"], s["dms"])
    assert np.all(s["hull"].values >= F2)


def test_one_view_of_free_space_carves_nothing(dent_scene):
    """Free space must be seen by several views: the dent from a single view stays hull."""
    s = dent_scene
    h = s["hull"].values
    F1 = fused_field(s["pts"], s["hull"], s["K"], s["Ts"][:1], s["dms"][:1])
    assert not np.any((h > 0) & (F1 <= 0))
    F = fused_field(s["pts"], s["hull"], s["K"], s["Ts"], s["dms"])
    assert np.sum((h > 0) & (F <= 0)) * 8.0 > 0.5 * 30 * 30 * 20  # the 30x30x20 mm dent, 2 mm voxels


def test_unjudgeable_stereo_keeps_the_hull(dent_scene):
    s = dent_scene
    F = fused_field(s["pts"], s["hull"], s["K"], s["Ts"][0::2], s["dms"][0::2])
    blind = [DepthMap(d.view, d.depth_mm, np.zeros_like(d.confidence)) for d in s["dms"][1::2]]
    ch = choose_regions(s["hull"], F, blind, s["K"], s["Ts"][1::2])
    assert ch.n_regions > 0 and ch.n_kept == 0
    np.testing.assert_array_equal(ch.values, s["hull"].values)


def test_dent_kept_by_held_out_views_in_one_watertight_piece(dent_scene):
    s = dent_scene
    hull = s["hull"]
    F = fused_field(s["pts"], hull, s["K"], s["Ts"][0::2], s["dms"][0::2])
    ch = choose_regions(hull, F, s["dms"][1::2], s["K"], s["Ts"][1::2])
    assert ch.n_kept >= 1 and ch.fused_err_mm < 0.5 * ch.hull_err_mm
    G = supported_field(hull.values, ch.values)
    mesh = clip_to_hull(mesh_from_hull(VoxelHull(G, hull.origin_table, hull.voxel_mm), max_faces=20000), hull)
    st = mesh_stats(mesh)
    assert st.watertight and st.n_bodies == 1
    assert _top_at_pit_centre(mesh.vertices_table) == pytest.approx(PIT_FLOOR_Y_MM, abs=PIT_TOL_MM)
    assert hull_excess_mm(mesh, hull) < OUTSIDE_TOL_MM


OUTSIDE_TOL_MM = 0.05   # vertices may sit this far outside the hull after clipping (trilinear hull)


def test_supported_field_fills_enclosed_voids_and_drops_cut_off_pieces():
    h = np.full((40, 20, 20), -3.0, np.float32)
    h[2:38, 2:18, 2:18] = 3.0                       # one hull body
    F = h.copy()
    F[10:13, 8:11, 8:11] = -1.0                     # a bubble no camera could see into
    F[30] = np.minimum(F[30], -1.0)                 # a cut that severs the end x > 30
    G = supported_field(h, F)
    assert np.all(h >= G)
    assert np.all(G[10:13, 8:11, 8:11] > 0)         # bubble filled
    assert np.all(G[31:38] <= 0)                    # the severed small piece is gone
    assert np.all(G[3:29, 3:17, 3:17] > 0)          # the big piece stays
    with pytest.raises(ValueError):
        supported_field(h, F[:-1])



def test_kept_and_rejected_regions_meet_in_a_ramp_not_a_step():
    """A slab whose top stereo lowered by 6 mm: where a kept region meets a rejected one the
    surface ramps from the fused height to the hull's (a hard switch left a 6 mm wall: box-shaped
    seams on real models); far from the border each side is exactly its own surface, and a kept
    region's border with space nobody carved (a cavity's wall) is left as fused."""
    from recon.regions import _blend_kept

    vox = 1.0
    y = np.arange(60) * vox
    h = np.broadcast_to((40.0 - y)[None, :, None], (90, 60, 30)).astype(np.float32).copy()  # top at Y = 40
    F = np.minimum(h, (34.0 - y)[None, :, None]).astype(np.float32)  # fused top at Y = 34
    labels = np.zeros(h.shape, np.int32)
    carved = (h > 0) & (F <= 0)
    labels[:45][carved[:45]] = 1  # x < 45: a region the held-out views confirm
    labels[45:][carved[45:]] = 2  # x >= 45: one they reject
    keep = np.array([False, True, False])
    out, _ = _blend_kept(h, F, labels, keep, vox, region_mm=15.0)

    def top(col):  # the surface's height (zero crossing of the field) in column x = col
        f = out[col, :, 15]
        k = int(np.flatnonzero(f > 0).max())
        return y[k] + f[k] / (f[k] - f[k + 1]) * vox

    tops = np.array([top(x) for x in range(90)])
    assert tops[:25] == pytest.approx(34.0, abs=1e-4) and tops[-25:] == pytest.approx(40.0, abs=1e-4)
    assert np.abs(np.diff(tops)).max() < 1.5, np.round(tops, 2)  # a ramp (a step: 6 mm at once)
    assert 35.0 < tops[44] < 39.0 and np.all(np.diff(tops) >= -1e-4)  # monotonic, half way near the border
    # a kept region next to uncarved hull (no rejected region near): exactly the fused grid
    out, kept = _blend_kept(h, F, np.where(labels == 1, 1, 0).astype(np.int32), keep, vox, region_mm=15.0)
    np.testing.assert_array_equal(out[kept], F[kept])
    assert np.array([top(x) for x in range(45)]) == pytest.approx(34.0, abs=1e-4)
