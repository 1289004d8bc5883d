"""Single-view solvers (paper, pencil, refine) against exact synthetic views."""

import numpy as np
import pytest

from calib.calibrate import MIN_TILT_DEG, SOLVERS, calibrate_view, tilt_deg
from calib.camera import (
    angle_between_deg,
    camera_centre_table,
    circle_conic,
    circle_points_table,
    make_T,
    project_points,
    rotation_from_normal,
)
from calib.conics import conic_coeffs, conic_to_ellipse, ellipse_points, normalize_conic
from calib.refine import edge_linearisation, edge_residuals, refine_view
from calib.solve_paper import eq23_conics, projected_centre_cross_ratio
from calib.solve_pencil import centred_frame, concentric_conics, fit_edge_conics
from calib.target import TargetSpec
from calib.types import CalibrationError, EdgePoints, TargetObservation

EXACT = 1e-6  # relative, noise-free data (the bar)
W, H = 1280, 960
R1, R2 = 50.0, 28.0


def _paper_view(f=3000.0, pp=None):
    """The paper's §5.1 set-up; normal flipped to point towards the camera."""
    cx, cy = pp if pp is not None else ((W - 1) / 2, (H - 1) / 2)
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    n = -np.array([-0.07, 0.93, 0.34])
    T = make_T(rotation_from_normal(n / np.linalg.norm(n)), [-4.3, 41.0, 750.0])
    return K, T


def _tilted_view(tilt_deg_, t=(0.0, 0.0, 750.0), f=3000.0):
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    a = np.radians(tilt_deg_)
    T = make_T(rotation_from_normal([0.0, -np.sin(a), -np.cos(a)]), t)
    return K, T


def _observe(K, T, *, sides=(0,), stroke=0.0, radii=(R1, R2), labels=None, n=200, sigma=0.0, rng=None):
    """Edge points of the rings; ``labels`` overrides the ring radii written in them."""
    labels = radii if labels is None else labels
    edges = []
    for R, label in zip(radii, labels, strict=True):
        for side in sides:
            uv = project_points(K, T, circle_points_table(R + side * stroke / 2, n))
            if sigma:
                uv = uv + rng.normal(0.0, sigma, uv.shape)
            edges.append(EdgePoints(uv, label, side))
    return TargetObservation(tuple(edges), W, H)


def _rel(a, b):
    return abs(a / b - 1.0)


def _assert_pose(cal, K, T, tol):
    assert _rel(cal.intrinsics.focal_px, K[0, 0]) < tol
    assert np.radians(angle_between_deg(cal.normal_cam, T[:3, 1])) < tol
    assert np.linalg.norm(cal.t_cam_table - T[:3, 3]) / np.linalg.norm(T[:3, 3]) < tol


# --- exactness -----------------------------------------------------------------

@pytest.mark.parametrize("solver", SOLVERS)
def test_every_solver_exact_on_centre_line_points(solver):
    K, T = _paper_view()
    cal = calibrate_view(_observe(K, T), TargetSpec(R1, R2, 3.0), solver=solver)
    _assert_pose(cal, K, T, EXACT)
    assert cal.rms_px < 1e-6


@pytest.mark.parametrize("solver", SOLVERS)
def test_every_solver_exact_on_stroke_edges_of_nominal_width(solver):
    K, T = _paper_view()
    obs = _observe(K, T, sides=(-1, 1), stroke=3.0)
    cal = calibrate_view(obs, TargetSpec(R1, R2, 3.0), solver=solver)
    _assert_pose(cal, K, T, EXACT)


@pytest.mark.parametrize("solver", SOLVERS)
def test_given_principal_point_is_used(solver):
    pp = (610.0, 505.0)
    K, T = _paper_view(f=2200.0, pp=pp)
    cal = calibrate_view(_observe(K, T), TargetSpec(R1, R2), solver=solver, principal_point_px=pp)
    _assert_pose(cal, K, T, EXACT)
    np.testing.assert_allclose(cal.intrinsics.principal_point_px, pp)


