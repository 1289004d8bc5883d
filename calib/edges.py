"""Sub-pixel edges of a dark printed stroke, searched along the normals of a conic.

Given a predicted image conic of a stroke's centre line (``x^T C x = 0``, pixels)
the stroke is looked for along the conic's outward normals: the image is sampled
on a grid ``p_k + s n_k`` (``p_k`` on the conic, ``n_k`` the unit normal
``(C x)_{1:2} / |(C x)_{1:2}|``, ``s`` the signed offset in pixels, positive
outwards), giving one grey-level profile per sample. Going outwards, a dark
stroke on white paper shows a falling edge (the inner edge, radius ``R - w/2``)
then a rising edge (the outer edge, ``R + w/2``). Each edge is located at the
extremum of the profile derivative ``dI/ds`` (the 50 % crossing of a blurred
step), refined to sub-pixel by a parabola through the three samples about the
extremum: ``delta = (d_{-1} - d_{+1}) / (2 (d_{-1} - 2 d_0 + d_{+1}))``.

A profile is kept only when it looks like the stroke: both edges strong,
white on both sides of a dark band, a band width near the expected one.
Runs of rejected profiles (the occluding object, angle marks, glare) are
widened so that edges near where the stroke meets something else are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import minimum_filter1d

from .conics import conic_to_ellipse

__all__ = ["StrokeEdges", "conic_samples", "line_conic_offsets", "sample_profiles", "find_stroke_edges"]


@dataclass(frozen=True)
class StrokeEdges:
    """Edges of one stroke found along the normals of its predicted centre line.

    Attributes
    ----------
    inner_uv_px, outer_uv_px : (M, 2) float64
        Sub-pixel points of the inner (``R - w/2``) and outer (``R + w/2``) edge,
        pixels; rows where ``ok`` is False are NaN.
    ok : (M,) bool
        The profile looked like the stroke (after widening rejected runs).
    width_px : (M,) float64
        Measured stroke width along the normal, pixels (NaN where not ok).
    """

    inner_uv_px: np.ndarray
    outer_uv_px: np.ndarray
    ok: np.ndarray
    width_px: np.ndarray


def conic_samples(C: np.ndarray, spacing_px: float, max_samples: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Points on an ellipse conic about ``spacing_px`` apart, with outward unit normals.

    Returns ``uv_px`` (M, 2) and ``normals`` (M, 2), in order around the ellipse;
    at least 120 points (or ``max_samples``), closer together on a small ellipse.
    """
    e = conic_to_ellipse(C)
    n_dense = 720
    t = np.linspace(0.0, 2.0 * np.pi, n_dense, endpoint=False)
    ca, sa = np.cos(e.angle_rad), np.sin(e.angle_rad)
    x, y = e.a * np.cos(t), e.b * np.sin(t)
    seg = np.hypot(np.diff(np.append(x, x[0])), np.diff(np.append(y, y[0])))
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    m = int(np.clip(np.ceil(arc[-1] / spacing_px), min(120, max_samples), max_samples))
    t_u = np.interp(np.linspace(0.0, arc[-1], m, endpoint=False), arc, np.append(t, 2 * np.pi))
    x, y = e.a * np.cos(t_u), e.b * np.sin(t_u)
    uv = np.column_stack([e.center_px[0] + ca * x - sa * y, e.center_px[1] + sa * x + ca * y])
    g = np.column_stack([uv, np.ones(m)]) @ C.T
    nrm = g[:, :2] / np.linalg.norm(g[:, :2], axis=1, keepdims=True)
    # outward: away from the centre
    flip = np.einsum("ij,ij->i", nrm, uv - e.center_px) < 0
    nrm[flip] *= -1.0
    return uv, nrm


