"""Raised horizontal faces, found by a sweep of image edges over horizontal planes, and the roof over them.

A flat top (a plinth's, a box's lid) is carved by no silhouette: cameras
above the table see it only from the side, and the hull keeps a roof over
it as high as the top is wide times the tangent of the elevation (13 mm
over a 57 mm box seen from 30 deg). Stereo finds nothing on a plain white
top. Its outline does show: the step of shading between the top and its
sides. Warped onto the horizontal plane at the top's height, every view's
edges fall on the same outline; at any other height they scatter (each
view's parallax points another way). So each view's edges (Canny, inside
its silhouette) are rectified onto planes ``y = h`` every ``STEP_MM``, and
a height where a large share of the views put an edge on the same texels,
sharply more than 2 mm above and below, is a face's. Its faces are the
regions the outline encloses inside the hull's section (the section closes
the outline where a white top's edge against white paper shows no step, but
the outline holds a fifth of their rim at least: a box's vertical corners are
points on every plane)
whose colour the views agree on (a leg standing on the top breaks both),
if they are flat:
of one colour all over (a flat top's normal turns with the table about
itself, so under a light fixed to the camera every view sees it equally
lit; a dome's shading runs across it) and outlining nothing inside
themselves higher up (a lid's knob, a dome's contour), and tops: the hull
over them no higher than a roof over a top that wide can be (a torso's
section, outlined at one height, has the torso standing on it). A lid's
rim is a horizontal edge too, and a plain white dome agrees with every
vote below.

A hull voxel above a face is free where the views whose ray through it
lands on the face (eroded by ``ERODE_MM``) see there the face's colour (its
median over the views): at least ``MIN_VOTES`` views and ``VOTE_SHARE`` of
those eligible. A view whose pixel shows something in front of the face
(a leg, a torso) shows that thing's colour and does not vote. Nothing is
carved that leaves a pixel of a view's silhouette without a voxel of the
hull behind it (the guard: a roof's pixels are covered by the face below
it); a face whose carving would is left alone.

Under a flat top the hull may show a slab (:func:`carve_under_slabs`): its
section holds the top's footprint down to the slab's underside, then falls
away. No view sees into the wedge the silhouettes leave under it; that wedge
goes where free space lies under it, the underside taken flat.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from calib.camera import camera_centre_table, plane_homography, project_points

from .image_edges import edge_thresholds, edges, smoothed_grey
from .silhouette_doubt import channel_max, rim_counts
from .types import VoxelHull

__all__ = ["Face", "Slab", "Sweep", "sweep", "find_faces", "carve_above_faces", "carve_under_slabs", "space_under",
           "same_top", "uncovered_share", "hull_uncovered_share", "shell_points", "coverage"]

STEP_MM = 0.5  # the sweep's step in height
PX_PER_MM = 3.0  # the planes' raster ...
MAX_TEXELS = 250_000  # ... coarser where the object's footprint would need more texels
MAX_HEIGHTS = 400  # the sweep's step grows where more heights would be needed
MIN_HEIGHT_MM = 2.0  # faces start this far above the table (the table's own print is at 0)
EDGE_SHARE = 0.7  # a texel is on an outline where this share of the views that see it show an edge there ...
SOFT_EDGE_SHARE = 0.5  # ... or, where that finds no sharp peak, this share (a soft image's spread edges)
PEAK = 2.5  # ... a height is a face's where it has this many times the outline texels of 2 mm above and below
PEAK_OFFSET_MM = 2.0
MIN_OUTLINE_MM = 20.0  # ... and at least this long an outline
MIN_FACE_MM2 = 30.0  # a face's least area
OUTLINED_SHARE = 0.2  # ... and the share of its rim at least on its outline (the hull's section closes the rest)
INNER_MM = 1.5  # a face is flat where, this far inside its outline, ...
RISE_MM = 10.0  # ... the heights up to this far above it ...
RISE_SHARE = 0.02  # ... put at most this share of its texels on an outline
UNDER_SHARE = 0.5  # a face this much of which another one 2 to RISE_MM mm above covers is a slab's underside
ROOF_SLACK_MM = 2.0  # the hull over a top rises at most its width times the steepest view's tangent, and this
MIN_AGREE = 0.5  # a face's texels are those where this share of the views agree with their median colour
AGREE_DN = 10.0  # a view agrees with a colour within this (8-bit, each channel)
FLAT_SPREAD_DN = 8.0  # a face's colour (the views' median) spreads over at most this (5th to 95th percentile)
ERODE_MM = 1.0  # votes count only for rays landing this far inside the face
MARGIN_MM = 1.0  # voxels this close above the face are kept
MIN_VOTES = 3
VOTE_SHARE = 0.4
GUARD_PX = 0.02  # a face's carving may uncover at most this share of any view's silhouette (a shadow left in it)


@dataclass(frozen=True)
class Face:
    """A horizontal face ``height_mm`` above the table: ``region`` on the raster (i: z, j: x) from ``origin_xz``."""

    height_mm: float
    region: np.ndarray  # (nz, nx) bool
    colour: np.ndarray  # (nz, nx, 3) float32, the views' median colour on the face
    origin_xz: tuple[float, float]
    px_per_mm: float

    @property
    def area_mm2(self) -> float:
        return float(self.region.sum()) / self.px_per_mm ** 2


def _plane_map(K, T, h, x0, z0, px) -> np.ndarray:
    """3x3 map from raster (j, i, 1) on the plane y = h to pixels."""
    on_plane = np.eye(4)
    on_plane[1, 3] = h  # the table frame lifted to the plane: its points (X, 0, Z) are (X, h, Z)
    return plane_homography(K, np.asarray(T, float) @ on_plane) @ np.array([[1.0 / px, 0.0, x0],
                                                                          [0.0, 1.0 / px, z0], [0.0, 0.0, 1.0]])


def _warp(img, M, size, nearest=False) -> np.ndarray:
    flags = (cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR) | cv2.WARP_INVERSE_MAP
    return cv2.warpPerspective(img, M, size, flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _near(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: within 3 px of ``mask``."""
    return cv2.dilate(mask.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0


def _edges(img_rgb: np.ndarray, mask: np.ndarray, thresholds: tuple[float, float]) -> np.ndarray:
    e = edges(smoothed_grey(img_rgb), thresholds).astype(np.uint8)
    return (cv2.dilate(e, np.ones((3, 3), np.uint8)) > 0) & _near(mask)


def _sections(hull: VoxelHull, heights, x0, z0, shape, px) -> list[np.ndarray]:
    """The hull's horizontal section at each height on the raster."""
    inside = np.asarray(hull.values) > 0
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    nz, nx = shape
    ii, jj = np.mgrid[0:nz, 0:nx]
    gx = np.clip(np.rint((x0 + jj / px - o[0]) / v).astype(int), 0, inside.shape[0] - 1)
    gz = np.clip(np.rint((z0 + ii / px - o[2]) / v).astype(int), 0, inside.shape[2] - 1)
    out = []
    for h in heights:
        iy = int(round((h - o[1]) / v))
        out.append(inside[gx, iy, gz] if 0 <= iy < inside.shape[1] else np.zeros(shape, bool))
    return out


@dataclass(frozen=True)
class Sweep:
    """The views' edges rectified onto horizontal planes ``y = heights[k]``, on a raster of the object's footprint.

    Built once by :func:`sweep`; :func:`find_faces` and :func:`recon.openings.find_openings` read it.
    """

    heights: np.ndarray
    step: float
    sections: list[np.ndarray]  # the hull's section at each height, on the raster
    edges: list[np.ndarray]  # each view's edge pixels (uint8)
    K: np.ndarray
    Ts: np.ndarray
    x0: float
    z0: float
    px: float
    shape: tuple[int, int]  # (nz, nx)

    @property
    def size(self) -> tuple[int, int]:
        return (self.shape[1], self.shape[0])

    def within(self, masks) -> Sweep:
        """This sweep with each view's edges kept within 3 px of ``masks`` (V, H, W) bool, a part of the masks
        it was swept in (the flat tops' sure silhouettes, of the openings' silhouettes and unknown pixels)."""
        return dataclasses.replace(self, edges=[(e & _near(m)).astype(np.uint8)
                                                for e, m in zip(self.edges, masks, strict=True)])

    def rectify(self, image: np.ndarray, T: np.ndarray, h: float, nearest: bool = False) -> np.ndarray:
        """``image`` (seen from ``T``) warped onto the plane ``y = h``, on the sweep's raster (0 off the image)."""
        return _warp(image, _plane_map(self.K, T, h, self.x0, self.z0, self.px), self.size, nearest=nearest)

    def agreement(self, h: float, images_rgb) -> tuple[np.ndarray, np.ndarray]:
        """The views' colours on the plane ``y = h``: per texel, the share of the views that see it and agree
        with their median colour (within ``AGREE_DN``), and that median (0 where no view sees it)."""
        rect = np.stack([self.rectify(im, T, h) for im, T in zip(images_rgb, self.Ts, strict=True)])
        rect = rect.astype(np.float32)
        ones = np.ones(images_rgb[0].shape[:2], np.uint8)
        seen = np.stack([self.rectify(ones, T, h, nearest=True) > 0 for T in self.Ts])
        rect[~seen] = np.nan
        med = np.nanmedian(rect, axis=0)
        agree = np.nansum(channel_max(np.abs(rect - med)) < AGREE_DN, axis=0) / np.maximum(seen.sum(0), 1)
        return agree, np.nan_to_num(med)

    def outline(self, k: int, share: float = EDGE_SHARE) -> np.ndarray:
        """The texels where ``share`` of the views put an edge at height ``heights[k]``, within 2 mm of the hull."""
        votes = np.zeros(self.shape, np.float32)
        for e, T in zip(self.edges, self.Ts, strict=True):
            votes += _warp(e, _plane_map(self.K, T, float(self.heights[k]), self.x0, self.z0, self.px), self.size,
                           nearest=True)
        near = np.ones((int(4 * self.px) + 1,) * 2, np.uint8)  # 2 mm round the hull's section
        # the share of the views with an edge there (the hull is in every view: its working volume is)
        return (votes >= share * len(self.Ts)) & (cv2.dilate(self.sections[k].astype(np.uint8), near) > 0)

    @functools.cached_property
    def scores(self) -> dict[float, np.ndarray]:
        """Outline texels at each height, for the strict and the loose edge share."""
        return {share: np.array([self.outline(k, share).sum() for k in range(len(self.heights))])
                for share in (EDGE_SHARE, SOFT_EDGE_SHARE)}

    @functools.cached_property
    def peaks(self) -> list[tuple[int, float]]:
        """``(k, share)`` for each height, bottom up, where a horizontal outline peaks (see the module's docstring).

        A soft image (defocus) spreads a top's edge: fewer views put it on the same texels, and the outline the
        stricter share finds is thin on both sides of the peak; the looser share's is sharp.
        """
        return self.peaks_with(PEAK)

    def peaks_with(self, ratio: float, offset_mm: float = PEAK_OFFSET_MM,
                   every: bool = False) -> list[tuple[int, float]]:
        """:attr:`peaks` where a peak has ``ratio`` times the outline texels of ``offset_mm`` above and below
        (``every``: each share that peaks at a height, the strict one first; else only the first)."""
        heights, step = self.heights, self.step
        off = max(int(round(offset_mm / step)), 1)

        def peak(k: int, score: np.ndarray) -> bool:
            return bool(score[k] >= MIN_OUTLINE_MM * self.px and score[k] >= score[max(k - 2, 0):k + 3].max()
                        and score[k] >= ratio * max(score[k - off], score[k + off]))

        out: list[tuple[int, float]] = []
        for k in range(off, len(heights) - off):
            if float(heights[k]) < MIN_HEIGHT_MM:
                continue
            shares = [s for s, score in self.scores.items() if peak(k, score)]
            out.extend((k, s) for s in (shares if every else shares[:1]))
        return out


def sweep(images_rgb, masks, K, Ts, hull: VoxelHull) -> Sweep | None:
    """The plane sweep of the views' edges over the hull's height (None for an empty hull).

    ``masks``: (V, H, W) bool, where each view's edges are the object's: those within 3 px are swept (the
    openings read the silhouettes' unknown pixels too; the flat tops the sure silhouettes, :meth:`Sweep.within`;
    see ``turntable.reconstruct``).
    """
    inside = np.asarray(hull.values) > 0
    if not inside.any():
        return None
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    idx = np.argwhere(inside)
    lo, hi = o + idx.min(0) * v, o + idx.max(0) * v
    x0, z0 = lo[0] - 3.0, lo[2] - 3.0
    width, depth = hi[0] - lo[0] + 6.0, hi[2] - lo[2] + 6.0
    px = min(PX_PER_MM, math.sqrt(MAX_TEXELS / (width * depth)))  # a large object: a coarser raster
    shape = (int(math.ceil(depth * px)) + 1, int(math.ceil(width * px)) + 1)
    step = max(STEP_MM, (hi[1] + PEAK_OFFSET_MM) / MAX_HEIGHTS)
    heights = np.arange(MIN_HEIGHT_MM - PEAK_OFFSET_MM, hi[1] + PEAK_OFFSET_MM, step)
    thresholds = edge_thresholds(images_rgb, Ts)
    views = [_edges(im, m, thresholds).astype(np.uint8) for im, m in zip(images_rgb, masks, strict=True)]
    sections = _sections(hull, heights, x0, z0, shape, px)
    return Sweep(heights, float(step), sections, views, np.asarray(K, float), np.asarray(Ts, float), float(x0),
                 float(z0), float(px), shape)


def find_faces(images_rgb, masks, K, Ts, hull: VoxelHull, swept: Sweep | None = None) -> list[Face]:
    """The raised horizontal faces the views' edges outline (see the module's docstring).

    ``swept``: the sweep of these views over this hull, where the caller has it (:func:`sweep`).
    """
    sw = swept if swept is not None else sweep(images_rgb, masks, K, Ts, hull)
    if sw is None:
        return []
    heights, step = sw.heights, sw.step
    faces: list[Face] = []
    for k, share in sw.peaks:
        for face in _faces_at(sw, k, share, images_rgb):
            # flat: nothing inside it outlines itself higher up (a lid's dome, a knob: their contours do)
            r = max(int(round(INNER_MM * sw.px)), 1)
            inner = cv2.erode(face.region.astype(np.uint8), np.ones((2 * r + 1,) * 2, np.uint8)) > 0
            above = range(k + max(int(round(1.0 / step)), 1), min(k + int(round(RISE_MM / step)) + 1, len(heights)))
            if not inner.any() or any(_rises_inside(sw.outline(j, share), face.region, inner) > RISE_SHARE * inner.sum()
                                      for j in above):
                continue
            if _stands_high(face, hull, Ts):
                continue
            faces.append(face)
    return [f for f in faces if not _under_a_top(f, faces)]


def _rises_inside(outline: np.ndarray, region: np.ndarray, inner: np.ndarray) -> int:
    """The texels of ``inner`` that a higher height's ``outline`` puts inside the face, not counting an outline
    that runs on to the face's edge: a wall standing on the edge (a chair's back on its seat's rear edge)."""
    on = outline & region
    _, lab = cv2.connectedComponents(on.astype(np.uint8), connectivity=8)
    edge = np.unique(lab[on & ~inner])
    return int((on & inner & ~np.isin(lab, edge[edge > 0])).sum())


def same_top(face: Face, lower: Face) -> bool:
    """Whether ``lower``, found less than ``PEAK_OFFSET_MM`` under ``face``, holds most of it: one top whose
    peak was found again at the next height with the looser edge share (a chair's seat at 51.0 and 51.5 mm).
    Both carve (the second where the first's region ends); the run notes them as one top."""
    return 0.0 <= face.height_mm - lower.height_mm < PEAK_OFFSET_MM and _holds_most(lower, face)


def _holds_most(other: Face, face: Face) -> bool:
    """Whether ``other``'s region holds ``UNDER_SHARE`` of ``face``'s or more."""
    return bool((face.region & other.region).sum() >= UNDER_SHARE * face.region.sum())


def _under_a_top(face: Face, faces: list[Face]) -> bool:
    """Whether most of ``face`` lies under another face found 2 to ``RISE_MM`` mm above it: a slab's lower edge.

    A slab (a seat, a table's top) a few mm thick has a horizontal lower edge that the views put on the same
    outline, and rectified onto that plane they see its plain top above, one colour: a face, though no view
    sees that plane. Its top's parallax moves it in each view's direction (6 mm seen from 30 deg: ~10 mm), so
    the views agree on a region inside the outline, and the top outlines the same region higher up; carved
    to the lower face, a white chair's seat was dug out 6 mm deep over 1700 mm2 (its true masks given, and
    the automatic ones in a dark room).
    """
    return any(PEAK_OFFSET_MM <= other.height_mm - face.height_mm <= RISE_MM and _holds_most(other, face)
               for other in faces)


def steepest_tan(Ts, centre_table) -> float:
    """The tangent of the steepest view down onto ``centre_table`` (table mm): the highest camera's elevation
    over it, 0 where every camera is below it."""
    c0 = np.asarray(centre_table, float)
    return max(0.0, max(float((c[1] - c0[1]) / max(np.hypot(c[0] - c0[0], c[2] - c0[2]), 1e-6))
                        for c in (camera_centre_table(T) for T in Ts)))


def column_run_mm(hull: VoxelHull, x: np.ndarray, z: np.ndarray, h: float) -> np.ndarray | None:
    """How high the hull rises without a break from height ``h`` in the columns over ``(x, z)`` (table mm;
    None where ``h`` is above the grid)."""
    inside = np.asarray(hull.values) > 0
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    gx = np.clip(np.rint((x - o[0]) / v).astype(int), 0, inside.shape[0] - 1)
    gz = np.clip(np.rint((z - o[2]) / v).astype(int), 0, inside.shape[2] - 1)
    iy0 = max(int(np.ceil((h - o[1]) / v)), 0)
    if iy0 >= inside.shape[1]:
        return None
    cols = inside[gx, iy0:, gz]  # (N, ny) the hull up each column from h
    return np.where(cols.all(axis=1), cols.shape[1], np.argmin(cols, axis=1)) * v


def _stands_high(face: Face, hull: VoxelHull, Ts) -> bool:
    """Whether the hull over most of the face rises higher than any roof over a top of its size could.

    A flat top's roof is at most as high as the top is wide times the tangent of the steepest view onto
    it; a region found inside a body (a torso's section, whose contour happened to be outlined at one
    height) has the body standing on it.
    """
    ii, jj = np.nonzero(face.region)
    x = face.origin_xz[0] + jj / face.px_per_mm
    z = face.origin_xz[1] + ii / face.px_per_mm
    run = column_run_mm(hull, x, z, face.height_mm)
    if run is None:
        return False
    tan_e = steepest_tan(Ts, (x.mean(), face.height_mm, z.mean()))
    width = float(np.hypot(x.max() - x.min(), z.max() - z.min()))
    return float(np.median(run)) > width * tan_e + ROOF_SLACK_MM


def _faces_at(sw: Sweep, k: int, share: float, images_rgb) -> list[Face]:
    """The regions the outline at ``heights[k]`` encloses in the hull's section, where the views agree on a
    colour.

    Where the outline has a gap (a white top's edge against white paper shows no step) the hull's section
    closes it: no face reaches out of the hull. A region the section encloses nearly alone (the outline under
    ``OUTLINED_SHARE`` of its rim) is none.
    """
    h, px = float(sw.heights[k]), sw.px
    outline = cv2.dilate(sw.outline(k, share).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    wall = outline | ~sw.sections[k]
    n, lab = cv2.connectedComponents((~wall).astype(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    # enclosed by the outline for OUTLINED_SHARE of its rim at least, not by the section alone: a box's vertical
    # corners are points on every plane, and at 35.5 mm inside a 57 mm box they and the section enclosed a
    # "face" whose roof, the box's upper part, was carved hollow (seed 17, light wall: 2.35 % of the diagonal)
    on_outline, rim = rim_counts(lab, n, lab > 0, outline)
    big = [c for c in range(1, n) if c not in border and (lab == c).sum() >= MIN_FACE_MM2 * px ** 2
           and on_outline[c] >= OUTLINED_SHARE * rim[c]]
    if not big:  # nothing enclosed that could be a face: no need to warp every view's colours
        return []
    agree, med = sw.agreement(h, images_rgb)
    out = []
    for c in big:
        region = lab == c
        # the texels the views agree on (a leg's foot, the shadow a leg casts on the top are not)
        region &= agree >= MIN_AGREE
        region = cv2.morphologyEx(region.astype(np.uint8), cv2.MORPH_OPEN, np.ones((5, 5), np.uint8)) > 0
        if region.sum() / px ** 2 < MIN_FACE_MM2:
            continue
        # one colour all over: a flat top's normal turns with the table about itself, so under a light
        # fixed to the camera every view sees it equally lit; a dome's shading runs across it
        grey = med.mean(axis=-1)[region]
        lo, hi = np.percentile(grey, [5.0, 95.0])
        if hi - lo > FLAT_SPREAD_DN:
            continue
        out.append(Face(h, region, med.astype(np.float32), (sw.x0, sw.z0), px))
    return out


def _votes(face: Face, pts, images_rgb, K, Ts) -> tuple[np.ndarray, np.ndarray]:
    """Per point (N, 3) above the face: the views whose ray through it lands on the face, and those that see it."""
    px, (x0, z0) = face.px_per_mm, face.origin_xz
    r = int(round(ERODE_MM * px))
    region = cv2.erode(face.region.astype(np.uint8), np.ones((2 * r + 1,) * 2, np.uint8)) > 0 if r else face.region
    nz, nx = region.shape
    eligible = np.zeros(len(pts), np.int32)
    votes = np.zeros(len(pts), np.int32)
    for img, T in zip(images_rgb, Ts, strict=True):
        c = camera_centre_table(T)
        dy = pts[:, 1] - c[1]
        ok = dy < -1e-6  # the camera is above the point
        s = np.where(ok, (face.height_mm - c[1]) / np.where(ok, dy, -1.0), 0.0)
        P = c + s[:, None] * (pts - c)
        j = np.rint((P[:, 0] - x0) * px).astype(int)
        i = np.rint((P[:, 2] - z0) * px).astype(int)
        ok &= (i >= 0) & (j >= 0) & (i < nz) & (j < nx)
        ok[ok] &= region[i[ok], j[ok]]
        uv = project_points(K, T, pts[ok])
        u, w = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        H, W = img.shape[:2]
        inb = (u >= 0) & (w >= 0) & (u < W) & (w < H)
        sel = np.flatnonzero(ok)[inb]
        eligible[sel] += 1
        col = img[w[inb], u[inb]].astype(np.float32)
        same = np.abs(col - face.colour[i[sel], j[sel]]).max(axis=1) < AGREE_DN
        votes[sel[same]] += 1
    return votes, eligible


def shell_points(inside: np.ndarray, origin_table, voxel_mm: float) -> np.ndarray:
    """(N, 3) table mm: the centres of the voxels of ``inside`` (a grid from ``origin_table``, ``voxel_mm``
    apart) on its surface."""
    shell = inside & ~ndimage.binary_erosion(inside)
    return np.asarray(origin_table, float) + np.argwhere(shell) * float(voxel_mm)


def coverage(pts: np.ndarray, K, T, shape) -> np.ndarray:
    """(H, W) bool: the pixels the points (a hull's shell voxels) project to, 3 x 3 each."""
    cov = np.zeros(shape, np.uint8)
    if len(pts):
        uv = project_points(K, T, pts)
        u, w = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        H, W = shape
        ok = (u >= 0) & (w >= 0) & (u < W) & (w < H)
        cov[w[ok], u[ok]] = 1
    return cv2.dilate(cov, np.ones((3, 3), np.uint8)) > 0


def _on_raster(region: np.ndarray, face: Face, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Bool, ``x``'s shape: the table points (``x``, ``z``) mm on ``region``, a raster of ``face``'s (off it: False)."""
    i = np.rint((z - face.origin_xz[1]) * face.px_per_mm).astype(int)
    j = np.rint((x - face.origin_xz[0]) * face.px_per_mm).astype(int)
    nz, nx = region.shape
    on = (i >= 0) & (j >= 0) & (i < nz) & (j < nx)
    on[on] &= region[i[on], j[on]]
    return on


def uncovered_share(inside: np.ndarray, trial: np.ndarray, hull: VoxelHull, masks, K, Ts) -> float:
    """The largest share of a view's silhouette that carving ``inside`` down to ``trial`` leaves with no hull behind."""
    o, v = hull.origin_table, hull.voxel_mm
    return _uncovered(shell_points(inside, o, v), shell_points(trial, o, v), masks, K, Ts)


def hull_uncovered_share(before: VoxelHull, after: VoxelHull, masks, K, Ts) -> float:
    """:func:`uncovered_share` between two hulls, each on its own grid: the largest share of a view's silhouette
    (``masks``) that ``before`` covers and ``after`` leaves with no hull behind."""
    return _uncovered(shell_points(np.asarray(before.values) > 0, before.origin_table, before.voxel_mm),
                      shell_points(np.asarray(after.values) > 0, after.origin_table, after.voxel_mm), masks, K, Ts)


def _uncovered(before: np.ndarray, after: np.ndarray, masks, K, Ts) -> float:
    """The largest share of a view's silhouette that the shell points ``before`` cover and ``after`` do not."""
    shape = masks[0].shape
    return max(float((m & coverage(before, K, T, shape) & ~coverage(after, K, T, shape)).sum())
               / max(float(m.sum()), 1.0) for m, T in zip(masks, Ts, strict=True))


def carve_above_faces(hull: VoxelHull, images_rgb, masks, K, Ts,
                      swept: Sweep | None = None) -> tuple[VoxelHull, list[tuple[Face, float]]]:
    """The hull without the roof over its raised faces; and each face with the volume carved above it, mm^3.

    ``swept``: :func:`sweep` of these views over this hull, where the caller has it.
    """
    faces = find_faces(images_rgb, masks, K, Ts, hull, swept)
    if not faces:
        return hull, []
    vals = np.asarray(hull.values, np.float32).copy()
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    done = []
    for face in faces:
        inside = vals > 0
        idx = np.argwhere(inside)
        pts = o + idx * v
        col = _on_raster(face.region, face, pts[:, 0], pts[:, 2])
        above = col & (pts[:, 1] > face.height_mm + MARGIN_MM)
        if not above.any():
            continue
        votes, eligible = _votes(face, pts[above], images_rgb, K, Ts)
        free = (votes >= MIN_VOTES) & (votes >= VOTE_SHARE * eligible)
        if not free.any():
            continue
        carve = idx[above][free]
        trial = inside.copy()
        trial[tuple(carve.T)] = False
        # no pocket inside: what the votes free must open to the outside
        lab, _ = ndimage.label(~trial)
        outside = np.unique(np.concatenate([lab[0].ravel(), lab[-1].ravel(), lab[:, 0].ravel(), lab[:, -1].ravel(),
                                            lab[:, :, 0].ravel(), lab[:, :, -1].ravel()]))
        pocket = ~np.isin(lab, outside[outside > 0]) & ~trial
        trial |= pocket
        carve = np.argwhere(inside & ~trial)
        if not len(carve):
            continue
        if uncovered_share(inside, trial, hull, masks, K, Ts) > GUARD_PX:
            continue
        # the face's plane is the surface: signed distance to it above the face (the margin kept too,
        # in the columns carved above it), unchanged below
        ci = tuple(carve.T)
        vals[ci] = np.minimum(np.minimum(vals[ci], np.float32(face.height_mm) - (o[1] + carve[:, 1] * v)), -0.5 * v)
        cols = np.unique(carve[:, [0, 2]], axis=0)
        lo = int(np.floor((face.height_mm - o[1]) / v)) + 1
        hi = int(np.ceil((face.height_mm + MARGIN_MM - o[1]) / v)) + 1
        for iy in range(max(lo, 0), min(hi, vals.shape[1])):
            band = vals[cols[:, 0], iy, cols[:, 1]]
            vals[cols[:, 0], iy, cols[:, 1]] = np.minimum(band, np.float32(face.height_mm - (o[1] + iy * v)))
        done.append((face, len(carve) * v ** 3))
    return VoxelHull(values=vals, origin_table=hull.origin_table, voxel_mm=hull.voxel_mm, meta=dict(hull.meta)), done


SLAB_FULL = 0.97  # under a top, the hull's section holds this share of the top's footprint down to its underside ...
SLAB_BREAK = 0.8  # ... and less than this share SLAB_BREAK_MM lower: a slab's edge, the silhouettes' wedge under it
SLAB_BREAK_MM = 3.0
FOOTPRINT_MM = 3.0  # a top's footprint: the hull's section just under it within this of the face
TIP_MM = 2.0  # under a slab's unseen voxels the hull may go on this far (the wedge's tip, which views graze)
_CHUNK_COLUMNS = 20_000
UNDER_MARGIN_MM = 2.5  # space_under: the footprint grown this much (a voxel or two past the seat's section)


@dataclass(frozen=True)
class Slab:
    """A flat top's slab: its footprint (on the top's raster) and its underside's height above the table."""

    top: Face
    underside_mm: float
    footprint: np.ndarray  # (nz, nx) bool


def _slab_under(face: Face, hull: VoxelHull) -> Slab | None:
    """The slab under a flat top, where the hull shows one: its section holds the top's footprint down to a
    height, then falls away within ``SLAB_BREAK_MM`` (the silhouettes' view under the slab's edge)."""
    x0, z0 = face.origin_xz
    px, shape, v = face.px_per_mm, face.region.shape, float(hull.voxel_mm)
    r = int(math.ceil(FOOTPRINT_MM * px))
    near = cv2.dilate(face.region.astype(np.uint8), np.ones((2 * r + 1,) * 2, np.uint8)) > 0
    footprint = _sections(hull, [face.height_mm - 0.5 * v], x0, z0, shape, px)[0] & near
    if footprint.sum() < MIN_FACE_MM2 * px ** 2:
        return None
    heights = np.arange(face.height_mm - 0.5 * v, MIN_HEIGHT_MM, -0.5 * v)
    share = np.array([(s & footprint).sum() for s in _sections(hull, heights, x0, z0, shape, px)]) / footprint.sum()
    broken = np.flatnonzero(share < SLAB_FULL)
    if not len(broken) or broken[0] == 0:
        return None
    under = float(heights[broken[0] - 1])
    lower = np.flatnonzero(heights <= under - SLAB_BREAK_MM)
    if not len(lower) or share[lower[0]] >= SLAB_BREAK:
        return None
    return Slab(face, under, footprint)


def _hidden_counts(slab: Slab, pts: np.ndarray, Ts) -> np.ndarray:
    """(N,) the views in which the ray to each point (below the slab) crosses the slab's underside first."""
    h = slab.underside_mm
    count = np.zeros(len(pts), np.int32)
    for T in Ts:
        c = camera_centre_table(T)
        if c[1] <= h:  # a view from under the slab's plane sees under it
            continue
        s = (h - c[1]) / (pts[:, 1] - c[1])
        P = c + s[:, None] * (pts - c)
        count += _on_raster(slab.footprint, slab.top, P[:, 0], P[:, 2])
    return count


def _slab_columns(slab: Slab, inside: np.ndarray, o: np.ndarray, v: float) -> tuple[int, np.ndarray] | None:
    """The grid's highest layer whose centres lie under the slab's underside, and the (Nx, Nz) columns of its
    footprint that ``inside`` (the hull's grid, bool) holds there; None where no layer is under it."""
    iy_top = int(math.floor((slab.underside_mm - o[1]) / v - 0.5))
    if iy_top < 1:
        return None
    nx_, _, nz_ = inside.shape
    gx, gz = np.meshgrid(np.arange(nx_), np.arange(nz_), indexing="ij")
    return iy_top, _on_raster(slab.footprint, slab.top, o[0] + gx * v, o[2] + gz * v) & inside[:, iy_top, :]


def space_under(slabs: list[Slab], hull: VoxelHull) -> np.ndarray:
    """Bool, the hull's grid: the columns of each slab's footprint that ``hull`` holds just under the underside,
    grown by ``UNDER_MARGIN_MM``, from there down to the table, but for the columns ``hull`` holds all the way
    from the table up to the underside: a leg, which stands there (:func:`recon.shadows.carve_cast_shadows` looks
    for a skirt up to the seat in the rest, and the legs, left out, still hide the paper behind them and keep
    their faces of the shadow's grey). The margin: what the silhouettes hold under a seat bulges past the
    seat's own section by a voxel or two, and its sides there would hide the paper between the legs."""
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    inside = np.asarray(hull.values) > 0
    r = max(int(math.ceil(UNDER_MARGIN_MM / v)), 1)
    out = np.zeros(inside.shape, bool)
    if not inside.any():
        return out
    low = int(np.flatnonzero(inside.any(axis=(0, 2)))[0])  # the hull's lowest layer: the table
    for slab in slabs:
        cols = _slab_columns(slab, inside, o, v)
        if cols is None:
            continue
        iy_top, on = cols
        on = cv2.dilate(on.astype(np.uint8), np.ones((2 * r + 1,) * 2, np.uint8)) > 0
        on &= ~inside[:, low: iy_top + 1, :].all(axis=1)  # a leg stands from the table up to the underside
        out[:, : iy_top + 1, :] |= on[:, None, :]
    return out


def carve_under_slabs(hull: VoxelHull, faces: list[Face], masks, K, Ts) -> tuple[VoxelHull, list[tuple[Slab, float]]]:
    """The hull without the space under a flat top's slab that no view sees; each slab with the volume carved, mm^3.

    Cameras above the table see a slab (a seat, a table's top, a lid's rim) only
    from above and from the side: under it the silhouettes leave a wedge, down
    to where the views past the slab's edge meet (a white chair's seat, 6 mm
    thick 45 mm up, 54 mm wide, seen from 30 deg: a pyramid 12 mm deep, 0.35 %
    of the diagonal of the chair's 0.97 with its true masks). Nothing in the
    wedge's core is seen by any view: the slab hides it. The hull shows the slab
    (:func:`_slab_under`): its section under the top holds the top's footprint
    down to the underside, then falls away. A hull voxel below the underside is
    unseen where the ray from all views but one (the hull's tolerance) crosses
    the underside within the footprint; in a column of the footprint the unseen
    voxels from the underside down are the slab's wedge and carved where
    free space (carved by the silhouettes) lies right under them: legs, a box
    under an overhanging lid, anything the views do see under the slab, go on
    below them and keep the column whole. Nothing is carved that leaves a pixel
    of a view's silhouette without a voxel behind it (the same guard as
    :func:`carve_above_faces`).
    """
    vals = np.asarray(hull.values, np.float32).copy()
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    V = len(Ts)
    done = []
    for face in faces:
        # on the hull as it came: on the one carved under a slab, the same top found again 0.5 mm up made another
        slab = _slab_under(face, hull)
        if slab is None:
            continue
        inside = vals > 0
        h = slab.underside_mm
        # the footprint's columns of the grid, and their voxels from the underside down
        cols = _slab_columns(slab, inside, o, v)
        if cols is None:
            continue
        iy_top, on = cols
        cx, cz = np.nonzero(on)
        if not len(cx):
            continue
        # per column, from the underside down: the hull's voxels, and those no view but one sees (in chunks of
        # columns: a wide top over a tall grid would hold a GB of points at once)
        held = inside[cx, iy_top::-1, cz]  # (columns, layers)
        unseen = np.zeros_like(held)
        ys = o[1] + (iy_top - np.arange(iy_top + 1)) * v
        for c0 in range(0, len(cx), _CHUNK_COLUMNS):
            sel = slice(c0, c0 + _CHUNK_COLUMNS)
            k, m = np.nonzero(held[sel])
            pts = np.column_stack([o[0] + cx[sel][k] * v, ys[m], o[2] + cz[sel][k] * v])
            unseen[sel][k, m] = _hidden_counts(slab, pts, Ts) >= V - 1
        run = np.where(unseen.all(axis=1), unseen.shape[1], np.argmin(unseen, axis=1))  # unseen voxels from the top
        reach = np.where(held.all(axis=1), held.shape[1], np.argmin(held, axis=1))  # the hull's run from the top
        # the column's hull ends in free space above the table (down to it, it stands there: a leg) ...
        ends = (run > 0) & (o[1] + (iy_top - reach) * v >= MIN_HEIGHT_MM)
        # ... right under its unseen voxels, but for the tip the views past the slab's edge graze
        carve_cols = ends & (reach - run <= max(int(round(TIP_MM / v)), 1))
        # and a needle: a column or two thin that a few views' masks hold on down, among carved ones (it hung from
        # the white chair's seat, 20 mm long, where the wedge had hidden it)
        kept = np.zeros(inside.shape[::2], bool)
        kept[cx[ends & ~carve_cols], cz[ends & ~carve_cols]] = True
        kept &= ~ndimage.binary_opening(kept, np.ones((3, 3), bool))
        carve_cols |= ends & kept[cx, cz]
        if not carve_cols.any():
            continue
        ux, uz, n = cx[carve_cols], cz[carve_cols], reach[carve_cols]
        k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)  # 0 .. n - 1 down each column
        carve = np.column_stack([np.repeat(ux, n), iy_top - k, np.repeat(uz, n)])
        trial = inside.copy()
        trial[tuple(carve.T)] = False
        if uncovered_share(inside, trial, hull, masks, K, Ts) > GUARD_PX:
            continue
        # the underside's plane is the surface: signed distance to it under the slab, and in the layer over it
        ci = tuple(carve.T)
        vals[ci] = np.minimum(np.minimum(vals[ci], (o[1] + carve[:, 1] * v) - np.float32(h)), -0.5 * v)
        iy = iy_top + 1
        if iy < vals.shape[1]:
            vals[ux, iy, uz] = np.minimum(vals[ux, iy, uz], np.float32((o[1] + iy * v) - h))
        done.append((slab, len(carve) * v ** 3))
    return VoxelHull(values=vals, origin_table=hull.origin_table, voxel_mm=hull.voxel_mm, meta=dict(hull.meta)), done
