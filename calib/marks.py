"""Reading the turntable angle from the printed angle marks.

The concentric rings fix the table plane but not the rotation about its normal:
a calibration's ``T_cam_table`` has an arbitrary table X axis. The mark track
(:mod:`calib.target`: Manchester-coded sectors between ``mark_r0_mm`` and
``mark_r1_mm``) fixes it absolutely. With the solver's table frame ("s") and
the printed one ("p"), a printed point at angle ``phi`` lies at solver angle

    theta_s = phi + alpha,        theta = atan2(Z, X)  (from +X towards +Z),

and :func:`read_turntable_angle` returns ``alpha`` (``angle_deg``): the angle,
in the solver's table frame, of the printed 0 deg mark. ``T_cam_table_p =
T_cam_table_s @ turntable_rotation(alpha)`` (:func:`align_pose_to_marks`) is the
pose whose table +X points to the printed 0 deg mark. Note the sense: turning
by +alpha in theta is the rotation by -alpha about +Y under the right-hand rule
(seen from above, theta grows clockwise).

Method
------
1. Rectify: sample the image on a polar grid of the table plane (``0.1 deg`` x
   ``0.25 mm``) through ``x ~ K [r1 r3 t] (X, Z, 1)^T`` with ``cv2.remap``,
   in four bands: the outer ring's core, the white gap, the mark track (minus
   1.5 mm at each side) and a white band just outside it.
2. Mask what is not the printed sheet: an angle counts only where the ring core
   is dark against the gap, the outer band is light, and the track is uniform
   across its radius (a radial edge is; the object's outline is not); the mask
   is grown by 1 deg.
3. Coarse: binarise the track against a running mid-level and correlate it
   with the expected pattern at all 3600 shifts (FFT); the best shift must
   agree on most visible samples and beat every other shift clearly.
4. Fine: at every visible radial edge, the sub-sample crossing of the mid-level
   between its two neighbouring half-sectors; ``alpha`` is the robust mean of
   (measured - printed) edge angles; rising and falling edges alternate, so a
   threshold bias cancels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from scipy import ndimage

from .camera import camera_centre_table, plane_homography
from .target import TargetSpec, mark_edges, mark_halfcells
from .types import CalibrationError

__all__ = ["AngleReading", "read_turntable_angle", "align_pose_to_marks", "turntable_rotation"]

STEP_DEG = 0.1          # polar sampling along theta
STEP_MM = 0.25          # polar sampling along r
GROW_MASK_DEG = 1.0     # occlusion mask grown by this much on both sides
MIN_SECTORS = 8         # fewer visible sectors than this: refuse (7-sector windows are unique)
MIN_SCORE = 0.5         # code agreement 2p - 1 of the best shift
MIN_MARGIN = 0.2        # best minus second-best score
EDGE_WINDOW_DEG = 1.0   # crossing searched within this of the predicted edge


@dataclass(frozen=True)
class AngleReading:
    """The turntable angle read from the angle marks of one image.

    Attributes
    ----------
    angle_deg : float
        ``alpha`` in [0, 360): the solver's table-frame angle ``atan2(Z, X)`` of
        the printed 0 deg mark (module docstring).
    std_deg : float
        One-sigma uncertainty of ``angle_deg`` from the scatter of the edges.
    n_edges : int
        Radial edges used for the fine angle.
    coverage : float
        Fraction of the code's sectors seen whole.
    score : float
        Agreement of the visible track with the code at the best shift,
        ``2 p - 1`` for a fraction ``p`` of matching samples (1 = perfect).
    margin : float
        ``score`` minus the best score at any other position (ambiguity).
    """

    angle_deg: float
    std_deg: float
    n_edges: int
    coverage: float
    score: float = float("nan")
    margin: float = float("nan")


def turntable_rotation(angle_deg: float) -> np.ndarray:
    """4x4 that turns table points by ``angle_deg`` in the turntable-angle sense.

    A point at angle ``theta`` (``atan2(Z, X)``) goes to ``theta + angle_deg``;
    the Y axis is fixed. Equals the right-hand rotation by ``-angle_deg`` about +Y.
    """
    a = np.radians(float(angle_deg))
    c, s = np.cos(a), np.sin(a)
    T = np.eye(4)
    T[0, 0], T[0, 2], T[2, 0], T[2, 2] = c, -s, s, c
    return T


def align_pose_to_marks(T_cam_table: np.ndarray, angle_deg: float) -> np.ndarray:
    """The pose whose table +X points to the printed 0 deg mark.

    Parameters
    ----------
    T_cam_table : (4, 4) float64
        The solver's pose (table X arbitrary), table mm -> camera mm.
    angle_deg : float
        :attr:`AngleReading.angle_deg` read with that pose.

    Returns
    -------
    (4, 4) float64
        ``T_cam_table @ turntable_rotation(angle_deg)``: the printed mark at
        angle ``theta`` projects through it at ``(r cos theta, 0, r sin theta)``.
    """
    T = np.asarray(T_cam_table, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_cam_table: expected (4, 4), got {T.shape}")
    return T @ turntable_rotation(angle_deg)


def read_turntable_angle(image: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, spec: TargetSpec,
                         *, dist: np.ndarray | None = None) -> AngleReading:
    """Read the absolute turntable angle from the angle marks.

    Parameters
    ----------
    image : (H, W) or (H, W, C) array
        The photo (any channel order; grey is the channel mean).
    K : (3, 3) float64
        Camera matrix, pixels.
    T_cam_table : (4, 4) float64
        Table (mm) to camera (mm) from the ring calibration; its rotation about
        the table normal is arbitrary.
    spec : TargetSpec
        The printed target; must carry marks.
    dist : (n,) float64, optional
        OpenCV distortion coefficients of ``image``; none by default.

    Returns
    -------
    AngleReading

    Raises
    ------
    CalibrationError
        "angle marks unreadable: ..." when too little of the track is visible,
        the code does not match, or the match is ambiguous.
    ValueError
        Bad argument shapes, or a pose whose table +Y points away from the camera.
    """
    grey = _grey(image)
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_cam_table, dtype=np.float64)
    if K.shape != (3, 3) or T.shape != (4, 4):
        raise ValueError(f"K must be (3, 3) and T_cam_table (4, 4), got {K.shape}, {T.shape}")
    if not spec.marks:
        raise CalibrationError("angle marks unreadable: the target spec has no marks")
    if camera_centre_table(T)[1] <= 0.0:
        raise ValueError("T_cam_table: the table's +Y must point to the camera's side (README conventions); "
                         "a flipped normal mirrors the angle")
    bands = _polar_bands(grey, K, T, spec, dist)
    valid, contrast = _visible(bands)
    track = bands["track"].mean(axis=0)
    binary, valid = _binarise(track, valid, contrast)
    n_cols = valid.size
    visible_sectors = valid.sum() / (n_cols / spec.n_sectors)
    if visible_sectors < MIN_SECTORS:
        raise CalibrationError(f"angle marks unreadable: only {visible_sectors:.1f} of {spec.n_sectors} "
                               f"sectors visible (need {MIN_SECTORS})")
    shift, score, margin = _coarse_shift(binary, spec)
    if score < MIN_SCORE:
        raise CalibrationError(f"angle marks unreadable: the visible marks do not match the code "
                               f"(agreement {score:.2f} < {MIN_SCORE})")
    if margin < MIN_MARGIN:
        raise CalibrationError(f"angle marks unreadable: ambiguous code position (margin {margin:.2f} "
                               f"< {MIN_MARGIN}); too few distinct sectors visible")
    phis, alphas = _edge_offsets(track, valid, contrast, shift, spec)
    if alphas.size < 4:
        raise CalibrationError(f"angle marks unreadable: only {alphas.size} sharp edges found")
    alpha, std, n = _robust_mean(phis, alphas)
    return AngleReading(angle_deg=float(np.mod(alpha, 360.0)), std_deg=std, n_edges=n,
                        coverage=_coverage(valid, alpha, spec), score=score, margin=margin)


# ----------------------------------------------------------------------------- steps

def _grey(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.transform(img[..., :3].astype(np.float32), np.full((1, 3), 1.0 / 3.0))
    elif img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim != 2:
        raise ValueError(f"image: expected (H, W) or (H, W, C), got {np.shape(image)}")
    return np.ascontiguousarray(img, dtype=np.float32)


def _band_radii(spec: TargetSpec) -> dict[str, np.ndarray]:
    """Radii (mm) sampled in each band; see the module docstring."""
    def span(a, b):
        n = max(int(np.floor((b - a) / STEP_MM)) + 1, 1)
        return np.linspace(a, b, n) if n > 1 else np.array([(a + b) / 2.0])

    ring_out = spec.r_outer_mm + spec.stroke_mm / 2.0
    core = max(spec.stroke_mm / 4.0, 0.25)
    r0, r1 = cast(float, spec.mark_r0_mm), cast(float, spec.mark_r1_mm)  # set by TargetSpec.__post_init__
    return {"core": span(spec.r_outer_mm - core, spec.r_outer_mm + core),
            "gap": span(ring_out + 1.0, r0 - 1.0),
            "track": span(r0 + 1.5, r1 - 1.5),
            "outer": span(r1 + 1.0, r1 + 3.0)}


def _polar_bands(grey, K, T, spec, dist) -> dict[str, np.ndarray]:
    """Polar samples (rows = radii, columns = theta_j = j * STEP_DEG), NaN off-image."""
    radii = _band_radii(spec)
    r = np.concatenate(list(radii.values()))
    th = np.radians(np.arange(int(round(360.0 / STEP_DEG))) * STEP_DEG)
    X = r[:, None] * np.cos(th)[None, :]
    Z = r[:, None] * np.sin(th)[None, :]
    if dist is not None and np.any(np.asarray(dist) != 0):
        pts = np.stack([X, np.zeros_like(X), Z], axis=-1).reshape(-1, 3)
        rvec, _ = cv2.Rodrigues(T[:3, :3])
        uv, _ = cv2.projectPoints(pts, rvec, T[:3, 3], K, np.asarray(dist, np.float64))
        u, v = uv[:, 0, 0].reshape(X.shape), uv[:, 0, 1].reshape(X.shape)
    else:
        H = plane_homography(K, T)
        w = H[2, 0] * X + H[2, 1] * Z + H[2, 2]
        u = (H[0, 0] * X + H[0, 1] * Z + H[0, 2]) / w
        v = (H[1, 0] * X + H[1, 1] * Z + H[1, 2]) / w
    depth = T[2, 0] * X + T[2, 2] * Z + T[2, 3]
    behind = depth <= 1e-6
    u[behind] = -1e6
    v[behind] = -1e6
    polar = cv2.remap(grey, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
    out, i = {}, 0
    for name, rr in radii.items():
        out[name] = polar[i:i + rr.size]
        i += rr.size
    return out


def _visible(bands) -> tuple[np.ndarray, float]:
    """Columns where the printed sheet is seen, (n,) bool, and the typical ink/paper contrast."""
    core = bands["core"].mean(axis=0)
    gap = bands["gap"].mean(axis=0)
    outer = bands["outer"].mean(axis=0)
    trk = bands["track"]
    contrast = gap - core
    finite = np.isfinite(contrast) & np.isfinite(outer) & np.all(np.isfinite(trk), axis=0)
    if not np.any(finite):
        raise CalibrationError("angle marks unreadable: the mark track is outside the image")
    typical = float(np.percentile(contrast[finite], 90))
    if not typical > 8.0:
        raise CalibrationError(f"angle marks unreadable: no ink/paper contrast around the outer ring "
                               f"({typical:.1f} grey levels)")
    c = np.where(finite, contrast, 0.0)
    srt = np.sort(np.where(finite, trk, 0.0), axis=0)
    lo, hi = srt[int(0.1 * (srt.shape[0] - 1))], srt[int(np.ceil(0.9 * (srt.shape[0] - 1)))]
    valid = (finite & (c > 0.3 * typical)
             & (outer > core + 0.6 * c)                 # light paper outside the track
             & (hi - lo < 0.4 * c)                      # uniform across the radius
             & (trk.mean(axis=0) < gap + 0.3 * c))      # nothing brighter than the paper
    grow = int(round(GROW_MASK_DEG / STEP_DEG))
    valid = ndimage.minimum_filter1d(valid.astype(np.uint8), 2 * grow + 1, mode="wrap").astype(bool)
    return valid, typical


def _binarise(track, valid, contrast: float) -> tuple[np.ndarray, np.ndarray]:
    """+1 paper / -1 ink / 0 unknown per column, against a running mid-level (+-4 deg)."""
    w = 2 * int(round(4.0 / STEP_DEG)) + 1
    hi = ndimage.maximum_filter1d(np.where(valid, track, -np.inf), w, mode="wrap")
    lo = ndimage.minimum_filter1d(np.where(valid, track, np.inf), w, mode="wrap")
    ok = valid & np.isfinite(hi) & np.isfinite(lo)
    ok[ok] &= hi[ok] - lo[ok] > 0.35 * contrast
    mid = np.zeros_like(track)
    mid[ok] = 0.5 * (hi[ok] + lo[ok])
    return np.where(ok, np.sign(track - mid), 0.0), ok


def _pattern(spec: TargetSpec, n_cols: int) -> np.ndarray:
    """Expected track per column at zero shift: +1 paper, -1 ink, sampled at theta_j + STEP/2."""
    ink = mark_halfcells(spec)
    phi = (np.arange(n_cols) + 0.5) * (360.0 / n_cols)
    i = np.floor(phi / (180.0 / spec.n_sectors)).astype(int) % ink.size
    return np.where(ink[i], -1.0, 1.0)


def _coarse_shift(binary, spec) -> tuple[int, float, float]:
    """Best circular shift (columns) of the pattern, its score and its margin."""
    n = binary.size
    p = _pattern(spec, n)
    corr = np.fft.irfft(np.fft.rfft(binary) * np.conj(np.fft.rfft(p)), n)
    corr /= max(np.abs(binary).sum(), 1.0)
    best = int(np.argmax(corr))
    d = np.abs((np.arange(n) - best + n // 2) % n - n // 2)
    lobe = int(round(1.5 / STEP_DEG))
    second = float(corr[d > lobe].max())
    return best, float(corr[best]), float(corr[best] - second)


def _edge_offsets(track, valid, contrast: float, shift: int, spec: TargetSpec) -> tuple[np.ndarray, np.ndarray]:
    """Printed angle (deg) and (measured - printed) angle (deg) of every visible radial edge."""
    n = track.size
    theta_e, to_ink = mark_edges(spec)
    half = 180.0 / spec.n_sectors                         # half-sector, deg

    def cols(deg: float) -> int:
        return int(round(deg / STEP_DEG))

    coarse = (shift - 0.5) * STEP_DEG                     # pattern sampled half a column late
    w = cols(EDGE_WINDOW_DEG)
    out = []
    for phi, falling in zip(np.degrees(theta_e), to_ink, strict=True):
        pred = (phi + coarse) / STEP_DEG                  # predicted column, unwrapped
        c0 = int(np.floor(pred))
        if not np.all(valid[np.arange(c0 - cols(0.75 * half), c0 + cols(0.75 * half) + 2) % n]):
            continue
        # levels: the middle 40 % of the half-sectors on either side of the edge
        a = float(track[np.arange(c0 - cols(0.7 * half), c0 - cols(0.3 * half) + 1) % n].mean())
        b = float(track[np.arange(c0 + 1 + cols(0.3 * half), c0 + 2 + cols(0.7 * half)) % n].mean())
        if (a - b if falling else b - a) < 0.3 * contrast:
            continue
        window = np.arange(c0 - w, c0 + w + 2)
        x = _crossing(track[window % n] - 0.5 * (a + b), window, pred)
        if x is not None:
            out.append((phi, x * STEP_DEG - phi))
    arr = np.asarray(out, dtype=np.float64).reshape(-1, 2)
    return arr[:, 0], arr[:, 1]


def _crossing(d: np.ndarray, cols: np.ndarray, pred: float) -> float | None:
    """Sub-sample zero crossing of ``d`` (samples at ``cols``) nearest ``pred``."""
    s = np.signbit(d)
    ks = np.flatnonzero(s[1:] != s[:-1])
    if ks.size == 0:
        return None
    k = int(ks[np.argmin(np.abs(cols[ks] + 0.5 - pred))])
    # linear fit through the transition samples around the crossing (at most 3 each side)
    amp = np.abs(d[max(k - 12, 0):k + 14]).max()
    lo, hi = k, k + 1
    while lo > max(k - 3, 0) and abs(d[lo - 1]) < 0.7 * amp and s[lo - 1] == s[k]:
        lo -= 1
    while hi < min(k + 4, d.size - 1) and abs(d[hi + 1]) < 0.7 * amp and s[hi + 1] == s[k + 1]:
        hi += 1
    x, y = cols[lo:hi + 1].astype(float), d[lo:hi + 1].astype(float)
    xm, ym = x.mean(), y.mean()
    slope = float(((x - xm) * (y - ym)).sum() / ((x - xm) ** 2).sum())   # least-squares line
    if slope == 0:
        return None
    root = xm - ym / slope
    return float(root) if cols[k] - 1 <= root <= cols[k + 1] + 1 else None


def _robust_mean(phi: np.ndarray, x: np.ndarray) -> tuple[float, float, int]:
    """Mean of the inlier offsets ``x`` (deg), its uncertainty (deg) and the inlier count.

    Inliers lie within 4 robust sigma (at least 0.05 deg) of the median. The
    uncertainty adds to the standard error of the mean a split-half term: half
    the difference between the means of the edges on either side of the
    visible arc's middle, which a pose error (tilt, focal length) makes
    differ while it barely moves the scatter.
    """
    med = float(np.median(x))
    sig = 1.4826 * float(np.median(np.abs(x - med)))
    keep = np.abs(x - med) <= max(4.0 * sig, 0.05)
    xi, pi = x[keep], np.radians(phi[keep])
    if xi.size < 2:
        return float(xi.mean()), float("nan"), int(xi.size)
    sem = float(xi.std(ddof=1) / np.sqrt(xi.size))
    middle = np.arctan2(np.sin(pi).sum(), np.cos(pi).sum())
    side = np.mod(pi - middle + np.pi, 2 * np.pi) - np.pi
    left = side < np.median(side)
    split = 0.5 * abs(xi[left].mean() - xi[~left].mean()) if 0 < left.sum() < xi.size else 0.0
    return float(xi.mean()), float(np.hypot(sem, split)), int(xi.size)


def _coverage(valid: np.ndarray, alpha_deg: float, spec: TargetSpec) -> float:
    """Fraction of the sectors whose whole span (at shift alpha) is visible."""
    n = valid.size
    per = n / spec.n_sectors
    seen = 0
    for k in range(spec.n_sectors):
        c0 = (k * 360.0 / spec.n_sectors + alpha_deg) / STEP_DEG
        idx = np.arange(int(np.ceil(c0)), int(np.floor(c0 + per)) + 1) % n
        seen += bool(np.all(valid[idx]))
    return seen / spec.n_sectors
