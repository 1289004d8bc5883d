"""Rasterising the printed target (rings only for now; angle marks: issue 3).

Image layout: a square raster centred on the pattern centre. Seen from above
(+Y towards the viewer), table +X is the raster's column direction and table +Z
its row direction (right-handed: X x Y = Z). Pixel (row i, column j) has its
centre at ``X = (j - c) / px_per_mm``, ``Z = (i - c) / px_per_mm`` with
``c = (N - 1) / 2``.
"""

from __future__ import annotations

import numpy as np

from calib.target import TargetSpec

__all__ = ["render_target_image"]


def render_target_image(spec: TargetSpec, px_per_mm: float, size_mm: float | None = None,
                        supersample: int = 4) -> np.ndarray:
    """Grey raster (N, N) uint8 of the target, white paper, black strokes.

    ``size_mm`` is the side of the square (default: outer ring + 25 mm margin
    on every side). Anti-aliased by ``supersample``² samples per pixel.
    """
    if size_mm is None:
        size_mm = 2.0 * (spec.r_outer_mm + 25.0)
    n = int(round(size_mm * px_per_mm))
    s = int(supersample)
    c = (n - 1) / 2.0
    # sample offsets inside each pixel, pixel-centre convention
    offs = (np.arange(s) + 0.5) / s - 0.5
    coords = (np.arange(n)[:, None] + offs[None, :]).ravel()  # (n*s,)
    xs = (coords - c) / px_per_mm
    X, Z = np.meshgrid(xs, xs, indexing="xy")
    r = np.hypot(X, Z)
    ink = np.zeros_like(r, dtype=bool)
    for R in (spec.r_outer_mm, spec.r_inner_mm):
        ink |= np.abs(r - R) <= spec.stroke_mm / 2.0
    white = (~ink).astype(np.float32).reshape(n, s, n, s).mean(axis=(1, 3))
    return np.round(white * 255.0).astype(np.uint8)
