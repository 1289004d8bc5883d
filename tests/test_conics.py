"""Conic fitting and ellipse parameters against exact projected circles."""

import re

import numpy as np
import pytest

from calib.camera import circle_conic, circle_points_table, make_T, project_points, rotation_from_normal
from calib.conics import (
    Ellipse,
    algebraic_residual,
    conic_center,
    conic_coeffs,
    conic_from_coeffs,
    conic_to_ellipse,
    ellipse_points,
    ellipse_to_conic,
    fit_conic,
    is_ellipse,
    normalize_conic,
    sampson_distance,
)
from calib.types import EdgePoints

EXACT = 1e-9  # relative, noise-free data


def _view(elev_deg=35.0, f=1500.0):
    K = np.array([[f, 0, 639.5], [0, f, 479.5], [0, 0, 1.0]])
    e = np.radians(elev_deg)
    normal_cam = np.array([0.0, -np.cos(e), -np.sin(e)])  # plane normal towards camera, table below
    T = make_T(rotation_from_normal(normal_cam), [5.0, 20.0, 450.0])
    return K, T


def test_fit_recovers_exact_projected_circle():
    K, T = _view()
    uv = project_points(K, T, circle_points_table(80.0, 50))
    C_true = normalize_conic(circle_conic(K, T, 80.0))
    np.testing.assert_allclose(fit_conic(uv), C_true, atol=EXACT)


def test_fit_on_partial_arc_noise_free_is_exact():
    K, T = _view(60)
    pts = circle_points_table(50.0, 400)[:120]  # a 108 degree arc
    uv = project_points(K, T, pts)
    np.testing.assert_allclose(fit_conic(uv), normalize_conic(circle_conic(K, T, 50.0)), atol=1e-7)


@pytest.mark.parametrize("sigma_px", [0.1, 0.5, 1.0])
def test_fit_with_noise_stays_close(sigma_px):
    rng = np.random.default_rng(1)
    K, T = _view()
    uv = project_points(K, T, circle_points_table(80.0, 400))
    C = fit_conic(uv + rng.normal(0, sigma_px, uv.shape))
    d = sampson_distance(C, project_points(K, T, circle_points_table(80.0, 90)))
    assert np.abs(d).max() < 3 * sigma_px / np.sqrt(400 / 30)  # well below the point noise


def test_ellipse_round_trip():
    e = Ellipse(center_px=np.array([300.0, 200.0]), a=120.0, b=45.0, angle_rad=0.4)
    e2 = conic_to_ellipse(ellipse_to_conic(e))
    np.testing.assert_allclose(e2.center_px, e.center_px, atol=1e-9)
    assert (e2.a, e2.b) == pytest.approx((e.a, e.b), rel=1e-12)
    assert e2.angle_rad == pytest.approx(e.angle_rad, abs=1e-12)
    assert np.abs(sampson_distance(ellipse_to_conic(e), ellipse_points(e, 64))).max() < 1e-9


def test_coeffs_round_trip_and_centre():
    coeffs = np.array([1.0, 0.2, 2.0, -3.0, 4.0, -10.0])
    C = conic_from_coeffs(coeffs)
    np.testing.assert_allclose(conic_coeffs(C), coeffs)
    c = conic_center(C)
    np.testing.assert_allclose(C[:2, :2] @ c + C[:2, 2], 0, atol=1e-12)


def test_sampson_distance_is_signed_geometric_distance_for_a_circle():
    e = Ellipse(center_px=np.zeros(2), a=100.0, b=100.0, angle_rad=0.0)
    C = ellipse_to_conic(e)
    d = sampson_distance(C, [[101.0, 0.0], [0.0, 99.0]])
    np.testing.assert_allclose(d, [1.0, -1.0], rtol=0.02)


def test_degenerate_inputs_raise():
    with pytest.raises(ValueError, match="at least 5"):
        fit_conic(np.zeros((4, 2)))
    line = np.column_stack([np.arange(20.0), 2 * np.arange(20.0)])
    with pytest.raises(ValueError):
        fit_conic(line)
    hyperbola = conic_from_coeffs([1.0, 0.0, -1.0, 0.0, 0.0, -1.0])
    assert not is_ellipse(hyperbola)


@pytest.mark.parametrize("shape", [(5, 3), (2, 8), (10,), (4, 1, 3)])
def test_wrong_point_shapes_raise_naming_the_argument(shape):
    bad = np.zeros(shape)
    C = ellipse_to_conic(Ellipse(center_px=np.zeros(2), a=100.0, b=50.0, angle_rad=0.0))
    expected = rf"uv_px must be \(N, 2\), got {re.escape(str(shape))}"
    for call in (lambda: fit_conic(bad), lambda: sampson_distance(C, bad), lambda: algebraic_residual(C, bad),
                 lambda: EdgePoints(bad, 50.0, 0)):
        with pytest.raises(ValueError, match=expected):
            call()


def test_opencv_point_layout_is_accepted():
    e = Ellipse(center_px=np.array([320.0, 240.0]), a=100.0, b=60.0, angle_rad=0.3)
    uv = ellipse_points(e, 50)
    np.testing.assert_array_equal(fit_conic(uv[:, None, :]), fit_conic(uv))
    np.testing.assert_array_equal(EdgePoints(uv[:, None, :], 50.0, 0).uv_px, uv)


def test_conic_weights_must_match_the_points():
    uv = ellipse_points(Ellipse(center_px=np.zeros(2), a=100.0, b=60.0, angle_rad=0.0), 20)
    with pytest.raises(ValueError, match=r"weights must be \(20,\) like uv_px, got \(19,\)"):
        fit_conic(uv, weights=np.ones(19))
