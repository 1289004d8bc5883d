"""Raised horizontal faces (recon.faces): a white box's flat top found by the edges' plane sweep, and the roof that
the silhouettes leave over it carved; a sphere (no flat top) left alone. Flat sides (recon.sides): the tent the
silhouettes leave over a white box's sides carved between its corners; round sides left alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synthetic_images import SEAT_HI, SEAT_LO, STOOL, box_hit, boxes_hit, hull_holds, turntable_ring

from recon.carving import carve_hull
from recon.faces import carve_above_faces, carve_under_slabs, find_faces, space_under
from recon.sides import flatten_sides

W, H, F_PX = 640, 480, 750.0
K = np.array([[F_PX, 0.0, (W - 1) / 2], [0.0, F_PX, (H - 1) / 2], [0.0, 0.0, 1.0]])
BOX_LO, BOX_HI = np.array([-30.0, 0.0, -20.0]), np.array([30.0, 40.0, 20.0])  # table mm, its top at 40


def _cameras() -> np.ndarray:
    return turntable_ring(24, look_y_mm=25.0)


def _rays(T):
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    d = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3).astype(float) @ np.linalg.inv(K).T @ T[:3, :3]
    return -T[:3, :3].T @ T[:3, 3], d / np.linalg.norm(d, axis=1, keepdims=True)


def _box_hit(o, d, lo=BOX_LO, hi=BOX_HI):
    """Distance along each ray to the box, and the normal there (inf where it misses)."""
    return box_hit(o, d, lo, hi)


def _sphere_hit(o, d, centre, radius):
    oc = o - centre
    b = d @ oc
    disc = b * b - (oc @ oc - radius ** 2)
    t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    return t, (p - centre) / radius


def _cylinder_side_hit(o, d, radius, height):
    """Distance along each ray to the side of the upright cylinder about the axis, from the table up to
    ``height`` (inf where it misses), and the height where it is met."""
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = 2 * (o[0] * d[:, 0] + o[2] * d[:, 2])
    c = o[0] ** 2 + o[2] ** 2 - radius ** 2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
    y = o[1] + t * d[:, 1]
    return np.where((disc >= 0) & (y >= 0.0) & (y <= height), t, np.inf), y


def _lid_hit(o, d):
    """A round box: a cylinder (radius 25, 30 high) under a domed lid rising 8.8 mm over its rim."""
    ts, _ = _cylinder_side_hit(o, d, 25.0, 30.0)
    p = o + np.where(np.isfinite(ts), ts, 0.0)[:, None] * d
    n_side = p * np.array([1.0, 0.0, 1.0]) / 25.0
    centre = np.array([0.0, 30.0 - np.sqrt(40.0 ** 2 - 25.0 ** 2), 0.0])
    tc, n_cap = _sphere_hit(o, d, centre, 40.0)
    yc = o[1] + np.where(np.isfinite(tc), tc, 0.0) * d[:, 1]
    tc = np.where(np.isfinite(tc) & (yc >= 30.0), tc, np.inf)
    side = ts <= tc
    return np.where(side, ts, tc), np.where(side[:, None], n_side, n_cap)


def _column_hit(o, d):
    """A plain column (radius 20, 80 high) with a dark band painted round it from 28 to 30 mm."""
    t, y = _cylinder_side_hit(o, d, 20.0, 80.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        t_top = (80.0 - o[1]) / d[:, 1]
    p_top = o + np.where(np.isfinite(t_top), t_top, 0.0)[:, None] * d
    top = np.isinf(t) & (np.hypot(p_top[:, 0], p_top[:, 2]) <= 20.0) & (t_top > 0)
    t = np.where(top, t_top, t)
    band = np.isfinite(t) & ~top & (y >= 28.0) & (y <= 30.0)
    return t, band


BODY_LO, BODY_HI = np.array([-20.0, 0.0, -10.0]), np.array([20.0, 35.0, 10.0])  # a box under a lid 5 mm thick
LIDBOX = [(BODY_LO, BODY_HI), (np.array([-28.0, 35.0, -18.0]), np.array([28.0, 40.0, 18.0]))]  # overhanging 8 mm


def _render(T_all, shape: str, rng, restyle=None):
    """White object on a grey paper disc, lit from above and behind the camera; (images, masks).

    ``restyle(i, points, normals, shade)``: the object's grey in view ``i`` from its points (table mm) and
    normals where the rays meet it, and the shading it would have (a glossy top's reflections)."""
    images, masks = [], []
    for i, T in enumerate(T_all):
        o, d = _rays(T)
        if shape == "column":  # lit evenly all round (no shading): only the band marks it
            t, band = _column_hit(o, d)
            n = np.tile([0.0, 1.0, 0.0], (len(d), 1))
        elif shape == "box":
            t, n = _box_hit(o, d)
        elif shape == "lid":
            t, n = _lid_hit(o, d)
        elif shape in ("stool", "lidbox"):
            t, n = boxes_hit(o, d, STOOL if shape == "stool" else LIDBOX)
        else:
            t, n = _sphere_hit(o, d, np.array([0.0, 30.0, 0.0]), 30.0)
        light = -d.mean(0) + np.array([0.0, 1.2, 0.0])
        light /= np.linalg.norm(light)
        shade = 40.0 + 180.0 * np.clip(n @ light, 0.0, 1.0)
        if shape == "column":
            shade = np.where(band, 90.0, 200.0)
        if restyle is not None:
            shade = restyle(i, o + np.where(np.isfinite(t), t, 0.0)[:, None] * d, n, shade)
        with np.errstate(divide="ignore", invalid="ignore"):
            tp = -o[1] / d[:, 1]
        p = o + np.where(tp > 0, tp, 0.0)[:, None] * d
        paper = np.where((tp > 0) & (np.hypot(p[:, 0], p[:, 2]) < 120.0), 150.0, 60.0)
        obj = np.isfinite(t) & (t < np.where(tp > 0, tp, np.inf))
        grey = np.where(obj, shade, paper) + rng.normal(0.0, 1.0, len(d))
        images.append(np.repeat(np.clip(grey, 0, 255).reshape(H, W, 1), 3, axis=2).astype(np.uint8))
        masks.append(obj.reshape(H, W))
    return images, np.array(masks)


def _hull(masks, T):
    return carve_hull(masks, K, T, radius_mm=60.0, height_mm=90.0, resolution=128, max_rejections=0)


@pytest.fixture(scope="module")
def box_scene():
    T = _cameras()
    images, masks = _render(T, "box", np.random.default_rng(0))
    return images, masks, T, _hull(masks, T)


def test_a_white_boxs_flat_top_is_found_and_the_roof_over_it_carved(box_scene):
    images, masks, T, hull = box_scene
    faces = find_faces(images, masks, K, T, hull)
    assert len(faces) == 1 and abs(faces[0].height_mm - 40.0) <= 0.5
    assert faces[0].area_mm2 > 0.6 * 60.0 * 40.0
    # the silhouettes' hull keeps a roof over the top: ~8 mm high over its middle
    column = np.array([[0.0, y, 0.0] for y in np.arange(41.0, 60.0, 0.5)])
    assert hull_holds(hull, column).sum() * 0.5 > 6.0
    carved, done = carve_above_faces(hull, images, masks, K, T)
    assert len(done) == 1 and done[0][1] > 3000.0  # mm^3
    assert not hull_holds(carved, column[column[:, 1] > 41.5]).any()
    # nothing of the box is carved: every voxel inside it (a voxel in from its faces) stays
    v = hull.voxel_mm
    g = np.stack(np.meshgrid(*[np.arange(lo + v, hi - v, v) for lo, hi in zip(BOX_LO, BOX_HI, strict=True)],
                             indexing="ij"), -1).reshape(-1, 3)
    assert hull_holds(hull, g).all() and hull_holds(carved, g).all()
    # the carved hull is closer to the box: its volume over the true one
    true = np.prod(BOX_HI - BOX_LO)
    assert (carved.values > 0).sum() * v ** 3 < (hull.values > 0).sum() * v ** 3 - 3000.0
    assert (carved.values > 0).sum() * v ** 3 < 1.12 * true


def _inner_grid(lo, hi, v):
    """Voxel centres a voxel or more inside the box (lo, hi)."""
    return np.stack(np.meshgrid(*[np.arange(a + v, b - v, v) for a, b in zip(lo, hi, strict=True)], indexing="ij"),
                    -1).reshape(-1, 3)


def test_a_seats_underside_edge_is_no_top_and_the_seat_keeps_its_inside():
    """A stool's seat, 6 mm thick on four legs, seen by 36 views: its lower edge is a horizontal outline at
    45 mm that the views put on the same texels, and rectified onto that plane they see the plain seat
    above it, one colour, as on a flat top. But the seat's parallax (6 mm up, seen from 30 deg) moves it
    ~10 mm in each view's direction: where they agree is a region well inside that outline, not one it
    bounds. No face there; the seat's top at 51 mm is one, and nothing inside the seat is carved (a white
    chair's seat, its true masks given, was dug out 6 mm deep over 1700 mm2: a face found at its
    underside's edge)."""
    T = turntable_ring(36, look_y_mm=25.0)
    images, masks = _render(T, "stool", np.random.default_rng(5))
    hull = _hull(masks, T)
    faces = find_faces(images, masks, K, T, hull)
    assert [round(f.height_mm) for f in faces] == [51]
    carved, _ = carve_above_faces(hull, images, masks, K, T)
    g = _inner_grid(SEAT_LO, SEAT_HI, hull.voxel_mm)
    assert hull_holds(hull, g).all()
    assert hull_holds(carved, g).all(), (~hull_holds(carved, g)).sum()


def test_an_outline_higher_up_that_runs_on_to_the_tops_edge_does_not_refuse_it():
    """A flat top is refused where a higher height outlines something inside it (a lid's dome, a knob); but a
    line that runs on to the top's edge is a wall standing there (a chair's back on its seat's rear edge: a
    white chair from 30 deg, seed 4, had its seat refused by such a line at 53-54.5 mm, 583 texels against the
    393 allowed, and kept its roof and the wedge under the seat, 1.68 % of the diagonal; 0.60 % found)."""
    from recon.faces import _rises_inside

    region = np.zeros((60, 60), bool)
    region[10:50, 10:50] = True
    inner = np.zeros_like(region)
    inner[13:47, 13:47] = True
    wall = np.zeros_like(region)
    wall[14:16, 10:50] = True  # across the top, on to its edge at both ends
    ring = np.zeros_like(region)
    ring[25:35, 25:35] = True
    ring[27:33, 27:33] = False  # a dome's contour, inside
    assert _rises_inside(wall, region, inner) == 0
    assert _rises_inside(ring, region, inner) == ring.sum()
    assert _rises_inside(wall | ring, region, inner) == ring.sum()


@pytest.fixture(scope="module")
def stool_scene():
    T = turntable_ring(36, look_y_mm=25.0)
    images, masks = _render(T, "stool", np.random.default_rng(6))
    hull = _hull(masks, T)
    roofed, roofs = carve_above_faces(hull, images, masks, K, T)
    return masks, T, roofed, [f for f, _ in roofs]


def test_the_space_under_a_seat_that_no_view_sees_is_carved(stool_scene):
    """Seen from 30 deg above, the stool's seat (54 mm wide, its underside 45 mm up) leaves a pyramid under it
    in the silhouettes' hull, down to ~29 mm over its middle; no view sees into it. Its slab shows in the hull
    (full to the underside, then the wedge): the wedge goes, the seat and the legs stay."""
    masks, T, roofed, tops = stool_scene
    middle = np.array([[0.0, y, 0.0] for y in np.arange(33.0, 44.0, 1.0)])
    assert hull_holds(roofed, middle).all()  # the wedge, before
    carved, slabs = carve_under_slabs(roofed, tops, masks, K, T)
    assert len(slabs) == 1 and abs(slabs[0][0].underside_mm - 45.0) <= 1.0
    assert not hull_holds(carved, middle).any()
    v = roofed.voxel_mm
    for lo, hi in STOOL:  # the seat and every leg, whole
        assert hull_holds(carved, _inner_grid(lo, hi, v)).all()
    true = sum(np.prod(hi - lo) for lo, hi in STOOL)
    assert (roofed.values > 0).sum() * v ** 3 > 1.4 * true
    assert (carved.values > 0).sum() * v ** 3 < 1.15 * true


def test_the_space_under_a_found_seat_holds_the_wedge_and_not_the_legs(stool_scene):
    """The space a second cast-shadow pass looks in (recon.faces.space_under): under the found seat's footprint,
    below its underside, where the hull does not stand from the table up to it. The wedge under the middle is in
    it; the legs, the seat and anything beyond the footprint's margin are not."""
    masks, T, roofed, tops = stool_scene
    _, slabs = carve_under_slabs(roofed, tops, masks, K, T)
    under = space_under([slab for slab, _ in slabs], roofed)
    o, v = roofed.origin_table, roofed.voxel_mm

    def at(pts):
        idx = np.rint((pts - o) / v).astype(int)
        return under[tuple(idx.T)]

    assert at(np.array([[x, y, z] for x in (-10.0, 0.0, 10.0) for z in (-10.0, 0.0, 10.0)
                        for y in (25.0, 35.0, 43.0)])).all()
    for lo, hi in STOOL:  # the seat, and every leg standing on the table
        assert not at(_inner_grid(lo, hi, v)).any()
    assert not at(np.array([[0.0, 30.0, 35.0], [35.0, 30.0, 0.0], [0.0, 47.0, 0.0]])).any()


def test_a_needle_a_few_masks_hold_under_the_seat_goes_with_the_wedge(stool_scene):
    """A column one voxel thin under the seat's middle, held on down past the wedge to 20 mm (as a few views' masks
    holding a flap there would): where the wedge hid it, it would hang from the seat as a needle. It goes too."""
    masks, T, roofed, tops = stool_scene
    vals = roofed.values.copy()
    v = roofed.voxel_mm
    ix, iz = (np.rint((np.zeros(2) - roofed.origin_table[[0, 2]]) / v)).astype(int)
    iy = np.arange(int(np.ceil((20.0 - roofed.origin_table[1]) / v)), int((45.0 - roofed.origin_table[1]) / v))
    vals[ix, iy, iz] = v
    needled = dataclasses.replace(roofed, values=vals)
    needle = np.array([[0.0, y, 0.0] for y in (21.0, 25.0, 30.0, 40.0)])
    assert hull_holds(needled, needle).all()
    carved, slabs = carve_under_slabs(needled, tops, masks, K, T)
    assert len(slabs) == 1 and not hull_holds(carved, needle).any()
    for lo, hi in STOOL:
        assert hull_holds(carved, _inner_grid(lo, hi, v)).all()


def test_a_box_under_an_overhanging_lid_keeps_its_body():
    """A lid 5 mm thick overhanging its box by 8 mm is a slab too, and the box's middle is hidden behind it
    from every view, as the stool's wedge is; but the hull goes on under it down to the table (the box's sides,
    which the views do see): nothing of the box is carved. (Under the overhang only a little near its corners:
    elsewhere the views past its edge see the box's side, and so hold what lies in front of it.)"""
    T = turntable_ring(36, look_y_mm=25.0)
    images, masks = _render(T, "lidbox", np.random.default_rng(7))
    hull = _hull(masks, T)
    roofed, roofs = carve_above_faces(hull, images, masks, K, T)
    assert roofs
    carved, slabs = carve_under_slabs(roofed, [f for f, _ in roofs], masks, K, T)
    assert len(slabs) == 1 and abs(slabs[0][0].underside_mm - 35.0) <= 1.0
    v = hull.voxel_mm
    for lo, hi in LIDBOX:
        assert hull_holds(carved, _inner_grid(lo, hi, v)).all()


def test_a_plain_box_has_no_slab(box_scene):
    images, masks, T, hull = box_scene
    roofed, roofs = carve_above_faces(hull, images, masks, K, T)
    carved, slabs = carve_under_slabs(roofed, [f for f, _ in roofs], masks, K, T)
    assert roofs and slabs == [] and np.array_equal(carved.values, roofed.values)


def test_a_sphere_has_no_flat_top_and_keeps_its_hull():
    T = _cameras()
    images, masks = _render(T, "sphere", np.random.default_rng(1))
    hull = _hull(masks, T)
    carved, done = carve_above_faces(hull, images, masks, K, T)
    assert done == [] and np.array_equal(carved.values, hull.values)


def test_a_domed_lid_is_no_flat_top_though_its_rim_is_a_horizontal_edge():
    """The rim of a round box's lid outlines a plain white region at one height, as a flat top's
    edge does; but the dome inside rises, and its contour outlines it higher up: no face, no voxel of
    the dome carved (a teapot's lid lost its top to a face found at its rim)."""
    T = _cameras()
    images, masks = _render(T, "lid", np.random.default_rng(2))
    hull = _hull(masks, T)
    assert find_faces(images, masks, K, T, hull) == []
    carved, done = carve_above_faces(hull, images, masks, K, T)
    assert done == [] and np.array_equal(carved.values, hull.values)


def test_a_band_painted_round_a_column_is_no_top():
    """A plain column, evenly lit, with a dark band round it: the band's edges are horizontal circles
    that every view puts on the same outline at 28 and 30 mm, and inside them the views agree on one
    colour, as on a flat top; but the column stands on that section up to 80 mm, higher than any roof
    over a top 40 mm wide: no face (a torso's section, outlined at one height, was taken for a top)."""
    T = _cameras()
    images, masks = _render(T, "column", np.random.default_rng(3))
    hull = carve_hull(masks, K, T, radius_mm=60.0, height_mm=120.0, resolution=128, max_rejections=0)
    assert find_faces(images, masks, K, T, hull) == []


def test_the_tent_over_a_white_boxs_sides_is_carved_between_its_corners(box_scene):
    """With views every 15 deg none looks along a side: the hull's section bows out in front of each side's
    middle (~3.9 mm over the 60 mm side). The corners' edges show in most views, the sides are plain: the
    hull outside the chords between the corners goes, and nothing of the box."""
    images, masks, T, _ = box_scene
    hull = carve_hull(masks, K, T, radius_mm=60.0, height_mm=90.0, resolution=200, max_rejections=0)
    tents = np.array([[0.0, y, BOX_HI[2] + 1.0] for y in (10.0, 20.0)]
                     + [[0.0, y, BOX_LO[2] - 1.0] for y in (10.0, 20.0)]
                     + [[BOX_HI[0] + 1.0, y, 0.0] for y in (10.0, 20.0, 30.0)])
    assert hull_holds(hull, tents).all()  # the silhouettes leave a tent over every side
    flat, sides = flatten_sides(hull, images, masks, K, T)
    assert sides and sum(s.volume_mm3 for s in sides) > 2000.0
    assert not hull_holds(flat, tents).any()
    v = hull.voxel_mm
    g = np.stack(np.meshgrid(*[np.arange(lo + v, hi - v, v) for lo, hi in zip(BOX_LO, BOX_HI, strict=True)],
                             indexing="ij"), -1).reshape(-1, 3)
    assert hull_holds(flat, g).all()
    # the mesh's surface (the values' zero) lies on the sides: a side's middle point is inside by under a voxel
    on = np.array([[0.0, 20.0, BOX_HI[2] - 0.5 * v], [0.0, 20.0, BOX_HI[2] + 1.0 * v]])
    assert hull_holds(flat, on[:1]).all() and not hull_holds(flat, on[1:]).any()


def test_a_side_lost_for_a_few_layers_goes_through_them(box_scene, monkeypatch):
    """A soft photo's corners wander by more than a layer's match allows here and there (the synth's box, blur
    1 px: one of its four sides kept at 22 mm): a side kept below and again within ``GAP_MM`` above goes through
    the layers between. Here every chord between 19 and 21 mm is lost; the tent there goes all the same, and
    nothing of the box. A side lost for longer than that is left to its hull."""
    import recon.sides as sides_mod

    images, masks, T, _ = box_scene
    hull = carve_hull(masks, K, T, radius_mm=60.0, height_mm=90.0, resolution=200, max_rejections=0)
    found = sides_mod._chords

    def lose(lo, hi):
        monkeypatch.setattr(sides_mod, "_chords",
                            lambda section, h, *a: [] if lo <= h <= hi else found(section, h, *a))

    tents = np.array([[0.0, 20.0, BOX_HI[2] + 1.0], [0.0, 20.0, BOX_LO[2] - 1.0], [BOX_HI[0] + 1.0, 20.0, 0.0]])
    lose(19.0, 21.0)
    flat, _ = flatten_sides(hull, images, masks, K, T)
    assert hull_holds(hull, tents).all() and not hull_holds(flat, tents).any()
    v = hull.voxel_mm
    g = np.stack(np.meshgrid(*[np.arange(lo + v, hi - v, v) for lo, hi in zip(BOX_LO, BOX_HI, strict=True)],
                             indexing="ij"), -1).reshape(-1, 3)
    assert hull_holds(flat, g).all()
    lose(17.0, 23.0)  # 6 mm: no side goes through
    flat, _ = flatten_sides(hull, images, masks, K, T)
    assert hull_holds(flat, tents).all()


def test_sides_gone_through_layers_are_dropped_where_they_cost_a_band_its_own_carving(box_scene, monkeypatch):
    """What the sides carried through layers uncover counts against the bands round them (the synth's box, dark
    room, seed 4: two bands refused with them, none without). Where the guard refuses a band with them that it
    would not refuse without, the carving is what each layer found itself."""
    import recon.sides as sides_mod

    images, masks, T, _ = box_scene
    hull = carve_hull(masks, K, T, radius_mm=60.0, height_mm=90.0, resolution=200, max_rejections=0)
    found, through, judge = sides_mod._chords, sides_mod._through, sides_mod._refused
    monkeypatch.setattr(sides_mod, "_chords", lambda section, h, *a: [] if 19.0 <= h <= 21.0 else found(section, h, *a))
    carried, _ = flatten_sides(hull, images, masks, K, T)
    monkeypatch.setattr(sides_mod, "_through", lambda kept_at, gap: {})
    own, _ = flatten_sides(hull, images, masks, K, T)
    assert not np.array_equal(carried.values, own.values)
    monkeypatch.setattr(sides_mod, "_through", through)
    calls = []

    def refuse_with_them(inside, carved, band, *a):
        bad, pts = judge(inside, carved, band, *a)
        calls.append(bad)
        return (bad | {int(20.0 // sides_mod.BAND_MM)}, pts) if len(calls) == 1 else (bad, pts)

    monkeypatch.setattr(sides_mod, "_refused", refuse_with_them)
    flat, sides = flatten_sides(hull, images, masks, K, T)
    assert len(calls) == 2 and sides and np.array_equal(flat.values, own.values)


@pytest.mark.parametrize("shape", ["sphere", "lid"])
def test_round_sides_have_no_corners_and_keep_their_hull(shape):
    """A sphere's and a round box's hull bows out between the views' silhouettes too, but no point of their
    outline lands on an edge in most views (their shading is smooth): nothing carved."""
    T = _cameras()
    images, masks = _render(T, shape, np.random.default_rng(4))
    hull = _hull(masks, T)
    flat, sides = flatten_sides(hull, images, masks, K, T)
    assert sides == [] and np.array_equal(flat.values, hull.values)


def test_a_top_found_again_half_a_mm_higher_is_the_same_top():
    """A seat's top peaks at 51.0 mm with the strict edge share and at 51.5 mm with the looser one: one top
    (noted twice, the second "0.0 cm³"). A face 3 mm higher over the same region (a slab's lower edge and
    its top), one beside it, or one lower is another."""
    from recon.faces import Face, same_top

    region = np.zeros((40, 40), bool)
    region[5:30, 5:30] = True
    beside = np.zeros_like(region)
    beside[5:30, 32:39] = True

    def face(h, r):
        return Face(h, r, np.zeros((40, 40, 3), np.float32), (0.0, 0.0), 3.0)

    first = face(51.0, region)
    assert same_top(face(51.5, region), first)
    assert not same_top(face(54.0, region), first)
    assert not same_top(face(51.5, beside), first)
    assert not same_top(face(50.5, region), first)


def test_a_volume_in_a_note_is_never_zero_cm3():
    from turntable.stages.hull import volume_text

    assert volume_text(24_400.0) == "24.4 cm³" and volume_text(40.0) == "40.0 mm³"
    assert volume_text(0.3) == "0.3 mm³"  # a speck of the hull dropped (the sample's)


def test_a_region_its_outline_encloses_only_at_the_corners_is_no_face():
    """A box's vertical corners are points on every horizontal plane, so every height inside the box has them on
    its outline; the hull's section closes the rest. Such a region is no face: the outline must enclose a share of
    its rim (``OUTLINED_SHARE``). Taken for one at 35.5 mm inside a white box on a light wall (seed 17), its roof —
    the box's upper part — was carved hollow: 2.35 % of the diagonal."""
    from recon.faces import OUTLINED_SHARE, Sweep, _faces_at

    px, shape = 3.0, (180, 240)
    section = np.zeros(shape, bool)
    section[30:150, 30:210] = True  # the box's section, 60 x 40 mm
    rim = section & ~np.pad(section[1:-1, 1:-1] & section[:-2, 1:-1] & section[2:, 1:-1] & section[1:-1, :-2]
                            & section[1:-1, 2:], 1)
    corners = np.zeros(shape, bool)
    for i, j in ((30, 30), (30, 209), (149, 30), (149, 209)):
        corners[i - 1:i + 2, j - 1:j + 2] = True

    class Outlined(Sweep):
        def outline(self, k, share=0.7):
            return self.drawn

        def agreement(self, h, images_rgb):  # the views agree all over, on one grey
            return np.ones(shape), np.full(shape + (3,), 200.0)

    heights = np.arange(30.0, 40.0, 0.5)

    def faces(drawn):
        sw = Outlined(heights, 0.5, [section] * len(heights), [], K, np.zeros((0, 4, 4)), 0.0, 0.0, px, shape)
        object.__setattr__(sw, "drawn", drawn)
        return _faces_at(sw, 11, 0.7, [])

    assert faces(corners) == []  # enclosed by the section: no face
    found = faces(rim)  # a top's edge all round
    assert len(found) == 1 and found[0].area_mm2 > 0.9 * 60 * 40 - 60
    gap = rim.copy()
    gap[:, 120:] = False  # half the edge shows no step (white on white): the section closes it
    assert OUTLINED_SHARE < 0.45 and len(faces(gap)) == 1
