"""Flat sides: the wedge the silhouettes leave outside a plain side between two of its corners.

A box's side is carved only by a view looking exactly along it. With views
every 10 deg of the turn none does, and the hull's section bulges over each
side in a low tent: the silhouette lines of the views on either side of it
cross in front of its middle, up to half the side times tan 5 deg out (3.8 mm
over an 87 mm side: 1.3 % of the box's diagonal with perfect silhouettes).
Stereo finds nothing on a plain white side. Its corners do show: the step
of shading between two sides, or the outline, in most views that see them.

So, height by height, the hull's section outline is walked and each of its
points projected into every view: a point on a corner lands on an image
edge in most views (``CORNER_SHARE``) and the outline turns there
(``MIN_TURN_DEG``), a point on a side's tent lands on one in few (a plain
side has no edge inside it). Between two consecutive corners whose outline
bows out of the chord by no more than a tent could (``MAX_BULGE`` of the
chord), the hull outside the chord goes, if the side is flat: the views
that face it see the chord of one shade all over (a plain flat side is
evenly lit; a cylinder's shading runs across it, a printed side has its
print), and the same chord is found in most of the layers either side (and
goes through up to ``GAP_MM`` of layers between two that found it, where
a soft photo's corners wandered). Nothing is carved that leaves a view's
silhouette pixels without a voxel behind them (``GUARD``, per band of
heights), except next to silhouette pixels the hull left unexplained already
(a cast shadow held in one view's mask, which the other views carved).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from calib.camera import camera_centre_table, project_points

from .faces import coverage, shell_points
from .image_edges import edge_thresholds, edges, smoothed_grey
from .types import VoxelHull

__all__ = ["Side", "flatten_sides"]

CORNER_SHARE = 0.45  # an outline point is a corner where this share of the views put an edge on it
EDGE_PX = 2  # ... within this many pixels
NMS_MM = 3.0  # one corner per this much outline ...
APEX_MM = 2.0  # ... where it turns sharpest over this much either side, ...
MIN_TURN_DEG = 30.0  # ... by at least this
MIN_SIDE_MM = 20.0  # a side's least width (the tent over a narrower one is under a millimetre)
MAX_BULGE = 0.2  # the outline bows out of a side's chord by at most this share of it ...
MIN_BULGE_MM = 0.5  # ... and at least this much (less: nothing to carve)
END_SHARE = 0.15  # the shade is read along the chord this far in from each corner
FLAT_DN = 8.0  # a side is of one shade where a view's 5th-95th percentile spread along it is at most this
FLAT_VIEWS = 0.7  # ... in this share of the views facing it (at least MIN_FACING)
MIN_FACING = 3
FACING_DEG = 20.0  # a view faces a side where it sees it at least this steeply
MIN_HEIGHT_MM = 2.0  # sections from this high above the table (the table's print lies at 0); ...
FOOT_MM = 1.0  # ... sides found this near it go on down to the table
GAP_MM = 4.0  # a side kept this near above and below goes through the layers between
BAND_MM = 4.0  # the guard judges the carving band by band of heights ...
GUARD = 0.003  # ... each may uncover at most this share of any view's silhouette, ...
FORGIVE_PX = 20  # ... not counting what lies near (FORGIVE_NEAR_PX) this many of its pixels together ...
FORGIVE_NEAR_PX = 12  # ... that the hull left unexplained already


@dataclass(frozen=True)
class Side:
    """A flattened band of sides: heights ``lo_mm``..``hi_mm``, the layers carved and the volume, mm^3."""

    lo_mm: float
    hi_mm: float
    layers: int
    volume_mm3: float


def _edge_maps(greys: list[np.ndarray], thresholds: tuple[float, float]) -> list[np.ndarray]:
    """Each view's edges (:func:`recon.image_edges.edges` of its smoothed grey), grown by ``EDGE_PX``."""
    k = np.ones((2 * EDGE_PX + 1,) * 2, np.uint8)
    return [cv2.dilate(edges(g, thresholds).astype(np.uint8), k) > 0 for g in greys]


def _lookup(maps, K, Ts, pts) -> np.ndarray:
    """(V, N): each view's map at the points' pixels (False / nan off the image)."""
    H, W = maps[0].shape[:2]
    out = np.zeros((len(Ts), len(pts)), maps[0].dtype if maps[0].dtype == bool else np.float32)
    if out.dtype != bool:
        out[:] = np.nan
    for k, (m, T) in enumerate(zip(maps, Ts, strict=True)):
        uv = np.rint(project_points(K, T, pts)).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < W) & (uv[:, 1] < H)
        out[k, ok] = m[uv[ok, 1], uv[ok, 0]]
    return out


