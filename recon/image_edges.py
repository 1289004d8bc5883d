"""The photos' edges that the hull's later stages read: Canny over the photos' own
noise.

Flat tops and openings (:mod:`recon.faces`, :mod:`recon.openings`), flat sides
(:mod:`recon.sides`) and the silhouettes' growth up to the next edge
(:func:`recon.carving.held_past_edges`) read each photo's edges: Canny's
hysteresis on the Sobel gradient of its grey levels smoothed with a Gaussian of
sigma 1 px. The thresholds, ``EDGE_LO`` / ``EDGE_HI`` = 8 / 16, are low: a white
box's lit face on the lit paper shows an edge of 30-50 grey levels, a white
cup's rim against its inside less (and the paper's grain at 4 / 8 is edges
everywhere). The synth's photos (noise 2 DN, JPEG) keep their noise under them;
a noisier camera's (4 DN) does not: Canny draws edges all over a plain white
surface, the views agree on some of them by chance, and a white cup's inside
looked outlined higher up, as under a knob (its opening refused, the inside left
solid: 0.5 -> 1.9 % of its diagonal).

So the thresholds rise with the noise, measured where it is alone. With a camera
that stays put, two consecutive photos differ in the room by their noise only:
the median over the image of the same gradient of their difference (over sqrt 2;
the object and the print, which move, are less than half the image) is the
noise's, and ``EDGE_LO`` becomes ``NOISE_MULT`` times it (the median of
``NOISE_PAIRS`` pairs), at least 8 and at most ``MAX_LO``; ``EDGE_HI`` twice
that. A camera that moves (hand-held, ``--masks``:
:func:`recon.silhouette_checks.camera_still`) keeps 8 / 16.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from .silhouette_checks import camera_still

__all__ = ["EDGE_LO", "EDGE_HI", "edge_thresholds", "photo_noise", "quieted", "smoothed_grey", "edges"]

EDGE_LO, EDGE_HI = 8.0, 16.0  # Canny's thresholds at the least
NOISE_MULT = 2.6  # EDGE_LO over the noise's median gradient (the synth's photos: 2.3-3.0 -> 8; noise 4 DN: 4.2-5.0)
MAX_LO = 16.0  # EDGE_LO at the most
NOISE_PAIRS = 6  # consecutive pairs of photos the noise is measured on, spread over the sequence
DENOISE_H = 3.0  # quieted: non-local means' filter strength for a noisy camera's photos (luminance and colour)


def smoothed_grey(image_rgb: np.ndarray) -> np.ndarray:
    """(H, W) uint8: the grey levels of ``image_rgb`` (H, W, 3) smoothed with a Gaussian of sigma 1 px."""
    return cv2.GaussianBlur(cv2.cvtColor(np.asarray(image_rgb), cv2.COLOR_RGB2GRAY), (0, 0), 1.0)


def edges(grey: np.ndarray, thresholds: tuple[float, float] = (EDGE_LO, EDGE_HI)) -> np.ndarray:
    """(H, W) bool: Canny's edges of ``grey`` (:func:`smoothed_grey`) at ``thresholds`` (:func:`edge_thresholds`)."""
    return cv2.Canny(grey, float(thresholds[0]), float(thresholds[1])) > 0


def _noise_gradient(a: np.ndarray, b: np.ndarray) -> float:
    """The median over the image of the smoothed gradient (Canny's, L1) of two photos' difference over sqrt 2."""
    def smooth(im):
        return cv2.GaussianBlur(cv2.cvtColor(np.asarray(im), cv2.COLOR_RGB2GRAY).astype(np.float32), (0, 0), 1.0)

    d = ((smooth(a) - smooth(b)) / np.sqrt(2.0)).astype(np.float32)
    g = np.abs(cv2.Sobel(d, cv2.CV_32F, 1, 0)) + np.abs(cv2.Sobel(d, cv2.CV_32F, 0, 1))
    return float(np.median(g))


def photo_noise(images_rgb: Sequence[np.ndarray], T_cam_table: np.ndarray) -> float | None:
    """The photos' noise as Canny sees it (see the module's docstring): the median over ``NOISE_PAIRS``
    consecutive pairs of the median smoothed gradient of their difference; None for a camera that moves (or
    fewer than two photos)."""
    n = len(images_rgb)
    if n < 2 or len(T_cam_table) != n or not camera_still(T_cam_table):
        return None
    starts = np.unique(np.linspace(0, n - 2, min(NOISE_PAIRS, n - 1)).round().astype(int))
    return float(np.median([_noise_gradient(images_rgb[k], images_rgb[k + 1]) for k in starts]))


def edge_thresholds(images_rgb: Sequence[np.ndarray], T_cam_table: np.ndarray) -> tuple[float, float]:
    """Canny's (low, high) thresholds for these photos (see the module's docstring): 8 / 16, higher for a noisy
    camera that stays put."""
    noise = photo_noise(images_rgb, T_cam_table)
    if noise is None:
        return EDGE_LO, EDGE_HI
    lo = float(np.clip(NOISE_MULT * noise, EDGE_LO, MAX_LO))
    return lo, 2.0 * lo


def quieted(images_rgb: np.ndarray, T_cam_table: np.ndarray) -> np.ndarray:
    """The photos (V, H, W, 3) uint8 RGB as the automatic silhouettes read them: where the camera is noisy
    (:func:`edge_thresholds` above 8 / 16), each denoised by non-local means (OpenCV's
    ``fastNlMeansDenoisingColored``, ``DENOISE_H``); otherwise the photos themselves, untouched.

    The silhouettes tell a white object from the white paper by a few grey levels, pixel by pixel, against
    the noise they measure on the plates: at 4 DN a white teapot's lit side and a figure's plinth fell within
    it (held as doubt, twenty views conservative; the plinth eaten), 1.38 and 1.01 % of their diagonals.
    Non-local means averages like patches, so the outline stays sharp.
    """
    imgs = np.asarray(images_rgb)
    if edge_thresholds(list(imgs), T_cam_table)[0] <= EDGE_LO:
        return imgs
    out = np.empty_like(imgs)
    for i, im in enumerate(imgs):  # OpenCV's colour denoiser reads BGR
        out[i] = cv2.fastNlMeansDenoisingColored(np.ascontiguousarray(im[..., ::-1]), None, DENOISE_H, DENOISE_H,
                                                 5, 15)[..., ::-1]
    return out
