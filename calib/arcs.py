"""Edge arcs and the ellipses they make up (coarse search for the rings).

Arcs: Canny edges of the log grey levels (illumination becomes an offset, so
thresholds are brightness ratios), split by the quadrant of the gradient
direction ``(sign g_u, sign g_v)`` and linked into 8-connected components. A
closed ellipse edge breaks into four arcs at its axis-aligned tangents; the two
edges of a dark stroke have opposite gradients, so they never share an arc
(and each is the other's "partner"); an edge meeting another at a right angle
(an occluder's outline) leaves the arc.

Ellipses: RANSAC over arcs. Every arc carries its scatter matrix
``S = sum_k d_k d_k^T`` with ``d = (x^2, x y, y^2, x, y, 1)`` (normalised
coordinates), so the direct least-squares ellipse fit (Fitzgibbon; Halir &
Flusser) of any union of arcs is the fit of the sum of their matrices: all
hypotheses (long single arcs, pairs of the longest arcs, chains of two or
three arcs meeting end to end) are fitted in one batch. Each hypothesis is
scored by the length of the arcs whose samples lie within a Sampson distance
``tol`` of it (arcs without a partner count less); the best is refitted on its
arcs, its arcs are removed, repeat. Last, ellipses that are pieces of one edge
(a ring an occluder cuts in two places) are fitted together where the joint fit
holds all their arcs.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import cv2
import numpy as np

__all__ = ["Arcs", "ArcEllipse", "extract_arcs", "find_ellipses", "fit_scatter", "to_pixels", "sampson_batch"]


@dataclass(frozen=True)
class Arcs:
    """Edge arcs of one image.

    Attributes
    ----------
    length : (A,) int
        Pixel count of each arc.
    scatter : (A, 6, 6) float64
        Scatter matrices of each arc's pixels in normalised coordinates
        ``x = (u - norm[0]) / norm[2]``, ``y = (v - norm[1]) / norm[2]``.
    samples_px : (A, Q, 2) float64
        Q pixels of each arc (pixels), spread along it.
    ends_px : (A, 2, 2) float64
        The two end pixels of each arc (extremes along its principal axis).
    quadrant : (A,) int
        Gradient quadrant of the arc in angular order: 0 for ``(g_u, g_v)``
        signs ``(+, +)``, 1 ``(-, +)``, 2 ``(-, -)``, 3 ``(+, -)``.
    partnered : (A,) bool
        An edge of opposite gradient runs alongside (within ``partner_px``): the
        arc is likely one side of a thin stroke (or band), not a lone outline.
    norm : (3,) float64
        ``(u0, v0, scale)`` of the normalisation.
    """

    length: np.ndarray
    scatter: np.ndarray
    samples_px: np.ndarray
    ends_px: np.ndarray
    quadrant: np.ndarray
    partnered: np.ndarray
    norm: np.ndarray


@dataclass(frozen=True)
class ArcEllipse:
    """An ellipse supported by arcs: conic (pixels), its arcs, and coverage.

    ``coverage`` is the supporting arcs' pixel count over the ellipse perimeter.
    """

    conic: np.ndarray
    arc_ids: np.ndarray
    support_px: float
    coverage: float


#: Grey level -> 255 ln((i + LOG_OFFSET) / LOG_OFFSET) / ln((255 + LOG_OFFSET) / LOG_OFFSET).
LOG_OFFSET = 8.0
_LOG_SCALE = 255.0 / np.log((255.0 + LOG_OFFSET) / LOG_OFFSET)
_LOG_LUT = np.round(_LOG_SCALE * np.log((np.arange(256) + LOG_OFFSET) / LOG_OFFSET)).astype(np.uint8)


def extract_arcs(grey: np.ndarray, *, min_length: int = 12, samples: int = 6,
                 low_ratio: float = 1.3, high_ratio: float = 1.8, partner_px: float = 10.0) -> Arcs:
    """Arcs of the Canny edges of ``grey`` (H, W) uint8.

    Edges are found on the logarithm of the grey level, where a change of
    illumination (dim light, a bright window elsewhere, uneven light) is an
    offset, so the Canny thresholds are brightness ratios across the edge:
    ``high_ratio`` starts an edge, ``low_ratio`` continues it (black ink on
    white paper is a ratio of 3 or more).
    """
    h, w = grey.shape
    g = cv2.GaussianBlur(cv2.LUT(grey, _LOG_LUT), (0, 0), 1.0)
    gx = cv2.Sobel(g, cv2.CV_16S, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_16S, 0, 1, ksize=3)
    gain = 3.0  # Sobel 3x3 peak response per grey level of a sigma-1 blurred step
    lo, hi = (gain * _LOG_SCALE * np.log(r) for r in (low_ratio, high_ratio))
    edges = cv2.Canny(gx, gy, lo, hi, L2gradient=True)
    vs, us = np.nonzero(edges)
    gxe, gye = gx[vs, us], gy[vs, us]
    # gradient quadrant in angular order: 0 (+,+), 1 (-,+), 2 (-,-), 3 (+,-)
    quad = np.where(gxe >= 0, np.where(gye >= 0, 0, 3), np.where(gye >= 0, 1, 2))
    lab = np.empty(len(vs), np.int64)
    n_total = 0
    quads = []
    near = []  # pixels within partner_px (Chebyshev) of an edge pixel of each quadrant
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * int(partner_px) + 1, 2 * int(partner_px) + 1))
    for q in range(4):
        sel = quad == q
        m = np.zeros((h, w), np.uint8)
        m[vs[sel], us[sel]] = 1
        near.append(cv2.dilate(m, kernel))
        n, labels = cv2.connectedComponents(m, connectivity=8, ltype=cv2.CV_32S)
        lab[sel] = labels[vs[sel], us[sel]] - 1 + n_total
        n_total += n - 1
        quads.append(np.full(n - 1, q))
    counts = np.bincount(lab, minlength=n_total)
    keep = counts >= min_length
    remap = -np.ones(n_total, np.int64)
    remap[keep] = np.arange(np.count_nonzero(keep))
    lab = remap[lab]
    sel = lab >= 0
    us, vs, lab = us[sel].astype(np.float64), vs[sel].astype(np.float64), lab[sel]
    n_arcs = int(np.count_nonzero(keep))
    norm = np.array([(w - 1) / 2.0, (h - 1) / 2.0, max(w, h) / 2.0])
    x, y = (us - norm[0]) / norm[2], (vs - norm[1]) / norm[2]
    scatter = _scatter(x, y, lab, n_arcs)
    order = np.argsort(lab, kind="stable")
    length = np.bincount(lab, minlength=n_arcs)
    starts = np.concatenate([[0], np.cumsum(length)[:-1]])
    pick = starts[:, None] + (np.arange(samples)[None, :] * length[:, None]) // samples
    pts = np.column_stack([us, vs])[order]
    samples_px = pts[pick] if n_arcs else np.zeros((0, samples, 2))
    ends_px = _ends(pts, lab[order], length, starts)
    quadrant = np.concatenate(quads)[keep]
    si = np.clip(np.round(samples_px).astype(np.int64), 0, [w - 1, h - 1]).reshape(-1, 2)
    # is there an edge pixel of opposite gradient near each arc sample?
    opp = np.stack([near[(q + 2) % 4][si[:, 1], si[:, 0]] for q in range(4)]).reshape(4, n_arcs, samples)
    partnered = np.mean(opp[quadrant, np.arange(n_arcs)] > 0, axis=1) >= 0.5
    return Arcs(length=length, scatter=scatter, samples_px=samples_px, ends_px=ends_px, quadrant=quadrant,
                partnered=partnered, norm=norm)


def _ends(pts: np.ndarray, lab: np.ndarray, length: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """End pixels (A, 2, 2) of arcs whose pixels ``pts`` are grouped by label ``lab``."""
    n = len(length)
    if n == 0:
        return np.zeros((0, 2, 2))
    mean = np.stack([np.bincount(lab, pts[:, k], n) for k in (0, 1)], 1) / length[:, None]
    d = pts - mean[lab]
    sxx = np.bincount(lab, d[:, 0] ** 2, n)
    sxy = np.bincount(lab, d[:, 0] * d[:, 1], n)
    syy = np.bincount(lab, d[:, 1] ** 2, n)
    ang = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # principal axis
    proj = d[:, 0] * np.cos(ang)[lab] + d[:, 1] * np.sin(ang)[lab]
    key_max = np.lexsort((proj, lab))  # sorted by label, then projection
    first = key_max[starts]
    last = key_max[starts + length - 1]
    return np.stack([pts[first], pts[last]], axis=1)


def _scatter(x: np.ndarray, y: np.ndarray, lab: np.ndarray, n: int) -> np.ndarray:
    """Per-label scatter matrices (n, 6, 6) of ``d = (x^2, xy, y^2, x, y, 1)``."""
    mon = {}
    for i in range(5):
        for j in range(5 - i):
            if i + j <= 4:
                mon[(i, j)] = np.bincount(lab, weights=x**i * y**j, minlength=n)
    powers = [(2, 0), (1, 1), (0, 2), (1, 0), (0, 1), (0, 0)]
    S = np.empty((n, 6, 6))
    for a, pa in enumerate(powers):
        for b, pb in enumerate(powers):
            S[:, a, b] = mon[(pa[0] + pb[0], pa[1] + pb[1])]
    return S


def fit_scatter(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched ellipse-specific direct fit from scatter matrices (B, 6, 6).

    Returns conics (B, 3, 3) in the normalised coordinates and a validity flag (B,).
    """
    S1, S2, S3 = S[:, :3, :3], S[:, :3, 3:], S[:, 3:, 3:]
    ok = np.abs(np.linalg.det(S3)) > 1e-14 * np.maximum(np.abs(S3[:, 2, 2]) ** 3, 1e-300)
    S3s = np.where(ok[:, None, None], S3, np.eye(3)[None])
    Tm = -np.linalg.solve(S3s, np.transpose(S2, (0, 2, 1)))
    M = S1 + S2 @ Tm
    M = np.stack([M[:, 2] / 2.0, -M[:, 1], M[:, 0] / 2.0], axis=1)
    M = np.where(np.isfinite(M), M, 0.0)
    w_, V = np.linalg.eig(M)
    V, w_ = np.real(V), np.real(w_)
    cond = 4 * V[:, 0, :] * V[:, 2, :] - V[:, 1, :] ** 2  # (B, 3)
    score = np.where(cond > 0, np.abs(w_), np.inf)
    k = np.argmin(score, axis=1)
    ok &= np.isfinite(score[np.arange(len(k)), k])
    a1 = V[np.arange(len(k)), :, k]  # (B, 3)
    a2 = np.einsum("bij,bj->bi", Tm, a1)
    A, B, C = a1[:, 0], a1[:, 1], a1[:, 2]
    D, E, F = a2[:, 0], a2[:, 1], a2[:, 2]
    Q = np.stack([np.stack([A, B / 2, D / 2], -1), np.stack([B / 2, C, E / 2], -1),
                  np.stack([D / 2, E / 2, F], -1)], axis=1)
    Q /= np.linalg.norm(Q, axis=(1, 2), keepdims=True) + 1e-300
    Q *= np.where(Q[:, 0, 0] + Q[:, 1, 1] < 0, -1.0, 1.0)[:, None, None]
    return Q, ok