def test_pencil_centre_line_conics_are_insensitive_to_the_nominal_stroke():
    # true stroke 3.45 mm, nominal 3.0: interpolation in r^2 moves r^2 by w^2/4 only
    K, T = _paper_view()
    cc = concentric_conics(fit_edge_conics(_observe(K, T, sides=(-1, 1), stroke=3.45).edges), 3.0)
    for R, C in cc.centre_line.items():
        true = normalize_conic(circle_conic(K, T, R))
        assert np.linalg.norm(C - true) < 1e-4
    centre = project_points(K, T, np.zeros((1, 3)))[0]
    np.testing.assert_allclose(cc.centre_px, centre, atol=1e-6)


def test_pencil_pose_with_a_known_focal_length_is_exact():
    from calib.solve_pencil import solve_pencil

    K, T = _tilted_view(25.0, t=(-40.0, 30.0, 500.0))
    cc = concentric_conics(fit_edge_conics(_observe(K, T).edges), 0.0)
    f, T_est = solve_pencil(cc, K[:2, 2], focal_px=K[0, 0])
    assert f == K[0, 0]
    assert angle_between_deg(T_est[:3, 1], T[:3, 1]) < 1e-6
    np.testing.assert_allclose(T_est[:3, 3], T[:3, 3], rtol=EXACT)


def test_cross_ratio_centre_is_the_image_of_the_circle_centre():
    K, T = _paper_view()
    c = projected_centre_cross_ratio(circle_conic(K, T, R1), circle_conic(K, T, R2), R1, R2)
    np.testing.assert_allclose(c, project_points(K, T, np.zeros((1, 3)))[0], atol=1e-6)
    ellipse_centre = conic_to_ellipse(circle_conic(K, T, R1)).center_px
    assert np.linalg.norm(ellipse_centre - c) > 1.0  # the test is not trivial


@pytest.mark.parametrize("radius", [R1, R2, 51.5])
def test_eq23_coefficients_reproduce_the_projected_circle(radius):
    K, T = _paper_view(3000.0)
    s = 1000.0  # pixels relative to the principal point, in units of s (conditioning)
    f = K[0, 0] / s
    S = centred_frame(K[:2, 2], s)
    Si = np.linalg.inv(S)
    C1 = normalize_conic(Si.T @ circle_conic(K, T, R1) @ Si)
    centre = (S @ np.append(project_points(K, T, np.zeros((1, 3)))[0], 1.0))[:2]
    M1, M2, M3 = eq23_conics(C1, centre, radius)
    Tz = T[2, 3]
    coeffs = conic_coeffs(f**2 * M1 + (f**2 / Tz**2) * M2 + M3)  # eq. (23): A_c .. F_c
    true = conic_coeffs(normalize_conic(Si.T @ circle_conic(K, T, radius) @ Si))
    true /= np.linalg.norm(true)
    coeffs = coeffs / np.linalg.norm(coeffs) * np.sign(coeffs @ true)
    np.testing.assert_allclose(coeffs, true, atol=1e-9)
    # and a wrong f does not: the coefficients carry f
    wrong = conic_coeffs((1.1 * f) ** 2 * M1 + ((1.1 * f) ** 2 / Tz**2) * M2 + M3)
    wrong = wrong / np.linalg.norm(wrong) * np.sign(wrong @ true)
    assert np.linalg.norm(wrong - true) > 1e-3


# --- pose convention -----------------------------------------------------------