def _corners(votes: np.ndarray, need: float, nms: int) -> list[int]:
    """Indices along a closed outline of the local maxima of ``votes`` at least ``need``, ``nms`` apart."""
    peak = (votes >= need) & (votes >= ndimage.maximum_filter1d(votes, 2 * nms + 1, mode="wrap"))
    idx = np.flatnonzero(peak)
    out: list[int] = []
    for i in idx:  # a plateau counts once
        if out and i - out[-1] <= nms:
            continue
        out.append(int(i))
    if len(out) > 1 and out[0] + len(votes) - out[-1] <= nms:
        out.pop()
    return out


def _apexes(rc: np.ndarray, corners: list[int], edge: np.ndarray, nms: int, w: int) -> list[int]:
    """Each corner moved to the sharpest turn of the outline near it among the points on edges; those
    where the outline turns less than ``MIN_TURN_DEG`` dropped.

    The edges' votes plateau a few voxels either side of a corner; a chord from a point along one side
    would cut the side it meets. Along a side, a horizontal edge (a lid's rim, the top's own edge just
    above) puts every point on an edge: no turn there."""
    n = len(rc)
    out = []
    for c in corners:
        best, score = c, -1.0
        for i in range(c - nms, c + nms + 1):
            if not edge[i % n]:
                continue
            turn = float(np.linalg.norm(rc[i % n] - 0.5 * (rc[(i - w) % n] + rc[(i + w) % n])))
            if turn > score:
                best, score = i % n, turn
        d0, d1 = rc[best] - rc[(best - w) % n], rc[(best + w) % n] - rc[best]
        cos = float(d0 @ d1) / max(float(np.linalg.norm(d0) * np.linalg.norm(d1)), 1e-9)
        if cos <= math.cos(math.radians(MIN_TURN_DEG)):
            out.append(best)
    return sorted(set(out))


def _flat(a3, b3, out_xz, grey, K, Ts, cams) -> bool:
    """Whether the views facing the chord ``a3``-``b3`` (outward normal ``out_xz``) see it of one shade."""
    n = max(int(np.linalg.norm(b3 - a3)), 4)
    t = np.linspace(END_SHARE, 1.0 - END_SHARE, n)
    q = a3 + t[:, None] * (b3 - a3)
    mid = 0.5 * (a3 + b3)
    d = cams[:, [0, 2]] - mid[[0, 2]]
    facing = d @ out_xz > math.sin(math.radians(FACING_DEG)) * np.linalg.norm(d, axis=1)
    if facing.sum() < MIN_FACING:
        return False
    g = _lookup([grey[k] for k in np.flatnonzero(facing)], K, Ts[facing], q)
    if np.isnan(g).any():
        return False
    spread = np.percentile(g, 95, axis=1) - np.percentile(g, 5, axis=1)
    return bool((spread <= FLAT_DN).mean() >= FLAT_VIEWS)


@dataclass(frozen=True)
class _Chord:
    A: np.ndarray  # (2,) the corners, voxel indices (ix, iz)
    B: np.ndarray
    arc: np.ndarray  # (M, 2) the outline from A to B, bowing out of the chord
    out: np.ndarray  # (2,) the chord's outward unit normal
    offset: float  # the side lies this many voxels out of the chord


