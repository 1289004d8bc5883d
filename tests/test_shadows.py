"""Cast shadows (recon.shadows): the skirt a key light's shadow, held in every view's silhouette, leaves under a
white teapot-like body's overhanging belly is carved; the body and its foot are kept; silhouettes without the
shadow carve nothing."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synthetic_images import STOOL, box_hit, boxes_hit, hull_holds, turntable_ring

from recon.carving import carve_hull
from recon.shadows import carve_cast_shadows

W, H, F_PX = 320, 240, 420.0
K = np.array([[F_PX, 0.0, (W - 1) / 2], [0.0, F_PX, (H - 1) / 2], [0.0, 0.0, 1.0]])
BELLY_C, BELLY_R = np.array([0.0, 30.0, 0.0]), 26.0  # a ball whose lowest point is 4 mm above the table ...
FOOT_R, FOOT_H = 12.0, 6.0  # ... resting on a foot
BOX_LO, BOX_HI = np.array([-22.0, 0.0, -16.0]), np.array([22.0, 30.0, 16.0])  # a plain white box
L_CAM = np.array([0.25, -0.8, -0.55])  # towards the key light, camera frame (up and behind the camera)
AMBIENT, DIFFUSE = 0.4, 0.6
SKY = 1.0  # a box's sides take as much ambient light as the paper: a side turned from the light has the shadow's grey


def _rays(T):
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    d = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3).astype(float) @ np.linalg.inv(K).T @ T[:3, :3]
    return -T[:3, :3].T @ T[:3, 3], d / np.linalg.norm(d, axis=1, keepdims=True)


def _ball(o, d):
    """Distance along rays (N, 3) from points ``o`` ((3,) or (N, 3)) to the belly (inf where they miss)."""
    oc = o - BELLY_C
    b = (d * oc).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - BELLY_R ** 2)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _foot(o, d):
    """Distance along the rays to the foot's side (an upright cylinder from the table up to FOOT_H)."""
    o = np.broadcast_to(o, d.shape)
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = 2 * (o[:, 0] * d[:, 0] + o[:, 2] * d[:, 2])
    c = o[:, 0] ** 2 + o[:, 2] ** 2 - FOOT_R ** 2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
    y = o[:, 1] + t * d[:, 1]
    return np.where((disc >= 0) & (t > 0) & (y >= 0.0) & (y <= FOOT_H), t, np.inf)


def _render(T_all, rng, with_shadow_in_mask: bool, shape: str = "teapot"):
    """White body on white paper under a key light fixed to the camera; (images, masks, unknown)."""
    images, masks, doubt = [], [], []
    for T in T_all:
        o, d = _rays(T)
        L = T[:3, :3].T @ (L_CAM / np.linalg.norm(L_CAM))  # the light turns with the camera about the table
        if shape in ("box", "stool"):
            parts = [(BOX_LO, BOX_HI)] if shape == "box" else STOOL
            t, n = boxes_hit(o, d, parts)
            p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        else:
            tb, tf = _ball(o, d), _foot(o, d)
            t = np.minimum(tb, tf)
            p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
            n = np.where((tb <= tf)[:, None], (p - BELLY_C) / BELLY_R, p * np.array([1.0, 0.0, 1.0]) / FOOT_R)
        sky = SKY if shape == "box" else 0.55 + 0.45 * n[:, 1]
        lit_obj = 0.85 * (AMBIENT * sky + DIFFUSE * np.clip(n @ L, 0.0, None))
        with np.errstate(divide="ignore", invalid="ignore"):
            tp = -o[1] / d[:, 1]
        q = o + np.where(tp > 0, tp, 0.0)[:, None] * d  # the plane point each ray meets
        Ls = np.tile(L, (len(d), 1))
        if shape in ("box", "stool"):
            shadowed = np.isfinite(boxes_hit(q + 1e-6 * Ls, Ls, parts)[0])
        else:
            shadowed = np.isfinite(_ball(q + 1e-6 * Ls, Ls)) | np.isfinite(_foot(q + 1e-6 * Ls, Ls))
        paper = 0.9 * (AMBIENT + DIFFUSE * L[1] * ~shadowed)
        on_paper = (tp > 0) & (np.hypot(q[:, 0], q[:, 2]) < 150.0)
        obj = np.isfinite(t) & (t < np.where(tp > 0, tp, np.inf))
        grey = 255.0 * np.where(obj, lit_obj, np.where(on_paper, paper, 0.2)) + rng.normal(0.0, 1.0, len(d))
        rgb = np.clip(grey[:, None] * np.array([1.0, 0.99, 0.95]), 0, 255)
        images.append(rgb.reshape(H, W, 3).astype(np.uint8))
        held = obj | (with_shadow_in_mask & on_paper & shadowed & (np.hypot(q[:, 0], q[:, 2]) < 60.0))
        masks.append(held.reshape(H, W))
        # the paper a stool's views see under its seat, between the legs, lit or shaded: doubt (as on a light wall)
        between = np.isfinite(box_hit(o, d, np.array([-27.0, 0.0, -27.0]), np.array([27.0, 45.0, 27.0]))[0])
        doubt.append((~held & on_paper & (shape == "stool") & between).reshape(H, W))
    masks = np.array(masks)
    return images, masks, np.array(doubt)


