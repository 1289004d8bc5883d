"""The photos' edges (recon.image_edges): Canny's thresholds over the noise a still camera's photos show."""

from __future__ import annotations

import math

import numpy as np

import recon.image_edges as ie
from calib.camera import look_at, make_T


def _turntable_poses(n: int = 8) -> np.ndarray:
    T_cam_axis = look_at(np.array([0.0, 250.0, -430.0]), np.zeros(3))
    rot = [make_T(np.array([[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]]), np.zeros(3))
           for t in np.linspace(0, 2 * math.pi, n, endpoint=False)]
    return np.stack([T_cam_axis @ R for R in rot])


def _photos(rng, sigma: float, n: int = 8) -> list[np.ndarray]:
    """A still room (a wall and a lit step between two greys) with fresh sensor noise in every photo."""
    room = np.full((120, 160, 3), 90.0)
    room[60:, :] = 200.0
    return [np.clip(room + rng.normal(0.0, sigma, room.shape), 0, 255).astype(np.uint8) for _ in range(n)]


def test_thresholds_rise_with_the_noise_of_a_still_camera_only():
    rng = np.random.default_rng(5)
    Ts = _turntable_poses()
    assert ie.edge_thresholds(_photos(rng, 1.0), Ts) == (ie.EDGE_LO, ie.EDGE_HI)  # a quiet camera: 8 / 16
    noisy = _photos(rng, 5.0)
    lo, hi = ie.edge_thresholds(noisy, Ts)
    assert ie.EDGE_LO < lo <= ie.MAX_LO and hi == 2 * lo
    assert ie.edge_thresholds(_photos(rng, 30.0), Ts) == (ie.MAX_LO, 2 * ie.MAX_LO)  # at most MAX_LO
    moved = Ts.copy()
    moved[::2, :3, 3] *= 1.15  # a camera carried round: its photos' differences are not noise
    assert ie.edge_thresholds(noisy, moved) == (ie.EDGE_LO, ie.EDGE_HI)
    # over the noise, the wall and the floor are plain and the step between them is the edge
    grey = ie.smoothed_grey(noisy[0])
    at_lo, over = ie.edges(grey), ie.edges(grey, (lo, hi))
    plain = np.ones(grey.shape, bool)
    plain[55:66] = False
    assert at_lo[plain].mean() > 0.01 and over[plain].mean() < 0.002
    assert over[58:62].any(axis=0).mean() > 0.95


def test_a_noisy_still_cameras_photos_are_denoised_for_the_silhouettes_others_untouched():
    rng = np.random.default_rng(6)
    Ts = _turntable_poses()
    quiet = np.stack(_photos(rng, 1.0))
    assert ie.quieted(quiet, Ts) is quiet  # a quiet camera's photos: the very same pixels
    noisy = np.stack(_photos(rng, 5.0))
    moved = Ts.copy()
    moved[::2, :3, 3] *= 1.15
    assert ie.quieted(noisy, moved) is noisy  # no noise measured where the camera moves
    out = ie.quieted(noisy, Ts)
    assert out.shape == noisy.shape and out.dtype == np.uint8
    flat = np.s_[:, 10:50, 20:140]
    assert out[flat].std() < 0.4 * noisy[flat].std()
    # the step from the wall to the floor stays where it was, and sharp
    col = out[:, :, 80, 1].astype(float).mean(axis=0)
    assert col[57] < 100 and col[62] > 190
