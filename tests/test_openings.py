"""Openings (recon.openings): a plain white cup's rim, outlined all round by the views' edges, and the inside under
it that no view sees hollowed; a domed lid, a box's flat top and a ball left solid. The pipeline's fusion stage
hollows the cup though stereo finds nothing on it."""

from __future__ import annotations

import io
import types
from pathlib import Path

import numpy as np
import pytest
from synthetic_images import hull_holds
from test_faces import _cameras, _hull, _render

from recon.carving import carve_hull
from recon.meshing import mesh_from_hull, mesh_stats
from recon.openings import find_openings, hollow_openings
from recon.types import VoxelHull
from turntable.cameras_io import read_cameras
from turntable.synth import SynthOptions, make_sequence

W, H, F_PX = 640, 480, 750.0
K = np.array([[F_PX, 0.0, (W - 1) / 2], [0.0, F_PX, (H - 1) / 2], [0.0, 0.0, 1.0]])
RIM_Y = 69.4  # the synth's cup (turntable.synth.objects): its rim's top, 3 mm walls, its inside down to 5 mm


def _synth(folder, obj: str, seed: int = 3, noise: float = 2.0, blur: float = 0.0):
    """A white (uniform off-white) ``obj`` rendered by the synth, 18 views, dark room, sensor noise ``noise`` DN,
    optical blur ``blur`` px; (images, masks, K, Ts, hull, the true mesh) from its true cameras and silhouettes."""
    import cv2
    import trimesh

    make_sequence(folder, SynthOptions(object=obj, backdrop="dark", seed=seed, width=W, height=H, focal_px=F_PX,
                                       frames=18, step_deg=20.0, albedo=(0.85, 0.84, 0.82), noise=noise,
                                       blur_px=blur))
    seq = read_cameras(folder / "cameras_gt.json")
    images = [np.ascontiguousarray(cv2.imread(str(folder / f.image))[..., ::-1]) for f in seq.frames]
    masks = np.stack([cv2.imread(str(folder / "masks" / (Path(f.image).stem + ".png")), 0) > 127
                      for f in seq.frames])
    K_, Ts = seq.intrinsics.K, np.stack([f.T_cam_table for f in seq.frames])
    hull = carve_hull(masks, K_, Ts, radius_mm=60.0, height_mm=130.0, resolution=128, max_rejections=0)
    return images, masks, K_, Ts, hull, trimesh.load(folder / "object_gt.ply")


@pytest.fixture(scope="module")
def cup_scene(tmp_path_factory):
    return _synth(tmp_path_factory.mktemp("white_cup"), "cup")


def _mesh(values, hull):
    mesh = mesh_from_hull(VoxelHull(values=values, origin_table=hull.origin_table, voxel_mm=hull.voxel_mm))
    st = mesh_stats(mesh)
    assert st.watertight and st.n_bodies == 1
    return mesh


def _chamfer_mm(mesh, truth) -> float:
    """Mean of the two mean nearest distances between 20 000 points sampled on each surface."""
    import trimesh
    from scipy.spatial import cKDTree

    a = trimesh.sample.sample_surface(trimesh.Trimesh(mesh.vertices_table, mesh.faces), 20_000, seed=0)[0]
    b = trimesh.sample.sample_surface(truth, 20_000, seed=0)[0]
    return 0.5 * (cKDTree(a).query(b)[0].mean() + cKDTree(b).query(a)[0].mean())


def _r_out(y):
    return 27.0 + 11.0 * (np.asarray(y) / 68.0) ** 1.4