def _hull(masks, T):
    return carve_hull(masks, K, T, radius_mm=60.0, height_mm=70.0, resolution=96, max_rejections=0)


def _points_in_body(margin: float, rng) -> np.ndarray:
    """Points inside the belly and the foot, ``margin`` mm in from their surfaces."""
    p = rng.uniform(-30.0, 60.0, (60000, 3))
    p[:, 1] = rng.uniform(0.0, 56.0, len(p))
    in_ball = np.linalg.norm(p - BELLY_C, axis=1) < BELLY_R - margin
    r = np.hypot(p[:, 0], p[:, 2])
    in_foot = (r < FOOT_R - margin) & (p[:, 1] > margin) & (p[:, 1] < FOOT_H)
    return p[in_ball | in_foot]


def _skirt_points(rng, r_lo: float, r_hi: float, y_hi: float) -> np.ndarray:
    """4000 points on the paper round the foot, ``r_lo`` to ``r_hi`` mm from the axis, 0.5 to ``y_hi`` mm up: where
    the held shadow leaves its skirt."""
    a = rng.uniform(0.0, 2 * np.pi, 4000)
    r = rng.uniform(r_lo, r_hi, len(a))
    return np.column_stack([r * np.cos(a), rng.uniform(0.5, y_hi, len(a)), r * np.sin(a)])


@pytest.fixture(scope="module")
def scene():
    T = turntable_ring(24, look_y_mm=25.0)
    images, masks, unknown = _render(T, np.random.default_rng(0), with_shadow_in_mask=True)
    return images, masks, unknown, T, _hull(masks, T)


def test_the_skirt_under_an_overhang_is_carved_and_the_body_kept(scene):
    images, masks, unknown, T, hull = scene
    rng = np.random.default_rng(1)
    skirt = _skirt_points(rng, FOOT_R + 2.0, 20.0, 2.5)  # the paper under the belly, outside the foot
    assert hull_holds(hull, skirt).mean() > 0.6  # the silhouettes left most of it (else the test tests nothing)
    out, info = carve_cast_shadows(hull, images, masks, unknown, K, T)
    assert info is not None
    up = (T[0][:3, :3].T @ (L_CAM / np.linalg.norm(L_CAM)))[1]  # the light's height, table frame
    assert abs(info.ratio - AMBIENT / (AMBIENT + DIFFUSE * up)) < 0.03  # shadowed paper over lit paper
    assert hull_holds(out, skirt).mean() < 0.2
    body = _points_in_body(1.5 * hull.voxel_mm, rng)
    body = body[hull_holds(hull, body)]
    assert hull_holds(out, body).mean() > 0.999
    assert (out.values > 0).sum() < (hull.values > 0).sum()


def test_the_pixels_just_below_the_overhangs_outline_count():
    """From high up (50 deg) the skirt against the foot under the belly shows only in the pixels just below the
    belly's outline. The high part's image is not grown by a pixel, so those pixels count (51 % of the skirt
    within 5 mm of the foot is left, 62 % with the image grown); the body is kept whole."""
    T = turntable_ring(24, look_y_mm=25.0, elevation_deg=50.0)
    images, masks, unknown = _render(T, np.random.default_rng(0), with_shadow_in_mask=True)
    hull = _hull(masks, T)
    rng = np.random.default_rng(1)
    skirt = _skirt_points(rng, FOOT_R + 1.0, FOOT_R + 5.0, 5.0)
    assert hull_holds(hull, skirt).mean() > 0.9
    out, info = carve_cast_shadows(hull, images, masks, unknown, K, T)
    assert info is not None
    assert hull_holds(out, skirt).mean() < 0.56
    body = _points_in_body(1.5 * hull.voxel_mm, rng)
    body = body[hull_holds(hull, body)]
    assert hull_holds(out, body).mean() > 0.999