def to_pixels(Q: np.ndarray, norm: np.ndarray) -> np.ndarray:
    """Conics in normalised coordinates (..., 3, 3) to pixel conics."""
    N = np.array([[1 / norm[2], 0, -norm[0] / norm[2]], [0, 1 / norm[2], -norm[1] / norm[2]], [0, 0, 1.0]])
    C = N.T @ Q @ N
    return C / np.linalg.norm(C, axis=(-2, -1), keepdims=True)


def _axes(C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Semi-axes (a >= b) of pixel conics (B, 3, 3); NaN where not an ellipse."""
    A2 = C[:, :2, :2]
    det2 = np.linalg.det(A2)
    ok = det2 > 0
    c = np.linalg.solve(np.where(ok[:, None, None], A2, np.eye(2)[None]), -C[:, :2, 2:3])[..., 0]
    xc = np.concatenate([c, np.ones((len(c), 1))], axis=1)
    k = -np.einsum("bi,bij,bj->b", xc, C, xc)
    ok &= k > 0
    ev = np.linalg.eigvalsh(A2)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.sqrt(k / ev[:, 0])
        b = np.sqrt(k / ev[:, 1])
    a = np.where(ok & (ev[:, 0] > 0), a, np.nan)
    b = np.where(ok & (ev[:, 0] > 0), b, np.nan)
    return a, b, c


def sampson_batch(C: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """|Sampson distance| (B, N), pixels, of points (N, 2) to conics (B, 3, 3)."""
    u, v = uv_px[:, 0], uv_px[:, 1]
    one = np.ones_like(u)
    mono = np.column_stack([u * u, 2 * u * v, v * v, 2 * u, 2 * v, one])  # (N, 6)
    coef = np.stack([C[:, 0, 0], C[:, 0, 1], C[:, 1, 1], C[:, 0, 2], C[:, 1, 2], C[:, 2, 2]])  # (6, B)
    num = mono @ coef
    X = np.column_stack([u, v, one])
    gu = X @ C[:, 0, :].T
    gv = X @ C[:, 1, :].T
    return (np.abs(num) / np.maximum(2.0 * np.hypot(gu, gv), 1e-300)).T


def find_ellipses(arcs: Arcs, image_size: tuple[int, int], *, tol_px: float = 1.5,
                  n_seeds: int = 8, n_eval: int = 80, max_ellipses: int = 12,
                  min_coverage: float = 0.2, min_axis_px: float = 4.0,
                  min_aspect: float = 0.08, gap_px: float = 5.0, lone_weight: float = 0.3) -> list[ArcEllipse]:
    """Ellipses made of several arcs, best supported first (RANSAC over arcs).

    Hypotheses are the fits of each of the ``n_eval`` longest curved arcs, of
    each pair of the ``n_seeds`` longest, and of chains of two or three arcs
    whose ends are within ``gap_px`` (an ellipse edge breaks into arcs at its
    axis-aligned tangents); the ``n_eval`` arcs vote. An arc supports a conic when
    80 % of its samples lie within ``tol_px`` (Sampson); arcs without a partner
    (see :class:`Arcs`) count ``lone_weight`` of their length. An ellipse is kept when
    at least two arcs covering ``min_coverage`` of its perimeter support it.
    """
    w, h = image_size
    n_arcs = len(arcs.length)
    if n_arcs < 2:
        return []
    curved = _curvature(arcs.scatter) > 0.03
    order = np.argsort(-np.where(curved, arcs.length, 0), kind="stable")[: np.count_nonzero(curved)]
    if len(order) < 2:
        return []
    ev = order[:n_eval]
    seeds = order[:n_seeds]
    i, j = np.triu_indices(len(seeds), k=1)
    ai, aj, ti, tk, tj = _adjacent(arcs.ends_px[ev], arcs.quadrant[ev], gap_px)
    sc = arcs.scatter[ev]
    S = np.concatenate([arcs.scatter[seeds], arcs.scatter[seeds[i]] + arcs.scatter[seeds[j]], sc[ai] + sc[aj],
                        sc[ti] + sc[tj] + sc[tk]])
    Q, ok = fit_scatter(S)
    C = to_pixels(Q[ok], arcs.norm)
    C = C[_plausible(C, w, h, min_axis_px, min_aspect)]
    if len(C) == 0:
        return []
    support = _support(C, arcs, ev, tol_px)  # (H, E) bool
    weight = arcs.length * np.where(arcs.partnered, 1.0, lone_weight)
    lengths = weight[ev]
    avail = np.ones(len(ev), bool)
    found: list[ArcEllipse] = []
    for _ in range(4 * max_ellipses):
        score = support.astype(np.float64) @ (lengths * avail)
        score[(support.astype(np.int32) @ avail.astype(np.int32)) < 2] = 0.0
        best = int(np.argmax(score))
        if score[best] <= 0:
            break
        members = support[best] & avail
        conic = C[best]
        refit = _fit_arcs(arcs, ev[members], w, h, min_axis_px, min_aspect)  # on the supporting arcs
        if refit is not None:  # collect again
            conic = refit
            members = _support(refit[None], arcs, ev, tol_px)[0] & avail
        cov = _coverage(conic, float(lengths[members].sum()))
        if np.count_nonzero(members) >= 2 and cov >= min_coverage:
            found.append(ArcEllipse(conic=conic, arc_ids=ev[members], support_px=float(lengths[members].sum()),
                                    coverage=cov))
            avail &= ~(members | support[best])
        else:
            support[best] = False
        if not avail.any() or len(found) == max_ellipses:
            break
    return _join_fragments(found, arcs, weight, (w, h), tol_px, min_axis_px, min_aspect)


def _fit_arcs(arcs: Arcs, ids: np.ndarray, w: int, h: int, min_axis_px: float,
              min_aspect: float) -> np.ndarray | None:
    """The ellipse (pixel conic) fitted to the arcs ``ids`` together, or None where it is not a plausible one."""
    Q, ok = fit_scatter(arcs.scatter[ids].sum(axis=0)[None])
    if not ok[0]:
        return None
    C = to_pixels(Q, arcs.norm)
    return C[0] if _plausible(C, w, h, min_axis_px, min_aspect)[0] else None


def _coverage(conic: np.ndarray, support_px: float) -> float:
    """``support_px`` over the ellipse's perimeter (Ramanujan's approximation); 0 where it has none."""
    a, b, _ = _axes(conic[None])
    perimeter = np.pi * (3 * (a[0] + b[0]) - np.sqrt((3 * a[0] + b[0]) * (a[0] + 3 * b[0])))
    return float(support_px / perimeter) if np.isfinite(perimeter) else 0.0


def _join_fragments(found: list[ArcEllipse], arcs: Arcs, weight: np.ndarray, size: tuple[int, int],
                    tol_px: float, min_axis_px: float, min_aspect: float) -> list[ArcEllipse]:
    """Ellipses that are pieces of one edge, fitted together.

    An occluder crossing a ring in two places (a chair's legs, seen from low
    down) leaves two pieces of it whose arcs no hypothesis spans (they are not
    chained end to end, and often not among the longest arcs): each piece is
    then fitted alone, short and off (a ring with a 64-70 px semi-axis for
    85 px, its centre 16 to 23 px aside, too far off to tell by size or
    centre). Two found ellipses are replaced by the fit of their arcs
    together when that fit keeps 90 % of their arcs' weight within
    ``tol_px`` (the two edges of one stroke, a few pixels apart, never do);
    repeated while any pair joins, the best-supported join first.
    """
    w, h = size
    found = list(found)
    while len(found) >= 2:
        best = None
        for p, q in combinations(range(len(found)), 2):
            ids = np.union1d(found[p].arc_ids, found[q].arc_ids)
            C = _fit_arcs(arcs, ids, w, h, min_axis_px, min_aspect)
            if C is None:
                continue
            held = _support(C[None], arcs, ids, tol_px)[0]
            total = float(weight[ids].sum())
            if weight[ids][held].sum() >= 0.9 * total and (best is None or total > best[0]):
                best = (total, p, q, C, ids)
        if best is None:
            break
        total, p, q, C, ids = best
        joined = ArcEllipse(conic=C, arc_ids=ids, support_px=total, coverage=_coverage(C, total))
        found = sorted([e for k, e in enumerate(found) if k not in (p, q)] + [joined], key=lambda e: -e.support_px)
    return found


def _adjacent(ends: np.ndarray, quadrant: np.ndarray, gap_px: float):
    """Index pairs (i, j) and triples (i, k, j) (k in the middle) of arcs chained end to end.

    Arcs are chained when an end of one lies within ``gap_px`` of an end of the other.

    Chained arcs of one ellipse edge have gradients in neighbouring quadrants.
    """
    n = len(ends)
    e = ends.reshape(-1, 2)
    d = np.linalg.norm(e[:, None, :] - e[None, :, :], axis=2).reshape(n, 2, n, 2).min(axis=(1, 3))
    dq = (quadrant[:, None] - quadrant[None, :]) % 4
    adj = (d < gap_px) & ((dq == 1) | (dq == 3))
    ai, aj = np.nonzero(np.triu(adj, 1))
    # triples: k in the middle, two distinct neighbours i < j
    triples = [(i, k, j) for k in np.flatnonzero(adj.sum(axis=1) >= 2)
               for i, j in combinations(np.flatnonzero(adj[k]), 2)]
    ti, tk, tj = np.array(triples, dtype=np.int64).reshape(-1, 3).T
    return ai, aj, ti, tk, tj


def _curvature(S: np.ndarray) -> np.ndarray:
    """sqrt(minor / major) eigenvalue of each arc's point covariance (A,): 0 for a straight arc."""
    n = S[:, 5, 5]
    mx, my = S[:, 3, 5] / n, S[:, 4, 5] / n
    sxx, sxy, syy = S[:, 0, 5] / n - mx * mx, S[:, 1, 5] / n - mx * my, S[:, 2, 5] / n - my * my
    tr, det = sxx + syy, sxx * syy - sxy * sxy
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0.0))
    lo, hi = tr / 2 - disc, tr / 2 + disc
    return np.sqrt(np.maximum(lo, 0.0) / np.maximum(hi, 1e-300))


def _plausible(C: np.ndarray, w: int, h: int, min_axis_px: float, min_aspect: float) -> np.ndarray:
    a, b, c = _axes(C)
    diag = np.hypot(w, h)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(a) & (b >= min_axis_px) & (a <= 1.5 * diag) & (b >= min_aspect * a)
        ok &= (c[:, 0] > -0.5 * w) & (c[:, 0] < 1.5 * w) & (c[:, 1] > -0.5 * h) & (c[:, 1] < 1.5 * h)
    return ok


def _support(C: np.ndarray, arcs: Arcs, ev: np.ndarray, tol_px: float) -> np.ndarray:
    q = arcs.samples_px.shape[1]
    d = sampson_batch(C, arcs.samples_px[ev].reshape(-1, 2)).reshape(len(C), len(ev), q)
    return np.mean(d < tol_px, axis=2) >= 0.8