def test_a_white_cups_rim_is_an_opening_and_its_inside_is_hollowed(cup_scene):
    images, masks, K_, T, hull, truth = cup_scene
    found = find_openings(images, masks, K_, T, hull)
    assert len(found) == 1
    op = found[0]
    assert abs(op.height_mm - RIM_Y) <= 3.0
    assert 0.7 * np.pi * (_r_out(68.0) - 3.0) ** 2 < op.area_mm2 < np.pi * (_r_out(68.0) - 3.0) ** 2
    assert 1.5 <= op.wall_mm <= 5.0
    assert op.floor_mm is None  # no view at 30 deg sees the floor 63 mm down a cup 70 mm across
    # the silhouettes' hull is solid inside: the cup full to its rim, and the roof over it
    inside = np.array([[0.0, y, 0.0] for y in np.arange(10.0, RIM_Y + 6.0, 1.0)])
    assert hull_holds(hull, inside).all()
    values, done = hollow_openings(hull, hull.values, found, masks, K_, T)
    assert len(done) == 1 and done[0][1] > 150_000.0  # mm^3
    carved = VoxelHull(values=values, origin_table=hull.origin_table, voxel_mm=hull.voxel_mm)
    assert not hull_holds(carved, inside).any()
    # the walls and the floor stay: a point in the middle of each
    walls = np.array([[np.cos(a) * (_r_out(y) - 1.5), y, np.sin(a) * (_r_out(y) - 1.5)]
                      for a in np.linspace(0, 2 * np.pi, 24, endpoint=False) for y in (10.0, 35.0, 60.0)])
    floor = np.array([[x, 2.5, z] for x in (-10.0, 0.0, 10.0) for z in (-10.0, 0.0, 10.0)])
    assert hull_holds(carved, walls).all() and hull_holds(carved, floor).all()
    # one closed body, near the cup (measured: Chamfer 0.76 mm against the hull's 2.45 mm)
    before, after = _mesh(hull.values, hull), _mesh(values, hull)
    assert _chamfer_mm(after, truth) < 0.4 * _chamfer_mm(before, truth)
    assert 0.85 * truth.volume < mesh_stats(after).volume_mm3 < 1.15 * truth.volume


def test_a_noisy_cameras_cup_is_an_opening_its_edges_over_the_noise(tmp_path, monkeypatch):
    """Sensor noise of 4 DN: at Canny's fixed 8 / 16 the views agree by chance on edges inside the cup, outlined
    as a knob's over its rim, and the opening was refused; over the noise the photos show
    (:func:`recon.image_edges.edge_thresholds`) it is found at the rim."""
    import recon.image_edges as ie

    images, masks, K_, Ts, hull, _ = _synth(tmp_path, "cup", noise=4.0)
    lo, hi = ie.edge_thresholds(images, Ts)
    assert 9.0 < lo < ie.MAX_LO and hi == 2 * lo
    found = find_openings(images, masks, K_, Ts, hull)
    assert len(found) == 1 and abs(found[0].height_mm - RIM_Y) < 2.0
    monkeypatch.setattr(ie, "NOISE_MULT", 0.0)  # the fixed thresholds
    assert find_openings(images, masks, K_, Ts, hull) == []


def test_an_evenly_lit_inside_is_an_opening_by_its_rim(tmp_path):
    """The synth's cup under seed 4's lights: its inside looks alike from every view (0.99 of the opening agrees
    end to end, as a flat top would), but its rim is two edges 3 mm and more apart; found, and hollowed."""
    from recon.openings import SURE_RIM_MM

    images, masks, K_, T, hull, truth = _synth(tmp_path / "cup4", "cup", seed=4)
    found = find_openings(images, masks, K_, T, hull)
    assert len(found) == 1 and found[0].wall_mm >= SURE_RIM_MM
    values, _ = hollow_openings(hull, hull.values, found, masks, K_, T)
    assert _chamfer_mm(_mesh(values, hull), truth) < 0.4 * _chamfer_mm(_mesh(hull.values, hull), truth)