def test_silhouettes_without_the_shadow_leave_nothing_to_carve():
    T = turntable_ring(24, look_y_mm=25.0)
    images, masks, unknown = _render(T, np.random.default_rng(2), with_shadow_in_mask=False)
    hull = _hull(masks, T)
    out, info = carve_cast_shadows(hull, images, masks, unknown, K, T)
    body = _points_in_body(1.5 * hull.voxel_mm, np.random.default_rng(3))
    assert hull_holds(hull, body).mean() > 0.95
    assert hull_holds(out, body[hull_holds(hull, body)]).all()
    carved = (hull.values > 0).sum() - (out.values > 0).sum()
    assert carved <= 0.01 * (hull.values > 0).sum()


def test_a_boxs_side_of_the_shadows_grey_is_kept():
    """A white box's side turned from the light, lit by the ambient light alone as the paper in the shadow is, has
    the shadow's grey in every view that sees it so; its face rises past the skirt's height in the image, a shadow
    on the plane does not, so nothing is released through the box."""
    T = turntable_ring(24, look_y_mm=20.0)
    images, masks, unknown = _render(T, np.random.default_rng(4), with_shadow_in_mask=True, shape="box")
    hull = _hull(masks, T)
    out, _ = carve_cast_shadows(hull, images, masks, unknown, K, T)
    rng = np.random.default_rng(5)
    m = 1.5 * hull.voxel_mm
    box = rng.uniform(BOX_LO + m, BOX_HI - m, (20000, 3))
    box = box[hull_holds(hull, box)]
    assert len(box) > 15000
    assert hull_holds(out, box).mean() > 0.999


def _block_hull():
    """A body (a post standing on the table, 3 x 40 x 3 voxels) with a slab at its foot (the skirt), as inside
    voxels of a 30 x 44 x 30 grid; the slab is what the carving takes."""
    inside = np.zeros((30, 44, 30), bool)
    inside[13:16, 1:41, 13:16] = True  # the post
    inside[2:28, 1:6, 2:28] = True  # the skirt round its foot
    return inside


def test_streaks_the_guard_gave_back_are_dropped_however_large():
    """The guard gives back voxels along the rays of pixels it holds for the object: under a chair's seat they
    are streaks through the skirt which, once the skirt round them is carved, are pieces cut loose. Weighed
    with them the pieces were parts of the object, and the whole skirt was kept (2.86 % of the diagonal)."""
    from recon.shadows import SMALL_PIECE, drop_cut_pieces

    inside = _block_hull()
    new = np.where(inside, 1.0, -1.0).astype(np.float32)
    carved = inside.copy()
    carved[13:16, 1:41, 13:16] = False  # the carving took the skirt, not the post
    new[carved] = -0.5
    restored = np.zeros_like(inside)
    for x in range(4, 26, 3):  # streaks given back, joined along the table: one piece, 16 % of the post
        restored[x, 1:6, 4] = True
    restored[4:26, 1, 4] = True
    new[restored] = 1.0
    assert restored.sum() >= SMALL_PIECE * (new > 0).sum()  # large enough to count as a part when weighed whole
    out = drop_cut_pieces(new, inside, restored, 1.0)
    assert out is not None
    assert not (out[restored] > 0).any()  # the streaks are gone
    assert (out[13:16, 1:41, 13:16] > 0).all()  # the post is kept
    # the same piece not given back is a part of the object the carving cut off: nothing is carved
    assert drop_cut_pieces(new, inside, np.zeros_like(inside), 1.0) is None


def test_a_part_cut_off_refuses_the_carving_and_crumbs_go():
    from recon.shadows import drop_cut_pieces

    inside = _block_hull()
    new = np.where(inside, 1.0, -1.0).astype(np.float32)
    new[2:28, 1:6, 2:28] = -0.5
    new[13:16, 1:41, 13:16] = 1.0
    new[13:16, 1:6, 13:16] = -0.5  # the post's foot carved: the post no longer stands on the table
    assert drop_cut_pieces(new, inside, np.zeros_like(inside), 1.0) is None
    new[13:16, 1:6, 13:16] = 1.0
    new[3, 1, 3] = 1.0  # one voxel of the skirt left: a crumb
    out = drop_cut_pieces(new, inside, np.zeros_like(inside), 1.0)
    assert out is not None and out[3, 1, 3] < 0 and (out[13:16, 1:41, 13:16] > 0).all()
    new[2:8, 1:6, 2:8] = 1.0  # a block of the skirt left: 180 voxels, > 2 % of the post's 360
    assert drop_cut_pieces(new, inside, np.zeros_like(inside), 1.0) is None


