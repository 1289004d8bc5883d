"""Ring detection on rendered photos with known ground truth (calib.rings, calib.edges, calib.arcs)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from synthetic_images import look_at_T, render_target_photo

from calib.camera import circle_conic, circle_points_table, project_points
from calib.conics import sampson_distance
from calib.edges import conic_samples, find_stroke_edges, line_conic_offsets
from calib.rings import detect_rings, edge_conic, pencil_ratio
from calib.target import TargetSpec
from calib.types import CalibrationError

SPEC = TargetSpec(r_outer_mm=100.0, r_inner_mm=62.5, stroke_mm=3.0)
W, H = 1280, 960

EDGE_MEDIAN_TOL_PX = 0.3      # median |Sampson| of detected edge points to the true edge conic
EDGE_P99_TOL_PX = 1.0         # 99th percentile of the same
CENTRE_TOL_PX = 0.5           # max |Sampson| of true centre-line points to the detected centre-line conic
OCCLUDER_CLEARANCE_PX = 1.5   # edge points keep at least this distance from the occluding object


def _camera(elev_deg, focal_px, rng, size=(W, H), ring_frac=0.6):
    w, h = size
    K = np.array([[focal_px, 0, (w - 1) / 2], [0, focal_px, (h - 1) / 2], [0, 0, 1.0]])
    dist = 2 * SPEC.r_outer_mm * focal_px / (ring_frac * h)
    look = rng.uniform(-20.0, 20.0, 2)
    T = look_at_T(elev_deg, rng.uniform(0, 360), dist, look_at_table=(look[0], 0.0, look[1]),
                  roll_deg=rng.uniform(-20, 20))
    return K, T


def _edge_errors(obs, K, T, spec):
    out = []
    for e in obs.edges:
        C_true = circle_conic(K, T, e.ring_radius_mm + e.side * spec.stroke_mm / 2.0)
        out.append(np.abs(sampson_distance(C_true, e.uv_px)))
    return out


@pytest.mark.parametrize("elev_deg, focal_px, backdrop", [
    (15, 1000, "dark"), (15, 3000, "clutter"), (45, 1000, "light"),
    (45, 3000, "dark"), (75, 1000, "clutter"), (75, 3000, "light"),
])
def test_detect_rings_accuracy(elev_deg, focal_px, backdrop):
    rng = np.random.default_rng(1000 * elev_deg + focal_px + len(backdrop))
    K, T = _camera(elev_deg, focal_px, rng)
    photo = render_target_photo(SPEC, K, T, (W, H), rng=rng, backdrop=backdrop, blur_px=0.8,
                                noise_sigma=2.5, jpeg_quality=85, gain_gradient=0.4)
    obs = detect_rings(photo.image, SPEC)

    assert (obs.width, obs.height) == (W, H)
    assert sorted((e.ring_radius_mm, e.side) for e in obs.edges) == [
        (62.5, -1), (62.5, 1), (100.0, -1), (100.0, 1)]
    c = obs.conics
    assert all(C is not None for C in (c.outer, c.inner, c.outer_plus, c.outer_minus, c.inner_plus, c.inner_minus))
    for d in _edge_errors(obs, K, T, SPEC):
        assert np.median(d) < EDGE_MEDIAN_TOL_PX
        assert np.percentile(d, 99) < EDGE_P99_TOL_PX
    # enough of each visible ring is used (the occluder hides up to 40 %)
    for e in obs.edges:
        perimeter = np.sum(np.linalg.norm(np.diff(project_points(
            K, T, circle_points_table(e.ring_radius_mm, 720)), axis=0), axis=1))
        assert len(e.uv_px) * 1.5 > 0.35 * perimeter
    # centre lines
    for name, R in (("outer", SPEC.r_outer_mm), ("inner", SPEC.r_inner_mm)):
        pts = project_points(K, T, circle_points_table(R, 360))
        assert np.max(np.abs(sampson_distance(getattr(obs.conics, name), pts))) < CENTRE_TOL_PX
    # no point at or next to the occluding object
    free = (~photo.occluder_mask).astype(np.uint8)
    dist = cv2.distanceTransform(free, cv2.DIST_L2, 5)
    for e in obs.edges:
        uv = np.round(e.uv_px).astype(int)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        assert inside.all()
        assert dist[uv[:, 1], uv[:, 0]].min() >= OCCLUDER_CLEARANCE_PX


def test_detect_rings_grey_input_and_small_target():
    rng = np.random.default_rng(7)
    K, T = _camera(35, 1200, rng, ring_frac=0.3)
    # linear (gamma 1) data, told so
    photo = render_target_photo(SPEC, K, T, (W, H), rng=rng, backdrop="clutter", gamma=1.0)
    grey = cv2.cvtColor(photo.image, cv2.COLOR_BGR2GRAY)
    obs = detect_rings(grey, SPEC, gamma=1.0)
    for d in _edge_errors(obs, K, T, SPEC):
        assert np.median(d) < EDGE_MEDIAN_TOL_PX
    # twice the spacing, about half the points
    sparse = detect_rings(grey, SPEC, edge_spacing_px=4.0, gamma=1.0)
    ratio = sum(len(e.uv_px) for e in sparse.edges) / sum(len(e.uv_px) for e in obs.edges)
    assert 0.35 < ratio < 0.65


def test_dim_target_next_to_a_bright_highlight():
    # a quarter exposure with a saturated window in the frame: edges are found on log grey levels
    rng = np.random.default_rng(11)
    K, T = _camera(40, 900, rng, size=(640, 480))
    photo = render_target_photo(SPEC, K, T, (640, 480), rng=rng, backdrop="dark")
    img = (photo.image.astype(np.float32) * 0.25).astype(np.uint8)
    img[10:120, 10:160] = 255
    obs = detect_rings(img, SPEC)
    for d in _edge_errors(obs, K, T, SPEC):
        assert np.median(d) < EDGE_MEDIAN_TOL_PX


@pytest.mark.parametrize("seed", [0, 4, 8, 13])
def test_rings_cut_in_two_by_legs_in_front_from_low_down(seed):
    """An object's far side hides the rings' far sides; two legs in front cut their near sides (a chair at 20°).

    Each ring is left in pieces that no arc hypothesis spans: fitted alone, the pieces made ellipses 20-30 %
    too small and 30 px off centre, no pair had the target's ratio, and 12 of these 16 views (seeds 0-15)
    failed with "radius ratio ... does not match". Found whole, the edges are as accurate as elsewhere.
    """
    rng = np.random.default_rng(seed)
    w, h, f = 640, 480, 700.0
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    T = look_at_T(20.0, rng.uniform(0, 360), 2 * SPEC.r_outer_mm * f / (0.45 * w), look_at_table=(0.0, 0.0, 0.0))
    photo = render_target_photo(SPEC, K, T, (w, h), rng=rng, backdrop="dark", max_hidden=0.3)
    img = photo.image.copy()
    eye = -T[:3, :3].T @ T[:3, 3]
    towards = np.array([eye[0], eye[2]]) / np.hypot(eye[0], eye[2])
    across = np.array([-towards[1], towards[0]])
    for side in (-1, 1):  # a leg from the top of the frame down to its foot just in front of the inner ring
        xz = 1.1 * SPEC.r_inner_mm * towards + side * rng.uniform(0.25, 0.45) * SPEC.r_inner_mm * across
        foot = project_points(K, T, np.array([[xz[0], 0.0, xz[1]]]))[0]
        half = int(rng.integers(5, 8))
        img[: int(foot[1]), int(foot[0]) - half: int(foot[0]) + half] = rng.integers(150, 220)
    obs = detect_rings(img, SPEC)
    for d in _edge_errors(obs, K, T, SPEC):
        assert np.median(d) < EDGE_MEDIAN_TOL_PX
    for name, R in (("outer", SPEC.r_outer_mm), ("inner", SPEC.r_inner_mm)):
        pts = project_points(K, T, circle_points_table(R, 360))
        assert np.max(np.abs(sampson_distance(getattr(obs.conics, name), pts))) < CENTRE_TOL_PX


def _bad_target_photo(rings_mm, rng, occluder=False):
    K, T = _camera(50, 900, rng, size=(640, 480))
    return render_target_photo(SPEC, K, T, (640, 480), rng=rng, backdrop="dark", occluder=occluder,
                               rings_mm=rings_mm).image


def test_blank_image_has_no_ring():
    rng = np.random.default_rng(3)
    img = np.full((480, 640, 3), 128, np.uint8) + rng.integers(0, 3, (480, 640, 3)).astype(np.uint8)
    with pytest.raises(CalibrationError, match="no ring found"):
        detect_rings(img, SPEC)


def test_one_ring_only():
    rng = np.random.default_rng(4)
    img = _bad_target_photo([(0.0, 0.0, SPEC.r_outer_mm)], rng)
    with pytest.raises(CalibrationError, match="inner ring not found"):
        detect_rings(img, SPEC)


def test_rings_not_concentric():
    rng = np.random.default_rng(5)
    img = _bad_target_photo([(0.0, 0.0, SPEC.r_outer_mm), (25.0, 5.0, SPEC.r_inner_mm)], rng)
    with pytest.raises(CalibrationError, match=r"rings not concentric \(centres \d+ px apart\)"):
        detect_rings(img, SPEC)


def test_wrong_radius_ratio():
    rng = np.random.default_rng(6)
    img = _bad_target_photo([(0.0, 0.0, SPEC.r_outer_mm), (0.0, 0.0, 80.0)], rng)
    with pytest.raises(CalibrationError, match=r"radius ratio 1\.2\d does not match the target's 1\.60"):
        detect_rings(img, SPEC)


@pytest.mark.parametrize("bad", [np.zeros((10, 10), np.float32), np.zeros((10, 10, 4), np.uint8)])
def test_bad_image_argument(bad):
    with pytest.raises(ValueError):
        detect_rings(bad, SPEC)


def test_bad_spacing_or_gamma_argument():
    with pytest.raises(ValueError, match="edge_spacing_px"):
        detect_rings(np.zeros((10, 10), np.uint8), SPEC, edge_spacing_px=0.0)
    with pytest.raises(ValueError, match="gamma"):
        detect_rings(np.zeros((10, 10), np.uint8), SPEC, gamma=0.0)


def test_pencil_ratio_and_edge_conics_exact():
    rng = np.random.default_rng(8)
    K, T = _camera(rng.uniform(15, 75), 1500, rng)
    Co, Ci = circle_conic(K, T, SPEC.r_outer_mm), circle_conic(K, T, SPEC.r_inner_mm)
    split, ratio, _ = pencil_ratio(Co, Ci)
    assert split < 1e-9
    assert ratio == pytest.approx(SPEC.radius_ratio, rel=1e-9)
    for r in (SPEC.r_inner_mm - 1.5, SPEC.r_outer_mm + 1.5, 40.0):
        C = edge_conic(Co, Ci, SPEC, r)
        pts = project_points(K, T, circle_points_table(r, 64))
        assert np.max(np.abs(sampson_distance(C, pts))) < 1e-6
    # non-concentric circles split the double eigenvalue
    T2 = T.copy()
    T2[:3, 3] += T[:3, 0] * 20.0  # shift the inner circle 20 mm along table X
    split2, _, _ = pencil_ratio(Co, circle_conic(K, T2, SPEC.r_inner_mm))
    assert np.sqrt(split2) > 0.2  # about offset / inner radius = 0.32


def test_stroke_edges_subpixel_on_ideal_ring():
    # a blurred ring of known edge radii, drawn analytically (no perspective)
    rng = np.random.default_rng(9)
    c = np.array([200.3, 190.7])
    r_in, r_out = 120.0 + rng.uniform(0, 1), 127.0 + rng.uniform(0, 1)
    v, u = np.mgrid[0:400, 0:400].astype(np.float64)
    r = np.hypot(u - c[0], v - c[1])
    sigma = 1.0
    from scipy.special import erf
    step = lambda x: 0.5 * (1 + erf(x / (np.sqrt(2) * sigma)))  # noqa: E731
    img = 230 - 200 * (step(r - r_in) - step(r - r_out))
    img = (img + rng.normal(0, 1.0, img.shape)).astype(np.float32)
    C_mid = np.diag([1.0, 1.0, 0.0])
    C_mid[:2, 2] = C_mid[2, :2] = -c
    C_mid[2, 2] = c @ c - (0.5 * (r_in + r_out)) ** 2
    uv, nrm = conic_samples(C_mid, spacing_px=2.0)
    off = (r_out - r_in) / 2
    found = find_stroke_edges(img, uv, nrm, np.full(len(uv), -off), np.full(len(uv), off), 3.0)
    assert found.ok.mean() > 0.99
    err_in = np.abs(np.linalg.norm(found.inner_uv_px[found.ok] - c, axis=1) - r_in)
    err_out = np.abs(np.linalg.norm(found.outer_uv_px[found.ok] - c, axis=1) - r_out)
    assert np.median(err_in) < 0.05 and np.median(err_out) < 0.05
    # line_conic_offsets finds the predicted circle exactly
    C_out = C_mid.copy()
    C_out[2, 2] = c @ c - r_out ** 2
    assert np.allclose(line_conic_offsets(C_out, uv, nrm), r_out - 0.5 * (r_in + r_out), atol=1e-6)


def test_detect_rings_on_bundled_sample():
    # data/sample comes from another renderer (project's synth command): an independent check
    import json
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "data" / "sample"
    if not (root / "cameras_gt.json").exists():
        pytest.skip("data/sample not present")
    gt = json.loads((root / "cameras_gt.json").read_text())
    opts = json.loads((root / "scene.json").read_text())["options"]
    spec = TargetSpec(opts["r_outer"], opts["r_inner"], opts["stroke"])
    K = np.array(gt["intrinsics"]["K"])
    for frame in gt["frames"][::12]:
        T = np.array(frame["T_cam_table"])
        obs = detect_rings(cv2.imread(str(root / frame["image"])), spec)
        for d in _edge_errors(obs, K, T, spec):
            assert np.median(d) < EDGE_MEDIAN_TOL_PX
        for name, R in (("outer", spec.r_outer_mm), ("inner", spec.r_inner_mm)):
            pts = project_points(K, T, circle_points_table(R, 360))
            assert np.max(np.abs(sampson_distance(getattr(obs.conics, name), pts))) < CENTRE_TOL_PX


def _coverage(obs, bins: int = 180) -> list[float]:
    """Share of ``bins`` angular sectors (about each edge's centre) that hold detected edge points, per edge."""
    out = []
    for e in obs.edges:
        d = e.uv_px - e.uv_px.mean(axis=0)
        k = ((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi) * bins).astype(int) % bins
        out.append(len(np.unique(k)) / bins)
    return out


COVERAGE_LOSS_TOL = 0.1  # share of the ring's sectors that may be lost at 48 MP against 1280x960


def test_rings_found_as_fully_at_48_mp_as_at_1280():
    """A frame the vase hides part of the inner ring in, upscaled 6.3x (8064x6048, INTER_CUBIC as in
    issue 9): the edges are found around as much of each ring as at 1280x960, as accurately (in the
    1280 frame's pixels). Before the fine search's first pass ran on a reduced crop, the inner ring's
    edges covered 12 % of its sectors here (72 % at 1280x960)."""
    import json
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "data" / "sample"
    if not (root / "cameras_gt.json").exists():
        pytest.skip("data/sample not present")
    gt = json.loads((root / "cameras_gt.json").read_text())
    spec = TargetSpec(80.0, 50.0, 3.0)
    frame = gt["frames"][7]
    img = cv2.imread(str(root / frame["image"]))
    s = 6.3
    K = np.array(gt["intrinsics"]["K"])
    S = np.array([[s, 0, 0.5 * s - 0.5], [0, s, 0.5 * s - 0.5], [0, 0, 1]])  # pixel centres (README)
    T = np.array(frame["T_cam_table"])
    small = detect_rings(img, spec)
    big = detect_rings(cv2.resize(img, (8064, 6048), interpolation=cv2.INTER_CUBIC), spec)
    for c_small, c_big in zip(_coverage(small), _coverage(big), strict=True):
        assert c_big >= c_small - COVERAGE_LOSS_TOL, (c_small, c_big)
    for d in _edge_errors(big, S @ K, T, spec):
        assert np.median(d) / s < EDGE_MEDIAN_TOL_PX