def test_a_surface_stereo_saw_stops_the_hollowing(cup_scene):
    """Points seen 30 mm above the table inside the cup (a floor stereo found there, say): nothing under
    them is hollowed, everything over them is."""
    images, masks, K_, T, hull, _ = cup_scene
    found = find_openings(images, masks, K_, T, hull)
    g = np.arange(-25.0, 25.5, 0.5)
    seen = np.stack(np.meshgrid(g, [30.0], g, indexing="ij"), -1).reshape(-1, 3)
    seen = seen[np.hypot(seen[:, 0], seen[:, 2]) < 25.0]
    values, done = hollow_openings(hull, hull.values, found, masks, K_, T, seen)
    carved = VoxelHull(values=values, origin_table=hull.origin_table, voxel_mm=hull.voxel_mm)
    assert len(done) == 1
    assert not hull_holds(carved, np.array([[0.0, y, 0.0] for y in np.arange(34.0, RIM_Y, 1.0)])).any()
    assert hull_holds(carved, np.array([[0.0, y, 0.0] for y in np.arange(6.0, 29.0, 1.0)])).all()


@pytest.mark.parametrize("shape", ["lid", "box", "sphere"])
def test_no_opening_on_a_domed_lid_a_flat_top_or_a_ball(shape):
    """A round box's domed lid (its rim a horizontal outline all round, but one edge, not a rim's two, and the
    views agree on the plain dome inside it: 0.87 of it), a box's flat top (the views agree on it; one edge,
    -0.7 mm of rim) and a ball: nothing found."""
    T = _cameras()
    images, masks = _render(T, shape, np.random.default_rng(11))
    assert find_openings(images, masks, K, T, _hull(masks, T)) == []


def test_no_opening_on_a_glossy_flat_top_the_views_disagree_on():
    """A white box whose flat top mirrors a room (a view-dependent pattern on it: each texel sees another
    colour in each view, as through an opening): closed all round, the views disagree, but its outline is one
    edge, not a rim's two: nothing found. Without the rim's test the box would be hollowed."""
    T = _cameras()

    def glossy_top(i, p, n, shade):
        return np.where(n[:, 1] > 0.5, 185.0 + 45.0 * np.sin(p[:, 0] / 20.0 + 0.9 * i)
                        * np.cos(p[:, 2] / 25.0 - 0.5 * i), shade)

    images, masks = _render(T, "box", np.random.default_rng(12), glossy_top)
    assert find_openings(images, masks, K, T, _hull(masks, T)) == []


def test_no_opening_on_a_white_vases_flat_top(tmp_path):
    """The synth's vase: its narrow neck ends in a flat top, a horizontal outline all round like a cup's rim,
    but the views agree on what lies inside it (a surface at that height): no opening."""
    images, masks, K_, T, hull, _ = _synth(tmp_path / "vase", "vase")
    assert find_openings(images, masks, K_, T, hull) == []


def test_the_fusion_stage_hollows_a_plain_cup_that_stereo_cannot_see(cup_scene):
    """Through the fusion stage: stereo carves nothing of the plain cup's inside, the opening does; the model
    is one closed body near the cup and the summary's note says what was done and that no view saw it."""
    from recon.meshing import clip_to_hull
    from turntable.progress import Progress
    from turntable.stages.fusion import run_fusion

    images, masks, K_, T, hull, truth = cup_scene
    hull_mesh = clip_to_hull(mesh_from_hull(hull), hull)
    opts = types.SimpleNamespace(max_faces=50_000)
    mesh, _, note = run_fusion(images, masks, K_, T, hull, hull_mesh, opts, Progress(io.StringIO(), enabled=False))
    assert "an opening" in note and "no view sees hollowed" in note, note
    st = mesh_stats(mesh)
    assert st.watertight and st.n_bodies == 1
    assert 0.85 * truth.volume < st.volume_mm3 < 1.15 * truth.volume
    assert _chamfer_mm(mesh, truth) < 0.4 * _chamfer_mm(hull_mesh, truth)


def _sweep(sections, heights, px=3.0):
    """A :class:`recon.faces.Sweep` with given sections (nothing rectified from it)."""
    from recon.faces import Sweep

    shape = sections[0].shape
    return Sweep(np.asarray(heights, float), float(heights[1] - heights[0]), list(sections), [], K,
                 np.zeros((0, 4, 4)), 0.0, 0.0, px, shape)


