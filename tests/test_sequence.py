"""Joint sequence calibration on edge observations synthesised from known cameras.

Edges are exact points on the projected (and distorted) edge circles plus
Gaussian noise; the angle marks are simulated by a reader that returns the
true rotation about the table normal plus noise. The single-view stage is
replaced by a perturbed ground truth where a test is about the joint maths
alone (``_single_view`` monkeypatched), and run for real in the end-to-end tests.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import calib.sequence as cs
from calib.camera import camera_centre_table, circle_points_table, make_T, project_points
from calib.distortion import distort_px
from calib.target import TargetSpec
from calib.types import CalibrationError, EdgePoints, Intrinsics, TargetObservation

W, H = 1280, 960
SPEC = TargetSpec(r_outer_mm=80.0, r_inner_mm=50.0, stroke_mm=3.0)
TRUE_STROKE_MM = 3.3  # printers spread ink: the truth differs from the nominal width


def look_at(C: np.ndarray, target: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """T_cam_world of an OpenCV camera at ``C`` looking at ``target`` (world +Y up)."""
    z = (target - C) / np.linalg.norm(target - C)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_world_cam = np.column_stack([x, y, z])
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    R_world_cam = R_world_cam @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    R = R_world_cam.T
    return make_T(R, -R @ C)


def camera_position(elev_deg: float, azim_deg: float, dist_mm: float) -> np.ndarray:
    e, a = math.radians(elev_deg), math.radians(azim_deg)
    return dist_mm * np.array([math.cos(e) * math.sin(a), math.sin(e), -math.cos(e) * math.cos(a)])


def synth_observation(K, dist, T, rng, noise_px=0.15, n_per_edge=360, hide_deg=60.0) -> TargetObservation:
    """Both edges of both rings, an arc of ``hide_deg`` hidden (the object), noisy pixels."""
    edges = []
    start = rng.uniform(0, 360)
    for R in (SPEC.r_outer_mm, SPEC.r_inner_mm):
        for side in (-1, 1):
            r = R + side * TRUE_STROKE_MM / 2
            pts = circle_points_table(r, n_per_edge)
            phi = np.degrees(np.arctan2(pts[:, 2], pts[:, 0])) % 360
            keep = (phi - start) % 360 > hide_deg
            uv = project_points(K, T, pts[keep])
            uv = distort_px(uv, K, dist)
            uv = uv + rng.normal(0, noise_px, uv.shape)
            edges.append(EdgePoints(uv, R, side))
    return TargetObservation(edges=tuple(edges), width=W, height=H)


def turntable_truth(rng, n=36, step=10.0, jitter=0.0, offset=(2.0, -1.5), f=1500.0, elev=30.0, dist=450.0):
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    T_cam_axis = look_at(camera_position(elev, 0.0, dist), np.array([0.0, 30.0, 0.0]))
    theta = np.radians(np.arange(n) * step + rng.uniform(-jitter, jitter, n))
    d = np.array([offset[0], 0.0, offset[1]])
    Ts = [T_cam_axis @ make_T(cs.rot_y(th), np.zeros(3)) @ make_T(np.eye(3), d) for th in theta]
    return K, theta, Ts


def handheld_truth(rng, n=8, f=1400.0, pp=(20.0, -12.0)):
    K = np.array([[f, 0, (W - 1) / 2 + pp[0]], [0, f, (H - 1) / 2 + pp[1]], [0, 0, 1.0]])
    Ts = []
    for k in range(n):
        C = camera_position(rng.uniform(25, 70), 360.0 * k / n + rng.uniform(-20, 20), rng.uniform(380, 520))
        aim = np.array([rng.uniform(-40, 40), 0.0, rng.uniform(-40, 40)])
        Ts.append(look_at(C, aim, math.radians(rng.uniform(-15, 15))))
    return K, Ts


def fake_reader(Ts_true, rng, std_deg=0.05):
    def read(k, K, T):
        psi = cs._yaw_of(T[:3, :3].T @ Ts_true[k][:3, :3]) + math.radians(rng.normal(0, std_deg))
        return make_T(T[:3, :3] @ cs.rot_y(psi), T[:3, 3]), std_deg

    return read


def perturbed_single_view(Ts_true, K_true, rng):
    """Stand-in for calib.calibrate: truth off by 1 % in f, 0.5 deg in the normal, 3 mm, random yaw."""
    lookup = {}

    def single(obs, spec, pp, max_per_edge):
        k = lookup[id(obs)]
        T = Ts_true[k]
        w = rng.normal(0, math.radians(0.5), 3)
        R = cs._exp_so3(w) @ T[:3, :3] @ cs.rot_y(rng.uniform(-np.pi, np.pi))
        return cs._Single(edges=cs._FrameEdges.from_observation(obs, max_per_edge),
                          T=make_T(R, T[:3, 3] + rng.normal(0, 3.0, 3)),
                          focal_px=K_true[0, 0] * (1 + rng.normal(0, 0.01)), rms_px=0.15, stroke_mm=3.0)

    return single, lookup


def run_synthetic(monkeypatch, rng, K, dist, Ts, **kw):
    obs = [synth_observation(K, dist, T, rng) for T in Ts]
    single, lookup = perturbed_single_view(Ts, K, rng)
    lookup.update({id(o): k for k, o in enumerate(obs)})
    monkeypatch.setattr(cs, "_single_view", single)
    return cs.calibrate_sequence(obs, None, SPEC, angle_reader=fake_reader(Ts, rng), **kw)


def centre_errors_mm(seq, Ts):
    return np.array([np.linalg.norm(camera_centre_table(f.T_cam_table) - camera_centre_table(T))
                     for f, T in zip(seq.frames, Ts) if f.ok])


def angle_errors_deg(seq, theta_true):
    est = np.radians([f.angle_deg for f in seq.frames])
    d = cs._wrap(est - cs.TURN_SIGN * theta_true)
    d = cs._wrap(d - math.atan2(np.sin(d).mean(), np.cos(d).mean()))  # common offset: a gauge
    return np.degrees(np.abs(d))


# --------------------------------------------------------------------------- turntable
def test_turntable_joint_fit_recovers_camera_axis_and_angles(monkeypatch):
    rng = np.random.default_rng(1)
    K, theta, Ts = turntable_truth(rng, n=24, step=15.0, jitter=3.0)
    seq = run_synthetic(monkeypatch, rng, K, np.zeros(5), Ts)
    assert seq.mode == "turntable"
    assert all(f.ok for f in seq.frames)
    f_rel_err = abs(seq.intrinsics.focal_px / K[0, 0] - 1)
    assert f_rel_err < 1e-3
    assert np.max(centre_errors_mm(seq, Ts)) < 0.5
    err = angle_errors_deg(seq, theta)
    assert np.median(err) < 0.05 and np.max(err) < 0.2
    off = seq.meta["turntable"]["pattern_offset_from_axis_mm"]
    assert np.allclose(off, [2.0, -1.5], atol=0.3)
    assert "unobservable" in seq.meta["not_estimated"]["principal_point"]
    assert abs(seq.meta["stroke_mm"] - TRUE_STROKE_MM) < 0.05


def test_turntable_step_fixes_angles_and_flags_disagreeing_marks(monkeypatch):
    rng = np.random.default_rng(2)
    K, theta, Ts = turntable_truth(rng, n=12, step=30.0)
    theta_bad = theta.copy()
    theta_bad[5] += math.radians(4.0)  # the table slipped in frame 5: the marks see it, the step does not
    Ts_bad = [Ts[k] if k != 5 else Ts[0] @ make_T(cs.rot_y(theta_bad[5]), np.zeros(3)) @ np.linalg.inv(Ts[0])
              @ Ts[0] for k in range(len(Ts))]
    Ts_bad[5] = Ts[0] @ make_T(cs.rot_y(theta_bad[5] - theta[0]), np.zeros(3))
    obs = [synth_observation(K, np.zeros(5), T, rng) for T in Ts_bad]
    single, lookup = perturbed_single_view(Ts_bad, K, rng)
    lookup.update({id(o): k for k, o in enumerate(obs)})
    monkeypatch.setattr(cs, "_single_view", single)
    seq = cs.calibrate_sequence(obs, None, SPEC, step_deg=30.0, mode="turntable",
                                angle_reader=fake_reader(Ts_bad, rng))
    assert [f.angle_deg for f in seq.frames][:3] == pytest.approx([0.0, 30.0, 60.0])
    flagged = [c["image"] for c in seq.meta.get("angle_checks", [])]
    assert flagged == ["frame_005"]
