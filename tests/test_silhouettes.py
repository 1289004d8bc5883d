"""Automatic silhouettes on a small ray-cast turntable scene with exact ground truth.

The scene: a fixed camera, a static room (textured floor below the table, a
textured backdrop), a turntable disc with a paper target and an asymmetric
mark track turning with the table, and a box with a blocky colour texture standing off-centre on it. (A box of
two flat colours is a known weak case: where it covers the same pixels in
most frames it looks static, see the report.)
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.camera import look_at, project_points
from calib.target import TargetSpec
from recon.silhouette_checks import fill_gaps
from recon.silhouettes import SilhouetteResult, cylinder_region, estimate_silhouettes, rectify_to_table

W, H, F_PX = 320, 240, 375.0
K = np.array([[F_PX, 0.0, (W - 1) / 2], [0.0, F_PX, (H - 1) / 2], [0.0, 0.0, 1.0]])
SPEC = TargetSpec(80.0, 50.0, 3.0)
BOX_LO, BOX_HI = np.array([-25.0, 0.0, -12.0]), np.array([20.0, 70.0, 18.0])  # table frame, mm
DISC_MM = 120.0


def _rot_y(th: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(th), np.sin(th)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    return T


def _camera_world(distance_mm=450.0, elevation_deg=30.0) -> np.ndarray:
    e = np.radians(elevation_deg)
    return look_at(distance_mm * np.array([np.cos(e), np.sin(e), 0.0]), (0.0, 30.0, 0.0))


def _blocks(a: np.ndarray, b: np.ndarray, size: float, seed: int) -> np.ndarray:
    """Static random colour blocks (N, 3) float indexed by two coordinates."""
    lut = np.random.default_rng(seed).uniform(20, 235, (64, 64, 3))
    return lut[np.floor(a / size).astype(int) % 64, np.floor(b / size).astype(int) % 64]


def _disc_colour(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    r = np.hypot(x, z)
    grey = np.full_like(r, 235.0)
    for ring in (SPEC.r_outer_mm, SPEC.r_inner_mm):
        grey[np.abs(r - ring) <= 1.5] = 15.0
    sector = np.floor((np.arctan2(z, x) + np.pi) / (2 * np.pi) * 72).astype(int)
    code = np.array([int(c) for c in SPEC.mark_code])
    grey[(r >= 86) & (r <= 98) & (code[sector % 72] == 1)] = 15.0
    out = np.repeat(grey[:, None], 3, axis=1)
    out[r > 105] = [90.0, 80.0, 110.0]  # the disc beyond the paper
    return out


def _render(T_cam_world: np.ndarray, th: float, with_object: bool = True, plain: bool = False,
            box=(BOX_LO, BOX_HI), white: bool = False):
    """Image (H, W, 3) uint8 and object mask (H, W) of the table turned by ``th``.

    ``plain``: a black room and a black disc without a target (a studio turntable, as on real
    photos): only the object is lit, so no plate knows what lies right behind it. ``white``: an
    off-white box shaded per face, its top exactly the paper's grey (white on white).
    """
    BOX_LO, BOX_HI = (np.asarray(b, float) for b in box)
    T_wt = _rot_y(th)
    T_cam_table = T_cam_world @ T_wt
    R, t = T_cam_table[:3, :3], T_cam_table[:3, 3]
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    d_cam = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(K).T
    d = d_cam @ R  # table frame
    o = -R.T @ t
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (BOX_LO - o) / d, (BOX_HI - o) / d
    t_box_in = np.nanmax(np.minimum(t1, t2), axis=1)
    t_box_out = np.nanmin(np.maximum(t1, t2), axis=1)
    hit_box = with_object & (t_box_in < t_box_out) & (t_box_out > 0)
    t_plane = np.where(d[:, 1] < 0, -o[1] / d[:, 1], np.inf)
    p = o + t_plane[:, None] * d
    p_world = np.where(np.isfinite(p), p, 0.0) @ T_wt[:3, :3].T
    on_disc = np.hypot(p[:, 0], p[:, 2]) <= DISC_MM
    d_world = d @ T_wt[:3, :3].T
    rgb = _blocks(np.arctan2(d_world[:, 2], d_world[:, 0]) * 300, d_world[:, 1] * 300, 9.0, 1)  # backdrop
    floor = np.isfinite(t_plane) & ~on_disc
    rgb[floor] = _blocks(p_world[floor, 0], p_world[floor, 2], 25.0, 2)
    rgb[on_disc] = _disc_colour(p[on_disc, 0], p[on_disc, 2])
    if plain:
        rgb[:] = 12.0
    q = (o + t_box_in[:, None] * d)[hit_box]
    rgb[hit_box] = 0.5 * _blocks(q[:, 0] + q[:, 2], q[:, 1], 6.0, 3) + 0.5 * _blocks(q[:, 2] - q[:, 0], q[:, 1], 5.0, 4)
    if white:  # the face hit: the slab whose entry is last; lit from above and from +X of the table
        face = np.argmax(np.minimum(t1, t2), axis=1)[hit_box]
        side = np.sign(d[hit_box, face])
        rgb[hit_box] = np.where(face == 1, 235.0, np.where((face == 0) & (side < 0), 228.0, 205.0))[:, None]
    return rgb.reshape(H, W, 3), hit_box.reshape(H, W), T_cam_table


@pytest.fixture(scope="module")
def sequence():
    rng = np.random.default_rng(3)
    T_cw = _camera_world()
    frames = [_render(T_cw, th) for th in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    imgs = np.stack([f[0] for f in frames])
    imgs = np.clip(imgs + rng.normal(0.0, 2.0, imgs.shape), 0, 255).astype(np.uint8)  # sensor noise
    return imgs, np.stack([f[1] for f in frames]), np.stack([f[2] for f in frames])


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


def test_silhouettes_match_ground_truth(sequence):
    imgs, gt, T = sequence
    res = estimate_silhouettes(imgs, K, T, SPEC)
    assert isinstance(res, SilhouetteResult) and res.masks.shape == gt.shape and res.masks.dtype == bool
    ious = [_iou(m, g) for m, g in zip(res.masks, gt, strict=True)]
    # measured: median 0.99, mean 0.96; two frames lose part of the box top where the box covers
    # the same far-floor pixels in most frames (0.90, 0.73): the room plate's weak case
    assert np.median(ious) >= 0.97 and np.mean(ious) >= 0.94, ious
    assert np.sum(np.array(ious) >= 0.95) >= 9, ious
    assert sum(s == "ok" for s in res.status) >= 10, res.status
    assert np.all((res.quality >= 0.0) & (res.quality <= 1.0)) and np.median(res.quality) > 0.6, res.quality


def test_empty_frame_is_flagged_not_fatal(sequence):
    imgs, gt, T = sequence
    imgs = imgs.copy()
    imgs[4] = 0  # a black frame: lens cap, failed capture
    res = estimate_silhouettes(imgs, K, T, SPEC)
    # frames are 30 deg apart: dropping frame 4 would leave 60 deg without a view, so it is kept
    # conservatively, and carving with mask | unknown cannot eat the object there
    assert res.status[4].startswith("conservative: "), res.status[4]
    assert (gt[4] & ~(res.masks[4] | res.unknown[4])).sum() == 0
    assert [s for i, s in enumerate(res.status) if i != 4].count("ok") >= 10
    assert np.median([_iou(res.masks[i], gt[i]) for i in range(12) if i != 4]) >= 0.97


def test_no_object_gives_empty_flagged_masks():
    T_cw = _camera_world()
    frames = [_render(T_cw, th, with_object=False) for th in np.linspace(0, 2 * np.pi, 6, endpoint=False)]
    imgs = np.stack([f[0] for f in frames]).astype(np.uint8)
    res = estimate_silhouettes(imgs, K, np.stack([f[2] for f in frames]), SPEC)
    assert res.masks.sum() < 0.01 * res.masks.size
    assert all(s != "ok" for s in res.status), res.status


def test_cylinder_region_holds_the_object(sequence):
    _, gt, T = sequence
    region = cylinder_region(K, T[0], (W, H), SPEC.extent_mm, 100.0)
    assert region[gt[0]].all()
    assert 0.1 < region.mean() < 0.9  # and it is not the whole image
    top = project_points(K, T[0], np.array([[0.0, 100.0, 0.0]]))[0]
    assert region[int(round(top[1])), int(round(top[0]))]


def test_rectify_to_table_layout():
    T = _camera_world()
    img = np.zeros((H, W), np.uint8)
    X, Z = 30.0, -20.0  # a bright dot at a known table point
    uv = project_points(K, T, np.array([[X, 0.0, Z]]))[0]
    img[int(round(uv[1])), int(round(uv[0]))] = 255
    ppm = 2.0
    rect = rectify_to_table(img, K, T, 60.0, ppm)
    c = (rect.shape[0] - 1) / 2
    i, j = np.unravel_index(np.argmax(rect), rect.shape)
    tol_px = 3.0  # one image pixel spans ~ 1.5 mm here
    assert abs(j - (c + X * ppm)) <= tol_px and abs(i - (c + Z * ppm)) <= tol_px


def test_three_states_are_disjoint_and_ok_frames_have_a_thin_unknown(sequence):
    imgs, gt, T = sequence
    res = estimate_silhouettes(imgs, K, T, SPEC)
    assert res.unknown.shape == res.masks.shape and res.unknown.dtype == bool
    assert not (res.unknown & res.masks).any()
    for i, s in enumerate(res.status):
        assert s == "ok" or s.startswith(("conservative: ", "rejected: ")), s
        if s == "ok":  # only the doubtful outline band, joined to the object or across its blended pixels
            assert res.unknown[i].sum() < res.masks[i].sum(), (i, res.unknown[i].sum())
            n, lab = cv2.connectedComponents(res.unknown[i].astype(np.uint8), connectivity=8)
            near = cv2.dilate(res.masks[i].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # doubt_across's gap
            assert set(range(1, n)) <= set(np.unique(lab[near])), i
    assert _touching_views(res.masks, T, SPEC.extent_mm + 5.0) == set()


def test_fill_gaps_keeps_no_gap_over_30_deg():
    az = np.arange(36) * 10.0
    status = tuple("rejected: x" if 5 <= i < 12 else "ok" for i in range(36))  # 70 deg dropped in a row
    out = fill_gaps(status, az)
    kept = np.sort(az[[i for i, s in enumerate(out) if not s.startswith("rejected")]])
    assert np.diff(np.append(kept, kept[0] + 360)).max() <= 30.0
    assert sum(s.startswith("conservative") for s in out) == 2  # no more than needed (70 and 100 deg)
    # half a turn, 0..170 deg, its last 8 frames dropped: kept up to its end, the open half stays open
    half = fill_gaps(tuple("rejected: x" if i >= 10 else "ok" for i in range(18)), np.arange(18) * 10.0)
    assert [i for i, s in enumerate(half) if s.startswith("conservative")] == [12, 15, 17], half


def test_a_thin_object_small_in_every_frame_is_not_empty():
    """A thin object (a pole, a figure side on) covers 1.5 % of the working volume's image in every frame:
    its masks are kept. A frame whose mask collapsed to a tenth of the others', or one with nothing, is
    empty; so is a sequence of specks."""
    from recon.silhouette_checks import frame_status

    V, region = 12, np.full(12, 100_000.0)
    area = np.full(V, 1500.0)
    area[3], area[7] = 150.0, 0.0
    _, status = frame_status(area, np.ones(V), np.zeros(V), region, (640, 480))
    assert [i for i, s in enumerate(status) if s != "ok"] == [3, 5, 7], status
    assert status[3] == ("rejected: nearly empty silhouette (150 px: 0.1 % of the working volume's image, "
                         "10 % of the median frame's)"), status[3]
    assert status[7] == "rejected: empty silhouette (0 px)"
    assert "area jumps" in status[5], status  # two of its four neighbours empty
    _, specks = frame_status(np.full(V, 150.0), np.ones(V), np.zeros(V), region, (640, 480))
    assert all("empty silhouette" in s for s in specks), specks


def test_real_studio_photos_outline_without_plates_is_ok():
    """Black room, black disc, no target, an object on the axis covering the same pixels in most
    frames (real turntable photos): no plate is trusted next to the outline, which must not count
    against it (it used to reject a third of these frames: "only 47 % of the outline is explained";
    35 of 36 real photos of a squirrel)."""
    rng = np.random.default_rng(4)
    T_cw = _camera_world(elevation_deg=5.0)  # low: the rays past the box's top half miss the table
    box = ([-22.0, 0.0, -22.0], [22.0, 80.0, 22.0])
    frames = [_render(T_cw, th, plain=True, box=box) for th in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    imgs = np.clip(np.stack([f[0] for f in frames]) + rng.normal(0.0, 2.0, (12, H, W, 3)), 0, 255).astype(np.uint8)
    gt, T = np.stack([f[1] for f in frames]), np.stack([f[2] for f in frames])
    res = estimate_silhouettes(imgs, K, T, radius_mm=60.0)  # no target: the volume from the caller
    assert all(s == "ok" for s in res.status), res.status
    assert np.mean([_iou(m, g) for m, g in zip(res.masks, gt, strict=True)]) >= 0.97
    assert _touching_views(res.masks, T, 60.0) == set()
    small = estimate_silhouettes(imgs, K, T, radius_mm=20.0)  # narrower than the box: it sticks out
    assert _touching_views(small.masks, T, 20.0) == set(range(12))


def _touching_views(masks, T, radius_mm) -> set[int]:
    """Views whose silhouette reaches the side or top of the working volume's image (what
    ``reconstruct`` grows the volume on)."""
    from recon.carving import largest_visible_height_mm
    from turntable.stages.volume import WorkingVolume, mask_touches

    h = largest_visible_height_mm(K, T, W, H)
    side, top = mask_touches(masks, K, T, WorkingVolume(radius_mm, h, radius_mm, h, "test"))
    return set(side) | set(top)


def test_bad_input():
    with pytest.raises(ValueError, match="images_rgb"):
        estimate_silhouettes(np.zeros((3, 10, 10), np.uint8), K, np.tile(np.eye(4), (3, 1, 1)), SPEC)
    with pytest.raises(ValueError, match="T_cam_table"):
        estimate_silhouettes(np.zeros((3, 10, 10, 3), np.uint8), K, np.tile(np.eye(4), (2, 1, 1)), SPEC)


@pytest.mark.xfail(strict=True, reason="issue 8 open: a white object's part that looks exactly like the paper "
                   "behind it is not joined to the mask's unknown (grown that way, the unknown flooded the paper of "
                   "every object with a pale colour: recon.silhouette_doubt.doubt_joined), so it can still be eaten")
def test_white_box_on_white_paper_is_never_eaten():
    """An off-white box on the white target (its top the paper's very grey): where the object is
    seen against the paper no colour tells them apart, so those pixels must be unknown, not
    background (carving with mask | unknown keeps them), while the printed ink the box does not
    hide stays confident background (other views' rays to it still carve)."""
    rng = np.random.default_rng(5)
    T_cw = _camera_world()
    frames = [_render(T_cw, th, white=True) for th in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    imgs = np.clip(np.stack([f[0] for f in frames]) + rng.normal(0.0, 2.0, (12, H, W, 3)), 0, 255).astype(np.uint8)
    gt, T = np.stack([f[1] for f in frames]), np.stack([f[2] for f in frames])
    res = estimate_silhouettes(imgs, K, T, SPEC)
    # where the box shows hardly anything but its top against the paper, the frame is rejected
    # (an empty silhouette: it carves nothing) or kept conservatively
    kept = [i for i, s in enumerate(res.status) if not s.startswith("rejected")]
    assert len(kept) >= 8, res.status
    keep = res.masks | res.unknown
    covered = [(g & k).sum() / g.sum() for g, k in zip(gt[kept], keep[kept], strict=True)]
    assert min(covered) >= 0.99, covered  # measured: >= 0.994 (the mask alone: 0.15-0.77; the old rule: 0.48)
    ink = np.stack([cylinder_region(K, t, (W, H), SPEC.r_inner_mm + 1.5, 0.0)
                    & ~cylinder_region(K, t, (W, H), SPEC.r_inner_mm - 1.5, 0.0) for t in T])
    visible_ink = ink & ~gt
    background = ~keep
    # the inner ring's visible ink is confident background in each kept frame (measured: 0.6-0.9 of
    # the band around it, which at this size also holds blended edge pixels; the old rule: 0.0 in one)
    assert min((background & visible_ink)[i].sum() / visible_ink[i].sum() for i in kept) >= 0.5


def _white_vase_hull(folder, backdrop: str, target_background: str = "white"):
    """Hull (trimesh, table frame, mm) of a 12-frame off-white vase render from ``masks | unknown`` of
    the automatic silhouettes with the true cameras, its Chamfer distance to the truth in % of the
    bounding-box diagonal, the true mesh and the printed ground the silhouettes recognised."""
    trimesh = pytest.importorskip("trimesh")
    from scipy.spatial import cKDTree

    from recon.carving import carve_hull
    from recon.meshing import mesh_from_hull
    from turntable.cameras_io import read_cameras
    from turntable.synth import SynthOptions, make_sequence

    make_sequence(folder, SynthOptions(object="vase", backdrop=backdrop, seed=5, width=W, height=H, focal_px=F_PX,
                                       albedo=(0.85, 0.84, 0.82), frames=12, step_deg=30.0,
                                       target_background=target_background), overwrite=True)
    seq = read_cameras(folder / "cameras_gt.json")
    imgs = np.stack([cv2.imread(str(folder / f.image))[..., ::-1] for f in seq.frames])
    T = np.stack([f.T_cam_table for f in seq.frames])
    res = estimate_silhouettes(imgs, seq.intrinsics.K, T, SPEC)
    assert not any(s.startswith("rejected") for s in res.status), res.status
    hull = carve_hull(res.masks | res.unknown, seq.intrinsics.K, T, radius_mm=SPEC.extent_mm + 5.0, resolution=128)
    mesh = mesh_from_hull(hull)
    gt = trimesh.load(folder / "object_gt.ply")
    m = trimesh.Trimesh(mesh.vertices_table, mesh.faces, process=False)
    a, b = m.sample(20000, seed=0), gt.sample(20000, seed=0)
    chamfer = 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())
    return m, 100.0 * chamfer / float(np.linalg.norm(gt.bounds[1] - gt.bounds[0])), gt, res.ground


def test_white_vase_on_white_paper_keeps_its_hull(tmp_path):
    """A uniformly off-white vase on the white target in a dark room (``turntable synth --albedo
    white``): a body of revolution looks the same in every frame, and the paper behind it is hidden
    by the same plain colour in most frames, so a median over the whole turn made the paper behind
    the vase look like the vase (and the vase like the paper); the vase's shaded body, a darker
    copy of the paper, was also taken for its shadow. The hull carved from ``masks | unknown`` must
    stay close to the true vase (measured 1.05 % of the bounding box diagonal at this size; before:
    3.5 %, with flakes over the paper)."""
    _, chamfer_pct, _, ground = _white_vase_hull(tmp_path / "white_vase", "dark")
    assert ground is None  # white paper: no coloured ground to report
    assert chamfer_pct <= 2.0, chamfer_pct


def test_white_vase_on_a_light_wall_keeps_its_neck_and_lip(tmp_path):
    """The same vase in front of a light grey wall. Static over the axis, its neck and lip are the room
    plate in every frame; the lit lip is brighter than any colour of the room and sits beyond an edge from
    the mask, the shaded neck has the wall's grey. Those parts are unknown where no plate vouches for them
    and they reach the object in a fifth of the views or more (``doubt_across``), so the hull keeps the
    vase's full height (measured at this size: top 115.6 mm for 110, Chamfer 3.5 % of the diagonal;
    before: the neck carved off at 78.5 mm, 5.3 %)."""
    m, chamfer_pct, gt, _ = _white_vase_hull(tmp_path / "white_vase_light", "light")
    assert m.bounds[1][1] >= 0.95 * gt.bounds[1][1], m.bounds[1][1]  # the lip is there
    assert chamfer_pct <= 4.5, chamfer_pct


def _white_vase_on_a_light_wall(tmp_path, seed: int):
    """The white vase on a light wall under the lights of ``seed``, a full turn of 36 frames: its automatic
    silhouettes and the true masks."""
    from turntable.cameras_io import read_cameras
    from turntable.synth import SynthOptions, make_sequence

    folder = tmp_path / f"white_vase_light_s{seed}"
    make_sequence(folder, SynthOptions(object="vase", backdrop="light", seed=seed, width=W, height=H, focal_px=F_PX,
                                       albedo=(0.85, 0.84, 0.82)), overwrite=True)
    seq = read_cameras(folder / "cameras_gt.json")
    imgs = np.stack([cv2.imread(str(folder / f.image))[..., ::-1] for f in seq.frames])
    gts = np.stack([cv2.imread(str(folder / "masks" / (Path(f.image).stem + ".png")), 0) > 127 for f in seq.frames])
    T = np.stack([f.T_cam_table for f in seq.frames])
    return estimate_silhouettes(imgs, seq.intrinsics.K, T, SPEC), gts


def test_white_vase_on_a_light_wall_leaves_the_paper_round_its_foot(tmp_path):
    """The vase on a light wall under another light (seed 2), a full turn of 36 frames. Its shadow's sweep
    rings the paper round its foot with untrusted texels, so that paper is an island of the table plate
    (``untrust_enclosed``), and nothing said it was not the vase: every mask took the disc inside the inner
    ring (mask pixels off the object: 47 % of the object's area on average, 3.06 % of the diagonal end to
    end at 640 x 480). The island's plate from the views on each point's own side vouches for it in those
    views: the lit paper in the masks, measured 0.2 %. What the masks take off the object is the vase's
    static shadow (24 %), in the grey of its own shaded side, which the room plate no longer vouches for
    (``reached_from_outside``); the hull's cast-shadow carving takes that skirt (0.36 % end to end at
    640 x 480). The vase itself is held (mask or unknown): 98 %."""
    res, gts = _white_vase_on_a_light_wall(tmp_path, seed=2)
    paths = sorted((tmp_path / "white_vase_light_s2" / "images").glob("*.jpg"))
    lit = []
    for path, m, g in zip(paths, res.masks, gts, strict=True):
        grey = cv2.imread(str(path)).astype(np.float32).mean(axis=-1)
        paper = float(np.median(grey[~m & ~g & (grey > 150)]))
        lit.append((m & ~g & (grey >= 0.85 * paper)).sum() / g.sum())
    assert np.mean(lit) <= 0.02, np.mean(lit)
    held = np.mean([((m | u) & g).sum() / g.sum() for m, u, g in zip(res.masks, res.unknown, gts, strict=True)])
    assert held >= 0.95, held


def test_white_vase_on_the_green_ground_leaves_the_paper_round_its_foot(tmp_path):
    """The same vase on the target printed on a green ground (``turntable pattern --background green``,
    what the README tells a user to print for a white object). The vase hides the paper round its foot
    in most frames, so no table plate is trusted there; the ground's colour still says it is paper,
    which the vase never shows. Measured at this size: 1.32 % of the diagonal (before the ground was
    recognised: the green disc inside the inner ring and the vase's shadow went to the vase, 4.13 %)."""
    _, chamfer_pct, _, ground = _white_vase_hull(tmp_path / "white_vase_green", "dark", "green")
    assert chamfer_pct <= 2.0, chamfer_pct
    # and the result says so (the run's notes and summary name it)
    from turntable.stages.silhouettes import ground_name

    assert ground is not None and ground_name(ground) == "green", ground


def test_printed_ground_is_recognised_lit_or_shaded_and_only_when_coloured():
    """A coloured printed ground's chromaticity comes from the trusted, plain paper of the table plate (not
    its ink, not the untrusted texels); a pixel of that ground matches lit or in a shadow, a white or grey
    object's pixel does not, nor a pixel too dark for its colour to be more than noise. A white or grey
    paper is no coloured ground."""
    from recon.silhouette_plates import ground_match, printed_ground

    n = 200
    rng = np.random.default_rng(7)
    green = np.array([91.0, 200.0, 91.0])
    plate = np.clip(green + rng.normal(0.0, 2.0, (n, n, 3)), 0, 255).astype(np.uint8)
    plate[::10, :] = 20  # ink lines
    trust = np.ones((n, n), np.uint8)
    trust[80:120, 80:120] = 0
    plate[80:120, 80:120] = 230  # untrusted: the object's colour where it hides the paper
    ground = printed_ground(plate, trust, radius_px=100.0, tau=6.0)
    assert ground is not None
    assert np.abs(ground - green / green.sum()).max() < 0.01
    img = np.array([[[91, 200, 91], [36, 80, 36], [230, 230, 225], [120, 121, 118], [8, 20, 8], [200, 200, 91]]],
                   np.uint8)
    assert ground_match(img, ground, tau=6.0).tolist() == [[True, True, False, False, False, False]]
    for paper in ([235.0, 233.0, 225.0], [150.0, 150.0, 150.0]):
        grey = np.clip(np.array(paper) + rng.normal(0.0, 2.0, (n, n, 3)), 0, 255).astype(np.uint8)
        assert printed_ground(grey, trust, radius_px=100.0, tau=6.0) is None


def test_a_recognised_ground_is_named_and_shown_in_the_summary():
    """The recognised ground's chromaticity is named by its hue (a printed green photographs as green, a blue
    as blue) and shown on its own summary line, which a summary without one does not print."""
    from turntable.stages.silhouettes import ground_name
    from turntable.stages.summary import ReconstructSummary

    assert [ground_name(c) for c in ((0.24, 0.53, 0.23), (0.22, 0.32, 0.46), (0.47, 0.28, 0.25))] == \
        ["green", "blue", "red"]
    d = {"frames_used": 12, "focal_px": 750.0, "fusion": "hull kept", "time_s": {"total": 1.0},
         "mesh": {"vertices": 4, "faces": 4, "watertight": True, "volume_cm3": 1.0, "extent_mm": [1, 1, 1]},
         "silhouettes": {"rejected": {}, "conservative": {},
                         "printed_ground": {"colour": "green", "chromaticity": [0.2421, 0.5252, 0.2327]}}}
    shown = [line for line in ReconstructSummary.from_json(d).lines() if "printed ground" in line]
    assert len(shown) == 1 and "green, chromaticity 0.24 0.53 0.23" in shown[0], shown
    del d["silhouettes"]["printed_ground"]
    assert not any("printed ground" in line for line in ReconstructSummary.from_json(d).lines())


def test_many_empty_silhouettes_get_a_hint_on_screen():
    """A quarter of the automatic silhouettes empty (dropped, or kept only to close a gap) makes the run say
    what would tell the object from its background; a few empty ones, or empty --masks, do not; with a
    coloured ground recognised it does not suggest printing one. The hint is a summary line of its own."""
    from turntable.stages.silhouettes import silhouette_advice
    from turntable.stages.summary import ReconstructSummary

    rejected = {f"f{i:02d}.jpg": f"empty silhouette ({900 + i} px)" for i in range(8)}
    kept = {"f20.jpg": "kept although empty silhouette (433 px) (dropping it leaves 40 deg of the turn without a view)",
            "f21.jpg": "silhouette area jumps to 222% of its neighbours'"}
    hint = silhouette_advice(rejected, kept, 36)  # 9 empty of 36: a quarter
    assert hint is not None and hint.startswith("9 of 36 automatic silhouettes") and "--background green" in hint
    assert silhouette_advice(rejected, {}, 36) is None  # 8 of 36: fewer than a quarter
    green = silhouette_advice(rejected, kept, 36, (0.24, 0.53, 0.23))
    assert green is not None and "--background" not in green and "dark backdrop" in green
    masks_given = {f"f{i:02d}.jpg": "the mask is empty (f.png has no pixel above 127, the brightest is 0)"
                   for i in range(20)}
    assert silhouette_advice(masks_given, {}, 36) is None
    d = {"frames_used": 28, "focal_px": 750.0, "fusion": "hull kept", "time_s": {"total": 1.0},
         "mesh": {"vertices": 4, "faces": 4, "watertight": True, "volume_cm3": 1.0, "extent_mm": [1, 1, 1]},
         "silhouettes": {"rejected": rejected, "conservative": kept, "advice": hint}}
    shown = [line for line in ReconstructSummary.from_json(d).lines() if line.startswith("  hint ")]
    assert shown == [f"  hint            {hint}"]
    del d["silhouettes"]["advice"]
    assert not any(line.startswith("  hint ") for line in ReconstructSummary.from_json(d).lines())


def test_doubt_joined_keeps_a_shaded_side_and_stops_at_the_wall():
    """A white object's lit half is in the mask; its shaded half fades smoothly from the lit grey to a
    dark grey and meets a wall of the object's mid grey at an edge. Every pixel outside the mask is
    doubtful (the object shows the wall's grey). Unknown: the shaded half, not the wall behind the
    edge; nor the paper of the plane's colour below, which the object touches without an edge."""
    from recon.silhouette_doubt import doubt_joined

    h, w = 60, 100
    img = np.full((h, w, 3), 145, np.uint8)  # the wall
    img[40:] = 220  # the paper
    cols = np.arange(20, 65)
    shade = np.interp(cols, [20, 34, 35, 64], [200, 200, 198, 110])  # lit half, then a smooth fade (3 DN/px)
    img[10:40, 20:65] = shade[None, :, None].astype(np.uint8)
    img[10:13, 20:65] = 200  # the lit rim on top: where the fade passes the wall's grey, it is inside the outline
    img[34:40, 20:35] = 220  # the lit half's foot is the paper's colour: no edge to the paper
    rng = np.random.default_rng(0)
    img = np.clip(img + rng.normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)
    mask = np.zeros((h, w), bool)
    mask[10:40, 20:35] = True
    mask[10:13, 20:65] = True
    doubtful = ~mask
    paper = np.zeros((h, w), bool)
    paper[40:] = True
    unknown = doubt_joined(img, mask, doubtful, paper, tau=6.0)
    shaded = np.zeros((h, w), bool)
    shaded[13:40, 35:65] = True
    assert unknown[shaded].mean() > 0.95
    wall = np.zeros((h, w), bool)
    wall[:40, 68:] = True
    wall[:7] = True
    assert not unknown[wall].any()
    assert unknown[42:, :].sum() == 0  # the paper two rows below the foot on
    assert not (unknown & mask).any()


def test_doubt_joined_does_not_step_from_a_fat_mask_into_a_doubtful_stretch_of_another_colour():
    """A mask one pixel too fat (it took a pixel of the background's colour past its outline) ends
    next to a smooth doubtful stretch of another colour: the dark underside of a vase against the paper in its
    shadow, the wood behind a neck. The mask's own colour next to it is not that stretch's (an edge lies
    between them): on the paper the stretch is not joined; a shaded side continuing the mask's colour still is.
    Off the paper (a wall) the rule is not applied: the wall's split takes a flood off whole there."""
    from recon.silhouette_doubt import doubt_joined

    h, w = 40, 90
    img = np.full((h, w, 3), 200, np.uint8)  # the paper in the shadow, plain
    img[:, :30] = 110  # the object's dark underside, in the mask
    img[:, 50:60] = 110  # another part of it, in the mask ...
    img[:, 60:] = np.linspace(110, 125, 30)[None, :, None].astype(np.uint8)  # ... and its shaded side, smooth
    rng = np.random.default_rng(1)
    img = np.clip(img + rng.normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)
    mask = np.zeros((h, w), bool)
    mask[:, :31] = True  # a column of the paper's colour in it
    mask[:, 50:61] = True
    doubtful = ~mask
    paper = np.zeros((h, w), bool)
    on_plate = np.ones((h, w), bool)
    unknown = doubt_joined(img, mask, doubtful, paper, tau=6.0, on_plate=on_plate)
    assert unknown[:, 34:46].sum() == 0  # the stretch of the paper's colour
    assert unknown[:, 63:].mean() > 0.95  # the shaded side
    wall = doubt_joined(img, mask, doubtful, paper, tau=6.0, on_plate=~on_plate)
    assert wall[:, 34:46].all() and wall[:, 63:].mean() > 0.95


def _shaded_disc(h=80, w=100, r=25.0, background=60.0, limb=95.0, seed=0):
    """A white ball on a plain backdrop with exact pixel coverage (16 x 16 sub-samples a pixel), shaded
    as a sphere lit from the front left, down to ``limb`` on its dark side. Returns (img, coverage)."""
    s = 16
    yy, xx = np.mgrid[0:h * s, 0:w * s]
    yy = (yy + 0.5) / s - 0.5
    xx = (xx + 0.5) / s - 0.5
    cy, cx = h / 2 - 0.3, w / 2 + 0.2
    inside = (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r
    nx, ny = (xx - cx) / r, (yy - cy) / r
    nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, 1.0))
    shade = limb + (235.0 - limb) * np.clip(-0.6 * nx + 0.8 * nz, 0.0, 1.0)  # turns fast near the limb
    img = np.where(inside, shade, background).reshape(h, s, w, s).mean(axis=(1, 3))
    cover = inside.reshape(h, s, w, s).mean(axis=(1, 3))
    rng = np.random.default_rng(seed)
    return np.clip(img[..., None] + rng.normal(0, 1.0, (h, w, 3)), 0, 255).astype(np.uint8), cover


def _outer_layer(held):
    return held & (cv2.erode(held.astype(np.uint8), np.ones((3, 3), np.uint8)) == 0)


@pytest.mark.parametrize("plate_known", [True, False])
def test_blend_behind_gives_each_outline_pixel_to_the_side_that_covers_most(plate_known):
    """Ground truth: a shaded ball's pixel coverage (the masks' convention: object where >= 1/2). Held
    one pixel too wide all round, the outer layer (coverage < 1/2) goes; held exactly, it stays, down to
    the dark limb, whose colour is far from the lit middle's (taken further in, that colour gave a fifth
    of it to the backdrop). With the backdrop's plate or, where no plate is trusted, from the pixels
    beyond."""
    from recon.silhouette_doubt import blend_behind

    img, cover = _shaded_disc()
    truth = cover >= 0.5
    bg = np.full(img.shape, 60, np.uint8)
    usable = np.full(truth.shape, plate_known)
    wide = cv2.dilate(truth.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    ring = _outer_layer(wide)
    drop = blend_behind(img, wide & ~ring, ring, bg, usable, 6.0)
    assert not (drop & ~ring).any()
    assert drop[ring].mean() > 0.95, drop[ring].mean()
    ring = _outer_layer(truth)
    drop = blend_behind(img, truth & ~ring, ring, bg, usable, 6.0)
    assert drop[ring].mean() < 0.1, drop[ring].mean()


def test_blend_behind_leaves_what_it_cannot_tell():
    """A ball of the backdrop's own grey (a white object's shade on a wall of that grey): no outline pixel
    can be told from the backdrop, and none is given to it."""
    from recon.silhouette_doubt import blend_behind

    img, cover = _shaded_disc(background=150.0, limb=150.0)
    img = np.clip(150 + np.random.default_rng(1).normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)
    truth = cover >= 0.5
    wide = cv2.dilate(truth.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    ring = _outer_layer(wide)
    for usable in (np.ones(truth.shape, bool), np.zeros(truth.shape, bool)):
        assert not blend_behind(img, wide & ~ring, ring, np.full(img.shape, 150, np.uint8), usable, 6.0).any()


def test_outline_trim_never_cuts_a_part_off():
    """The outline's blended pixels go to the side that covers most of each, but not one whose loss would
    cut a held part off the mask, nor that part's own (a doubtful part joined through a blended pixel
    stays whole and joined); a pixel that cuts nothing goes."""
    from recon.silhouettes import _keep_joined

    mask = np.zeros((20, 30), bool)
    mask[5:15, 2:10] = True
    held = mask.copy()
    held[9, 10:14] = True  # a one-pixel bridge ...
    held[6:13, 14:20] = True  # ... to a doubtful part
    held[15, 4] = True  # a doubtful pixel next to the mask
    drop = np.zeros_like(held)
    drop[9, 11] = True  # dropping the bridge would cut the part off
    drop[12, 19] = True  # an outline pixel of that part: kept with it
    drop[15, 4] = True  # cuts nothing
    kept = _keep_joined(held, mask, drop)
    assert not kept[9, 11] and not kept[12, 19] and kept[15, 4]
    assert _keep_joined(held, mask, np.zeros_like(held)).sum() == 0


def test_doubt_unlike_keeps_a_thin_arm_and_stops_at_the_wall():
    """A white figure's arm, 4 px wide, its shading turning across it (every pixel an edge, so
    ``doubt_joined`` cannot grow into it), sticks out of the held body over a wall of the figure's
    grey. The arm's pixels are doubtful and unlike the wall's own colour: unknown. The wall, as
    doubtful but its plate's colour, is not; nor an unlike blob apart from the body, nor one that
    touches the body only through the wall."""
    from recon.silhouette_doubt import doubt_unlike

    h, w = 60, 80
    mask = np.zeros((h, w), bool)
    mask[20:60, 30:45] = True  # the body
    held = np.zeros_like(mask)
    held[10:20, 32:43] = True  # the head, unknown already
    arm = np.zeros_like(mask)
    for r in range(22, 42):  # a diagonal arm from the shoulder down to the left
        c = 29 - (r - 22) // 2
        arm[r, c - 3:c + 1] = True
    blob = np.zeros_like(mask)
    blob[30:36, 60:66] = True  # unlike the wall, 15 px from the body
    bridge = np.zeros_like(mask)
    bridge[50:52, 47:58] = True  # unlike, but 2 px of wall between it and the body
    doubtful = ~mask & ~held  # the figure's grey is the wall's: all doubtful
    unlike = arm | blob | bridge
    got = doubt_unlike(mask, held, doubtful, unlike)
    assert got[arm].all()
    assert not (got & ~arm).any()
    assert not doubt_unlike(mask, held, doubtful, np.zeros_like(mask)).any()  # the wall alone: nothing


def test_a_camera_carried_round_a_still_table_is_refused():
    """The plates need a camera that stays put while the table turns; a handheld sequence (the camera's
    height and distance from the axis change) gets a clear error, not empty or wrong silhouettes."""
    from recon.silhouettes import check_camera_still

    T_cw = _camera_world()
    still = np.stack([T_cw @ _rot_y(th) for th in np.linspace(0, 2 * np.pi, 8, endpoint=False)])
    check_camera_still(still)  # a turntable: one circle about the axis
    moved = still.copy()
    moved[::2, :3, 3] *= 1.15  # every other photo from 15 % further away
    with pytest.raises(ValueError, match="camera moves between frames"):
        check_camera_still(moved)
    with pytest.raises(ValueError, match="give --masks"):
        estimate_silhouettes(np.zeros((8, H, W, 3), np.uint8), K, moved, SPEC)


def test_doubt_enclosed_closes_a_smooth_belly_and_keeps_views_through_the_object():
    """A white belly's lit side in front of the paper: a doubtful hole surrounded by the mask and the
    unknown, the shading smooth across its rim, is unknown too. A view between an arm and the body,
    ringed by the outline's edge, stays background; so does a smooth hole showing one pixel of the
    printed ink (confident background), and the doubtful paper open to the box's border."""
    from recon.silhouette_doubt import doubt_enclosed

    h, w, tau = 60, 80, 4.0
    img = np.full((h, w, 3), 200, np.uint8)  # white object, white paper: one shade
    held = np.zeros((h, w), bool)
    held[10:50, 10:40] = True  # the body (mask and unknown)
    belly = np.zeros_like(held)
    belly[20:30, 25:35] = True  # lit side, the paper's colour
    held[belly] = False
    arm = np.zeros_like(held)
    arm[20:40, 45:65] = True
    gap = np.zeros_like(held)
    gap[25:35, 50:60] = True  # the view between arm and body, its outline an edge
    held |= arm & ~gap
    img[arm & ~gap] = 170  # the arm's shade: an edge all round the gap
    doubtful = ~held
    got = doubt_enclosed(img, held, doubtful, tau)
    assert got[belly].all()
    assert not (got & ~belly).any()  # not the gap, not the paper around (open to the border)
    img[arm & ~gap] = 200  # no edge round the gap: closed as well
    assert doubt_enclosed(img, held, doubtful, tau)[gap].all()
    doubtful[30, 55] = False  # ... unless a pixel of it is confident background (ink)
    got = doubt_enclosed(img, held, doubtful, tau)
    assert not got[gap].any() and got[belly].all()
    # 4-connected holes: a diagonal chain of free pixels through the body's wall does not open the belly
    held2 = held.copy()
    for k in range(10):
        held2[19 - k, 24 - k] = False
    assert doubt_enclosed(img, held2, ~held2, tau)[belly].all()


def test_a_hole_in_a_turning_part_that_shows_the_still_room_stays_open():
    """A chair's back before a wall of its grey: the wall between its rails is a doubtful hole with no edge
    round it. Where the rails moved against the still room and the wall between them did not, it stays open;
    where nothing moved (a static body's surface) or the hole moved as well, it is filled as before."""
    from recon.silhouette_doubt import doubt_enclosed

    h, w, tau = 60, 80, 4.0
    img = np.full((h, w, 3), 150, np.uint8)
    held = np.zeros((h, w), bool)
    held[10:50, 20:60] = True  # the back
    gap = np.zeros_like(held)
    gap[18:42, 28:52] = True  # the wall between its rails
    held &= ~gap
    doubtful = ~held
    assert doubt_enclosed(img, held, doubtful, tau)[gap].all()
    moved = held.copy()
    moved[10:50, 20:23] = False  # not every rail pixel moved (a faint part)
    got = doubt_enclosed(img, held, doubtful, tau, moved=moved)
    assert not got.any()
    assert doubt_enclosed(img, held, doubtful, tau, moved=np.zeros_like(held))[gap].all()
    assert doubt_enclosed(img, held, doubtful, tau, moved=held | gap)[gap].all()
    few = held & (np.arange(w)[None, :] < 32)  # a third of the rim moved
    assert doubt_enclosed(img, held, doubtful, tau, moved=few)[gap].all()


def test_a_static_objects_dark_crease_that_no_plate_vouches_for_is_doubtful():
    """One row of a frame on a light wall (200): the mask holds the figure's light grey body (180); beside it
    its chin's dark crease (60, a colour the mask does not show) where the room plate is trusted (the static
    head is the plate there) but does not vouch for the room; then a dark spot of the wall (60) where no
    plate is trusted at all (something passed in most frames). Both are unlike the object's colours; the
    spot is confident background, as before, the crease is not: it is the static object itself."""
    from recon.silhouette_doubt import Evidence, doubtful_pixels

    w = 40
    img = np.full((1, w, 3), 200, np.uint8)
    img[0, :20] = 180  # the body, in the mask
    img[0, 20:24] = 60  # the crease
    img[0, 30:34] = 60  # the dark spot of the wall
    mask = np.zeros((1, w), bool)
    mask[0, :20] = True
    region = np.ones((1, w), bool)
    trusted = np.ones((1, w), bool)
    trusted[0, 20:24] = trusted[0, 30:34] = False  # the verified plates say nothing at either
    no = np.zeros((1, w), bool)
    ev = Evidence(np.zeros((1, w), np.uint8), trusted, trusted, no, trusted, no, img, trusted)
    static = np.zeros((1, w), bool)
    static[0, 20:24] = True  # the unverified room plate is trusted at the crease: a static object
    before = doubtful_pixels(img, mask, region, ev, no, False)
    assert not before[0, 20:24].any() and not before[0, 30:34].any()
    got = doubtful_pixels(img, mask, region, ev, no, False, static)
    assert got[0, 20:24].all() and not got[0, 30:34].any()
    assert not got[0, 24:30].any() and not got[0, 34:].any()  # the wall the plate vouches for: confident
    strict = doubtful_pixels(img, mask, region, ev, no, True, static)  # a frame in doubt doubts both
    assert strict[0, 20:24].all() and strict[0, 30:34].all()


def test_pinholes_are_small_enclosed_doubtful_holes():
    """A frame holds a body (mask and unknown) with a pinhole of 5 x 5 doubtful pixels. Not pinholes: a hole
    with one confident pixel (the printed ink), a hole larger than the share of what the frame holds, the
    background open to the image's border. 4-connected: a diagonal chain of free pixels does not open the
    pinhole to the border."""
    from recon.silhouette_doubt import doubt_pinholes

    h, w = 80, 100
    held = np.zeros((h, w), bool)
    held[10:70, 10:90] = True  # 4 800 px: the share 0.01 allows holes up to 48 px
    pin, inked, big = (np.zeros_like(held) for _ in range(3))
    pin[20:25, 20:25] = True
    inked[20:25, 40:45] = True
    big[40:48, 40:48] = True  # 64 px
    for hole in (pin, inked, big):
        held[hole] = False
    doubtful = ~held
    doubtful[22, 42] = False
    got = doubt_pinholes(held, doubtful)
    assert got[pin].all()
    assert not (got & ~pin).any()  # not the inked hole, the big hole, the background
    assert doubt_pinholes(held, doubtful, share=0.02)[big].all()  # 64 <= 96 px: a pinhole
    assert doubt_pinholes(held)[inked].all()  # without the doubt, any small enclosed hole
    held2 = held.copy()
    for k in range(11):
        held2[19 - k, 19 - k] = False  # a diagonal chain from the pinhole's corner to the background
    assert doubt_pinholes(held2, ~held2)[pin].all()


def _tunnelled_drum(n_views: int = 12, size=(160, 120), f_px: float = 300.0):
    """An upright drum (radius 30 mm, 0..80 mm) with a horizontal tunnel (radius 6 mm, along the table's X axis
    at 40 mm), seen by ``n_views`` level cameras 400 mm away round the axis (views 0 and n/2 look along the
    tunnel): the true silhouettes, ray-marched at 0.5 mm, the poses and K."""
    w, h = size
    K = np.array([[f_px, 0.0, (w - 1) / 2], [0.0, f_px, (h - 1) / 2], [0.0, 0.0, 1.0]])
    Ts, masks = [], []
    vs, us = np.mgrid[0:h, 0:w]
    pix = np.column_stack([us.ravel(), vs.ravel(), np.ones(us.size)])
    for a in np.linspace(0.0, 2 * np.pi, n_views, endpoint=False):
        centre = np.array([400.0 * np.cos(a), 40.0, 400.0 * np.sin(a)])
        T = look_at(centre, np.array([0.0, 40.0, 0.0]))
        rays = pix @ np.linalg.inv(K).T @ T[:3, :3]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        hit = np.zeros(len(rays), bool)
        for d in np.arange(360.0, 440.0, 0.5):
            p = centre + d * rays
            body = (np.hypot(p[:, 0], p[:, 2]) <= 30.0) & (p[:, 1] >= 0.0) & (p[:, 1] <= 80.0)
            hit |= body & (np.hypot(p[:, 1] - 40.0, p[:, 2]) > 6.0)
        Ts.append(T)
        masks.append(hit.reshape(h, w))
    return np.stack(masks), np.stack(Ts), K


def test_a_pinhole_only_one_view_carves_through_is_held_a_tunnel_is_not():
    """A pinhole of 3 x 3 pixels in one side view's silhouette of a drum: its rays run through what every other
    view holds, so that view alone would carve a thread through the body; it is returned. The tunnel seen
    through from its end is a hole of that size too, but the view from its other end carves it as well: not
    returned. Nothing where there are no candidates."""
    from recon.silhouettes import carved_alone

    masks, Ts, K = _tunnelled_drum()
    V = len(masks)
    side, end = 3, 0
    n, lab = cv2.connectedComponents((~masks[end]).astype(np.uint8), connectivity=4)
    tunnel = lab == lab[60, 80]  # the image centre: the tunnel's axis
    assert 20 < tunnel.sum() < 200 and masks[side][58:63, 78:83].all()
    held = masks.copy()
    pin = np.zeros_like(held)
    pin[side, 59:62, 79:82] = True
    held[side] &= ~pin[side]
    cands = pin.copy()
    cands[end] = tunnel
    got = carved_alone(cands, held, K, Ts, 60.0, 100.0)
    assert got[side][pin[side]].all()
    assert not got[end].any() and not got[[k for k in range(V) if k != side]].any()
    held[V // 2] = True  # the other end's view holds everything: now the end view alone carves the tunnel
    assert carved_alone(cands, held, K, Ts, 60.0, 100.0)[end][tunnel].all()
    assert not carved_alone(np.zeros_like(cands), held, K, Ts, 60.0, 100.0).any()


def test_static_votes_keep_a_head_the_masks_hold_and_not_a_poster():
    """36 views. A head pixel: across in 3 views, in the mask in the 30 others (kept: 33 of 36 hold it). A
    part across in 8 views (kept: a fifth or more). A poster pixel: across in 5 views while the object
    turns past, in the mask in 10 (not kept: 5 < 7.2 and 15 < 28.8)."""
    from recon.silhouettes import static_votes

    V = 36
    across = np.zeros((V, 1, 3), bool)
    masks = np.zeros_like(across)
    across[:3, 0, 0] = True
    masks[6:, 0, 0] = True
    across[10:18, 0, 1] = True
    across[:5, 0, 2] = True
    masks[5:15, 0, 2] = True
    assert static_votes(across, masks)[0].tolist() == [True, True, False]
    masks[6:8, 0, 0] = False  # the head held in 31 of 36 views only: 0.86, still kept; in 28 (0.78): not
    assert static_votes(across, masks)[0, 0]
    masks[8:11, 0, 0] = False
    assert not static_votes(across, masks)[0, 0]


def test_wide_votes_count_the_views_that_reach_a_pixel_across_as_well_as_those_that_hold_it():
    """36 views. A head pixel no view holds, across in 9 views (kept: a quarter); one across in 3 views and
    held in 5 (kept: 8 of 36); a poster pixel across in 5 views while the object turns past (not kept)."""
    from recon.silhouettes import wide_votes

    V = 36
    across = np.zeros((V, 1, 3), bool)
    held = np.zeros_like(across)
    across[::4, 0, 0] = True
    across[:3, 0, 1] = True
    held[10:15, 0, 1] = True
    across[20:25, 0, 2] = True
    assert wide_votes(across, held)[0].tolist() == [True, True, False]
    across[::4, 0, 0] = False
    across[::6, 0, 0] = True  # 6 of 36 views: under a fifth
    assert not wide_votes(across, held)[0, 0]


def test_views_that_show_the_same_colour_get_the_same_verdict():
    """36 views of a static white vase, one row of pixels: its body (in every mask); its lit foot in front of
    the paper, the same colour in every view and in the mask of 11 of them; the paper beside the foot, in
    the mask of 5 (a shadow taken in); its shaded neck, in no mask; a pixel a textured part turns
    past (the static colour in 20 views only, in the mask of 10 of them); a foot pixel one view sees in
    another colour. The foot is held in every view that shows its colour; the paper (5 < 7.2 views), the
    neck and the passing pixel (20 < 27 views alike) are not, unless the neck's unknown votes (the caller
    passes the unknown off the paper). A turning object (its body's pixels change colour from view to view)
    gets nothing held."""
    from recon.silhouettes import held_alike

    V = 36
    alike = np.ones((V, 1, 6), bool)
    masks = np.zeros_like(alike)
    body, foot, paper, neck, passing, crossed = range(6)
    masks[:, 0, body] = True
    masks[:11, 0, foot] = True
    masks[:5, 0, paper] = True
    alike[20:, 0, passing] = False
    masks[:10, 0, passing] = True
    masks[:11, 0, crossed] = True
    alike[30, 0, crossed] = False
    got = held_alike(alike, masks)
    assert got[:, 0, foot].all()
    assert not got[:, 0, paper].any() and not got[:, 0, neck].any() and not got[:, 0, passing].any()
    assert got[:, 0, crossed].sum() == 35 and not got[30, 0, crossed]
    masks[:8, 0, paper] = True  # 8 of 36: a fifth or more, held everywhere
    assert held_alike(alike, masks)[:, 0, paper].all()
    doubt = np.zeros_like(alike)  # the neck's unknown, where it votes (off the paper)
    doubt[5:16, 0, neck] = True
    got = held_alike(alike, masks, doubt)
    assert got[:, 0, neck].all() and got[:, 0, foot].all()
    alike[::2, 0, body] = False  # a turning object
    assert not held_alike(alike, masks).any() and not held_alike(alike, masks, doubt).any()


def test_a_turning_objects_static_part_the_masks_hold_is_held_where_no_plate_vouches_for_it():
    """36 views of a turning figure, one row of pixels: its head over the axis (the static colour in every
    view, in the mask of 12, a doubtful candidate no plate vouches for in the other 24); a pixel of the head
    held in only 6 masks (under a fifth); a pixel an arm turns past (the static colour in 20 views only);
    the wall beside the head, in the mask of 12 views too but only where the arm covered it (not alike
    there); a head pixel in the mask of 12 views that is no candidate elsewhere (vouched for). Only the
    head's candidates are held; never a pixel that is no candidate, nor one a view shows in another colour."""
    from recon.silhouettes import held_static

    V = 36
    alike = np.ones((V, 1, 5), bool)
    masks = np.zeros_like(alike)
    cands = np.zeros_like(alike)
    head, few, passing, wall, vouched = range(5)
    masks[:12, 0, head] = True
    cands[12:, 0, head] = True
    alike[20, 0, head] = False  # one view sees the arm there
    masks[:6, 0, few] = True
    cands[6:, 0, few] = True
    alike[20:, 0, passing] = False
    masks[:10, 0, passing] = True
    cands[10:20, 0, passing] = True
    masks[:12, 0, wall] = True
    alike[:12, 0, wall] = False
    cands[12:, 0, wall] = True
    masks[:12, 0, vouched] = True
    got = held_static(alike, masks, cands)
    assert got[12:, 0, head].sum() == 23 and not got[20, 0, head] and not got[:12, 0, head].any()
    assert not got[:, 0, few].any() and not got[:, 0, passing].any() and not got[:, 0, wall].any()
    assert not got[:, 0, vouched].any()
    masks[:8, 0, few] = True  # 8 of 36: a fifth or more
    assert held_static(alike, masks, cands)[8:, 0, few].all()


def test_white_vase_on_a_light_wall_is_not_carved_by_the_views_that_see_it_like_the_paper(tmp_path):
    """The white vase on a light wall under another light (seed 4), a full turn. A body of revolution: every
    view shows the same picture, yet where its lit foot matched the paper some views' masks held it and the
    others carved it (missed: 23.5 % of the vase's pixels on average, 17 % in the best view and 32 % in the
    worst). What the views showing the same colour hold is held in all of them (``held_alike``): measured
    17-19.7 % (the rest, the shaded neck against the wall's grey, is missed by all views alike at this size)."""
    res, gts = _white_vase_on_a_light_wall(tmp_path, seed=4)
    missed = np.array([(g & ~h).sum() / g.sum() for h, g in zip(res.masks | res.unknown, gts, strict=True)])
    assert missed.max() <= 0.22, missed.max()
    assert missed.max() - missed.min() <= 0.05, (missed.min(), missed.max())
    # few pinholes in what a view holds over the vase: each view's ray through one carves a thread, and the
    # threads of every view a hollow sheet inside the body (412 true pixels in such holes before carved_alone,
    # 59 after: the rest are holes whose rays cross another view's)
    in_holes = 0
    for h, g in zip(res.masks | res.unknown, gts, strict=True):
        n, lab = cv2.connectedComponents((~h).astype(np.uint8), connectivity=4)
        border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
        in_holes += int((g & ~h & ~np.isin(lab, border)).sum())
    assert in_holes <= 100, in_holes


def test_reach_crosses_narrow_gaps_in_chains_and_stops_at_wide_ones():
    """A head above a shaded neck: its lower half 3 px above the body, its upper half 2 px above that
    (a terminator band of the wall's grey between them): both reached with a 4 px gap, in chain; a
    poster 12 px to the side is not, and nothing is reached with a 1 px gap."""
    from recon.silhouette_doubt import reach

    base = np.zeros((60, 60), bool)
    base[40:, 20:40] = True  # the body
    cand = np.zeros_like(base)
    cand[30:37, 22:38] = True  # the head's lower half, rows 37-39 the neck's gap
    cand[20:28, 22:38] = True  # its upper half, rows 28-29 the band
    cand[30:50, 52:58] = True  # a poster, 12 px right of the body
    got = reach(cand, base, 4)
    assert got[30:37, 22:38].all() and got[20:28, 22:38].all()
    assert not got[:, 50:].any() and not (got & ~cand).any()
    assert not reach(cand, base, 1).any()


def test_untrust_enclosed_drops_plain_islands_only():
    """The table plate of a surface turning with the table above the plane (a white plinth's top)
    is trusted and has the paper's colour, but an untrusted band (its edges' parallax) encloses it:
    that island loses its trust. The paper around (reaching the border) keeps it, and so does an
    enclosed island showing printed ink (paper seen through a gap of the object)."""
    from recon.silhouette_plates import untrust_enclosed

    n = 120
    rng = np.random.default_rng(3)
    plate = np.clip(np.full((n, n, 3), 225.0) + rng.normal(0.0, 1.0, (n, n, 3)), 0, 255).astype(np.uint8)
    trust = np.ones((n, n), np.uint8)
    trust[20:50, 20:60] = 0  # band around a plain island
    trust[20:50, 70:110] = 0  # band around an inked island
    trust[80:100, 10:30] = 0  # an untrusted blob enclosing nothing
    plain = (slice(26, 44), slice(26, 54))
    inked = (slice(26, 44), slice(76, 104))
    trust[plain] = 1
    trust[inked] = 1
    plate[30:40, 80:100:3] = 20  # printed marks
    out = untrust_enclosed(trust, plate, tau=6.0)
    assert out.dtype == np.uint8 and out.shape == trust.shape
    assert not out[plain].any()  # the island of the paper's plain colour: no longer trusted
    assert out[inked].all()  # the island with ink keeps its trust
    assert (out[trust == 0] == 0).all()  # never trusts what was untrusted
    outside = trust.astype(bool).copy()
    outside[plain] = False
    assert out[outside].all()  # the paper around keeps its trust


def test_untrust_enclosed_takes_pale_shading_for_no_ink():
    """A plinth top seen from 45 deg: the island's plate has texture at its rim and round the feet (shading
    ramps, a few tens of grey levels under the paper's), over more than a tenth of it. That is no printed
    ink: the island loses its trust. The same share of black ink keeps it (paper seen through a gap)."""
    from recon.silhouette_plates import ISLAND_INK_SHARE, plate_ink, untrust_enclosed

    n = 120
    rng = np.random.default_rng(5)
    plate = np.clip(np.full((n, n, 3), 225.0) + rng.normal(0.0, 1.0, (n, n, 3)), 0, 255).astype(np.uint8)
    trust = np.ones((n, n), np.uint8)
    trust[20:50, 20:60] = 0
    trust[20:50, 70:110] = 0
    pale = (slice(26, 44), slice(26, 54))
    inked = (slice(26, 44), slice(76, 104))
    trust[pale] = 1
    trust[inked] = 1
    plate[26:44, 26:54:4] = 185  # shading ramps: pale stripes
    plate[26:44, 76:104:4] = 20  # printed marks, as many
    tex = plate_ink(plate, 6.0)
    assert tex[pale].mean() > ISLAND_INK_SHARE and tex[inked].mean() > ISLAND_INK_SHARE  # both textured
    out = untrust_enclosed(trust, plate, tau=6.0)
    assert not out[pale].any()
    assert out[inked].all()


def test_untrust_shade_drops_a_grey_that_turns_with_the_table():
    """The table plate under a white box in a dark room is its sides' grey in every view (0.63 of the
    paper's): trusted, it would explain the sides away as paper. A plain mid-grey piece inside the volume
    loses its trust; the paper, black ink (darker, textured) and a grey rim that reaches the volume's edge
    (a turntable's own rim, which turns with it too) keep theirs."""
    from recon.silhouette_plates import untrust_shade

    n = 161
    rng = np.random.default_rng(7)
    plate = np.clip(np.full((n, n, 3), 230.0) + rng.normal(0.0, 1.0, (n, n, 3)), 0, 255).astype(np.uint8)
    box = (slice(55, 105), slice(50, 110))
    plate[box] = 145  # the box's sides, seen from every azimuth
    plate[20:24, 30:130] = 20  # a stroke of black ink
    plate[:, :6] = 120  # the rim's grey, out to the raster's edge
    trust = np.ones((n, n), np.uint8)
    out = untrust_shade(trust, plate, 6.0, radius_px=70.0)
    assert out.dtype == np.uint8
    assert not out[box].any()
    assert out[20:24, 30:130].all() and out[:, :6].all()
    paper = np.ones((n, n), bool)
    paper[box] = False
    assert out[paper].all()
    # a paper whose grey varies little (vignetting, a soft light) keeps all of it
    soft = np.clip(230.0 - 0.15 * np.arange(n)[None, :, None].repeat(n, 0).repeat(3, 2), 0, 255).astype(np.uint8)
    assert untrust_shade(trust, soft, 6.0, radius_px=70.0).all()


def test_untrust_shade_finds_the_grey_against_a_foot_off_the_axis():
    """An object standing off the axis: the plate where it stands is its grey in every view (trusted), and
    round it the views disagree (its sides against the paper: untrusted). Not over the axis, it loses its
    trust all the same. The same grey with nothing untrusted round it (a shade of the paper the views agree
    on) and a shade that rings an untrusted foot (its outer edge on the lit paper: the shaded paper round a
    vase's foot) keep theirs."""
    from recon.silhouette_plates import untrust_shade

    n = 201
    rng = np.random.default_rng(11)
    plate = np.clip(np.full((n, n, 3), 230.0) + rng.normal(0.0, 1.0, (n, n, 3)), 0, 255).astype(np.uint8)
    trust = np.ones((n, n), np.uint8)
    # a box 30-60 px right of the axis (centre 100): its grey, in a band where the views disagree, open on one side
    grey = np.zeros((n, n), bool)
    grey[85:115, 130:160] = True
    plate[grey] = 145
    trust[80:120, 125:165] = 0
    trust[grey] = 1
    trust[85:115, 160:165] = 1  # the lit side: the paper, trusted
    # a lone patch of the same size and grey, nothing untrusted round it
    plate[40:70, 40:70] = 145
    # a shade ringing a foot further round: an annulus round an untrusted disc
    yy, xx = np.mgrid[:n, :n]
    r = np.hypot(yy - 150, xx - 60)
    trust[r <= 10] = 0
    ring = (r > 10) & (r <= 16)
    plate[ring] = 150
    out = untrust_shade(trust, plate, 6.0, radius_px=95.0)
    assert not out[grey].any()
    assert out[40:70, 40:70].all()
    assert out[ring].all()
    assert (out[trust > 0] | grey[trust > 0]).all()  # nothing else changes


def test_hue_unlike_tells_a_grain_from_shading():
    """Against a white mask's hues, a grey shade of the same white (its dull side) is not unlike, a brown
    table's grain is, and a dark pixel (whose hue is noise) never is."""
    from recon.silhouette_doubt import hue_unlike

    img = np.zeros((40, 60, 3), np.uint8)
    img[:, :20] = (200, 199, 195)  # the mask: a lit white body
    img[:, 20:30] = (120, 119, 116)  # its shade
    img[:, 30:45] = (107, 85, 64)  # wood
    img[:, 45:] = (30, 22, 16)  # dark wood
    mask = np.zeros((40, 60), bool)
    mask[:, :20] = True
    out = hue_unlike(img, mask)
    assert not out[:, :30].any()
    assert out[:, 30:45].all()
    assert not out[:, 45:].any()
    assert not hue_unlike(img, np.zeros_like(mask)).any()  # no mask: nothing to compare with


def test_doubt_joins_through_a_ramp_of_shading_not_across_a_step():
    """A white ball's underside falls ever more steeply from the mask's edge (up to 8 grey levels a pixel,
    a 3 x 3 range over 2 tau): a smooth ramp, so the doubt joins it. A step of that size is an edge, and
    stops it."""
    from recon.silhouette_doubt import doubt_joined

    h, w = 60, 80
    x = np.arange(w, dtype=np.float32)[None, :].repeat(h, 0)
    ramp = np.clip(200.0 - 0.2 * np.clip(x - 30, 0, None) ** 2, 40, 255)  # the mask up to x = 30, then the fall
    step = np.where(x < 45, 200.0, 80.0)
    mask = np.zeros((h, w), bool)
    mask[:, :30] = True
    doubtful = ~mask
    paper = np.zeros_like(mask)
    for grey, joined in ((ramp, True), (step, False)):
        img = np.repeat(grey[..., None], 3, axis=2).astype(np.uint8)
        out = doubt_joined(img, mask, doubtful, paper, 6.0)
        assert bool(out[5:-5, 40:50].all()) is joined, grey[0, 28:50]


def test_ink_is_reproduced_only_with_its_contrast():
    """The table plate's ink (a black ring's edge on white paper) seen in the photo is sure background; the
    same edge drawn at a tenth of its contrast (a white object's faint shading in front of it, correlated
    with it by chance) is not, nor is a flat white object; a shadow over the ink (half its contrast) still is."""
    from recon.silhouette_doubt import Plate, plate_envelope, texture_match

    x = np.arange(40)[None, :].repeat(40, 0)
    paper = np.where(x < 20, 30.0, 230.0)  # the ring's edge: black ink, white paper
    plate = np.repeat(paper[..., None], 3, axis=2).astype(np.uint8)
    lo, hi = plate_envelope(plate)
    trusted = Plate(mid=plate, lo=lo, hi=hi, trust=np.ones((40, 40), bool), strong=np.ones((40, 40), bool))
    edge = np.s_[5:35, 19:21]  # the pixels whose 3 x 3 window holds the edge

    def seen(grey):
        return texture_match(np.repeat(np.asarray(grey)[..., None], 3, axis=2).astype(np.uint8), trusted, 6.0)

    assert seen(paper)[edge].mean() > 0.9
    assert seen(130.0 + 0.5 * (paper - 130.0))[edge].mean() > 0.9  # a shadow halves the ink's contrast
    assert seen(200.0 + 0.1 * (paper - 130.0))[edge].mean() == 0.0  # white shading along the edge
    assert not seen(np.full((40, 40), 200.0)).any()


def _grained_room(room: np.ndarray, grain: tuple[slice, slice], inside: np.ndarray, seed: int):
    """A synthetic room plate (float (h, w, 3)) with a patch of wood grain (4 px stripes of 120 / 160) at
    ``grain``, noise of 1 grey level added: the plate as uint8, and the room's colour set (what it shows
    outside the volume's image ``inside``, and the wood, which the room shows elsewhere too)."""
    from recon.silhouette_doubt import colour_set

    xx = np.mgrid[: room.shape[0], : room.shape[1]][1]
    room = room.copy()
    room[grain] = (120.0 + 40.0 * (np.sin(xx[grain] * 1.3) > 0))[..., None]
    room = np.clip(room + np.random.default_rng(seed).normal(0.0, 1.0, room.shape), 0, 255).astype(np.uint8)
    return room, colour_set(np.concatenate([room[~inside], room[grain].reshape(-1, 3)]))


def test_room_plate_vouches_only_for_the_plain_room_it_reaches():
    """A light grey wall (150) seen outside and inside the volume's image, and inside it a static plain
    object (a disc of 156, one of the wall's colours, ringed by its darker outline) and a patch of wood
    grain. The wall inside is the room's; the object is not, though its colour is; the grain keeps the
    colour rule (its own edges would cut it off)."""
    from recon.silhouette_plates import reached_from_outside

    room = np.full((130, 170, 3), 150.0)
    yy, xx = np.mgrid[:130, :170]
    r = np.hypot(yy - 65, xx - 62)
    room[r < 32] = 156.0  # the object's plain shade: within a bin of the wall's
    room[(r >= 30) & (r < 32)] = 110.0  # its outline, darker (the edge between it and the wall)
    grain = (slice(30, 90), slice(110, 150))
    inside = np.zeros((130, 170), bool)
    inside[10:120, 20:160] = True
    room, colours = _grained_room(room, grain, inside, seed=0)
    reached = reached_from_outside(room, inside, colours, tau=6.0, shading=False)
    assert reached[15:25, 105:150].all()  # the wall inside the volume's image
    assert not reached[r < 20].any()  # the object's plain interior (its outline's texture reaches a few px in)
    assert reached[grain][5:-5, 5:-5].all()  # the grain, by its texture
    # with smooth stretches joined to the object's colours no texture, it vouches for less, and only on the object
    smooth = reached_from_outside(room, inside, colours, tau=6.0)
    assert not (smooth & ~reached).any() and (r[reached & ~smooth] < 30).all()


def test_room_plate_does_not_vouch_for_a_static_head_shaded_through_the_walls_grey():
    """A static head on the axis (a sphere, lit from above) seen against a grey wall: its shade ramps
    smoothly from light to dark through the wall's grey (150). The ramp is steep enough to count as
    texture, but a plane fits it where grain or a step would not: off the table, it is no room's."""
    from recon.silhouette_doubt import shading_ramp
    from recon.silhouette_plates import reached_from_outside

    room = np.full((120, 160, 3), 150.0)
    yy, xx = np.mgrid[:120, :160]
    r = np.hypot(yy - 60, xx - 50)
    head = r < 24
    room[head] = (150.0 - 100.0 * (yy[head] - 60) / 24.0)[:, None]  # 250 at its top, 50 at its bottom
    grain = (slice(30, 90), slice(100, 140))
    inside = np.zeros((120, 160), bool)
    inside[10:110, 15:150] = True
    room, colours = _grained_room(room, grain, inside, seed=1)
    wall_grey = head & (np.abs(yy - 60) < 3) & (r < 18)  # the head's pixels in the wall's grey, off its outline
    old = reached_from_outside(room, inside, colours, tau=6.0, shading=False)
    assert old[wall_grey].all()  # by its texture alone, the head's grey band was the wall's
    new = reached_from_outside(room, inside, colours, tau=6.0)
    assert not new[wall_grey].any()
    assert new[grain][5:-5, 5:-5].all() and new[15:25, 100:145].all()  # the grain and the wall stay the room's
    ramp = shading_ramp(room, 6.0)
    assert ramp[head & (r < 18)].mean() > 0.9 and not ramp[grain][5:-5, 5:-5].any() and not ramp[15:25, 100:145].any()


def test_room_plate_does_not_vouch_for_a_static_bodys_gentle_shade_in_the_walls_grey():
    """A static bottle lit from the left, in front of the table: its side shades from 210 to 90 at
    1.4 grey levels a pixel, through the wall's grey (150). Noise makes so gentle a slope count as
    texture, yet it rises too little across a window for a shading ramp; a plane still fits it, and it
    runs into the bottle's lit colours, which the room never shows: no stretch of the room (a white
    bottle on a light wall lost a shell half its radius deep, 3.6 % of the diagonal)."""
    from recon.silhouette_doubt import shading_ramp
    from recon.silhouette_plates import reached_from_outside

    room = np.full((120, 170, 3), 150.0)
    yy, xx = np.mgrid[:120, :170]
    body = (np.abs(xx - 60) < 40) & (yy > 15) & (yy < 105)
    room[body] = (210.0 - 1.4 * (xx[body] - 20))[:, None]
    room[body & (np.abs(xx - 60) >= 38)] = 90.0  # its dark outline
    grain = (slice(30, 90), slice(115, 155))
    inside = np.zeros((120, 170), bool)
    inside[8:112, 12:162] = True
    room, colours = _grained_room(room, grain, inside, seed=2)
    grey = body & (np.abs(room[..., 0].astype(int) - 150) < 6) & (np.abs(xx - 60) < 34) & (yy > 22) & (yy < 98)
    assert grey.sum() > 400
    old = reached_from_outside(room, inside, colours, tau=6.0, shading=False)
    assert old[grey].mean() > 0.8  # the colour rule took the bottle's grey for the wall's
    assert shading_ramp(room, 6.0)[grey].mean() < 0.2  # too gentle for a shading ramp
    new = reached_from_outside(room, inside, colours, tau=6.0)
    assert not new[grey].any()
    assert new[grain][5:-5, 5:-5].all() and new[10:20, 100:160].all()  # the grain and the wall stay the room's


def test_table_plate_knows_the_arc_of_views_a_hidden_point_is_seen_from():
    """A plane point next to an object is hidden from the far side of the turn: most views show the
    object's colour there. Its plate comes from the views on its own side (paper, trusted), and it
    says which views those are: what the others show there may be the object in front of it."""
    from recon.silhouette_plates import table_plate

    V, n = 36, 61
    rng = np.random.default_rng(5)
    az = np.radians(np.arange(V) * 10.0)
    T = np.stack([look_at(450.0 * np.array([np.cos(a) * 0.87, 0.5, np.sin(a) * 0.87]), np.zeros(3)) for a in az])
    rect = np.clip(225.0 + rng.normal(0.0, 1.0, (V, n, n, 3)), 0, 255).astype(np.uint8)
    c = (n - 1) // 2
    side = (slice(c - 3, c + 4), slice(c + 12, c + 20))  # raster (i, j): plane X = j - c > 0, azimuth ~0 deg
    far = np.abs(np.mod(np.degrees(az) + 180.0, 360.0) - 180.0) > 60.0  # the views from the other side
    for v in np.flatnonzero(far):
        rect[v][side] = 150  # the object's colour hides it from there
    seen = np.ones((V, n, n), bool)
    tp = table_plate(rect, seen, T, tau=6.0, radius_px=c - 2)
    inner = (slice(c - 1, c + 2), slice(c + 14, c + 18))  # (3 x 3 envelopes near its edge span both colours)
    assert tp.trust[side].all()  # the views from its own side agree: paper, trusted
    assert np.abs(tp.plate[inner].astype(float) - 225.0).max() < 6.0
    assert tp.in_arc(0.0)[inner].all() and tp.in_arc(80.0)[inner].all()
    assert not tp.in_arc(180.0)[inner].any() and not tp.in_arc(-110.0)[inner].any()
    rest = np.ones((n, n), bool)
    rest[c - 4:c + 5, c + 11:c + 21] = False
    assert tp.trust[rest].all() and not tp.in_arc(0.0)[rest].any()  # elsewhere every view counted


def test_a_turning_part_in_the_walls_colour_is_held_by_the_frames_either_side():
    """A white box's shaded side passes through the wall's grey for a frame or two of the turn: those frames take
    it for the wall. The frames up to 25 deg either side hold it in a shade of its own (held_between); the wall
    beside the box, which no neighbour holds on both sides, and what the neighbours hold in another colour (a
    dark room between two white ears that sweep past it) are not held."""
    from recon.silhouettes import held_between

    az = np.arange(0.0, 360.0, 10.0)
    masks = np.zeros((36, 8, 8), bool)
    masks[:, 2:6, 2:4] = True  # the lit side, held in every frame
    masks[:, 2:6, 4:6] = True  # the shaded side ...
    masks[[15, 16], 2:6, 4:6] = False  # ... taken for the wall in frames 15 and 16
    masks[14, 2:6, 6] = True  # the box's corner sweeps over the wall in frame 14 only
    got = held_between(masks, az)
    assert got[15, 2:6, 4:6].all() and got[16, 2:6, 4:6].all()
    assert not got[15, :, 6].any() and not got[13, :, 7].any()
    # the frames either side must both be near in the turn: a gap of 40 deg holds nothing
    far = held_between(masks[[0, 4, 8]], az[[0, 4, 8]])
    assert far.sum() == 0
    # with the images: held only where the frames either side show a shade near this frame's. The shaded side is
    # 120 in frames 15 and 16 (the wall's grey), 100 in the others; the dark room between two ears (20) is held by
    # the white ears (230) sweeping past it in frames 14 and 17
    images = np.full((36, 8, 8, 3), 120, np.uint8)
    images[:, 2:6, 2:4] = 220
    images[:, 2:6, 4:6] = 100
    images[[15, 16], 2:6, 4:6] = 120
    images[:, 0, :] = 20
    masks[[14, 17], 0, :] = True
    images[[14, 17], 0, :] = 230
    got = held_between(masks, az, images)
    assert got[15, 2:6, 4:6].all() and got[16, 2:6, 4:6].all()
    assert held_between(masks, az)[15, 0].all() and not got[15, 0].any()


def test_what_a_few_views_carve_from_behind_other_views_masks_is_given_back():
    """Six views of the tunnelled drum (36 views), three on each side of the turn, take a band round it below the
    tunnel (rows 70..77, ~18-27 mm up: a white part like the paper behind it) for the background. What they
    carve leaves pixels of other views' masks, ringed by what those views hold, with no hull behind them: the
    voxels on those rays that six views or fewer carve are drawn back into the six (explained_back; measured:
    all of each band, and 26-32 pixels of rim beside it; carved_deep_alone finds nothing there, carved from
    both sides of the turn). The true silhouettes need nothing back, the tunnel seen through from both ends
    included; a speck in one view's mask beside the drum, which every other view sees through, gives nothing
    back."""
    from recon.silhouettes import explained_back

    masks, Ts, K = _tunnelled_drum(36)
    speck = masks.copy()
    right = int(np.nonzero(masks[13][60])[0].max())
    speck[13, 55:65, right + 2:right + 8] = True  # beside the drum: every other view carves behind it
    assert not explained_back(speck, speck, K, Ts, 40.0, 90.0).any()  # (with any share of the views: 1728 px)
    band = np.zeros(masks.shape[1:], bool)
    band[70:78] = True
    held = masks.copy()
    out = [3, 4, 5, 21, 22, 23]
    for v in out:
        held[v] &= ~band
    got = explained_back(masks, held, K, Ts, 40.0, 90.0)
    for v in out:
        assert (got[v] & masks[v] & band).sum() >= 0.9 * (masks[v] & band).sum(), v
        assert (got[v] & ~masks[v]).sum() <= 0.15 * (masks[v] & band).sum(), v  # a rim at most
    others = [k for k in range(36) if k not in out]
    assert (got[others] & ~held[others]).sum() <= 0.01 * masks[others].sum()  # the hull's rim, where few carve


def test_a_thick_part_along_the_outline_is_kept_a_sliver_is_not():
    """What explained_back draws is kept in parts mostly ringed by what the view holds, or, with ``thick``, in
    parts half ringed by it and thick (a blurred plinth's top, whose front edge is the object's outline); a
    sliver along the outline is half ringed too, and stays out."""
    from recon.silhouettes import _enclosed_parts

    held = np.zeros((40, 40), bool)
    held[5:35, 5:35] = True
    cand = np.zeros_like(held)
    cand[20:35, 5:25] = True  # a block in the corner of what the view holds: two sides on the outline
    held[20:35, 5:25] = False
    sliver = np.zeros_like(held)
    sliver[5:35, 35:37] = True  # two columns beside the outline
    both = cand | sliver
    assert not _enclosed_parts(both, held).any()
    kept = _enclosed_parts(both, held, thick=True)
    assert kept[cand].all() and not kept[sliver].any()


@pytest.mark.parametrize("n_out", [2, 5])
def test_a_notch_neighbouring_views_leave_out_is_found_a_tunnel_many_see_through_is_not(n_out):
    """``n_out`` neighbouring side views of the tunnelled drum (36 views) leave out the same notch, cut from the
    outline 17 px into the body at 60 mm (the lit shoulder of a white teapot beside its lid, like the paper):
    their rays carve, with a few views on the same side of the turn only, space deep inside what every other
    view holds, so the notch is returned in them. The tunnel, seen through by the two views at its ends only,
    opposite each other, is an opening: not returned; nor any rim of a view whose silhouette is right. A
    notch below ``DEEP_FLOOR_MM`` is returned apart (``low``), only where the views that carve it do not see
    it as bright as the lit paper (a shaded foot, not a cast shadow's paper seen lit). Of the candidates, a
    notch mostly ringed by the view's held pixels is kept, a sliver along the outline is not (_enclosed_parts)."""
    from recon.silhouettes import DEEP_FLOOR_MM, _enclosed_parts, carved_deep_alone

    masks, Ts, K = _tunnelled_drum(36)
    held = masks.copy()
    side = 9  # a side view: the tunnel runs across it
    out = list(range(side - n_out // 2, side - n_out // 2 + n_out))
    right = int(np.nonzero(masks[side][45])[0].max())
    notch = np.zeros(masks.shape[1:], bool)
    notch[42:49, right - 16:right + 1] = True  # rows 42..48: 56..64 mm up
    assert masks[side][notch].all()
    for v in out:
        held[v] &= ~notch
    got, low = carved_deep_alone(held, K, Ts, 60.0, 100.0)
    assert not low.any()  # without ``lit``, nothing below the floor
    for v in out[1:-1] if n_out > 2 else out:  # the outer views of five carve little the others do not
        inner = notch & ~held[v]
        inner[:, right - 3:] = False  # the notch's mouth at the outline is a rim: it may stay open
        assert got[v][inner].mean() > 0.8, (v, got[v][inner].mean())
    others = [k for k in range(len(masks)) if k not in out]
    assert not (got[others] & ~held[others]).any()  # no rim, and not the tunnel seen from either end
    # rows 80..84: the rays meet the drum 8-14 mm up, under DEEP_FLOOR_MM (the camera is 40 mm up, 300 px focal)
    assert DEEP_FLOOR_MM >= 15.0
    held_low = held.copy()
    low_notch = np.zeros_like(notch)
    low_notch[80:85, right - 16:right + 1] = True
    held_low[out] &= ~low_notch
    dark = np.zeros_like(held)
    high, low = carved_deep_alone(held_low, K, Ts, 60.0, 100.0, lit=dark)
    assert not high[side][80:85].any()
    inner = low_notch & ~held_low[side]
    inner[:, right - 3:] = False
    assert low[side][inner].mean() > 0.8, low[side][inner].mean()
    assert not (low[others] & ~held_low[others]).any()
    high, low = carved_deep_alone(held_low, K, Ts, 60.0, 100.0, lit=~dark)  # seen lit: a cast shadow's paper
    assert not high[side][80:85].any() and not low.any()
    sliver = np.zeros_like(notch)
    sliver[30:40, right + 1:right + 3] = True  # two columns beside the outline, above the notch
    kept = _enclosed_parts(notch | sliver, held[side])
    assert kept[notch].all() and not kept[sliver].any()


def test_a_whole_part_one_view_lost_is_held_where_its_area_dropped():
    """One side view of 36 lost the drum's top (from 55 mm up, its rim the room's: not a notch ringed by what
    it holds): its mask's area drops under ``AREA_DROP`` of its neighbours'. What it alone carves deep inside
    what every other view holds makes up most of what it lacks: that part is held (_lost_parts), where
    _enclosed_parts keeps nothing of it. The same part in a view whose area did not drop, or a part smaller
    than half of what the view lacks, is not held."""
    from recon.silhouette_checks import AREA_DROP, area_shortfall
    from recon.silhouettes import DEEP_LOST_SHARE, _enclosed_parts, _lost_parts, carved_deep_alone

    masks, Ts, K = _tunnelled_drum(36)
    side = 9
    rows = np.nonzero(masks[side].any(axis=1))[0]
    top = np.zeros(masks.shape[1:], bool)
    top[:rows.min() + int(0.35 * (rows.max() - rows.min()))] = True
    lost = masks[side] & top
    held = masks.copy()
    held[side] &= ~lost
    areas = held.reshape(len(held), -1).sum(axis=1)
    shortfall = area_shortfall(areas)
    assert areas[side] < AREA_DROP * np.median(areas) and shortfall[side] > 0.9 * lost.sum()
    assert not np.delete(shortfall, side).any()
    deep, _ = carved_deep_alone(held, K, Ts, 60.0, 100.0)
    cand = deep[side] & ~held[side]
    assert cand.sum() >= DEEP_LOST_SHARE * shortfall[side]
    assert not _enclosed_parts(cand, held[side]).any()  # its rim is mostly the room's
    back = _lost_parts(cand, held[side], float(shortfall[side]))
    assert back[lost].mean() > 0.7 and not (back & ~lost).any()
    assert not _lost_parts(cand, held[side], 0.0).any()  # a view whose area did not drop
    assert not _lost_parts(cand, held[side], 2.1 * cand.sum() / DEEP_LOST_SHARE).any()  # too small a part


def test_channel_max_is_the_max_over_the_colour_channels():
    from recon.silhouette_doubt import channel_max

    rng = np.random.default_rng(11)
    for a in (rng.integers(-300, 300, (5, 7, 3)).astype(np.int16), rng.normal(size=(4, 6, 3)).astype(np.float32),
              rng.normal(size=(2, 3, 4))):  # (not three channels: numpy's own max)
        got = channel_max(a)
        assert got.dtype == a.dtype and got.shape == a.shape[:-1]
        np.testing.assert_array_equal(got, a.max(axis=-1))
    a = rng.normal(size=(3, 3, 3)).astype(np.float32)
    a[1, 1, 2] = np.nan  # NaN where a channel is NaN, as numpy's max
    assert np.isnan(channel_max(a)[1, 1]) and np.isnan(a.max(axis=-1)[1, 1])
    np.testing.assert_array_equal(np.isnan(channel_max(a)), np.isnan(a.max(axis=-1)))


def test_channel_sum_is_numpys_sum_over_the_colour_channels():
    from recon.silhouette_doubt import channel_sum

    rng = np.random.default_rng(12)
    for a in (rng.normal(size=(40, 30, 3)).astype(np.float32) * 1e3, rng.normal(size=(6, 5, 3)),
              rng.integers(0, 256, (4, 4, 3)).astype(np.uint8), rng.normal(size=(2, 3, 4))):
        got, want = channel_sum(a), a.sum(axis=-1)
        assert got.dtype == want.dtype and got.shape == want.shape  # (uint8: numpy's wider sum, no wrap-around)
        np.testing.assert_array_equal(got, want)


def _wall_with_a_turning_rail(rail_dn: float, seed: int = 0):
    """Twelve frames of a still wall (its grey varies across it; camera noise 1.5 DN), a rail ``rail_dn`` brighter
    than the wall that moves 8 px a frame, and a post 30 DN brighter in the same place in every frame (a body of
    revolution). Returns the frames, the room plate (their median) and the rail's pixels per frame."""
    from recon.silhouette_plates import median_frames

    rng = np.random.default_rng(seed)
    h, w, V = 120, 200, 12
    base = np.repeat((100 + 40 * np.linspace(0, 1, w))[None, :, None], h, 0).repeat(3, 2)
    frames, rails = [], []
    for i in range(V):
        f = base + rng.normal(0, 1.5, (h, w, 3))
        rail = np.zeros((h, w), bool)
        rail[40:50, 40 + 8 * i:80 + 8 * i] = True
        f[rail] += rail_dn
        f[60:110, 20:30] += 30.0  # the post
        frames.append(np.clip(np.round(f), 0, 255).astype(np.uint8))
        rails.append(rail)
    frames = np.stack(frames)
    return frames, median_frames(frames), np.stack(rails)


def test_moved_pixels_find_a_faint_turning_part_and_not_the_still_room():
    """A rail 4 DN brighter than the wall (under the camera's per-pixel noise, 99.9th percentile ~5 DN) that turns
    with the table has moved; the still wall and a post in the same pixels of every frame have not. Judged
    pixel by pixel (a 1 x 1 window) the rail is lost in the noise. Without enough still pixels to measure the
    noise on, nothing has moved."""
    from recon.silhouette_plates import MOVED_MIN_STILL, moved_pixels

    frames, room, rails = _wall_with_a_turning_rail(4.0)
    still = np.zeros(room.shape[:2], bool)
    still[:20] = True  # the room above: nothing there ever turns
    still[:, -10:] = True
    moved = moved_pixels(frames, room, still, 5)
    core = np.stack([cv2.erode(r.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0 for r in rails])
    assert moved[core].mean() > 0.95
    far = ~np.stack([cv2.dilate(r.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0 for r in rails])
    assert moved[far].mean() < 0.001  # the wall and the post
    assert moved[:, 60:110, 20:30].mean() < 0.001
    assert moved_pixels(frames, room, still, 1)[core].mean() < 0.3
    few = np.zeros_like(still)
    few.flat[:MOVED_MIN_STILL - 1] = True
    assert not moved_pixels(frames, room, few, 5).any()


def test_moved_doubt_joins_what_the_view_holds_only_where_it_touches():
    """The moved doubtful pixels join a view's unknown in parts that touch what it holds (a chair's back beyond
    the edge at its seat), not in parts apart from it (something else moving in the room)."""
    from recon.silhouettes import _moved_joined

    held = np.zeros((60, 80), bool)
    held[30:50, 20:60] = True  # the seat
    cand = np.zeros_like(held)
    cand[5:31, 25:30] = True  # the back's post, overlapping the seat's top row
    cand[5:20, 70:75] = True  # apart
    got = _moved_joined(held, cand)
    assert got[5:30, 25:30].all()
    assert not got[5:20, 70:75].any()
    assert not (got & held).any()
    assert not _moved_joined(held, np.zeros_like(held)).any()


def test_the_room_behind_what_the_masks_often_hold_is_the_room():
    """Where an object covers a pixel in most frames (a snowman's off-axis head) the plain median is the object,
    and the frames that show the wall there differ from it: moved, though the room. The room from the frames
    whose masks leave the pixel is the wall's: nothing moves there, and the turning rail still does. A pixel
    that nearly every mask holds has no room to say."""
    from recon.silhouette_plates import median_frames, moved_pixels, room_off_masks

    frames, _, rails = _wall_with_a_turning_rail(6.0)
    head = np.zeros(frames.shape[1:3], bool)
    head[70:100, 100:140] = True
    frames = frames.copy()
    away = [0, 1, 2]  # the head elsewhere in three frames of twelve
    for i in range(len(frames)):
        if i not in away:
            frames[i][head] = np.clip(frames[i][head].astype(int) + 20, 0, 255).astype(np.uint8)
    masks = np.stack([head if i not in away else np.zeros_like(head) for i in range(len(frames))])
    still = np.zeros_like(head)
    still[:20] = True
    core = cv2.erode(head.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    plain = moved_pixels(frames, median_frames(frames), still, 5)
    assert plain[away][:, core].mean() > 0.95  # the wall where the head usually is: moved
    room, known = room_off_masks(frames, masks)
    assert known.all()
    moved = moved_pixels(frames, room, still, 5)
    assert moved[away][:, core].mean() < 0.01
    assert moved[[i for i in range(len(frames)) if i not in away]][:, core].mean() > 0.95  # the head over the wall
    rail_core = np.stack([cv2.erode(r.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0 for r in rails])
    assert moved[rail_core & ~head].mean() > 0.95
    masks[3:] = True  # held everywhere in nine frames: only three give the room
    assert room_off_masks(frames, masks)[1].all()
    masks[2] = True
    assert not room_off_masks(frames, masks)[1].any()
