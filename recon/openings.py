"""Openings: a vessel's rim, outlined all round by the views' edges, and the inside under it that no view sees.

A white cup's inside is what neither the silhouettes nor stereo can show:
every silhouette's upper edge is the far half of the rim, so the hull keeps
the cone the rim allows over the opening and is solid down to the table;
a plain white inner wall gives stereo nothing to match, and its shading,
fixed to the light as the cup turns, is no evidence of depth either. What
the views do show is the rim: its far half is the silhouette's edge, its
near half an edge inside it (the outer wall below, the far inner wall seen
over it), and rectified onto the plane at the rim's height every view puts
both halves on the same circle (the plane sweep of :mod:`recon.faces`).

An *opening* is such a horizontal outline that

- closes the region it encloses by itself, all round (``CLOSED_SHARE`` of
  the region's border lies on the outline; an edge seen only part of the
  way round, closed by the hull's section, is none);
- encloses at least ``MIN_OPENING_MM2``;
- is a rim, not a top's single edge: the outline's band is wider than one
  edge's by ``MIN_RIM_MM`` or more (a glossy flat top, which the views see
  reflecting different things, is closed all round too; the flat tops measured
  give -1.3 to 0.1 mm, a vase's rounded top 2.0, the synth's cup 2.5 to 4.3);
- under ``SURE_RIM_MM`` of rim, encloses a region over which the views do not
  agree on a colour (each sees another part of the inside through it; a flat
  top with a rounded edge, which they all see alike, is not an opening). An
  evenly lit inside looks alike from every view too (the synth's cup under one
  of its lights: 0.99 of it agrees), so a wider rim is enough; from
  ``WIDE_RIM_MM`` the views need only not agree all over, as on a flat top;
- is not on the roof over another opening: a little lower the hull's section
  reaches out past it no more than a vessel's wall does, not as far as a
  roof sloped as the views (a soft photo's thick silhouette edges enclose
  a region in the roof's section at every height);
- has nothing standing on it: the hull over it no higher than the roof the
  rim itself leaves from its top (at ``d`` inside the rim, ``d`` times the
  steepest view's tangent; the top up to ``RIM_WIDE_OFFSET_MM`` over the height
  the outline closed at), and no outline inside it higher up (a knob) but the
  roof's own and what is outlined as much under the rim (static shading near
  the axis).

Under it the inside is hollowed as a vessel's: down each column of the
opening, hull voxels farther than the wall from the hull's outside (the
wall: the rim's width, as the outline and the hull's section show it) and
higher than the floor (a floor outlined inside the opening where the views
see one, else a floor as thick as the wall on the hull's bottom), with the
roof over the opening; a surface stereo observed stops the descent, and
nothing is hollowed that would leave a pixel of a view's silhouette with no
hull behind it. It is a prior, as the cavity prior of :mod:`recon.surface`
is: no view sees the lower inside; the run says so in its summary.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from .faces import (
    EDGE_SHARE,
    GUARD_PX,
    MIN_AGREE,
    MIN_OUTLINE_MM,
    RISE_MM,
    RISE_SHARE,
    ROOF_SLACK_MM,
    Sweep,
    column_run_mm,
    steepest_tan,
    sweep,
    uncovered_share,
)
from .surface import lateral_mm
from .types import VoxelHull

__all__ = ["Opening", "find_openings", "hollow_openings"]

RIM_PEAK = 1.5  # a rim's outline peaks less sharply than a flat top's edge: a rounded rim spans its thickness
MIN_OPENING_MM2 = 100.0  # an opening's least area (a pen holder 12 mm across)
RIM_WIDE_OFFSET_MM = 3.0  # ... and, blurred, peaks against the outline this far above and below
CLOSED_SHARE = 0.85  # this share of the region's border lies on the outline itself (a soft rim, light wall: 0.88)
MAX_AGREE = 0.3  # the views agree on a colour over at most this share of it (more: a flat top's)
BAND_MM = 2.0  # the outline's band reaches this far past an edge (the hull's section's, at most)
MIN_RIM_MM = 1.0  # a rim this wide at least: two edges, the wall's inner and outer, not a top's one ...
SURE_RIM_MM = 3.0  # ... and from this wide the views need not disagree inside it (an evenly lit inside) ...
WIDE_RIM_MM = 2.5  # ... from this wide they need only not agree as on a flat top
WIDE_MAX_AGREE = 0.9  # ... (flat tops: 0.99-1.00 of their texels agree; the synth's cup at seed 8, rim 2.9 mm: 0.75)
MIN_WALL_MM = 1.5  # the thinnest wall left
FLOOR_DROP_MM = 3.0  # a floor is outlined this far under the rim or more ...
FLOOR_INSET_MM = 2.0  # ... inside the opening, this far from its border, ...
RING_RADIUS = 0.5  # ... its texels a median this share of the opening's radius from its centre ...
RING_BINS = 60  # ... and all round it, closely: in this many of the 72 sectors of 5 deg
WALL_DROP_MM = 2.0  # under a rim the hull's section reaches out past the rim's by less than half a roof's over this
MAX_OVER_ROOF = 0.1  # the hull may rise over the rim's roof on this share of the region (its noise)
ROOF_CLEAR_MM = 4.0  # a knob's outline is looked for this far inside the hull's section above the opening
TAU_MM = 3.0  # the signed distance's band at the hollowed surface


@dataclass(frozen=True)
class Opening:
    """A rim ``height_mm`` above the table round ``region`` (its inside, on the raster; i: z, j: x)."""

    height_mm: float
    region: np.ndarray  # (nz, nx) bool
    origin_xz: tuple[float, float]
    px_per_mm: float
    wall_mm: float
    floor_mm: float | None  # the floor the views outline inside it, if any
    lift_mm: float = 0.0  # the rim's top over ``height_mm``: the roof the rim leaves starts there

    @property
    def area_mm2(self) -> float:
        return float(self.region.sum()) / self.px_per_mm ** 2


def _border(region: np.ndarray) -> np.ndarray:
    """The region's own texels on its border (8-connected to outside it)."""
    return region & ~(cv2.erode(region.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)


def _rim_mm(region: np.ndarray, section: np.ndarray, band: np.ndarray, px: float) -> float:
    """The rim's width: from the region's border to the hull's outside, less the band's spread past an edge.

    The outline is a band round each edge (the edges' blur, the views' small disagreements); its reach past
    the hull's section, where the outer edge is, is its reach inside the opening too. A top's single edge
    gives about nothing (a white box's top: -0.7 mm; a domed lid's rim: 0.7 mm), a cup's rim its wall
    (the synth's cup, 3 mm: 3.1 mm).
    """
    dist = cv2.distanceTransform(np.pad(section, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1] / px
    width = float(np.median(dist[_border(region)]))
    outside = cv2.distanceTransform((~section).astype(np.uint8), cv2.DIST_L2, 5) / px
    past = band & ~section
    spread = min(float(np.percentile(outside[past], 90)), BAND_MM) if past.any() else 0.0
    return width - spread


def _rings(texels: np.ndarray, region: np.ndarray, px: float) -> bool:
    """Whether outline texels inside an opening ring it as a floor's edge does: long enough, all round it and
    away from its centre (an edge that stands still in the images as the object turns, a shadow's on the
    inner wall, is put on the same texels only near the axis, where every view's parallax is small)."""
    if texels.sum() < 0.5 * MIN_OUTLINE_MM * px:
        return False
    ii, jj = np.nonzero(region)
    ci, cj = ii.mean(), jj.mean()
    ti, tj = np.nonzero(texels)
    r = np.hypot(ti - ci, tj - cj)
    if np.median(r) < RING_RADIUS * np.sqrt(region.sum() / np.pi):
        return False
    bins = np.unique((np.degrees(np.arctan2(ti - ci, tj - cj)) // 5).astype(int))
    return len(bins) >= RING_BINS


def _knob(sw: Sweep, k: int, share: float, region: np.ndarray) -> bool:
    """Whether something inside the region outlines itself up to ``RISE_MM`` above it (a knob, a lid's dome).

    Not counted: the outline along the hull's own section up there, ``ROOF_CLEAR_MM`` from its border (the roof
    over an opening is made of the silhouettes' edges, and a soft, noisy photo's thick edges put ~10 % of the
    opening on it at every height: the synth's cup, blur 0.5 px, noise 4), and texels outlined as much under
    the rim (an edge that stands still in the images as the object turns, the inside's shading, is put on the
    same texels near the axis at every height; a knob's outline is where the knob is).
    """
    px, step = sw.px, sw.step
    inner = cv2.erode(region.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=max(int(px), 1)) > 0
    if not inner.any():
        return True
    reach, gap = int(round(RISE_MM / step)), max(int(round(1.0 / step)), 1)
    below = np.zeros(region.shape, bool)
    for j in range(max(k - reach, 0), k - gap + 1):
        below |= sw.outline(j, share)
    look = inner & ~below
    for j in range(k + gap, min(k + reach + 1, len(sw.heights))):
        clear = cv2.distanceTransform(np.pad(sw.sections[j], 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
        if (sw.outline(j, share) & look & (clear > ROOF_CLEAR_MM * px)).sum() > RISE_SHARE * inner.sum():
            return True
    return False


def _on_a_roof(sw: Sweep, k: int, region: np.ndarray, rim_mm: float, tan_e: float) -> bool:
    """Whether the hull's section at ``heights[k]`` is a roof's round the region: ``WALL_DROP_MM`` lower it
    reaches out past it by half what a roof would or more.

    The hull over an opening is the roof its rim leaves, sloped as the steepest view (its section shrinks by
    ``dh / tan_e`` over ``dh`` of height), and its section's border is on the silhouettes' edges, outlined at every
    height: a soft photo's thick edges enclose a region in it (the synth's dark-room cup, blur 0.5 px, noise 4:
    at 76 mm, 8 mm over its rim; the roof's section grows 5.9 mm over 2 mm). Under a rim is the vessel's wall,
    whose section grows no more than the vessel widens (the synth's cups: 0 mm).
    """
    j = k - max(int(round(WALL_DROP_MM / sw.step)), 1)
    if j < 0:
        return False
    sec, lower = sw.sections[k], sw.sections[j]
    roof = WALL_DROP_MM / max(tan_e, 1e-3)
    # the lower section's border near the region: within the rim and the roof's reach of it
    near = cv2.distanceTransform((~region).astype(np.uint8), cv2.DIST_L2, 5) / sw.px <= rim_mm + roof + 2.0
    border = lower & ~(cv2.erode(lower.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0) & near
    if not border.any():
        return False
    past = cv2.distanceTransform((~sec).astype(np.uint8), cv2.DIST_L2, 5) / sw.px
    return float(np.median(past[border])) >= 0.5 * roof


def _over_roof(sw: Sweep, k: int, region: np.ndarray, hull: VoxelHull, tan_e: float) -> tuple[float, float]:
    """The share of the region over which the hull rises higher than the roof its rim leaves, and the roof's lift.

    Over an opening the hull is what the silhouettes' upper edges, the far half of the rim, leave: at a
    distance ``d`` inside the rim no higher than ``d`` times ``tan_e``, the tangent of the steepest view onto
    the region (and ``ROOF_SLACK_MM``), over the rim's top. A dome steeper than the views, or anything standing
    on the region that the silhouettes show, rises above that.

    The rim's top is the hull's over the region's border, up to ``RIM_WIDE_OFFSET_MM`` over ``heights[k]``
    (the lift, mm): a soft photo spreads the rim's outline over its height, and the share that closes it may
    peak under its top (the synth's cup, blur 1 px: 2.3 mm under it, the hull over the opening exactly the
    roof from there; sharp: 0.2 to 1.4 mm).
    """
    h = float(sw.heights[k])
    ii, jj = np.nonzero(region)
    x, z = sw.x0 + jj / sw.px, sw.z0 + ii / sw.px
    run = column_run_mm(hull, x, z, h)
    if run is None:
        return 0.0, 0.0
    d = cv2.distanceTransform(np.pad(sw.sections[k], 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1][ii, jj] / sw.px
    over = run - d * tan_e  # the hull's height over a roof sloped as the steepest view from the rim
    border = _border(region)[ii, jj]
    lift = float(np.clip(np.median(over[border]), 0.0, RIM_WIDE_OFFSET_MM)) if border.any() else 0.0
    return float(np.mean(over > lift + ROOF_SLACK_MM)), lift


def rim_peaks(sw: Sweep) -> list[tuple[int, float]]:
    """``(k, share)``, bottom up, where a rim's outline may peak: :meth:`Sweep.peaks_with` at ``RIM_PEAK``,
    against the outline ``PEAK_OFFSET_MM`` or ``RIM_WIDE_OFFSET_MM`` away (a soft, noisy photo spreads a rim's
    outline over ~4 mm of height: the synth's cup, blur 0.5 px, noise 4, light wall), for each edge share that
    peaks there (the strict share's outline may peak but not close: the synth's cup on a light wall, seed 8,
    where the loose share's closes the rim all round)."""
    found = set(sw.peaks_with(RIM_PEAK, every=True)) | set(sw.peaks_with(RIM_PEAK, RIM_WIDE_OFFSET_MM, every=True))
    return sorted(found)  # at a height the loose share's first: find_openings, top down, tries the strict one first


def find_openings(images_rgb, masks, K, Ts, hull: VoxelHull, swept: Sweep | None = None) -> list[Opening]:
    """The openings the views' edges outline (see the module's docstring), top down."""
    sw = swept if swept is not None else sweep(images_rgb, masks, K, Ts, hull)
    if sw is None:
        return []
    heights, px = sw.heights, sw.px
    peaks = rim_peaks(sw)
    found: list[Opening] = []
    for k, share in reversed(peaks):
        h = float(heights[k])
        outline = sw.outline(k, share)
        band = cv2.dilate(outline.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        n, lab = cv2.connectedComponents((~(band | ~sw.sections[k])).astype(np.uint8), connectivity=4)
        edge = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
        agree = None
        for c in range(1, n):
            if c in edge:
                continue
            region = ndimage.binary_fill_holes(lab == c)  # specks of outline inside it are no border of it
            if region.sum() < MIN_OPENING_MM2 * px ** 2:
                continue
            if any((region & f.region).any() for f in found):  # under an opening found higher up
                continue
            rim = (cv2.dilate(region.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0) & ~region
            if (rim & band).sum() < CLOSED_SHARE * rim.sum():
                continue
            rim_mm = _rim_mm(region, sw.sections[k], band, px)
            if rim_mm < MIN_RIM_MM:  # one edge round it: a top's (a glossy one the views disagree on)
                continue
            if rim_mm < SURE_RIM_MM:  # a narrow rim, or a top's rounded edge: the inside must look like one
                if agree is None:
                    agree = sw.agreement(h, images_rgb)[0]
                if (agree[region] >= MIN_AGREE).mean() > (WIDE_MAX_AGREE if rim_mm >= WIDE_RIM_MM else MAX_AGREE):
                    continue
            ii, jj = np.nonzero(region)
            tan_e = steepest_tan(sw.Ts, (sw.x0 + jj.mean() / px, h, sw.z0 + ii.mean() / px))
            if _on_a_roof(sw, k, region, rim_mm, tan_e):
                continue
            over, lift = _over_roof(sw, k, region, hull, tan_e)
            if over > MAX_OVER_ROOF:
                continue
            if _knob(sw, k, share, region):
                continue
            wall = max(rim_mm, MIN_WALL_MM)
            r = max(int(round(FLOOR_INSET_MM * px)), 1)
            deep = cv2.erode(region.astype(np.uint8), np.ones((2 * r + 1,) * 2, np.uint8)) > 0
            floor = next((float(heights[j]) for j, s in reversed(sw.peaks)
                          if heights[j] <= h - FLOOR_DROP_MM and s == EDGE_SHARE
                          and _rings(sw.outline(j, s) & deep, region, px)), None)
            found.append(Opening(h, region, (sw.x0, sw.z0), px, wall, floor, lift))
    return found


def _columns(op: Opening, hull: VoxelHull, top: np.ndarray) -> np.ndarray:
    """(Nx, Nz) bool: the grid's columns over the texels of ``top`` (a raster of ``op``'s)."""
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    nx, _, nz = np.asarray(hull.values).shape
    X, Z = np.meshgrid(o[0] + np.arange(nx) * v, o[2] + np.arange(nz) * v, indexing="ij")
    i = np.rint((Z - op.origin_xz[1]) * op.px_per_mm).astype(int)
    j = np.rint((X - op.origin_xz[0]) * op.px_per_mm).astype(int)
    ok = (i >= 0) & (j >= 0) & (i < top.shape[0]) & (j < top.shape[1])
    out = np.zeros(X.shape, bool)
    out[ok] = top[i[ok], j[ok]]
    return out


def _walled(section: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """A slice of the hull (x, z) with its holes that meet ``cols`` filled: a roof carved over the opening
    (:func:`recon.faces.carve_above_faces`) is the cavity, and a wall is measured from the outside only."""
    filled = ndimage.binary_fill_holes(section)
    holes, n = ndimage.label(filled & ~section)
    if n == 0:
        return section
    return section | np.isin(holes, np.unique(holes[cols & (holes > 0)])) & (holes > 0)


def _inside_of(op: Opening, hull: VoxelHull, inside: np.ndarray, solid: np.ndarray | None, tan_e: float) -> np.ndarray:
    """The voxels hollowed under (and over) the opening: a bool grid like the hull's.

    Over it only the roof the rim leaves goes (``d`` inside the rim, up to ``d`` times ``tan_e``, the steepest
    view's tangent, and ``ROOF_SLACK_MM`` over the rim's top, ``lift_mm`` over the opening): anything higher is
    something the silhouettes show (a handle arching over it)."""
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    ny = inside.shape[1]
    y = o[1] + np.arange(ny) * v
    jr = min(max(int(np.floor((op.height_mm - o[1]) / v)), 0), ny - 1)  # the rim's slice
    # the cavity's top: the rim's slice of the hull farther than the wall from its outside, where it meets the
    # opening (the outline's band eats into the opening's border)
    cols = _columns(op, hull, op.region)
    lateral_rim = lateral_mm(_walled(inside[:, jr, :], cols), v)
    lab, _ = ndimage.label(lateral_rim > op.wall_mm)
    top = np.isin(lab, np.unique(lab[cols & (lab > 0)])) & (lab > 0)
    # and the opening's columns; where a flat top's roof was carved down under the rim (recon.faces took the
    # opening's evenly lit inside for a top: the synth's cup at seed 11 in a dark room), a column's hull starts
    # lower, and the descent waits for it there
    top = (top | cols) & inside[:, :jr + 1, :].any(axis=1)
    floor_y = np.where(inside, np.arange(ny)[None, :, None], ny).min(axis=1)  # (Nx, Nz) the hull's bottom slice
    E = np.zeros_like(inside)
    roof = (y[None, jr + 1:, None] - op.height_mm - op.lift_mm) <= lateral_rim[:, None, :] * tan_e + ROOF_SLACK_MM
    E[:, jr + 1:, :] = inside[:, jr + 1:, :] & top[:, None, :] & roof  # the roof over the opening
    if solid is not None:
        E[:, jr + 1:, :] &= ~solid[:, jr + 1:, :]
    cur = top.copy()
    waiting = top & ~inside[:, jr, :]  # (the columns whose hull has not started yet)
    for j in range(jr, -1, -1):
        lateral = lateral_rim if j == jr else lateral_mm(_walled(inside[:, j, :], cols), v)
        ok = inside[:, j, :] & (lateral > op.wall_mm) & ((j - floor_y + 0.5) * v > op.wall_mm)
        if op.floor_mm is not None:
            ok &= y[j] > op.floor_mm
        if solid is not None:
            ok &= ~solid[:, j, :]
        waiting &= ~inside[:, j, :]
        cur &= ok | waiting
        if not cur.any():
            break
        E[:, j, :] = cur & ~waiting
    return E


def hollow_openings(hull: VoxelHull, values: np.ndarray, openings: list[Opening], masks, K, Ts,
                    solid_pts_table: np.ndarray | None = None) -> tuple[np.ndarray, list[tuple[Opening, float]]]:
    """``values`` (a signed grid on the hull's, inside positive) with each opening's inside hollowed.

    ``solid_pts_table``: surface points stereo observed (table mm); the descent stops at them. An opening
    whose hollowing would leave more than ``GUARD_PX`` of a view's silhouette with no hull behind it is left.
    Returns the grid and each opening hollowed with its volume, mm^3.
    """
    vals = np.asarray(values, np.float32).copy()
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    solid = None
    if solid_pts_table is not None and len(solid_pts_table):
        g = np.rint((np.asarray(solid_pts_table, float) - o) / v).astype(int)
        ok = np.all((g >= 0) & (g < np.array(vals.shape)), axis=1)
        solid = np.zeros(vals.shape, bool)
        solid[tuple(g[ok].T)] = True
        solid = ndimage.binary_dilation(solid)
    done = []
    for op in openings:
        inside = vals > 0
        ii, jj = np.nonzero(op.region)
        tan_e = steepest_tan(Ts, (op.origin_xz[0] + jj.mean() / op.px_per_mm, op.height_mm,
                                  op.origin_xz[1] + ii.mean() / op.px_per_mm))
        E = _inside_of(op, hull, inside, solid, tan_e)
        if not E.any():
            continue
        if uncovered_share(inside, inside & ~E, hull, masks, K, Ts) > GUARD_PX:
            continue
        # a signed distance to the hollowed surface in a box round it: negative inside the hollow, and no
        # larger than the distance to it outside
        idx = np.argwhere(E)
        pad = int(np.ceil(TAU_MM / v)) + 2
        lo = np.maximum(idx.min(0) - pad, 0)
        hi = np.minimum(idx.max(0) + pad + 1, vals.shape)
        box = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))
        e = E[box]
        d_in = ndimage.distance_transform_edt(e) * v
        d_out = ndimage.distance_transform_edt(~e) * v
        sub = vals[box]
        vals[box] = np.where(e, -np.minimum(d_in - 0.5 * v, TAU_MM).clip(0.5 * v),
                             np.minimum(sub, d_out - 0.5 * v)).astype(np.float32)
        done.append((op, float(E.sum()) * v ** 3))
    return vals, done
