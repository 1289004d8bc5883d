"""Background plates of a turntable sequence: the room (image median) and the table (rectified median).

The camera does not move, so the room is static in the image: the per-pixel
median over frames is the *room plate*. The turntable disc and the printed
target turn with the table: every frame rectified onto the plane ``Y = 0``
(:func:`rectify_to_table`) and the median there is the *table plate*, warped
back into each frame (:meth:`Plates.table_in_frame`). A plate is trusted where
most frames agree with it, except a plain island of the table plate that
untrusted texels enclose (:func:`untrust_enclosed`: the top of something that
turns with the table above the plane, such as a plinth). Used by
:mod:`recon.silhouettes`.
"""

from __future__ import annotations

import math
from typing import NamedTuple, cast

import cv2
import numpy as np

from calib.camera import camera_centre_table, plane_homography

from .silhouette_checks import camera_azimuths_deg
from .silhouette_doubt import (
    Plate,
    channel_max,
    chromaticity,
    colour_dist,
    colour_gradient,
    in_set,
    plane_fits,
    plate_envelope,
    range_dist,
    rim_counts,
)

__all__ = ["Plates", "TablePlate", "rectify_to_table", "raster_to_table", "median_frames", "below_horizon",
           "table_plate", "moved_pixels", "moved_window_px", "room_off_masks",
           "PLANE_PX_PER_MM", "PLATE_BORDER_MM", "TRUST", "STRONG", "untrust_enclosed"]

PLANE_PX_PER_MM = 2.5  # table-plate resolution
PLATE_BORDER_MM = 40.0  # the table plate reaches this far beyond the working volume
TRUST = 0.6  # a plate is trusted where this fraction of frames agrees with it
STRONG = 0.75  # ... and its explanations are hard constraints where this fraction does


def raster_to_table(size_px: int, px_per_mm: float) -> np.ndarray:
    """3x3 map from raster pixels (j, i, 1) to table plane (X, Z, 1); centre pixel at the origin."""
    c = (size_px - 1) / 2.0
    return np.array([[1.0 / px_per_mm, 0.0, -c / px_per_mm], [0.0, 1.0 / px_per_mm, -c / px_per_mm], [0.0, 0.0, 1.0]])


def raster_radius_px(size_px: int) -> np.ndarray:
    """(N, N) float64: each raster pixel's distance from the raster's centre (the table's origin), in pixels."""
    c = (size_px - 1) / 2.0
    ii, jj = np.mgrid[0:size_px, 0:size_px]
    return np.hypot(ii - c, jj - c)


def azimuth_gap_deg(a, b) -> np.ndarray:
    """|a - b| in degrees on the circle, in [0, 180] (broadcast)."""
    return np.abs(np.mod(np.asarray(a) - b + 180.0, 360.0) - 180.0)