def line_conic_offsets(C: np.ndarray, uv_px: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Signed offsets ``s`` (M,) where the lines ``uv + s n`` meet conic ``C``, nearest root.

    Solves ``(x + s d)^T C (x + s d) = 0`` with ``d = (n, 0)``; NaN where the line
    misses the conic.
    """
    x = np.column_stack([uv_px, np.ones(len(uv_px))])
    d = np.column_stack([normals, np.zeros(len(normals))])
    a = np.einsum("ij,jk,ik->i", d, C, d)
    b = 2.0 * np.einsum("ij,jk,ik->i", d, C, x)
    c = np.einsum("ij,jk,ik->i", x, C, x)
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        r1 = (-b + sq) / (2 * a)
        r2 = (-b - sq) / (2 * a)
    return np.where(np.abs(r1) < np.abs(r2), r1, r2)


def sample_profiles(grey: np.ndarray, uv_px: np.ndarray, normals: np.ndarray,
                    offsets_px: np.ndarray) -> np.ndarray:
    """Bilinear grey-level profiles (M, P) float32 at ``uv + s n`` for ``s`` in ``offsets_px``.

    ``grey`` is (H, W) float32; pixel centres at integer coordinates (README).
    Samples outside the image are NaN.
    """
    s = np.asarray(offsets_px, np.float32)[None, :]
    mx = (uv_px[:, 0:1] + s * normals[:, 0:1]).astype(np.float32)
    my = (uv_px[:, 1:2] + s * normals[:, 1:2]).astype(np.float32)
    prof = cv2.remap(grey, mx, my, interpolation=cv2.INTER_CUBIC,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return prof


def _parabola_peak(d: np.ndarray, k: np.ndarray) -> np.ndarray:
    rows = np.arange(len(k))
    km = np.clip(k, 1, d.shape[1] - 2)
    y0, y1, y2 = d[rows, km - 1], d[rows, km], d[rows, km + 1]
    den = y0 - 2.0 * y1 + y2
    with np.errstate(invalid="ignore", divide="ignore"):
        delta = np.where(np.abs(den) > 1e-12, 0.5 * (y0 - y2) / den, 0.0)
    return km + np.clip(delta, -0.5, 0.5)


def find_stroke_edges(grey: np.ndarray, uv_px: np.ndarray, normals: np.ndarray,
                      s_inner: np.ndarray, s_outer: np.ndarray, margin_px: np.ndarray | float,
                      *, step_px: float = 0.5, width_tol: float = 0.45,
                      gap_px: float = 3.0) -> StrokeEdges:
    """Find the two edges of a dark stroke along each normal.

    Parameters
    ----------
    grey : (H, W) float32
        Grey image (lightly smoothed), pixels.
    uv_px, normals : (M, 2) float64
        Sample points on the predicted centre line, in order around it, and their
        outward unit normals.
    s_inner, s_outer : (M,) float64
        Predicted offsets (pixels along the normal) of the inner and outer edge.
    margin_px : float or (M,)
        The search window is ``[s_inner - margin, s_outer + margin]``.
    step_px : float
        Profile sampling step, pixels.
    width_tol : float
        Accepted relative deviation of the measured width from ``s_outer - s_inner``
        (plus one pixel).
    gap_px : float
        Samples within this arc length (pixels) of a rejected one are dropped too.
    """
    m = len(uv_px)
    margin = np.broadcast_to(np.asarray(margin_px, float), (m,))
    lo_s, hi_s = s_inner - margin, s_outer + margin
    good = np.isfinite(lo_s) & np.isfinite(hi_s)
    lo_s, hi_s = np.where(good, lo_s, 0.0), np.where(good, hi_s, 0.0)
    s0 = float(np.min(lo_s)) - 2 * step_px
    p = int(np.ceil((float(np.max(hi_s)) + 2 * step_px - s0) / step_px)) + 1
    offs = s0 + step_px * np.arange(p)
    prof = sample_profiles(grey, uv_px, normals, offs)
    d = np.full_like(prof, np.nan)
    d[:, 1:-1] = (prof[:, 2:] - prof[:, :-2]) / (2.0 * step_px)
    idx = np.arange(p)[None, :]
    win = (offs[None, :] >= lo_s[:, None]) & (offs[None, :] <= hi_s[:, None])
    win[:, [0, -1]] = False
    dn = np.where(win & np.isfinite(d), d, 0.0)
    k_in = np.argmin(dn, axis=1)
    k_out = np.argmax(dn, axis=1)
    rows = np.arange(m)
    g_in, g_out = -dn[rows, k_in], dn[rows, k_out]
    # white on both sides of a dark band
    finite = np.isfinite(prof)
    pw = np.where(finite, prof, 0.0)
    inside = win & (idx <= k_in[:, None])
    outside = win & (idx >= k_out[:, None])
    band = win & (idx >= k_in[:, None]) & (idx <= k_out[:, None])
    white_in = np.max(np.where(inside, pw, -np.inf), axis=1)
    white_out = np.max(np.where(outside, pw, -np.inf), axis=1)
    dark = np.min(np.where(band, pw, np.inf), axis=1)
    c_in, c_out = white_in - dark, white_out - dark
    f_in = offs[0] + step_px * _parabola_peak(d, k_in)
    f_out = offs[0] + step_px * _parabola_peak(d, k_out)
    width = f_out - f_in
    w_pred = s_outer - s_inner
    ok = good & (k_in < k_out) & np.all(finite | ~win, axis=1)
    ok &= np.abs(width - w_pred) <= width_tol * w_pred + 1.0
    with np.errstate(invalid="ignore"):
        ok &= (c_in > 0) & (c_out > 0)
    if np.count_nonzero(ok) >= 8:
        # contrasts relative to the local paper white: a shadow across the ring keeps them
        white = np.maximum(np.maximum(white_in, white_out), 1.0)
        c_rel, g_rel = np.minimum(c_in, c_out) / white, np.minimum(g_in, g_out) / white
        ok &= (c_rel > 0.45 * np.median(c_rel[ok])) & (np.maximum(c_in, c_out) < 2.2 * np.minimum(c_in, c_out))
        if ok.any():  # none left with a paper-like contrast: no gradient to compare, nothing to keep
            ok &= (g_rel > 0.4 * np.median(g_rel[ok])) & (np.maximum(g_in, g_out) < 2.5 * np.minimum(g_in, g_out))
    ok = _widen_rejections(ok, uv_px, gap_px)
    inner = np.where(ok[:, None], uv_px + f_in[:, None] * normals, np.nan)
    outer = np.where(ok[:, None], uv_px + f_out[:, None] * normals, np.nan)
    return StrokeEdges(inner_uv_px=inner, outer_uv_px=outer, ok=ok, width_px=np.where(ok, width, np.nan))


def _widen_rejections(ok: np.ndarray, uv_px: np.ndarray, gap_px: float) -> np.ndarray:
    """Drop samples within ``gap_px`` (arc length) of a rejected one, cyclically."""
    if ok.all() or not ok.any() or gap_px <= 0:
        return ok
    spacing = float(np.median(np.linalg.norm(np.diff(uv_px, axis=0), axis=1)))
    k = int(np.ceil(gap_px / max(spacing, 1e-6)))
    return minimum_filter1d(ok.astype(np.uint8), size=2 * k + 1, mode="wrap").astype(bool)
