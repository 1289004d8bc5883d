"""Detect the printed two-ring target in a photo: sub-pixel edges of both strokes.

Pipeline (``detect_rings``):

1. Coarse search on the image area-downsampled to about 640 px: Canny arcs,
   RANSAC over arcs into ellipses (``calib.arcs``); if that finds no target,
   again at full resolution (a target too small for the coarse image).
2. Strokes: ellipses that are the two edges of one printed stroke (concentric,
   radius ratio near 1) are merged; each remaining ellipse is a ring candidate.
3. Pairs: two candidates whose conics ``C_o``, ``C_i`` may belong to concentric
   circles with the target's radius ratio (loose tolerances: the coarse fits of
   occluded, foreshortened rings are rough). For concentric circles the pencil
   ``inv(C_i) C_o`` has eigenvalues ``(s, s, s (R_o / R_i)^2)``: the split of the
   double eigenvalue measures non-concentricity (its square root grows about
   like centre offset / radius), the distinct / double ratio is the squared
   radius ratio, both projectively (no camera needed).
4. Fine search at full resolution along the normals of each ring's conic
   (``calib.edges``), twice: first from the coarse conic, the stroke's
   half-width predicted as ``(w/2) / R`` of the distance to the ellipse centre,
   then from the edge conics fitted to the first pass. Robust conic fits drop
   far outliers (Sampson > 3 px). The best pairs are tried in turn; the refined
   centre-line conics must pass the pencil tests with tight tolerances.
   The first pass runs on the crop area-reduced ``q`` times when the outer ring
   is large (semi-major axis ``a`` >= ``PASS1_RING_PX``, ``q = floor(a / PASS1_RING_PX)``:
   12-48 MP photos), so its search windows, gaps and blur, tuned on rings a few
   hundred pixels across, keep their meaning; the second pass is always at full
   resolution. Below that size (1280x960 photos) nothing changes.

:func:`edge_conic` predicts the conic of any radius ``r`` from the two
centre-line conics scaled alike (``C_o / s``):
``C(r) = a C_o / s + (1 - a) C_i`` with ``a = (r^2 - R_i^2) / (R_o^2 - R_i^2)``.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from .arcs import extract_arcs, find_ellipses
from .conics import conic_center, conic_to_ellipse, fit_conic, normalize_conic, sampson_distance
from .edges import conic_samples, find_stroke_edges, line_conic_offsets
from .target import TargetSpec
from .types import CalibrationError, EdgePoints, RingConics, TargetObservation

__all__ = ["detect_rings", "detect_rings_near", "pencil_ratio", "edge_conic", "grey_image", "coarse_ellipses",
           "COARSE_SIZE_PX"]

log = logging.getLogger(__name__)

COARSE_SIZE_PX = 640        # long side of the coarse search image
COARSE_CONCENTRIC_TOL = 0.45  # coarse pairs: max sqrt of the pencil's relative eigenvalue split
COARSE_RATIO_TOL = 0.12     # coarse pairs: relative tolerance on the radius ratio (plus the stroke)
CONCENTRIC_TOL = 0.1        # refined pair: max sqrt split (about centre offset / inner radius)
RATIO_TOL = 0.005           # refined pair: relative tolerance on the radius ratio (see below)
MAX_PAIRS = 3               # coarse pairs tried at full resolution, best first
MAX_OUTLIER_PX = 3.0        # Sampson distance beyond which an edge point is dropped
MIN_EDGE_POINTS = 30
PASS1_RING_PX = 640         # fine pass 1 runs on the crop reduced q = floor(a_outer / this) times


def pencil_ratio(C_big: np.ndarray, C_small: np.ndarray) -> tuple[float, float, float]:
    """Concentricity and radius ratio of two image conics of coplanar circles.

    Returns ``(split, ratio, s)``: ``split`` is the relative gap of the closest
    pair of eigenvalues of ``inv(C_small) C_big`` (0 for concentric circles),
    ``ratio`` the square root of distinct / double eigenvalue (the radius ratio
    ``R_big / R_small``), ``s`` the double eigenvalue (the relative scale of the
    two conics).
    """
    ev = np.linalg.eigvals(np.linalg.solve(C_small, C_big))
    pairs = [(0, 1, 2), (0, 2, 1), (1, 2, 0)]
    gaps = [abs(ev[i] - ev[j]) / max(abs(ev[i]), abs(ev[j]), 1e-300) for i, j, _ in pairs]
    i, j, k = pairs[int(np.argmin(gaps))]
    s = 0.5 * (ev[i] + ev[j])
    ratio = float(np.sqrt(abs(ev[k] / s))) if abs(s) > 0 else float("inf")
    return float(min(gaps)), ratio, float(np.real(s))


def edge_conic(C_outer: np.ndarray, C_inner: np.ndarray, spec: TargetSpec, radius_mm: float) -> np.ndarray:
    """Predicted image conic of the table circle of ``radius_mm`` (normalised).

    ``C_outer``/``C_inner`` are the centre-line conics of the rings of radii
    ``spec.r_outer_mm``/``spec.r_inner_mm`` (module docstring).
    """
    _, _, s = pencil_ratio(C_outer, C_inner)
    ro2, ri2 = spec.r_outer_mm ** 2, spec.r_inner_mm ** 2
    a = (radius_mm ** 2 - ri2) / (ro2 - ri2)
    return normalize_conic(a * C_outer / s + (1.0 - a) * C_inner)


def grey_image(image) -> np.ndarray:
    """A uint8 image (H, W) or BGR (H, W, 3) as one contiguous grey (H, W) uint8 array; ValueError otherwise."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"image: expected uint8, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim == 2:
        return np.ascontiguousarray(img)
    raise ValueError(f"image: expected (H, W) or (H, W, 3), got {img.shape}")