def test_a_soft_rims_outline_spread_over_4_mm_of_height_still_peaks():
    from recon.faces import EDGE_SHARE, SOFT_EDGE_SHARE
    from recon.openings import RIM_PEAK, rim_peaks

    heights = np.arange(60.0, 84.0, 0.5)
    # the strict share's outline texels over the synth's cup, blur 0.5 px, noise 4, light wall (auto silhouettes):
    # a plateau from 67 to 70 mm over the rim at 68
    strict = [2300, 2310, 2320, 2330, 2340, 2350, 2360, 2380, 2524, 2635, 2649, 2689, 2754, 4627, 8843, 10197, 11756,
              11417, 10761, 9826, 7942, 3425, 2115, 2067, 1896, 1635, 1347, 1100, 863, 767, 711, 764, 830, 735, 790,
              933, 961, 833, 902, 1070, 1124, 1010, 942, 1202, 955, 488, 217, 0]
    assert len(strict) == len(heights)
    sw = _sweep([np.zeros((4, 4), bool)] * len(heights), heights)
    sw.__dict__["scores"] = {EDGE_SHARE: np.array(strict), SOFT_EDGE_SHARE: np.array(strict) * 2}
    k68 = int(np.argmin(np.abs(heights - 68.0)))
    assert k68 not in dict(sw.peaks_with(RIM_PEAK))  # 2 mm off, the plateau's shoulder is too high
    assert (k68, EDGE_SHARE) in rim_peaks(sw)
    # where both shares peak, both are tried (the strict share's outline may not close the rim all round)
    assert (k68, SOFT_EDGE_SHARE) in rim_peaks(sw)
    assert [s for k, s in sw.peaks_with(RIM_PEAK, 3.0) if k == k68] == [EDGE_SHARE]


def test_a_region_in_the_roofs_section_over_a_rim_is_on_a_roof():
    from recon.openings import _on_a_roof

    px, tan_e = 3.0, 0.4
    heights = np.arange(60.0, 84.0, 0.5)
    jj, ii = np.meshgrid(np.arange(241), np.arange(241))
    r_mm = np.hypot(ii - 120, jj - 120) / px
    # a cup's wall up to its rim at 68 mm, 35 mm round; over it the roof the views leave, sloped as the steepest
    sections = [r_mm <= (35.0 if h <= 68.0 else 35.0 - (h - 68.0) / tan_e) for h in heights]
    sw = _sweep(sections, heights, px)
    k_rim, k_roof = (int(np.argmin(np.abs(heights - h))) for h in (68.0, 76.0))
    assert not _on_a_roof(sw, k_rim, r_mm <= 32.0, 3.0, tan_e)
    assert _on_a_roof(sw, k_roof, r_mm <= 13.0, 2.0, tan_e)
    # a bowl flaring out to its rim is no roof either
    bowl = _sweep([r_mm <= 20.0 + 0.2 * (h - 60.0) for h in heights], heights, px)
    assert not _on_a_roof(bowl, k_rim, r_mm <= 18.0, 3.0, tan_e)