def rectify_to_table(image: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, radius_mm: float,
                     px_per_mm: float) -> np.ndarray:
    """The table plane around the origin as a square raster, seen from above.

    Pixel (i, j) of the (N, N[, 3]) result shows the plane point ``X = (j - c)
    / px_per_mm``, ``Z = (i - c) / px_per_mm`` (``c = (N - 1) / 2``, the
    layout of :func:`turntable.pattern.render_target_image`), ``N`` covering
    ``[-radius_mm, radius_mm]``; bilinear, zero outside the image.
    """
    n = int(2 * math.ceil(radius_mm * px_per_mm) + 1)
    M = plane_homography(K, T_cam_table) @ raster_to_table(n, px_per_mm)
    return cv2.warpPerspective(image, M, (n, n), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def median_frames(stack: np.ndarray) -> np.ndarray:
    """Per-pixel median (lower middle) over axis 0 of a uint8 stack."""
    k = (len(stack) - 1) // 2
    return np.partition(stack, k, axis=0)[k]


MOVED_WINDOW_PX = 5  # moved_pixels: colour differences averaged over this window (odd; at 640 x 480, scaled) ...
MOVED_NOISE = 1.5  # ... a pixel moved where that exceeds this many times its 99.9th percentile on still pixels ...
MOVED_MIN_STILL = 1000  # ... measured on at least this many still pixels (fewer: nothing is said to have moved)


def moved_window_px(size_wh: tuple[int, int]) -> int:
    """:data:`MOVED_WINDOW_PX` for an image of ``size_wh`` (scaled with its diagonal, 800 px at 640 x 480; odd)."""
    return 2 * int(round(MOVED_WINDOW_PX / 2.0 * math.hypot(*size_wh) / 800.0)) + 1


def room_off_masks(frames: np.ndarray, masks: np.ndarray, min_frames: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The room plate from the frames whose mask does not hold the pixel: their per-pixel median (lower middle),
    (h, w, 3) uint8, and where at least ``min_frames`` frames give one, (h, w) bool.

    Where an object covers a pixel in most frames (a snowman's off-axis head) the
    plain median (:func:`median_frames`) is the object, and a frame that shows the
    wall there differs from it (:func:`moved_pixels`) as much as one that shows the
    object over the wall elsewhere. Leaving out the frames whose mask holds the
    pixel leaves the room's.
    """
    frames, masks = np.asarray(frames), np.asarray(masks, bool)
    V, h, w = frames.shape[:3]
    ref = np.zeros((h, w, 3), np.uint8)
    n = (~masks).sum(axis=0)
    rows = max(1, (1 << 24) // max(1, V * w * 3))  # ~32 MiB of int16 at a time
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        st = frames[:, r0:r1].astype(np.int16)
        st[masks[:, r0:r1]] = np.iinfo(np.int16).max  # held: sorted past the room's values
        st.sort(axis=0)
        k = np.maximum((n[r0:r1] - 1) // 2, 0)
        ref[r0:r1] = np.take_along_axis(st, k[None, ..., None].repeat(3, axis=-1), axis=0)[0].clip(0, 255)
    return ref, n >= min_frames


def moved_pixels(frames: np.ndarray, room: np.ndarray, still: np.ndarray, window_px: int) -> np.ndarray:
    """(V, h, w) bool: where a frame is not the still room.

    A pixel has moved where its colour, averaged over ``window_px`` x
    ``window_px``, differs from the room plate's (``room``, (h, w, 3) uint8:
    :func:`room_off_masks`, or the frames' median), in its largest channel, by more than :data:`MOVED_NOISE`
    times the 99.9th percentile of the same measure on the ``still`` pixels
    ((h, w) bool: the room off the working volume's image and off the turning
    disc, which only the camera's noise and exposure change). The window lets
    a faint but coherent difference show: a white chair's top rail before a
    light wall of nearly its grey (4 - 10 levels from it; the wall's own
    99.9th percentile 2.3 at 5 x 5) turns with the table, the wall stays. A
    body of revolution that covers the same pixels in every frame is the room
    plate there, and does not move. With fewer than :data:`MOVED_MIN_STILL`
    still pixels (the volume fills the image) nothing is said to have moved.
    """
    frames = np.asarray(frames)
    out = np.zeros(frames.shape[:3], bool)
    if int(np.count_nonzero(still)) < MOVED_MIN_STILL:
        return out
    ref = room.astype(np.float32)
    k = (window_px, window_px)

    def diff(i: int) -> np.ndarray:
        return channel_max(np.abs(cv2.blur(frames[i].astype(np.float32) - ref, k)))

    step = max(1, int(np.count_nonzero(still)) * len(frames) // 1_000_000)  # ~1e6 samples at most
    noise = float(np.percentile(np.concatenate([diff(i)[still][::step] for i in range(len(frames))]), 99.9))
    for i in range(len(frames)):
        out[i] = diff(i) > MOVED_NOISE * noise
    return out


def below_horizon(K, T, box, size_hw) -> np.ndarray:
    """(h, w) bool: pixels of the box whose rays meet the table plane in front of the camera."""
    y0, x0 = box
    h, w = size_hw
    a = (T[:3, :3].T @ np.linalg.inv(K))[1]  # table-Y component of the ray through (u, v, 1)
    u = np.arange(x0, x0 + w, dtype=np.float64)
    v = np.arange(y0, y0 + h, dtype=np.float64)
    dy = a[0] * u[None, :] + a[1] * v[:, None] + a[2]
    cam_above = camera_centre_table(T)[1] > 0
    return dy < 0 if cam_above else dy > 0


ISLAND_INK_SHARE = 0.1  # an enclosed island of the table plate with this share of ink is paper seen through a gap
INK_DARK = 0.6  # ink: texture darker than this fraction of the paper's grey level (the island's 90th percentile)
ARC_DEG = 90.0  # where the views disagree, a plane point's table plate comes from those within this azimuth of it
ARC_BIN_DEG = 10.0


class TablePlate(NamedTuple):
    """The table plate (:func:`table_plate`), on the raster of :func:`rectify_to_table`."""

    plate: np.ndarray  # (n, n, 3) uint8: the median colour of each plane point
    lo: np.ndarray  # (n, n, 3) uint8: its 3 x 3 envelope
    hi: np.ndarray
    trust: np.ndarray  # (n, n) uint8: most of the counted views agree and all of them see it
    arc_centre_deg: np.ndarray  # (n, n) float32: a point whose plate comes from an arc of views: its centre
    arc_half_deg: np.ndarray  # (n, n) float32: ... and half its width (360 where every view counted)

    def in_arc(self, azimuth_deg: float) -> np.ndarray:
        """(n, n) bool: the points whose plate comes from the views on their own side, the view from
        ``azimuth_deg`` (:func:`recon.silhouette_checks.camera_azimuths_deg`) among them."""
        d = azimuth_gap_deg(azimuth_deg, self.arc_centre_deg)
        return (self.arc_half_deg < 360.0) & (d <= self.arc_half_deg)


def table_plate(rect: np.ndarray, seen: np.ndarray, T: np.ndarray, tau: float, radius_px: float) -> TablePlate:
    """The table plate: per plane point the median of the rectified frames, and where it is trusted.

    ``rect`` (V, n, n, 3) uint8 and ``seen`` (V, n, n) bool come from
    :func:`rectify_to_table`. A plane point next to the object is hidden by
    it from the far side of the turn and seen from its own side (the camera's
    azimuth about the table axis near the point's). Behind a plainly coloured
    object the hiding frames all show the same colour, and over a whole turn
    they can be the majority: a white vase made the paper behind it look like
    the vase, and so the vase like the paper. So each point also has a median
    over the views within ``ARC_DEG`` of its azimuth (at least a third of the
    sequence: the nearest ones, for a partial turn); where it differs from
    the median over all views (by more than ``tau``), it replaces it, and the
    agreement that decides trust is counted over those views (looked for only
    where fewer than 95 % of all views agree: elsewhere nothing hid the
    point). Elsewhere all
    views count: seen from its own side a point is nearer and less oblique
    than through a gap of the object from the far side (a chair's back), so
    the arc alone would explain the latter worse. Within the working volume
    only (``radius_px`` from the raster's centre): beyond it the plane ``Y =
    0`` may be air past the turntable's edge, which shows the rim from its
    own side and the table behind from the other.
    Returns a :class:`TablePlate`: the plate, its 3x3 envelope (lo, hi),
    where it is trusted (most of the counted views agree and all of them
    see it), and, where the plate comes from the views on the point's own
    side, which views those are (:meth:`TablePlate.in_arc`): a view among
    them sees the plate there, the others saw the object in front of it.
    """
    V, n = rect.shape[:2]
    cam = camera_azimuths_deg(T)
    c = (n - 1) / 2.0
    ii, jj = np.mgrid[0:n, 0:n]
    phi = np.degrees(np.arctan2(ii - c, jj - c))  # raster (i, j) is the plane point X = j - c, Z = i - c
    nb = int(round(360.0 / ARC_BIN_DEG))
    bins = np.floor(np.mod(phi + 180.0, 360.0) / ARC_BIN_DEG).astype(int) % nb
    bins[raster_radius_px(n) > radius_px] = nb  # beyond the volume: one group, every view
    least = min(V, max(5, int(math.ceil(V / 3))))
    full = median_frames(rect)
    lo_f, hi_f = plate_envelope(full)
    agree = np.mean([range_dist(r, lo_f, hi_f) < tau for r in rect], axis=0)
    all_seen = cast(np.ndarray, seen.all(axis=0))  # numpy's stubs allow a scalar for axis=0
    # where (nearly) every view agrees nothing hid the point: the arcs are needed only elsewhere
    doubt = (bins < nb) & (agree < 0.95)
    plate = full.copy()
    frames_of = []
    centres = -180.0 + (np.arange(nb + 1) + 0.5) * ARC_BIN_DEG
    halves = np.full(nb + 1, 360.0)
    for b in range(nb):
        d = azimuth_gap_deg(cam, centres[b])
        sel = np.flatnonzero(d <= ARC_DEG)
        if len(sel) < least:
            sel = np.argsort(d, kind="stable")[:least]
        halves[b] = d[sel].max()
        pix = doubt & (bins == b)
        frames_of.append((sel, pix))
        if pix.any():
            plate[pix] = median_frames(rect[:, pix][sel])
    changed = colour_dist(plate, full) >= tau
    arc_centre = centres[bins].astype(np.float32)
    arc_half = np.where(changed, halves[bins], 360.0).astype(np.float32)
    if not changed.any():
        trust = ((agree >= TRUST) & all_seen).astype(np.uint8)
        return TablePlate(full, lo_f, hi_f, trust, arc_centre, arc_half)
    lo, hi = plate_envelope(plate)
    near = cv2.dilate(changed.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # the envelope changed there
    for sel, pix in frames_of:
        pix = pix & changed
        if pix.any():
            agree[pix] = np.mean(range_dist(rect[:, pix][sel], lo[pix], hi[pix]) < tau, axis=0)
            all_seen[pix] = seen[:, pix][sel].all(axis=0)
    rest = near & ~changed  # the envelope moved under them: count all views again
    if rest.any():
        agree[rest] = np.mean(range_dist(rect[:, rest], lo[rest], hi[rest]) < tau, axis=0)
    return TablePlate(plate, lo, hi, ((agree >= TRUST) & all_seen).astype(np.uint8), arc_centre, arc_half)


def plate_ink(plate: np.ndarray, tau: float) -> np.ndarray:
    """(n, n) bool: the table plate's texels showing printed ink (or any texture): grey-level 3 x 3
    spread above ``2 tau``."""
    g = cv2.cvtColor(plate, cv2.COLOR_RGB2GRAY).astype(np.float32)
    m = cv2.blur(g, (3, 3))
    return (cv2.blur(g * g, (3, 3)) - m * m) > (2.0 * tau) ** 2


def untrust_enclosed(trust: np.ndarray, plate: np.ndarray, tau: float) -> np.ndarray:
    """The table plate's trust (uint8) less its plain islands: trusted texels that untrusted ones enclose.

    A surface that turns with the table above the plane (a plinth's top) looks
    the same in every frame rectified onto the plane, so the plate there is
    that surface, trusted, and where it has the paper's colour it explains
    itself away as paper in every view: the white figure's plinth was carved
    off whole (0.97 of its 1.55 % Chamfer). Its outline gives it away: the
    parallax of its edges (up to ``h cot(elevation)`` on the plane) and its
    shaded sides change from frame to frame, so the plate is untrusted in a
    closed band around it. The paper itself is one trusted expanse around the
    object, reaching the plate's border, and the islands a trusted but plain
    texture (grey-level 3 x 3 spread under ``2 tau`` on most of it) the band
    encloses are no longer trusted: a view then tells them from the paper only
    by what joins them to the mask. An island showing printed ink (the ring,
    the marks: texture darker than ``INK_DARK`` of the island's paper) is paper
    seen through a gap of the object and keeps its trust. A plinth's rim and the
    feet standing on it leave texture too, but pale: seen from 45 deg the white
    figure's plinth top had 10.1 % of it, kept its trust, and was carved down in
    every view that saw it from above.
    The paper round a vase's foot, which the belly's overhang hides from the
    far side, is such an island too: its plate comes from the views on its
    own side (:meth:`TablePlate.in_arc`), and for those views it still stops
    the unknown's growth (``paper`` in :func:`recon.silhouette_doubt.doubt_joined`;
    grown over, it left a skirt round the white vase at 1280 x 960, 2.3 % of
    the diagonal), while for the others it protects the belly in front of it.
    """
    t = (trust > 0).astype(np.uint8)
    n, lab = cv2.connectedComponents(t, connectivity=4)
    if n <= 2:
        return trust
    sizes = np.bincount(lab.ravel(), minlength=n)
    sizes[0] = 0
    outer = np.zeros(n, bool)
    outer[np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))] = True
    outer[int(np.argmax(sizes))] = True
    inked = plate_ink(plate, tau)
    ink_share = np.bincount(lab.ravel(), weights=inked.ravel(), minlength=n) / np.maximum(sizes, 1)
    grey = cv2.cvtColor(plate, cv2.COLOR_RGB2GRAY).astype(np.float32)
    for k in np.flatnonzero(~outer & (ink_share > ISLAND_INK_SHARE)):
        # ink is dark on the paper; the shading ramps of a plinth's rim and round the feet on it are pale
        at = lab == k
        ink_share[k] = np.mean(inked[at] & (grey[at] < INK_DARK * np.percentile(grey[at], 90)))
    keep = outer | (ink_share > ISLAND_INK_SHARE)
    keep[0] = False
    return (keep[lab] & (t > 0)).astype(np.uint8)


SHADE_LO, SHADE_HI = 0.35, 0.8  # untrust_shade: a plain texel this dark against the paper's grey (ink: darker) ...
SHADE_MIN_DN = 4.0  # ... and at least this many tau darker than it, ...
SHADE_AXIS_PX = 3.0  # ... in a piece over the axis (this near), ...
SHADE_RINGED = 0.65  # ... or in a piece this much of whose outer rim is untrusted (the foot of an object off the axis)
SHADE_MIN_MM2 = 20.0  # ... and at least this large


def untrust_shade(trust: np.ndarray, plate: np.ndarray, tau: float, radius_px: float) -> np.ndarray:
    """The table plate's trust (uint8) less its plain mid-grey shades that do not reach the volume's rim.

    A room light's shadow on the paper stays in the room while the table
    turns: in the table frame it moves, and it is never one trusted plate.
    What shows one grey at the same point of the table in every frame turns
    with the table: an object standing there or its contact shadow. The plate
    under and behind a white box in a dark room, its sides lit by the ambient
    light alone, was their grey in every view (0.63 of the paper's), trusted,
    and explained the lower half of the sides away as paper wherever they
    showed it (4.45 % of the diagonal; seed 4 at 640 x 480). Neither is the
    paper as a view sees it: trusted texels darker than ``SHADE_HI`` of the
    paper's grey (the trusted plate's 90th percentile) and ``SHADE_MIN_DN tau``
    or more below it, yet lighter than ``SHADE_LO`` of it (printed ink is
    darker, and textured: within a pixel of its dark :func:`plate_ink` they stay), in
    pieces (8-connected) under the object that do not reach ``radius_px``
    (a turntable's rim of its own grey turns with it too, and is no object),
    are no longer trusted. Under the object: over the axis (within
    ``SHADE_AXIS_PX``), or, off it, a piece of ``SHADE_MIN_MM2`` or more
    whose outer rim is untrusted for ``SHADE_RINGED`` of its length or more:
    where an object stands, every view shows its grey, and round it the views
    disagree (its sides against the paper, the paper beyond them: a white box
    standing 8 mm off the axis kept its grey trusted, 2.06 % of the
    diagonal; its rim 0.77 untrusted). A shade that rings a foot (the shaded paper round
    a vase's foot, which untrusted, the vase's masks took) has its longer,
    outer edge on the lit paper, and the blended edges of the printed ink
    none untrusted (the white figures' largest such share: 0.54). A view then
    tells such a shade from the object by what joins it to the mask (the
    doubt), as an island's (:func:`untrust_enclosed`).
    """
    t = trust > 0
    if not t.any():
        return trust
    g = cv2.cvtColor(plate, cv2.COLOR_RGB2GRAY).astype(np.float32)
    ref = float(np.percentile(g[t], 90))
    ink = cv2.dilate((plate_ink(plate, tau) & (g < SHADE_LO * ref)).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    shade = t & ~ink & (g >= SHADE_LO * ref) & (g <= SHADE_HI * ref) & (g <= ref - SHADE_MIN_DN * tau)
    if not shade.any():
        return trust
    n, lab = cv2.connectedComponents(shade.astype(np.uint8), connectivity=8)
    rr = raster_radius_px(len(g))
    rim = np.unique(lab[rr >= radius_px])
    inner = np.zeros(n, bool)
    inner[np.unique(lab[rr <= SHADE_AXIS_PX])] = True  # under the object: over the axis ...
    # ... or, off it, where it stands: the piece's outer rim (the texels beside it) mostly untrusted, as the views
    # disagree round an object (a shade ringing a foot has its longer, outer edge on the trusted paper)
    untrusted, total = rim_counts(lab, n, shade, ~t)
    size = np.bincount(lab.ravel(), minlength=n)
    inner |= (untrusted >= SHADE_RINGED * np.maximum(total, 1)) & (size >= SHADE_MIN_MM2 * PLANE_PX_PER_MM ** 2)
    inner[rim] = False
    inner[0] = False
    return (t & ~inner[lab]).astype(np.uint8)


GROUND_CHROMA = 0.08  # a printed ground is coloured when its chromaticity is this far from grey's (1/3 each)
GROUND_SHARE = 0.5  # ... and when this share of the paper's plain texels has its chromaticity
_GROUND_TOL = 0.04  # chromaticity tolerance of a ground pixel (plus the noise's share at its brightness)
_GROUND_MIN_SUM = 90.0  # R + G + B: darker pixels' chromaticity is mostly noise


def printed_ground(plate: np.ndarray, trust: np.ndarray, radius_px: float, tau: float) -> np.ndarray | None:
    """The chromaticity (3,) of a coloured printed ground, or None where the paper is white or grey.

    The paper is the table plate's trusted, plain texels (no ink: grey-level 3 x 3
    spread under ``2 tau``) within ``radius_px`` of its centre. Its chromaticity
    survives shading (a shadow on green paper stays green), so a ground chosen
    unlike the object (``turntable pattern --background green`` for a white one)
    tells paper from object wherever the table plate cannot: next to the object,
    where it hides the paper in most frames.
    """
    sel = (trust > 0) & ~plate_ink(plate, tau) & (raster_radius_px(plate.shape[0]) <= radius_px)
    chroma, total = chromaticity(plate[sel])
    chroma = chroma[total >= _GROUND_MIN_SUM]
    if len(chroma) < 100:
        return None
    ground = np.median(chroma, axis=0)
    if np.abs(ground - 1.0 / 3.0).max() < GROUND_CHROMA:
        return None
    if np.mean(channel_max(np.abs(chroma - ground)) < _GROUND_TOL) < GROUND_SHARE:
        return None
    return ground


def ground_match(img: np.ndarray, ground: np.ndarray, tau: float, noise: float = 3.0) -> np.ndarray:
    """(h, w) bool: pixels with the printed ground's chromaticity (:func:`printed_ground`), lit or shaded,
    within ``_GROUND_TOL`` plus ``noise`` x ``tau`` over the pixel's R + G + B."""
    chroma, total = chromaticity(img)
    tol = _GROUND_TOL + noise * tau / np.maximum(total, 1.0)
    return (total >= _GROUND_MIN_SUM) & (channel_max(np.abs(chroma - ground)) < tol)


def reached_from_outside(room: np.ndarray, inside: np.ndarray, room_colours: np.ndarray, tau: float,
                         shading: bool = True) -> np.ndarray:
    """(h, w) bool: where the room plate may vouch for the room inside the volume's image, by where it lies.

    A plain stretch of the plate is the room's where it joins the room outside
    the volume's image through pixels of the room's colours without crossing
    an edge of the plate (colour gradient above ``2 tau``, widened by a pixel):
    the wall behind the object. A static object inside the volume (a white
    body of revolution, which the plate shows in every frame) is enclosed by
    its outline's edge even where its shade is one of the wall's colours; by
    colour alone it was the room's or not by chance (a vase seen at 40 deg on
    a light wall: its shaded side taken for background, 6.1 % of the diagonal).
    Textured stretches (the gradient's 9 x 9 mean above ``2 tau``: a wooden
    table's grain, clutter) keep the colour rule: their own edges would cut
    them off, and no plain static object looks like them. Except (``shading``)
    a smooth stretch (a tilted plane fits it, :func:`plane_fits`) joined to a
    colour the room never shows: a static body's shading, whose grey runs
    through the wall's between its lit side and its dark outline, is no
    stretch of the room. A static head lit from above (a white figure on a
    light wall: its head, vouched for, was missing from every view and the
    model, 1.75 % of the diagonal); a static bottle lit from the side, whose
    gentle shade in front of the paper (too gentle for :func:`shading_ramp`,
    steep enough to count as texture) was vouched for as a stripe of the
    room down its whole height in every view, and the hull lost a shell half
    its radius deep (3.6 % of the diagonal on a light wall).
    """
    grad = colour_gradient(room)
    edge = cv2.dilate((grad > 2.0 * tau).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    roomlike = in_set(room, room_colours)
    free = roomlike & ~edge
    n, lab = cv2.connectedComponents(free.astype(np.uint8), connectivity=4)
    hit = np.zeros(n, bool)
    hit[np.unique(lab[free & ~inside])] = True
    hit[0] = False
    textured = cv2.blur(grad, (9, 9)) > 2.0 * tau
    if shading:
        # a smooth stretch that runs into a colour the room never shows is an object's shading
        ramp = inside & textured & plane_fits(room, tau)
        n, rl = cv2.connectedComponents(ramp.astype(np.uint8), connectivity=8)
        foreign = cv2.dilate((inside & ~roomlike).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        smooth = np.zeros(n, bool)
        smooth[np.unique(rl[ramp & foreign])] = True
        smooth[0] = False
        textured &= ~smooth[rl]
    return hit[lab] | textured


class Plates:
    """Room plate (image) and table plate (rectified plane), with where they are trusted."""

    def __init__(self, crops, images, K, T, box, radius_mm, tau, inside, room_colours):
        room = median_frames(crops)
        lo, hi = plate_envelope(room)
        # (V, h, w) bool: where each frame shows the room plate's colour (within its 3 x 3 range and tau)
        self.room_alike = np.stack([range_dist(c, lo, hi) < tau for c in crops])
        agree = self.room_alike.mean(axis=0)
        # Inside the cylinder's image a static plate pixel may be a static object (a uniformly
        # coloured body of revolution looks the same in every frame): trust it as background only
        # where its colour is one the surroundings show outside the cylinder, and, where the plate
        # is plain, where it joins them without crossing an edge (reached_from_outside).
        self.room = Plate(room, lo, hi, agree >= TRUST, agree >= STRONG)
        self.room_colours = room_colours
        self.plane_radius = radius_mm + PLATE_BORDER_MM
        rect = np.stack([rectify_to_table(im, K, t, self.plane_radius, PLANE_PX_PER_MM)
                         for im, t in zip(images, T, strict=True)])
        ones = np.ones(images.shape[1:3], np.uint8)
        seen = np.stack([rectify_to_table(ones, K, t, self.plane_radius, PLANE_PX_PER_MM) > 0 for t in T])
        tp = table_plate(rect, seen, T, tau, radius_mm * PLANE_PX_PER_MM)
        self.table, self.table_lo, self.table_hi, self.table_trust = tp.plate, tp.lo, tp.hi, tp.trust
        self._table_arcs = tp
        trust = untrust_enclosed(self.table_trust, self.table, tau)
        # an island is no room's either: a static object there (a body of revolution) is the room plate too
        self.table_island = (self.table_trust > trust).astype(np.uint8)
        # and the shades that turn with the table (an object's face standing there: untrust_shade) are trusted
        # by no view, nor made islands, whose plate the views on their own side would trust again
        trust = untrust_shade(trust, self.table, tau, radius_mm * PLANE_PX_PER_MM)
        self.table_trust = trust
        self.ground = printed_ground(self.table, trust, radius_mm * PLANE_PX_PER_MM, tau)
        self.table_disc = (raster_radius_px(self.table.shape[0])
                           <= self.plane_radius * PLANE_PX_PER_MM).astype(np.uint8)  # the plate's disc
        self.K, self.box = K, box
        verified = ~inside | (in_set(room, room_colours) & reached_from_outside(room, inside, room_colours, tau))
        self.room_verified = Plate(room, lo, hi, self.room.trust & verified, self.room.strong & verified)

    def _to_box(self, T: np.ndarray) -> np.ndarray:
        """3x3 map from the table-plate raster to the pixels of frame ``T``'s box."""
        y0, x0 = self.box
        return np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1.0]]) @ plane_homography(self.K, T) \
            @ raster_to_table(self.table.shape[0], PLANE_PX_PER_MM)

    def table_in_frame(self, T: np.ndarray, size_hw) -> Plate:
        """The table plate warped into the box of frame ``T``."""
        h, w = size_hw
        M = self._to_box(T)
        table, lo, hi = [cv2.warpPerspective(p, M, (w, h), flags=cv2.INTER_LINEAR, borderValue=0)
                         for p in (self.table, self.table_lo, self.table_hi)]
        trust = cv2.warpPerspective(self.table_trust, M, (w, h), flags=cv2.INTER_NEAREST, borderValue=0) > 0
        trust &= below_horizon(self.K, T, self.box, size_hw)
        return Plate(table, lo, hi, trust, trust)

    def in_arc_in_frame(self, T: np.ndarray, size_hw) -> np.ndarray:
        """(h, w) bool: the pixels of frame ``T``'s box whose plane point has its table plate from the views
        on its own side, this one among them (:meth:`TablePlate.in_arc`)."""
        h, w = size_hw
        az = float(camera_azimuths_deg(T[None])[0])
        inside = self._table_arcs.in_arc(az).astype(np.uint8)
        if not inside.any():
            return np.zeros((h, w), bool)
        on = cv2.warpPerspective(inside, self._to_box(T), (w, h), flags=cv2.INTER_NEAREST, borderValue=0) > 0
        return on & below_horizon(self.K, T, self.box, size_hw)

    def plate_in_frame(self, T: np.ndarray, size_hw) -> np.ndarray:
        """(h, w) bool: the pixels of frame ``T``'s box whose rays meet the plane on the table plate's disc."""
        h, w = size_hw
        on = cv2.warpPerspective(self.table_disc, self._to_box(T), (w, h), flags=cv2.INTER_NEAREST, borderValue=0) > 0
        return on & below_horizon(self.K, T, self.box, size_hw)

    def island_in_frame(self, T: np.ndarray, size_hw) -> np.ndarray:
        """(h, w) bool: the pixels of frame ``T``'s box that show an untrusted island of the table plate
        (:func:`untrust_enclosed`): no plate explains them, the room plate neither."""
        h, w = size_hw
        if not self.table_island.any():
            return np.zeros((h, w), bool)
        island = cv2.warpPerspective(self.table_island, self._to_box(T), (w, h), flags=cv2.INTER_NEAREST,
                                     borderValue=0) > 0
        return island & below_horizon(self.K, T, self.box, size_hw)