def _seat_hull():
    """A stool: a seat (26 x 3 x 26 voxels at 30-33) on four posts, a skirt under it down to the table (1-16)."""
    inside = np.zeros((30, 40, 30), bool)
    inside[2:28, 30:33, 2:28] = True  # the seat
    for x in (2, 25):
        for z in (2, 25):
            inside[x:x + 3, 1:30, z:z + 3] = True  # the posts
    inside[3:27, 1:16, 3:27] = True  # the skirt between and round them
    return inside


def _seat_skirt_carved():
    """:func:`_seat_hull` and its values with the skirt carved but not the posts."""
    inside = _seat_hull()
    new = np.where(inside, 1.0, -1.0).astype(np.float32)
    new[3:27, 1:16, 3:27] = -0.5
    for x in (2, 25):
        for z in (2, 25):
            new[x:x + 3, 1:30, z:z + 3] = 1.0
    return inside, new


def test_the_rest_of_a_skirt_under_the_seat_is_dropped_a_block_in_the_open_or_a_bar_is_not():
    """The carving took a stool's skirt but its core under the seat's centre (in a darker shade than the shadow's,
    which nothing releases): cut loose, resting on the table under the seat, it is the skirt's rest and goes. A
    piece cut loose that stands in the open (a block beside a post) or floats (a bar between the posts)
    refuses the carving: the object is never eaten (a plinth cut from its figure leaves the figure off the table,
    which refuses it too)."""
    from recon.shadows import drop_cut_pieces

    inside, new = _seat_skirt_carved()
    new[11:19, 1:14, 11:19] = 1.0  # not its core: 832 voxels, far over SMALL_PIECE of the stool
    none = np.zeros_like(inside)
    out = drop_cut_pieces(new, inside, none, 1.0)
    assert out is not None
    assert (out[11:19, 1:14, 11:19] < 0).all() and (out[2:28, 30:33, 2:28] > 0).all()
    # a post with a block beside it, joined by a slab on the table that the carving takes: the block, cut loose,
    # stands in the open (nothing of the body above it): a part, and nothing is carved; under a seat it would go
    post = np.zeros((30, 40, 30), bool)
    post[2:8, 1:40, 2:8] = True
    post[12:20, 1:12, 12:20] = True  # the block, 704 voxels
    post[5:16, 1:4, 5:16] = True  # the slab joining them
    new2 = np.where(post, 1.0, -1.0).astype(np.float32)
    slab = np.zeros_like(post)
    slab[5:16, 1:4, 5:16] = True
    slab[2:8, :, 2:8] = False
    slab[12:20, :, 12:20] = False
    new2[slab] = -0.5
    assert drop_cut_pieces(new2, post, none, 1.0) is None
    seat = post.copy()
    seat[2:22, 30:33, 2:22] = True
    new3 = np.where(seat, 1.0, -1.0).astype(np.float32)
    new3[slab] = -0.5
    out3 = drop_cut_pieces(new3, seat, none, 1.0)
    assert out3 is not None and (out3[12:20, 1:12, 12:20] < 0).all() and (out3[2:8, 1:40, 2:8] > 0).all()
    # a bar between two posts, floating once the skirt under it is carved
    bar = new.copy()
    bar[11:19, 1:14, 11:19] = -0.5
    bar[5:25, 8:10, 13:15] = 1.0  # a bar joined to nothing after the carving (its ends carved)
    assert drop_cut_pieces(bar, inside, none, 1.0) is None