@pytest.mark.parametrize("solver", SOLVERS)
def test_pose_convention(solver):
    K, T = _tilted_view(35.0, t=(30.0, -20.0, 600.0))
    cal = calibrate_view(_observe(K, T), TargetSpec(R1, R2), solver=solver)
    R = cal.R_cam_table
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert camera_centre_table(cal.T_cam_table)[1] > 0  # camera above the table
    assert cal.normal_cam @ cal.t_cam_table < 0
    # table points project where the truth projects them (in-plane rotation is free, so use the circle)
    ring = circle_points_table(R1, 64)
    d = edge_residuals(cal.intrinsics.K, cal.T_cam_table, 0.0, (EdgePoints(project_points(K, T, ring), R1, 0),))
    assert np.max(np.abs(d)) < 1e-6


# --- refine: stroke, noise, residual -------------------------------------------

def test_refine_estimates_the_stroke_and_a_fixed_nominal_width_biases_f():
    K, T = _paper_view()
    nominal, true = 3.0, 3.0 * 1.15  # ink spread: 15 % wider than printed
    obs = _observe(K, T, sides=(-1, 1), stroke=true, n=360)
    cal = calibrate_view(obs, TargetSpec(R1, R2, nominal))
    assert _rel(cal.intrinsics.focal_px, K[0, 0]) < 1e-3  # 0.1 %
    assert _rel(cal.stroke_mm, true) < 0.03
    fixed = refine_view(obs.edges, cal.intrinsics.K, cal.T_cam_table, nominal, fit_stroke=False)
    assert _rel(fixed.focal_px, K[0, 0]) > 3e-3  # the nominal width biases f
    assert fixed.rms_px > 0.1


def test_refine_stroke_estimate_under_noise():
    rng = np.random.default_rng(7)
    K, T = _paper_view()
    true = 3.45
    obs = _observe(K, T, sides=(-1, 1), stroke=true, n=500, sigma=0.3, rng=rng)
    cal = calibrate_view(obs, TargetSpec(R1, R2, 3.0))
    assert abs(cal.stroke_mm - true) < 4 * cal.std.stroke_mm
    assert cal.std.stroke_mm < 0.03 * true  # "within a few %"


def test_refine_absorbs_a_constant_pixel_offset_of_the_detected_edges():
    # blur and threshold pull both edges of a stroke inwards by the same number
    # of pixels; no width in mm reproduces that under perspective
    K, T = _paper_view()
    offset_px = 0.4
    edges = []
    for R in (R1, R2):
        for side in (-1, 1):
            r = R + side * 1.5
            uv = project_points(K, T, circle_points_table(r, 720))
            C = normalize_conic(circle_conic(K, T, r))
            grad = (np.column_stack([uv, np.ones(len(uv))]) @ C.T)[:, :2]
            uv -= side * offset_px * grad / np.linalg.norm(grad, axis=1, keepdims=True)
            edges.append(EdgePoints(uv, R, side))
    obs = TargetObservation(tuple(edges), W, H)
    cal = calibrate_view(obs, TargetSpec(R1, R2, 3.0))
    assert _rel(cal.intrinsics.focal_px, K[0, 0]) < 2e-4
    assert cal.stroke_mm == pytest.approx(3.0, rel=0.01)
    r = refine_view(obs.edges, cal.intrinsics.K, cal.T_cam_table, 3.0)
    assert r.edge_offset_px == pytest.approx(offset_px, abs=0.01)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_refine_error_within_reported_sigma(seed):
    rng = np.random.default_rng(seed)
    K, T = _paper_view()
    obs = _observe(K, T, sides=(-1, 1), stroke=3.2, n=360, sigma=0.5, rng=rng)
    cal = calibrate_view(obs, TargetSpec(R1, R2, 3.0))
    s = cal.std
    assert abs(cal.intrinsics.focal_px - K[0, 0]) < 4 * s.focal_px
    assert angle_between_deg(cal.normal_cam, T[:3, 1]) < 4 * s.normal_deg
    assert np.all(np.abs(cal.t_cam_table - T[:3, 3]) < 4 * s.t_mm)
    assert abs(cal.stroke_mm - 3.2) < 4 * s.stroke_mm
    assert cal.rms_px == pytest.approx(0.5, rel=0.1)
    assert 0 < s.focal_px < 0.05 * K[0, 0]  # the sigma is informative