def test_a_rim_found_under_its_top_lifts_the_roof_it_leaves():
    """A soft photo spreads a rim's outline over its height, and the outline may close it 2.4 mm under its top
    (the synth's cup, blur 1 px, automatic silhouettes). The hull over the opening is the roof the rim's top
    leaves: from there it is no higher than the steepest view allows, and hollowing takes it all; a knob standing
    on the region rises over it still. Measured from the rim's height alone, that roof read as something
    standing on 35 % of the opening, and the cup was left solid (2.0 % of its diagonal from the truth)."""
    from recon.openings import Opening, _inside_of, _over_roof

    px, tan_e, v, top, r_out = 3.0, 0.4, 0.5, 69.4, 35.0
    heights = np.arange(60.0, 84.0, 0.5)
    jj, ii = np.meshgrid(np.arange(241), np.arange(241))
    r_mm = np.hypot(ii - 120, jj - 120) / px  # the raster: x0 = z0 = -40 mm
    sw = _sweep([r_mm <= r_out] * len(heights), heights, px)
    sw.__dict__.update(x0=-40.0, z0=-40.0)
    # the silhouettes' hull: the cup (solid) up to its rim's top, the roof the views leave over it
    ax = np.arange(-40.0, 40.0 + v / 2, v)
    x, y, z = np.meshgrid(ax, np.arange(0.0, 100.0, v), ax, indexing="ij")
    r = np.hypot(x, z)
    cup = (r <= r_out) & (y <= top + np.maximum(r_out - r, 0.0) * tan_e)
    k = int(np.argmin(np.abs(heights - 67.0)))
    region = r_mm <= r_out - 4.0

    def hull_of(inside):
        return VoxelHull(values=np.where(inside, 1.0, -1.0).astype(np.float32), origin_table=(-40.0, 0.0, -40.0),
                         voxel_mm=v)

    over, lift = _over_roof(sw, k, region, hull_of(cup), tan_e)
    assert over <= 0.05 and abs(lift - (top - 67.0)) <= 2 * v
    knob = cup | ((r <= 15.0) & (y <= 90.0))
    assert _over_roof(sw, k, region, hull_of(knob), tan_e)[0] > 0.15
    # hollowed: nothing over the opening stays, not even a lid under the rim's roof
    op = Opening(67.0, region, (-40.0, -40.0), px, 4.0, None, lift)
    E = _inside_of(op, hull_of(cup), cup, None, tan_e)
    over_opening = (r <= r_out - 6.0) & (y > 67.0)
    assert not (cup & ~E & over_opening).any()
    flat = Opening(67.0, region, (-40.0, -40.0), px, 4.0, None)  # the roof measured from 67 mm: a lid left
    assert (cup & ~_inside_of(flat, hull_of(cup), cup, None, tan_e) & over_opening).sum() > 1000


def test_an_opening_whose_roof_a_flat_top_took_is_hollowed_from_where_its_hull_starts():
    """The flat tops' stage may take an evenly lit inside for a top and carve the roof over it down under the
    rim (the synth's cup at seed 11 in a dark room: a flat top at 67.0 mm, the rim at 68.0). The descent then
    starts where each column's hull does, and the wall is measured from the outside, not from the carved hole:
    from the rim's slice alone, 1.3 cm³ was hollowed and the cup stayed solid (1.72 % of its diagonal)."""
    from recon.openings import Opening, _inside_of

    px, tan_e, v, rim, r_out, wall = 3.0, 0.4, 0.5, 68.0, 35.0, 4.0
    ax = np.arange(-40.0, 40.0 + v / 2, v)
    x, y, z = np.meshgrid(ax, np.arange(0.0, 100.0, v), ax, indexing="ij")
    r = np.hypot(x, z)
    cup = (r <= r_out) & (y <= rim + 1.0 + np.maximum(r_out - r, 0.0) * tan_e)
    carved = cup & ~((r <= r_out - 5.0) & (y > 67.0))  # the roof a flat top at 67 mm took, the rim left round it
    jj, ii = np.meshgrid(np.arange(241), np.arange(241))
    region = np.hypot(ii - 120, jj - 120) / px <= r_out - 2.0  # the rim's outline, inside the rim's top
    hull = VoxelHull(values=np.where(carved, 1.0, -1.0).astype(np.float32), origin_table=(-40.0, 0.0, -40.0),
                     voxel_mm=v)
    E = _inside_of(Opening(rim, region, (-40.0, -40.0), px, wall, None), hull, carved, None, tan_e)
    assert not (E & ~carved).any()
    left = carved & ~E
    # a vessel: walls about as thick as asked all the way up to the flat top, a floor, nothing inside
    for h in (20.0, 40.0, 60.0, 66.0):
        j = int(round(h / v))
        hollow = ~left[:, j, :] & (r[:, j, :] < r_out)
        inner = r[:, j, :][hollow].max() if hollow.any() else 0.0  # the cavity's radius
        assert r_out - wall - 1.0 <= inner <= r_out - wall + 1.0, (h, inner)
    assert (left & (r <= 10.0) & (y < wall + 1.0)).any()  # the floor
    assert not (left & (r <= r_out - wall - 1.5) & (y > wall + 1.5)).any()
