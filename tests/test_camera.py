"""Pose helpers and circle projection."""

import numpy as np

from calib.camera import (
    angle_between_deg,
    camera_centre_table,
    circle_conic,
    circle_points_table,
    invert_T,
    make_T,
    plane_homography,
    project_points,
    rotation_from_normal,
    values_at_points,
)


def test_rotation_from_normal_is_right_handed_with_normal_as_second_column():
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = rng.normal(size=3)
        R = rotation_from_normal(n)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0.999999
        np.testing.assert_allclose(R[:, 1], n / np.linalg.norm(n), atol=1e-12)


def test_invert_T_round_trip():
    rng = np.random.default_rng(2)
    R = rotation_from_normal(rng.normal(size=3))
    T = make_T(R, rng.normal(size=3) * 100)
    np.testing.assert_allclose(T @ invert_T(T), np.eye(4), atol=1e-12)


def test_projected_circle_points_lie_on_circle_conic():
    K = np.array([[1200.0, 0, 640], [0, 1200.0, 480], [0, 0, 1]])
    n = np.array([0.1, -0.8, -0.6])
    T = make_T(rotation_from_normal(n), [10.0, 30.0, 500.0])
    for r in (30.0, 80.0):
        uv = project_points(K, T, circle_points_table(r, 100))
        x = np.column_stack([uv, np.ones(len(uv))])
        C = circle_conic(K, T, r)
        assert np.abs(np.einsum("ij,jk,ik->i", x, C, x)).max() < 1e-12
        # projected centre inside the conic
        c = plane_homography(K, T) @ [0, 0, 1.0]
        c /= c[2]
        assert c @ C @ c < 0


def test_camera_centre_and_angle():
    T = make_T(np.eye(3), [0.0, 0.0, 100.0])
    np.testing.assert_allclose(camera_centre_table(T), [0, 0, -100.0])
    assert abs(angle_between_deg([1, 0, 0], [0, 1, 0]) - 90.0) < 1e-12
    assert angle_between_deg([1, 0, 0], [1, 1e-9, 0]) < 1e-6


def test_look_at_centres_the_target_with_table_up_on_top():
    from calib.camera import look_at

    K = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    T = look_at([300.0, 200.0, -100.0], [0.0, 30.0, 0.0])
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) > 0.999999
    np.testing.assert_allclose(camera_centre_table(T), [300.0, 200.0, -100.0], atol=1e-9)
    top, bottom = project_points(K, T, np.array([[0.0, 60.0, 0.0], [0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(project_points(K, T, np.array([[0.0, 30.0, 0.0]]))[0], [320, 240], atol=1e-9)
    assert top[1] < bottom[1] and abs(top[0] - bottom[0]) < 1e-6  # +Y is straight up in the image
    rolled = look_at([300.0, 200.0, -100.0], [0.0, 30.0, 0.0], roll_rad=np.pi / 2)
    t2, b2 = project_points(K, rolled, np.array([[0.0, 60.0, 0.0], [0.0, 0.0, 0.0]]))
    assert abs(t2[1] - b2[1]) < 1e-6  # a quarter roll turns the vertical sideways


def test_values_at_points_reads_the_nearest_pixel_and_zero_off_the_image():
    """A point projecting onto pixel (u, v) reads image[v, u]; one projecting off the image reads zero (False)."""
    K = np.array([[100.0, 0.0, 9.5], [0.0, 100.0, 7.5], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[2, 3] = 500.0  # the table origin 500 mm in front of the camera
    image = np.arange(16 * 20, dtype=np.int32).reshape(16, 20) + 1  # no zero on the image
    pts = np.array([[0.0, 0.0, 0.0], [12.0, -9.0, 0.0], [200.0, 0.0, 0.0], [0.0, -200.0, 0.0]])
    uv = np.rint(project_points(K, T, pts[:2])).astype(int)
    got = values_at_points(K, T, pts, image)
    assert got.dtype == image.dtype
    assert list(got[:2]) == [image[v, u] for u, v in uv]
    assert list(got[2:]) == [0, 0]
    assert values_at_points(K, T, pts, image > 0).tolist() == [True, True, False, False]