def test_refine_beats_closed_forms_under_noise():
    errors = {s: [] for s in SOLVERS}
    for seed in range(8):
        rng = np.random.default_rng(100 + seed)
        K, T = _paper_view()
        obs = _observe(K, T, n=360, sigma=1.0, rng=rng)
        for s in SOLVERS:
            errors[s].append(_rel(calibrate_view(obs, TargetSpec(R1, R2), solver=s).intrinsics.focal_px, K[0, 0]))
    assert np.median(errors["refine"]) < np.median(errors["paper"])
    assert np.median(errors["refine"]) < np.median(errors["pencil"])


def test_refine_resists_outliers():
    rng = np.random.default_rng(11)
    K, T = _paper_view()
    obs = _observe(K, T, n=360, sigma=0.2, rng=rng)
    bad = obs.edges[0].uv_px.copy()
    bad[::20] += rng.normal(0, 15.0, bad[::20].shape)  # 5 % wild points on the outer ring
    edges = (EdgePoints(bad, R1, 0),) + obs.edges[1:]
    cal = calibrate_view(TargetObservation(edges, W, H), TargetSpec(R1, R2))
    assert abs(cal.intrinsics.focal_px - K[0, 0]) < 4 * cal.std.focal_px
    assert cal.rms_px < 0.3


def test_edge_residual_is_the_geometric_distance():
    K, T = _paper_view()
    e = conic_to_ellipse(circle_conic(K, T, R2))
    dense = ellipse_points(e, 200_000)
    on = project_points(K, T, circle_points_table(R2, 90))
    # move the points off along the conic normal by known signed distances
    C = normalize_conic(circle_conic(K, T, R2))
    x = np.column_stack([on, np.ones(len(on))])
    g = (x @ C.T)[:, :2]
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    offset = np.resize([-2.0, -1.0, 1.0, 2.0], len(on))
    pts = on + offset[:, None] * g
    exact = np.min(np.linalg.norm(pts[:, None, :] - dense[None, ::4, :], axis=2), axis=1)
    r = edge_residuals(K, T, 0.0, (EdgePoints(pts, R2, 0),))
    np.testing.assert_allclose(np.sign(r), np.sign(offset))
    # measured: <= 0.034 px at 2 px off this ellipse (curvature radius down to 17 px)
    np.testing.assert_allclose(np.abs(r), exact, atol=0.04)
    near = np.abs(offset) == 1.0
    np.testing.assert_allclose(np.abs(r[near]), exact[near], atol=0.01)


def test_edge_linearisation_matches_finite_differences():
    """Analytic derivatives = central differences with the pixel weight held.

    The weight ``1 / |grad rho|`` is frozen per evaluation (its derivative is
    multiplied by the residual and is dropped, module docstring), so the
    differences are taken of ``(rho(p) - r) / g(p0)``.
    """
    from calib.refine import edge_geometry, stack_edges

    K, T = _paper_view()
    obs = _observe(K, T, sides=(-1, 1), stroke=3.0, n=50)
    n1 = T[:3, 1] + [0.002, 0.0, 0.001]  # off the solution: residuals of ~2 px
    T1 = make_T(rotation_from_normal(n1), T[:3, 3] + [0.2, -0.1, 1.5])
    w = 3.3
    L = edge_linearisation(K, T1, w, obs.edges)
    assert 0.5 < np.max(np.abs(L.residual_px)) < 10.0
    uv, R, side = stack_edges(obs.edges)
    f, cx, cy, n, t = K[0, 0], K[0, 2], K[1, 2], T1[:3, 1], T1[:3, 3]
    g0 = edge_geometry(f, cx, cy, n, t, uv).g
    np.testing.assert_allclose(L.residual_px, edge_residuals(K, T1, w, obs.edges), atol=1e-12)

    def res(f=f, cx=cx, cy=cy, n=n, t=t, w=w):
        rho = edge_geometry(f, cx, cy, n / np.linalg.norm(n), t, uv).rho
        return (rho - (R + 0.5 * side * w)) / g0

    def central(fun, h):
        return (fun(h) - fun(-h)) / (2 * h)

    tangent = np.linalg.svd(n.reshape(1, 3))[2][1:]
    cases = [
        (central(lambda h: res(f=f + h), 1e-2), L.d_focal),
        (central(lambda h: res(cx=cx + h), 1e-3), L.d_principal[:, 0]),
        (central(lambda h: res(cy=cy + h), 1e-3), L.d_principal[:, 1]),
        (central(lambda h: res(w=w + h), 1e-3), L.d_stroke),
    ]
    np.testing.assert_array_equal(L.d_offset, side)
    cases += [(central(lambda h, i=i: res(t=t + h * np.eye(3)[i]), 1e-4), L.d_t[:, i]) for i in range(3)]
    cases += [(central(lambda h, v=v: res(n=n + h * v), 1e-7), L.d_normal @ v) for v in tangent]
    for numeric, analytic in cases:
        np.testing.assert_allclose(numeric, analytic, atol=1e-6 * np.max(np.abs(analytic)))