def test_a_soft_shadow_held_by_every_view_still_gives_its_ratio():
    """A soft image's shadow under a belly is held by every view alike, so the hull covers it: the held pixels
    it leaves uncovered are the penumbra, spread from the shadow's ratio to the lit paper's, with no peak. The
    held pixels low down, the shadow's among them, still peak at its ratio; where they do not either (a shaded
    body's own greys), there is no shadow."""
    from recon.shadows import _shadow_ratio, _View

    rng = np.random.default_rng(7)
    shape = (60, 80)

    def view(low_ratios):
        ratio = np.ones(shape, np.float32)
        held = np.zeros(shape, bool)
        cover = np.zeros(shape, bool)
        held[:40] = True
        cover[:30] = True  # the hull covers the shadow and the body ...
        ratio[30:40] = rng.uniform(0.5, 1.0, (10, 80))  # ... and leaves the penumbra: no peak
        ratio[:30] = low_ratios((30, 80))
        ones = np.ones(shape, bool)
        return _View(held=held, high=np.zeros(shape, bool), paperlike=ones, ratio=ratio, near=ones, cover=cover)

    def shadow(s):
        return np.where(rng.random(s) < 0.5, rng.normal(0.58, 0.005, s), rng.uniform(0.3, 0.85, s))

    k = _shadow_ratio([view(shadow) for _ in range(6)])
    assert k is not None and abs(k - 0.58) < 0.01
    assert _shadow_ratio([view(lambda s: rng.uniform(0.3, 0.85, s)) for _ in range(6)]) is None


def test_the_skirts_rest_floating_under_the_seat_goes_where_no_silhouette_needs_it():
    """The carving took the stool's skirt up to the shadow's height, and above that its core under the seat's centre
    (darker still, held by the views only as doubt) floats, cut loose: it goes where dropping it leaves no pixel of
    the object's own in any view without a voxel behind it, and refuses the carving where the masks hold it (a
    bar between the legs)."""
    from recon.shadows import drop_cut_pieces

    inside, new = _seat_skirt_carved()
    new[11:19, 8:14, 11:19] = 1.0  # not its core's upper part: floating under the seat
    none = np.zeros_like(inside)
    asked = []

    def unheld(piece):
        asked.append(int(piece.sum()))
        return True

    out = drop_cut_pieces(new, inside, none, 1.0, unheld)
    assert out is not None and asked == [8 * 6 * 8]
    assert (out[11:19, 8:14, 11:19] < 0).all() and (out[2:28, 30:33, 2:28] > 0).all()
    assert drop_cut_pieces(new, inside, none, 1.0, lambda piece: False) is None  # the masks hold it: a part
    assert drop_cut_pieces(new, inside, none, 1.0) is None  # no silhouettes to ask: a part
    # a piece floating in the open (not under the body) is a part whatever the silhouettes say
    post = np.zeros((30, 40, 30), bool)
    post[2:8, 1:40, 2:8] = True
    post[12:20, 5:12, 12:20] = True  # a block beside the post ...
    post[5:16, 1:6, 5:16] = True  # ... on a slab joining them, which the carving takes
    new2 = np.where(post, 1.0, -1.0).astype(np.float32)
    slab = np.zeros_like(post)
    slab[5:16, 1:6, 5:16] = True
    slab[2:8, :, 2:8] = False
    new2[slab] = -0.5
    new2[12:20, 5:6, 12:20] = -0.5  # the block's foot too: it floats
    assert drop_cut_pieces(new2, post, none, 1.0, lambda piece: True) is None


def test_the_guard_kept_shallow_gives_back_only_what_lies_just_behind_the_nearest(scene):
    """``guard_depth_mm``: on each pixel's ray the guard gives back the carved voxels within that depth of the
    nearest one, not the whole ray (from 20 deg a ray runs ~35 mm through a skirt 12 mm high, and a few pixels of
    a shadow's soft edge gave a whole skirt back). Kept shallow, the guard still keeps the body whole and the
    skirt goes at least as far as with the whole rays."""
    from recon.shadows import GUARD_DEPTH_MM, _nearest_on_rays

    T = turntable_ring(1, look_y_mm=25.0)[0]
    centre = -T[:3, :3].T @ T[:3, 3]
    ray = np.array([10.0, 5.0, 0.0]) - centre
    ray /= np.linalg.norm(ray)
    depths = np.arange(0.0, 12.0)  # along one pixel's ray, 1 mm apart, and a point off it, alone on its pixel
    pts = np.vstack([np.array([10.0, 5.0, 0.0]) + depths[:, None] * ray, [[-20.0, 5.0, 0.0]]])
    kept = _nearest_on_rays(K, T, pts, 3.0)
    assert kept.tolist() == [True] * 4 + [False] * 8 + [True]

    images, masks, unknown, Ts, hull = scene
    rng = np.random.default_rng(1)
    skirt = _skirt_points(rng, FOOT_R + 2.0, 20.0, 2.5)
    whole, _ = carve_cast_shadows(hull, images, masks, unknown, K, Ts)
    shallow, info = carve_cast_shadows(hull, images, masks, unknown, K, Ts, guard_depth_mm=GUARD_DEPTH_MM)
    assert info is not None
    assert hull_holds(shallow, skirt).mean() <= hull_holds(whole, skirt).mean()
    body = _points_in_body(1.5 * hull.voxel_mm, rng)
    body = body[hull_holds(hull, body)]
    assert hull_holds(shallow, body).mean() > 0.999