def coarse_ellipses(grey: np.ndarray, f: int) -> tuple[list[np.ndarray], list[float]]:
    """Ellipse conics (full-resolution pixels) found on ``grey`` downsampled ``f`` times, and their support."""
    h, w = grey.shape
    if f > 1:
        small = cv2.resize(grey[: h // f * f, : w // f * f], (w // f, h // f), interpolation=cv2.INTER_AREA)
    else:
        small = grey
    arcs = extract_arcs(small)
    ells = find_ellipses(arcs, (small.shape[1], small.shape[0]))
    # small pixel centre i <-> full f i + (f - 1) / 2
    A = np.array([[1.0 / f, 0, -(f - 1) / (2.0 * f)], [0, 1.0 / f, -(f - 1) / (2.0 * f)], [0, 0, 1.0]])
    return [normalize_conic(A.T @ e.conic @ A) for e in ells], [e.support_px * f for e in ells]


def _strokes(conics: list[np.ndarray], support: list[float], spec: TargetSpec) -> list[tuple[np.ndarray, float]]:
    """Merge ellipses that are the two edges of one stroke; (conic, support) per stroke."""
    same_max = (spec.r_inner_mm + spec.stroke_mm / 2) / (spec.r_inner_mm - spec.stroke_mm / 2)
    same_max = 1.0 + 1.5 * (same_max - 1.0) + 0.01
    order = np.argsort(support)[::-1]
    out: list[list] = []
    for k in order:
        C = conics[k]
        e = conic_to_ellipse(C)
        for group in out:
            g = group[0]
            near = np.linalg.norm(e.center_px - g.center_px) <= 1.0 + 0.1 * min(e.b, g.b)
            if near and max(e.a, g.a) / min(e.a, g.a) < same_max and max(e.b, g.b) / min(e.b, g.b) < same_max:
                group[1].append((C, support[k]))
                break
        else:
            out.append([e, [(C, support[k])]])
    merged = []
    for _, members in out:
        wsum = sum(s for _, s in members)
        C = sum(s * normalize_conic(c) for c, s in members) / wsum
        merged.append((normalize_conic(C), wsum))
    return merged


def _centre_distance(C1: np.ndarray, C2: np.ndarray) -> float:
    return float(np.linalg.norm(conic_center(C1) - conic_center(C2)))


def _candidate_pairs(rings: list[tuple[np.ndarray, float]], spec: TargetSpec) -> list[tuple[np.ndarray, np.ndarray]]:
    """(outer, inner) conic pairs that may be the target, best supported first.

    Raises CalibrationError saying why no pair of ellipses can be the target.
    """
    if not rings:
        raise CalibrationError("no ring found")
    if len(rings) == 1:
        c = conic_center(rings[0][0])
        raise CalibrationError(f"inner ring not found: only one ring-like ellipse, centre ({c[0]:.0f}, {c[1]:.0f}) px")
    hw = spec.stroke_mm / 2
    r_lo = (spec.r_outer_mm - hw) / (spec.r_inner_mm + hw) * (1 - COARSE_RATIO_TOL)
    r_hi = (spec.r_outer_mm + hw) / (spec.r_inner_mm - hw) * (1 + COARSE_RATIO_TOL)
    good, concentric, strongest = [], None, None
    ells = [conic_to_ellipse(C) for C, _ in rings]
    for i in range(len(rings)):
        for j in range(i + 1, len(rings)):
            (Ci, si), (Cj, sj) = rings[i], rings[j]
            big, small = (Ci, Cj) if ells[i].a * ells[i].b >= ells[j].a * ells[j].b else (Cj, Ci)
            split, ratio, _ = pencil_ratio(big, small)
            score = si + sj
            if strongest is None or score > strongest[0]:
                strongest = (score, float(np.linalg.norm(ells[i].center_px - ells[j].center_px)))
            if np.sqrt(split) >= COARSE_CONCENTRIC_TOL:
                continue
            if concentric is None or score > concentric[0]:
                concentric = (score, ratio)
            if r_lo <= ratio <= r_hi:
                good.append((score, big, small))
    if good:
        good.sort(key=lambda g: -g[0])
        return [(g[1], g[2]) for g in good[:MAX_PAIRS]]
    if concentric is not None:
        raise CalibrationError(f"radius ratio {concentric[1]:.2f} does not match the target's {spec.radius_ratio:.2f}")
    assert strongest is not None  # two rings or more: the loop above ran
    raise CalibrationError(f"rings not concentric (centres {strongest[1]:.0f} px apart)")


def _robust_fit(uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Conic of ``uv_px`` (N, 2) refitted without outliers; (conic, inlier mask)."""
    keep = np.ones(len(uv_px), bool)
    C = fit_conic(uv_px)
    for _ in range(3):
        d = np.abs(sampson_distance(C, uv_px))
        sigma = 1.4826 * float(np.median(d[keep]))
        thr = min(MAX_OUTLIER_PX, max(4.0 * sigma, 0.5))
        new = d < thr
        if new.sum() < 5:
            break
        if np.array_equal(new, keep):
            keep = new
            break
        keep = new
        C = fit_conic(uv_px[keep])
    return C, keep


def _search_pencil(gf, C_mid, C_in, C_out, margin_px, gap_px, spacing_px):
    """Stroke edges along the normals of ``C_mid``, edges predicted by the conics ``C_in``, ``C_out``."""
    uv, nrm = conic_samples(C_mid, spacing_px=spacing_px, max_samples=2000)
    s_in = line_conic_offsets(C_in, uv, nrm)
    s_out = line_conic_offsets(C_out, uv, nrm)
    return find_stroke_edges(gf, uv, nrm, s_in, s_out, margin_px, gap_px=gap_px)


def _search_scaled(gf, C_mid, half_width_rel, spacing_px):
    """Stroke edges along the normals of ``C_mid``, half-width ``half_width_rel`` of the radius.

    The predicted half-width at a sample ``p`` with normal ``n`` is
    ``half_width_rel * n . (p - c)`` (``c`` the ellipse centre): exact for a
    fronto-parallel circle, close enough to open the search window otherwise.
    """
    uv, nrm = conic_samples(C_mid, spacing_px=spacing_px, max_samples=2000)
    c = conic_center(C_mid)
    hw = half_width_rel * np.einsum("ij,ij->i", nrm, uv - c)
    hw_med = float(np.median(hw))
    return find_stroke_edges(gf, uv, nrm, -hw, hw, 2.5 + hw_med, gap_px=2.0 + 2.0 * hw_med)


def _fit_ring(found, name: str):
    """Robust conics of a stroke's two edges and of its centre line (midpoints)."""
    ok = found.ok
    if np.count_nonzero(ok) < MIN_EDGE_POINTS:
        raise CalibrationError(f"{name} ring not found: only {np.count_nonzero(ok)} stroke profiles")
    try:
        C_in, k_in = _robust_fit(found.inner_uv_px[ok])
        C_out, k_out = _robust_fit(found.outer_uv_px[ok])
        mid = 0.5 * (found.inner_uv_px[ok] + found.outer_uv_px[ok])
        C_mid, _ = _robust_fit(mid[k_in & k_out])
    except ValueError as exc:
        raise CalibrationError(f"{name} ring not found: {exc}") from exc
    return C_in, C_out, C_mid, found.inner_uv_px[ok][k_in], found.outer_uv_px[ok][k_out]


def detect_rings(image, spec: TargetSpec, *, principal_point_px=None,
                 edge_spacing_px: float = 2.0, gamma: float = 2.2) -> TargetObservation:
    """Find the two printed rings and return sub-pixel points on both edges of each.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
        Grey or BGR photo (as ``cv2.imread`` gives).
    spec : TargetSpec
        Radii and stroke width of the printed target, mm.
    principal_point_px : (2,) array_like, optional
        Not needed by the detector (the pencil tests are projective); accepted so
        that callers can pass their intrinsics uniformly.
    edge_spacing_px : float
        Spacing of the returned edge points along each edge, pixels (one point
        per normal profile); larger values return fewer points (faster
        refinement), smaller ones more.
    gamma : float
        Encoding gamma of the grey levels (2.2: sRGB-like, as cameras and the
        project's renderer write; 1.0: linear data). Edges are located in
        linear light.

    Returns
    -------
    TargetObservation
        ``edges``: four ``EdgePoints`` (outer ring side +1 and -1, inner ring
        side +1 and -1), points in pixels, outliers removed; ``conics``: the
        rings' normalised pixel conics (:class:`calib.types.RingConics`: centre
        lines and both edges of each stroke).

    Raises
    ------
    CalibrationError
        "no ring found", "inner ring not found ...", "rings not concentric
        (centres N px apart)", "radius ratio X does not match the target's Y", ...
    ValueError
        For an image that is not uint8 (H, W) or (H, W, 3).
    """
    grey = grey_image(image)
    _check_search(edge_spacing_px, gamma)
    h, w = grey.shape
    f = max(1, int(round(max(h, w) / COARSE_SIZE_PX)))
    first_error, seen = None, []
    for factor in dict.fromkeys((f, 1)):  # full resolution again for a target too small to see at f
        try:
            conics, support = coarse_ellipses(grey, factor)
            rings = _strokes(conics, support, spec)
            seen.append(rings)
            pairs = _candidate_pairs(rings, spec)
        except CalibrationError as exc:
            first_error = first_error or exc
            continue
        for Co, Ci in pairs:
            try:
                return _fine(grey, Co, Ci, spec, edge_spacing_px, gamma)
            except CalibrationError as exc:
                first_error = first_error or exc
    hint = next((h for h in (_ratio_hint(r, spec) for r in seen) if h), "")  # only when failing
    if hint and "ratio" not in str(first_error):
        raise CalibrationError(f"{first_error} ({hint})")
    assert first_error is not None  # every factor either returned or failed with a CalibrationError
    raise first_error


def detect_rings_near(image, spec: TargetSpec, C_outer: np.ndarray, C_inner: np.ndarray, *,
                      edge_spacing_px: float = 2.0, gamma: float = 2.2) -> TargetObservation:
    """The rings' edges searched where they are expected: around the centre-line conics ``C_outer``,
    ``C_inner`` (pixels; e.g. where the other frames of a turntable sequence put them).

    For a frame in which the coarse search (``detect_rings``, step 1) failed,
    typically because the object hides much of the inner ring. The fine search
    and the pencil tests are ``detect_rings``'s (steps 4), so a wrong prediction
    or a target that is not there raises ``CalibrationError`` as it does.
    """
    grey = grey_image(image)
    _check_search(edge_spacing_px, gamma)
    return _fine(grey, normalize_conic(np.asarray(C_outer, float)), normalize_conic(np.asarray(C_inner, float)),
                 spec, edge_spacing_px, gamma)


def _check_search(edge_spacing_px: float, gamma: float) -> None:
    """``detect_rings``' and ``detect_rings_near``'s checks of their search settings (ValueError)."""
    if not edge_spacing_px > 0:
        raise ValueError(f"edge_spacing_px must be positive, got {edge_spacing_px}")
    if not 0.2 <= gamma <= 5.0:
        raise ValueError(f"gamma must be between 0.2 and 5, got {gamma}")


def _ratio_hint(rings: list[tuple[np.ndarray, float]], spec: TargetSpec) -> str:
    """A note for the error message: the radius ratios of the concentric stroke
    pairs the image does show, when none is near the target's (wrong radii given)."""
    top = sorted(rings, key=lambda r: -r[1])[:4]
    ells = [conic_to_ellipse(C) for C, _ in top]
    ratios = []
    for i in range(len(top)):
        for j in range(i + 1, len(top)):
            big, small = (i, j) if ells[i].a * ells[i].b >= ells[j].a * ells[j].b else (j, i)
            split, ratio, _ = pencil_ratio(top[big][0], top[small][0])
            if np.sqrt(split) < COARSE_CONCENTRIC_TOL:
                ratios.append(ratio)
    if not ratios or min(abs(r / spec.radius_ratio - 1.0) for r in ratios) < 0.03:
        return ""
    seen = ", ".join(f"{r:.2f}" for r in sorted(set(np.round(ratios, 2))))
    return (f"concentric rings in the image have radius ratios {seen}; --r-outer/--r-inner give "
            f"{spec.radius_ratio:.2f}: check the radii printed on the sheet")


def _fine(grey: np.ndarray, Co: np.ndarray, Ci: np.ndarray, spec: TargetSpec,
          spacing_px: float = 2.0, gamma: float = 2.2) -> TargetObservation:
    """Full-resolution edges of the pair of coarse ring conics ``Co``, ``Ci`` (module docstring, 4.)."""
    h, w = grey.shape
    lin, origin = _fine_roi(grey, Co, gamma)
    gf = _smooth(lin)
    radii = {"outer": spec.r_outer_mm, "inner": spec.r_inner_mm}
    # pass 1 on the ROI reduced q times, so that the ring is about as many pixels across as the
    # detector was tuned for (module docstring, 4.); q = 1 (no reduction) up to PASS1_RING_PX
    q = max(1, int(conic_to_ellipse(Co).a // PASS1_RING_PX))
    g1 = gf if q == 1 else _smooth(_reduce(lin, q))
    A = _reduce_map(q)  # ROI pixel -> reduced ROI pixel (pixel centres, README)
    Ainv = np.linalg.inv(A)
    fits = {}
    for name, R in radii.items():  # pass 1: each ring on its own, from the coarse conic
        C1 = _shift(Co if name == "outer" else Ci, origin)
        if q > 1:
            C1 = normalize_conic(Ainv.T @ C1 @ Ainv)
        fits[name] = _fit_ring(_search_scaled(g1, C1, spec.stroke_mm / 2.0 / R, spacing_px=4.0), name)
        if q > 1:
            fits[name] = tuple(normalize_conic(A.T @ C @ A) for C in fits[name][:3])
    for name in radii:  # pass 2: from the fitted edge conics
        C_in, C_out, C_mid = fits[name][:3]
        w_px = _median_width(C_mid, C_in, C_out)
        found = _search_pencil(gf, C_mid, C_in, C_out, 1.5 + 0.25 * w_px, gap_px=2.0 + w_px,
                               spacing_px=spacing_px)
        fits[name] = _fit_ring(found, name)
    split, ratio, _ = pencil_ratio(fits["outer"][2], fits["inner"][2])
    if np.sqrt(split) > CONCENTRIC_TOL:
        d = _centre_distance(fits["outer"][2], fits["inner"][2])
        raise CalibrationError(f"rings not concentric (centres {d:.0f} px apart)")
    # The pencil ratio is projective: on rendered frames it is within 0.05 % of
    # the printed one (0.13 % under k1 = -0.1 distortion), while a 1 % error in
    # the radii the user gives moves f by ~12 %. So the tolerance is tight.
    if abs(ratio / spec.radius_ratio - 1.0) > RATIO_TOL:
        raise CalibrationError(
            f"radius ratio {ratio:.3f} does not match the target's {spec.radius_ratio:.3f} "
            f"(--r-outer {spec.r_outer_mm:g} / --r-inner {spec.r_inner_mm:g}; the image says --r-inner "
            f"{spec.r_outer_mm / ratio:.1f} for --r-outer {spec.r_outer_mm:g}): check the radii printed on the sheet")
    edges, out_conics = [], {}
    back = -origin
    for name, R in radii.items():
        C_in, C_out, C_mid, uv_in, uv_out = fits[name]
        edges += [EdgePoints(uv_out + origin, R, +1), EdgePoints(uv_in + origin, R, -1)]
        out_conics.update({name: _shift(C_mid, back), name + "_plus": _shift(C_out, back),
                           name + "_minus": _shift(C_in, back)})
    log.debug("rings: %d/%d/%d/%d edge points, ratio %.4f, split %.2e",
              *(len(e.uv_px) for e in edges), ratio, split)
    return TargetObservation(edges=tuple(edges), width=w, height=h, conics=RingConics(**out_conics))


def _fine_roi(grey: np.ndarray, C_outer: np.ndarray, gamma: float = 2.2) -> tuple[np.ndarray, np.ndarray]:
    """Crop of ``grey`` around the outer ring in linear light (float32), and its origin (u0, v0).

    Pixel area and optical blur average light linearly, so an edge is the 50 %
    crossing of a blurred step in linear light, not in the gamma-encoded grey
    levels (there a dark stroke looks thinner: 0.2-0.5 px per edge).
    """
    h, w = grey.shape
    e = conic_to_ellipse(C_outer)
    pad = 0.15 * e.a + 10.0
    u0, v0 = (int(max(0, np.floor(e.center_px[i] - e.a - pad))) for i in (0, 1))
    u1 = int(min(w, np.ceil(e.center_px[0] + e.a + pad) + 1))
    v1 = int(min(h, np.ceil(e.center_px[1] + e.a + pad) + 1))
    lut = (255.0 * np.power(np.arange(256) / 255.0, gamma)).astype(np.float32)
    return lut[grey[v0:v1, u0:u1]], np.array([u0, v0], float)


def _smooth(lin: np.ndarray) -> np.ndarray:
    """The light smoothing the edge search expects (0.7 px Gaussian)."""
    return cv2.GaussianBlur(lin, (0, 0), 0.7)


def _reduce(lin: np.ndarray, q: int) -> np.ndarray:
    """``lin`` area-averaged ``q`` times (linear light: the average is what a coarser sensor would see)."""
    h, w = lin.shape
    return cv2.resize(lin[: h // q * q, : w // q * q], (w // q, h // q), interpolation=cv2.INTER_AREA)


def _reduce_map(q: int) -> np.ndarray:
    """Homogeneous map of full pixel centres to those of the image reduced ``q`` times: u' = (u + 0.5) / q - 0.5."""
    return np.array([[1.0 / q, 0, 0.5 / q - 0.5], [0, 1.0 / q, 0.5 / q - 0.5], [0, 0, 1.0]])


def _shift(C: np.ndarray, origin) -> np.ndarray:
    """Conic in coordinates shifted by ``origin``: ``u' = u - origin``."""
    Tr = np.array([[1.0, 0, origin[0]], [0, 1.0, origin[1]], [0, 0, 1.0]])
    return normalize_conic(Tr.T @ C @ Tr)


def _median_width(C_mid, C_in, C_out) -> float:
    uv, nrm = conic_samples(C_mid, spacing_px=20.0, max_samples=64)
    wd = line_conic_offsets(C_out, uv, nrm) - line_conic_offsets(C_in, uv, nrm)
    wd = wd[np.isfinite(wd)]
    return float(np.median(wd)) if len(wd) else 2.0