# --- refusals ------------------------------------------------------------------

def test_refuses_fronto_parallel_view():
    K, T = _tilted_view(3.0)
    with pytest.raises(CalibrationError, match="fronto-parallel: tilt 3.0°"):
        calibrate_view(_observe(K, T), TargetSpec(R1, R2))
    rng = np.random.default_rng(5)
    with pytest.raises(CalibrationError, match="fronto-parallel"):
        calibrate_view(_observe(K, T, sigma=0.5, rng=rng), TargetSpec(R1, R2))


def test_off_centre_target_on_a_sensor_parallel_table_is_refused():
    # 0° from the optical axis, ~7° from the ray to the centre: f is unobservable
    K, T = _tilted_view(0.5, t=(90.0, 0.0, 750.0))
    with pytest.raises(CalibrationError, match="fronto-parallel"):
        calibrate_view(_observe(K, T), TargetSpec(R1, R2))


def test_accepts_a_view_just_above_the_tilt_threshold():
    K, T = _tilted_view(MIN_TILT_DEG + 2.0)
    cal = calibrate_view(_observe(K, T), TargetSpec(R1, R2))
    assert tilt_deg(cal.T_cam_table) == pytest.approx(MIN_TILT_DEG + 2.0, abs=1e-6)


@pytest.mark.parametrize("true_inner", [30.0, 26.0])
def test_refuses_wrong_radius_ratio(true_inner):
    K, T = _paper_view()
    obs = _observe(K, T, radii=(R1, true_inner), labels=(R1, R2))
    with pytest.raises(CalibrationError, match="radius ratio"):
        calibrate_view(obs, TargetSpec(R1, R2))


def test_refuses_non_concentric_rings():
    K, T = _paper_view()
    inner = project_points(K, T, circle_points_table(R2, 200) + [2.0, 0.0, 0.0])  # 2 mm off
    obs = TargetObservation((EdgePoints(project_points(K, T, circle_points_table(R1, 200)), R1, 0),
                             EdgePoints(inner, R2, 0)), W, H)
    with pytest.raises(CalibrationError, match="concentric"):
        calibrate_view(obs, TargetSpec(R1, R2))


def test_refuses_a_single_ring():
    K, T = _paper_view()
    obs = _observe(K, T, sides=(-1, 1), stroke=3.0, radii=(R1,))
    with pytest.raises(CalibrationError, match="two concentric rings"):
        calibrate_view(obs, TargetSpec(R1, R2))


def test_unknown_solver_is_a_value_error():
    K, T = _paper_view()
    with pytest.raises(ValueError, match="unknown solver"):
        calibrate_view(_observe(K, T), TargetSpec(R1, R2), solver="magic")