def test_under_a_seat_the_skirt_is_looked_for_up_to_the_underside():
    """A white stool (seat 54 mm wide, its underside 45 mm up) whose views hold its shadow in their masks and the
    lit paper they see between the legs as doubt (as on a light wall). Once the skirt within SKIRT_MM is carved
    a block floats under the seat, and the rays that see the paper between the legs meet it: a pass that looks
    only up to SKIRT_MM takes none of it. Given the space under the seat (recon.faces.space_under: the legs,
    standing from the table up to the underside, are not in it), the pass takes the block (21-26 mm) but the
    tip of the wedge no view sees (recon.faces.carve_under_slabs's), and keeps the seat and the legs whole."""
    from recon.faces import Face, Slab, space_under
    from recon.shadows import SKIRT_MM

    T = turntable_ring(36, look_y_mm=25.0)
    images, masks, unknown = _render(T, np.random.default_rng(4), with_shadow_in_mask=True, shape="stool")
    hull = carve_hull(masks | unknown, K, T, radius_mm=60.0, height_mm=70.0, resolution=96, max_rejections=0)
    o, v = hull.origin_table, hull.voxel_mm
    X, Y, Z = np.meshgrid(*(o[i] + np.arange(hull.values.shape[i]) * v for i in range(3)), indexing="ij")
    legs = np.zeros(X.shape, bool)
    for lo, hi in STOOL[1:]:
        c, half = (lo + hi) / 2, (hi - lo) / 2
        legs |= (np.abs(X - c[0]) < half[0] + 1.0) & (np.abs(Z - c[2]) < half[2] + 1.0)
    vals = hull.values.copy()  # the skirt round the legs within SKIRT_MM, carved by the first pass
    vals[(np.abs(X) < 30.0) & (np.abs(Z) < 30.0) & ~legs & (Y <= SKIRT_MM)] = -0.5 * v
    floating = dataclasses.replace(hull, values=vals)
    block = o + np.argwhere((np.abs(X) < 27.0) & (np.abs(Z) < 27.0) & ~legs & (Y > 21.0) & (Y < 26.0) & (vals > 0)) * v
    assert len(block) > 5000  # the block is there (else nothing is tested)
    seat = Face(51.0, np.ones((55, 55), bool), np.zeros((55, 55, 3), np.float32), (-27.0, -27.0), 1.0)
    under = space_under([Slab(seat, 45.0, seat.region)], floating)
    assert under[(np.abs(X) < 20.0) & (np.abs(Z) < 20.0) & (Y < 44.0)].all()
    assert not under[(Y > 45.0) | (np.abs(X) > 33.0) | (np.abs(Z) > 33.0)].any()
    for lo, hi in STOOL[1:]:  # a leg stands from the table up to the underside: not in the space under the seat
        c, half = (lo + hi) / 2, (hi - lo) / 2
        assert not under[(np.abs(X - c[0]) < half[0] - v) & (np.abs(Z - c[2]) < half[2] - v)].any()
    first, _ = carve_cast_shadows(floating, images, masks, unknown, K, T, guard_depth_mm=3.0)
    assert hull_holds(first, block).all()  # up to SKIRT_MM only: nothing of the block
    out, info = carve_cast_shadows(floating, images, masks, unknown, K, T, guard_depth_mm=3.0, under=under)
    assert info is not None
    assert hull_holds(out, block).mean() < 0.1  # (what is left: over the middle, the wedge's tip reaches ~24 mm)
    rng = np.random.default_rng(5)
    for lo, hi in STOOL:  # the seat and every leg, whole (1.5 voxels in from their faces)
        p = rng.uniform(lo + 1.5 * v, hi - 1.5 * v, (2000, 3))
        assert hull_holds(out, p).all()
