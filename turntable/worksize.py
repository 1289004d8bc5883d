"""The working resolution: the image size silhouettes, stereo, fusion and colour work at.

Ring detection and calibration use every photo at full resolution (more edge
points, a better focal length); the later stages need the object's outline
and texture, not 12-48 MP of them. Each photo is reduced once, as it is
decoded, to the **work size** ``(w, h)`` (``cv2.INTER_AREA``: the average of
the full-resolution pixels each work pixel covers), and those stages get the
camera matrix of that image.

Scaling keeps the pixel-centre convention (README: pixel (0, 0) is the centre
of the top-left pixel). With ``s_x = w / W`` and ``s_y = h / H``, the pixel
``(u, v)`` of the full image lies at

    u' = s_x (u + 0.5) - 0.5,    v' = s_y (v + 0.5) - 0.5

in the work image (the map ``cv2.resize`` samples with), so ``K' = S K`` with
``S = [[s_x, 0, 0.5 s_x - 0.5], [0, s_y, 0.5 s_y - 0.5], [0, 0, 1]]``:
``f_x' = s_x f_x``, ``c_x' = s_x (c_x + 0.5) - 0.5``. Distortion coefficients
act on normalised coordinates and stay as they are. A conic ``C`` (``x^T C x = 0``)
becomes ``S^-T C S^-1``.

**Default policy** (:func:`choose_work_size`): full size up to
:data:`MAX_DEFAULT_PIXELS` (1.3 MP, so 1280x960 photos are used as before);
above it, the size with about that many pixels, unless the object would then
be small: the outer ring (whose size the object is photographed at) keeps at
least :data:`MIN_RING_PX` pixels across, up to :data:`MAX_WORK_PIXELS`.
``--work-size N`` sets the long side to N pixels instead (``full``: no
reduction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .errors import UserError

__all__ = ["WorkSize", "choose_work_size", "parse_work_size", "scale_matrix",
           "MAX_DEFAULT_PIXELS", "MIN_RING_PX", "MAX_WORK_PIXELS"]

MAX_DEFAULT_PIXELS = 1.3e6  # full size up to this many pixels; reduced to about this many above it
MIN_RING_PX = 480  # ... but the outer ring's image keeps at least this long axis (pixels) ...
MAX_WORK_PIXELS = 4.0e6  # ... as long as the work image stays within this many pixels
MIN_WORK_LONG_SIDE = 64  # --work-size below this is refused


def scale_matrix(full: tuple[int, int], work: tuple[int, int]) -> np.ndarray:
    """``S`` (3, 3): homogeneous map of full-image pixel centres to those of the ``work`` image.

    ``full`` and ``work`` are (width, height); see the module docstring.
    """
    (W, H), (w, h) = full, work
    sx, sy = w / W, h / H
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class WorkSize:
    """Full and work image sizes, (width, height) pixels, and why this work size was chosen."""

    full: tuple[int, int]
    work: tuple[int, int]
    why: str

    @property
    def scale(self) -> float:
        """Work long side over full long side."""
        return max(self.work) / max(self.full)

    @property
    def is_full(self) -> bool:
        return tuple(self.work) == tuple(self.full)

    @property
    def S(self) -> np.ndarray:
        return scale_matrix(self.full, self.work)

    def K(self, K_full: np.ndarray) -> np.ndarray:
        """Camera matrix (3, 3) of the work image from that of the full image."""
        return self.S @ np.asarray(K_full, np.float64)

    def conic(self, C_full: np.ndarray) -> np.ndarray:
        """A full-image conic in work pixels."""
        Si = np.linalg.inv(self.S)
        return Si.T @ np.asarray(C_full, np.float64) @ Si

    def to_work(self, uv_px: np.ndarray) -> np.ndarray:
        """Full-image pixels (N, 2) -> work pixels (N, 2)."""
        uv = np.asarray(uv_px, np.float64)
        return uv * np.diag(self.S)[:2] + self.S[:2, 2]

    def to_full(self, uv_px: np.ndarray) -> np.ndarray:
        """Work pixels (N, 2) -> full-image pixels (N, 2)."""
        uv = np.asarray(uv_px, np.float64)
        return (uv - self.S[:2, 2]) / np.diag(self.S)[:2]

    def reduce(self, image: np.ndarray) -> np.ndarray:
        """``image`` (H, W[, C]) at the work size (a copy only when reduced)."""
        if image.shape[1::-1] != tuple(self.full):
            raise ValueError(f"image is {image.shape[1]}x{image.shape[0]}, expected {self.full[0]}x{self.full[1]}")
        if self.is_full:
            return image
        return cv2.resize(image, tuple(self.work), interpolation=cv2.INTER_AREA)

    def report(self) -> dict:
        return {"width": int(self.work[0]), "height": int(self.work[1]), "scale": round(self.scale, 4),
                "full_width": int(self.full[0]), "full_height": int(self.full[1]), "why": self.why}

    def describe(self) -> str:
        if self.is_full:
            return f"{self.work[0]} x {self.work[1]} (full size; {self.why})"
        return (f"{self.work[0]} x {self.work[1]} ({self.scale:.3f} of {self.full[0]} x {self.full[1]}; "
                f"{self.why})")


def parse_work_size(text: str | None) -> int | None:
    """``--work-size``: None (default policy), 0 (``full``) or a long side in pixels."""
    if text is None:
        return None
    t = str(text).strip().lower()
    if t == "full":
        return 0
    try:
        n = int(t)
    except ValueError:
        raise UserError(f"--work-size must be a long side in pixels (e.g. 1600) or 'full', got {text!r}") from None
    if n < MIN_WORK_LONG_SIDE:
        raise UserError(f"--work-size must be at least {MIN_WORK_LONG_SIDE} pixels (or 'full'), got {n}")
    return n


def _size_for_scale(full: tuple[int, int], s: float) -> tuple[int, int]:
    W, H = full
    return max(1, int(round(W * s))), max(1, int(round(H * s)))


def choose_work_size(full: tuple[int, int], ring_px: float | None = None,
                     requested: int | None = None) -> WorkSize:
    """The work size for photos of ``full`` (width, height) pixels.

    Parameters
    ----------
    full : (int, int)
        Width and height of the photos, pixels.
    ring_px : float, optional
        Long axis (pixels, full image) of the outer ring's image: how large the
        object is photographed. Unknown (None): the pixel count alone decides.
    requested : int, optional
        ``--work-size``: the long side in pixels (never more than the photo's),
        0 for full size; None for the default policy (module docstring).
    """
    W, H = int(full[0]), int(full[1])
    if W < 1 or H < 1:
        raise ValueError(f"full size must be positive, got {full}")
    long_side = max(W, H)
    if requested is not None:
        if requested == 0 or requested >= long_side:
            why = "--work-size full" if requested == 0 else f"--work-size {requested}: the photos are not larger"
            return WorkSize((W, H), (W, H), why)
        return WorkSize((W, H), _size_for_scale((W, H), requested / long_side), f"--work-size {requested}")
    pixels = W * H
    if pixels <= MAX_DEFAULT_PIXELS:
        return WorkSize((W, H), (W, H), f"default: photos of at most {MAX_DEFAULT_PIXELS / 1e6:.1f} MP are used whole")
    s = math.sqrt(MAX_DEFAULT_PIXELS / pixels)
    why = f"default: about {MAX_DEFAULT_PIXELS / 1e6:.1f} MP"
    if ring_px is not None and np.isfinite(ring_px) and ring_px * s < MIN_RING_PX:
        s = min(MIN_RING_PX / ring_px, math.sqrt(MAX_WORK_PIXELS / pixels), 1.0)
        why = (f"default: the outer ring ({ring_px:.0f} px across in the photos) kept at least {MIN_RING_PX} px "
               f"across, within {MAX_WORK_PIXELS / 1e6:.0f} MP")
    elif ring_px is not None and np.isfinite(ring_px):
        why += f" (the outer ring {ring_px * s:.0f} px across)"
    size = _size_for_scale((W, H), s)
    return WorkSize((W, H), (W, H) if size == (W, H) else size, why)