def _chords(section, h, o, v, edges, grey, K, Ts, cams, need) -> list[_Chord]:
    """The chords between consecutive corners of the section's outline over flat sides (one height)."""
    cnts, _ = cv2.findContours(section.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    nms = max(int(round(NMS_MM / v)), 1)
    found = []
    for c in cnts:
        rc = c[:, 0, ::-1].astype(float)  # (N, 2) (ix, iz)
        n = len(rc)
        if n * v < 2 * MIN_SIDE_MM:
            continue
        pts = np.column_stack([o[0] + rc[:, 0] * v, np.full(n, h), o[2] + rc[:, 1] * v])
        votes = _lookup(edges, K, Ts, pts).sum(axis=0).astype(float)
        corners = _apexes(rc, _corners(votes, need, nms), votes >= need, nms, max(int(round(APEX_MM / v)), 2))
        if len(corners) < 2:
            continue
        for a, b in zip(corners, corners[1:] + corners[:1], strict=True):
            arc = rc[a:b + 1] if b > a else np.vstack([rc[a:], rc[:b + 1]])
            A, B = rc[a], rc[b]
            L = float(np.linalg.norm(B - A))
            if L * v < MIN_SIDE_MM:
                continue
            nrm = np.array([-(B - A)[1], (B - A)[0]]) / L
            d = (arc - A) @ nrm
            if d.max() < -d.min():  # the arc bows out of the chord: outward is its side
                nrm = -nrm
                d = -d
            bulge = float(d.max()) * v
            if d.min() < -1.0 or bulge < MIN_BULGE_MM or bulge > MAX_BULGE * L * v:
                continue
            if not _flat(pts[a], pts[b], nrm, grey, K, Ts, cams):
                continue
            # the chord runs through voxel centres at two of the outline's steps: the side lies out of it by
            # the corners' steps (the outline a voxel either side of each) and half a voxel
            ends = rc[np.r_[a - 1:a + 2, b - 1:b + 2] % n]
            found.append(_Chord(A, B, arc, nrm, max(float(((ends - A) @ nrm).max()), 0.0) + 0.5))
    return found


def _matches(c: _Chord, others: list[_Chord], tol: float) -> bool:
    return any(np.abs(c.A - o.A).max() <= tol and np.abs(c.B - o.B).max() <= tol for o in others)


def _through(kept_at: dict[int, list[_Chord]], gap: int) -> dict[int, list[_Chord]]:
    """Per layer, the sides that go through it from the layers above and below: a chord kept in a layer and again
    within ``gap`` layers higher, where the layers between did not keep it (a soft photo's corners wander by more
    than the match allows in a layer or two: the synth's box, blur 1 px, kept one of four sides at 22 mm)."""
    out: dict[int, list[_Chord]] = {}
    for j, kept in kept_at.items():
        for c in kept:
            top = next((j2 for j2 in range(j + gap + 1, j + 1, -1) if _matches(c, kept_at.get(j2, []), 2.0)), None)
            if top is None:
                continue
            for iy in range(j + 1, top):
                if not _matches(c, kept_at.get(iy, []), 2.0) and not _matches(c, out.get(iy, []), 2.0):
                    out.setdefault(iy, []).append(c)
    return out


def _apply(section: np.ndarray, chords: list[_Chord], v: float, strip: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(carve, value) for one height: the voxels of ``section`` outside the chords (between the chord and
    its arc; with ``strip``, anywhere beside the chord), and their new values."""
    carve = np.zeros(section.shape, bool)
    value = np.full(section.shape, np.inf, np.float32)
    rows, cols = np.mgrid[0:section.shape[0], 0:section.shape[1]]
    for c in chords:
        dist = (rows - c.A[0]) * c.out[0] + (cols - c.A[1]) * c.out[1] - c.offset  # out of the side, voxels
        ab = c.B - c.A
        along = ((rows - c.A[0]) * ab[0] + (cols - c.A[1]) * ab[1]) / float(ab @ ab)
        if strip:
            poly = ((along >= 0.0) & (along <= 1.0)).astype(np.uint8)
        else:
            poly = np.zeros(section.shape, np.uint8)
            cv2.fillPoly(poly, [np.rint(c.arc[:, ::-1]).astype(np.int32).reshape(-1, 1, 2)], 1)
        out = (poly > 0) & section & (dist > 0.5)
        near = section & (dist > -1.5) & (dist <= 0.5) & (along >= 0.0) & (along <= 1.0)
        carve |= out
        value = np.where(out | near, np.minimum(value, -dist * v), value)
    return carve, value


def _refused(inside: np.ndarray, carved: np.ndarray, band: np.ndarray, o, v: float, masks, K,
             Ts) -> tuple[set[int], dict[int, np.ndarray]]:
    """The guard, band by band of heights (``band``: each layer's): the bands whose carving uncovers too much of
    a view's silhouette, and the voxels carved in each band (table mm)."""
    after = inside & ~carved
    before_pts, after_pts = shell_points(inside, o, v), shell_points(after, o, v)
    bands = sorted(set(band[np.flatnonzero(carved.any(axis=(0, 2)))].tolist()))
    cidx = np.argwhere(carved)
    band_pts = {b: o + cidx[band[cidx[:, 1]] == b] * v for b in bands}
    bad: set[int] = set()
    shape = masks[0].shape
    for m, T in zip(masks, Ts, strict=True):
        cov_before = coverage(before_pts, K, T, shape)
        lost = m & cov_before & ~coverage(after_pts, K, T, shape)
        if not lost.any():
            continue
        # silhouette pixels the hull left unexplained already (a shadow the other views carved): what the
        # carving uncovers next to them extends them, it does not cut what this view alone saw
        old = m & ~cov_before
        n, lab = cv2.connectedComponents(old.astype(np.uint8), connectivity=8)
        big = np.bincount(lab[old], minlength=n) >= FORGIVE_PX
        big[0] = False
        r = 2 * FORGIVE_NEAR_PX + 1
        forgiven = cv2.dilate(big[lab].astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (r, r))) > 0
        n, lab = cv2.connectedComponents((lost | forgiven).astype(np.uint8), connectivity=8)
        joined = np.zeros(n, bool)
        joined[lab[forgiven]] = True
        lost &= ~joined[lab]
        if not lost.any():
            continue
        for b in bands:
            if b in bad:
                continue
            nl = (lost & coverage(band_pts[b], K, T, shape)).sum()
            if nl > GUARD * max(m.sum(), 1):
                bad.add(b)
    return bad, band_pts


def flatten_sides(hull: VoxelHull, images_rgb, masks, K, Ts) -> tuple[VoxelHull, list[Side]]:
    """The hull without the tents over its flat sides (see the module's docstring); and the bands flattened."""
    vals = np.asarray(hull.values, np.float32)
    inside = vals > 0
    if not inside.any() or len(Ts) < 2 * MIN_FACING:
        return hull, []
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    Ts = np.asarray(Ts, float)
    cams = camera_centre_table(Ts)
    greys = [smoothed_grey(im) for im in images_rgb]
    edge = _edge_maps(greys, edge_thresholds(images_rgb, Ts))
    grey = [g.astype(np.float32) for g in greys]
    need = CORNER_SHARE * len(Ts)

    def h_of(iy: int) -> float:
        return float(o[1] + iy * v)

    chords: dict[int, list[_Chord]] = {}
    for iy in range(inside.shape[1]):
        if h_of(iy) >= MIN_HEIGHT_MM and inside[:, iy, :].any():
            chords[iy] = _chords(inside[:, iy, :], h_of(iy), o, v, edge, grey, K, Ts, cams, need)
    # a side is a side over some height: the same chord (within a voxel or two) in most of the layers either
    # side (a smooth object's shading puts an edge here and there)
    kept_at = {iy: [c for c in found
                    if sum(_matches(c, chords.get(j, []), 2.0) for j in (iy - 2, iy - 1, iy + 1, iy + 2)) >= 3]
               for iy, found in chords.items()}
    through = _through(kept_at, max(int(round(GAP_MM / v)), 1))

    def carving(carried: dict[int, list[_Chord]]) -> tuple[np.ndarray, np.ndarray]:
        carved = np.zeros(inside.shape, bool)
        new = vals.copy()
        lowest = True
        for iy, kept in kept_at.items():
            if not kept and not carried.get(iy):
                continue
            carve, value = _apply(inside[:, iy, :], kept, v)
            if carried.get(iy):
                carve2, value2 = _apply(inside[:, iy, :], carried[iy], v, strip=True)
                carve, value = carve | carve2, np.minimum(value, value2)
            carved[:, iy, :] = carve
            new[:, iy, :] = np.minimum(new[:, iy, :], value)
            if lowest and h_of(iy) <= MIN_HEIGHT_MM + FOOT_MM:
                # the sides stand on the table: below the lowest section looked at (the table's print is
                # too near for corners), the lowest one's sides go on down
                for j in range(iy):
                    if h_of(j) > 0.0 and inside[:, j, :].any():
                        carve, value = _apply(inside[:, j, :], kept, v, strip=True)
                        carved[:, j, :] = carve
                        new[:, j, :] = np.minimum(new[:, j, :], value)
            lowest = False
        return carved, new

    carved, new = carving(through)
    if not carved.any():
        return hull, []
    band = np.floor(np.array([h_of(iy) for iy in range(inside.shape[1])]) / BAND_MM).astype(int)
    bad, band_pts = _refused(inside, carved, band, o, v, masks, K, Ts)
    if through and bad:
        # the sides gone through layers may not fit them as well as their own would, and what they uncover
        # counts against the bands round them: kept only where they cost no band its own carving (with no band
        # refused they cost none)
        own_carved, own_new = carving({})
        own_bad, own_pts = _refused(inside, own_carved, band, o, v, masks, K, Ts)
        if not bad <= own_bad:
            carved, new, bad, band_pts = own_carved, own_new, own_bad, own_pts
    bands = sorted(band_pts)
    keep = ~np.isin(band, sorted(bad))[None, :, None]
    done = []
    for b in bands:
        if b in bad:
            continue
        layers = np.flatnonzero((band == b) & carved.any(axis=(0, 2)))
        done.append(Side(h_of(int(layers[0])), h_of(int(layers[-1])), len(layers),
                         len(band_pts[b]) * v ** 3))
    if not done:
        return hull, []
    vals = np.where(keep, new, vals).astype(np.float32)
    vals = np.where(keep & carved, np.minimum(vals, -0.5 * v), vals)
    return VoxelHull(values=vals, origin_table=hull.origin_table, voxel_mm=hull.voxel_mm, meta=dict(hull.meta)), done
