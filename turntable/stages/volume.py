"""The working volume: the cylinder on the table that silhouettes and carving look in.

A vertical cylinder about the turntable axis (table +Y), from the table plane
``Y = 0`` up to ``height_mm``, of radius ``radius_mm``. Its first guess comes
from what is known — the printed target's extent (a guess, not a limit: objects
overhang their target) or, with cameras from a file and no target, the largest
table circle every view sees whole — and its height is the highest point of
the axis that most views see (``recon.carving``). It GROWS when the data show
the object reaching past it: an automatic silhouette touching the image of the
cylinder's side or top, or the carved hull touching the cylinder's wall or top.
It grows up to the largest cylinder carving can still decide (half of the views
see it); an object reaching past that is reported as clipped, never silently.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

__all__ = ["WorkingVolume", "initial_volume", "mask_touches", "doubt_off_the_outline", "MIN_TOUCH_VIEWS",
           "SPLIT_MAX_GROWTH", "SPLIT_MAX_PAPER", "given_paper_share"]

_GROWTH = 1.25  # each step grows the radius by this factor ...
_MIN_STEP_MM = 10.0  # ... and by at least this much
_BAND_PX = 2  # a mask pixel within this many pixels inside the cylinder's image outline touches it
_MIN_TOUCH_PX = 3  # ... and a view touches the outline when at least this many of its mask pixels do
_SPLIT_MIN_VIEWS = 3  # the object's side of the split is voted on where at least this many views split a pixel
SPLIT_MAX_GROWTH = 1.3  # the split's hull may be this many times the one without the pieces (a neck given back)
SPLIT_MAX_PAPER = 0.25  # ... or more, where at most this share of what the split gives back is the paper
SPLIT_MAX_UNCOVERED = 0.03  # where the hull fits, a split may leave at most this share of a view's mask uncovered
_SPLIT_SIGMA_PX = 0.5  # the split's colour gradient: Gaussian sigma, pixels (_wall_side)
MIN_TOUCH_VIEWS = 2  # the volume grows when this many views' silhouettes touch it (one may be noise)


@dataclass(frozen=True)
class WorkingVolume:
    """Cylinder ``hypot(X, Z) <= radius_mm``, ``0 <= Y <= height_mm`` (table frame, mm).

    ``max_radius_mm``/``max_height_mm``: how far it can grow (the cameras'
    view); ``view_radius_mm``: the table circle every view sees whole, the
    first step of growth from a smaller guess; ``source``: where the first
    guess came from.
    """

    radius_mm: float
    height_mm: float
    max_radius_mm: float
    max_height_mm: float
    source: str
    view_radius_mm: float = 0.0

    def grown(self, side: bool, top: bool) -> WorkingVolume | None:
        """The next larger volume in the directions that touch; None when none of them can grow."""
        r, h = self.radius_mm, self.height_mm
        if side and r < self.max_radius_mm:
            # straight to the common view first: a volume that only just holds the object leaves the
            # silhouettes too little background around it (measured: hull IoU 0.75 at 1.2x the object's radius)
            r = min(max(_GROWTH * r, r + _MIN_STEP_MM, self.view_radius_mm), self.max_radius_mm)
        if top and h < self.max_height_mm:
            h = min(max(_GROWTH * h, h + _MIN_STEP_MM), self.max_height_mm)
        if (r, h) == (self.radius_mm, self.height_mm):
            return None
        return replace(self, radius_mm=r, height_mm=h)

    def key(self) -> list[float]:
        """What the stage-cache keys hold of it (0.01 mm)."""
        return [round(self.radius_mm, 2), round(self.height_mm, 2)]

    def describe(self) -> str:
        return f"radius {self.radius_mm:.0f} mm, height {self.height_mm:.0f} mm"


def initial_volume(K: np.ndarray, T_cam_table: np.ndarray, size: tuple[int, int],
                   target_extent_mm: float | None) -> WorkingVolume:
    """First guess and limits from the cameras (and the printed target's extent, when there is one).

    Raises ``ValueError`` when the views share no part of the table around the axis.
    """
    from recon.carving import largest_carvable_radius_mm, largest_visible_height_mm, largest_visible_radius_mm

    W, H = size
    h = largest_visible_height_mm(K, T_cam_table, W, H)
    r_max = largest_carvable_radius_mm(K, T_cam_table, W, H, h)
    if not (h > 0 and r_max > 0):
        raise ValueError("the views share no part of the turntable axis: most cameras do not see the table centre")
    r_view = largest_visible_radius_mm(K, T_cam_table, W, H)
    if target_extent_mm is not None:
        r, source = float(target_extent_mm) + 5.0, "the printed target's extent + 5 mm"
    elif r_view > 0:
        r, source = min(r_view, r_max), "the table circle every view sees whole"
    else:
        r, source = 0.5 * r_max, "half the carvable radius (no view sees the table circle whole)"
    return WorkingVolume(radius_mm=r, height_mm=h, max_radius_mm=max(r_max, r), max_height_mm=h, source=source,
                         view_radius_mm=min(r_view, r_max))


def mask_touches(masks: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, vol: WorkingVolume) -> tuple[list, list]:
    """Views whose silhouette touches the image of the volume's side / top.

    Automatic silhouettes are confined to the image of the cylinder, so an
    object larger than it shows as mask pixels along that outline. A touching
    pixel is put on the top when a taller cylinder's image holds it well inside
    (more height would free it), else on the side. The image border is not the
    cylinder's outline and does not count.

    Returns ``(side_views, top_views)``: indices into ``masks``.
    """
    from recon.silhouettes import cylinder_region

    masks = np.asarray(masks, bool)
    V, H, W = masks.shape
    kernel = np.ones((3, 3), np.uint8)
    inner = np.zeros((H, W), bool)
    inner[_BAND_PX:H - _BAND_PX, _BAND_PX:W - _BAND_PX] = True
    taller_h = vol.height_mm * _GROWTH + _MIN_STEP_MM
    side, top = [], []
    for i in range(V):
        if not masks[i].any():
            continue
        region = cylinder_region(K, T_cam_table[i], (W, H), vol.radius_mm, vol.height_mm).astype(np.uint8)
        band = (region > 0) & (cv2.erode(region, kernel, iterations=_BAND_PX) == 0)
        touch = masks[i] & band & inner
        if np.count_nonzero(touch) < _MIN_TOUCH_PX:
            continue
        taller = cylinder_region(K, T_cam_table[i], (W, H), vol.radius_mm, taller_h).astype(np.uint8)
        freed = cv2.erode(taller, kernel, iterations=2 * _BAND_PX) > 0
        if np.count_nonzero(touch & freed) >= _MIN_TOUCH_PX:
            top.append(i)
        if np.count_nonzero(touch & ~freed) >= _MIN_TOUCH_PX:
            side.append(i)
    return side, top


def doubt_off_the_outline(masks: np.ndarray, unknown: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray,
                          vol: WorkingVolume, images_rgb: np.ndarray | None = None,
                          whole: bool = False, moved: np.ndarray | None = None) -> tuple[np.ndarray, list[int]]:
    """``unknown`` less, per view, the doubt that runs to the volume's image outline.

    Carved from ``masks | unknown``, a hull that reaches the working volume's
    top or side while the masks fit inside it was grown by doubt, not by the
    object: a wall of the object's grey joined through a stretch of outline
    where the object's shade is close to the wall's (a static white vase on a
    light wall: the whole wall above it, the hull the volume's full height,
    22.8 % of the diagonal). Such a piece (8-connected, off the mask) reaches
    the outline of the cylinder's image, which the object's own doubtful
    parts do not.

    With ``images_rgb``, a piece is split along the image's edges first: a
    watershed of the colour gradient flooded from the mask and from the
    piece's pixels on the outline gives the object the part it reaches
    before crossing an edge (the neck through which the wall joined) and
    drops only the wall's side, except where most views that split the
    pixel give it to the object. Where the room is plain, the object's flood
    also starts from the piece's pixels off the table top in a colour the
    room never shows (:func:`recon.silhouettes.room_colour_set`): a figure's
    lit head, joined to a grey wall through its shaded side. ``whole=True`` (or no images) drops every
    such piece whole: the fallback where the split still leaves the hull at
    the outline (no edge between the object and the wall), at the price of
    the object's parts inside the piece. Where the split runs, a piece's pixels
    that ``moved`` ((V, H, W) bool, :attr:`recon.silhouettes.SilhouetteResult.moved`:
    not the still room) are never the wall's: a white chair's top rail before a
    light wall of its grey, joined to the wall on every side, went with it in
    the views that saw the back broad (1.27 % of the diagonal; 0.64 kept). They
    are closed over the window they were measured in
    (:func:`recon.silhouette_plates.moved_window_px`), to take in a faint part's
    pixels under the noise between them (1.15 % unclosed), then eroded as much,
    for the window spreads a part's difference past its outline: unshrunk, a
    white snowman's turning nose kept a rim of the wall all round (0.40 -> 0.49
    %). The moved pixels hold no seed of the object's flood: from there it ran
    out over the wall past the rail's faint edges (1.88 %). A dropped pixel that would leave a
    pinhole in what the view holds (:func:`recon.silhouette_doubt.doubt_pinholes`)
    through which the view alone would carve what every other view holds
    (:func:`recon.silhouettes.carved_alone`) stays.

    Returns ``(unknown, views)``: the pruned unknown pixels and the views that lost any.
    """
    from recon.silhouette_doubt import doubt_pinholes, in_set
    from recon.silhouette_plates import PLATE_BORDER_MM, moved_window_px
    from recon.silhouettes import carved_alone, cylinder_region, plain_room, room_colour_set

    masks, unknown = np.asarray(masks, bool), np.asarray(unknown, bool)
    V, H, W = masks.shape
    kernel = np.ones((3, 3), np.uint8)
    inner = np.zeros((H, W), bool)
    inner[_BAND_PX:H - _BAND_PX, _BAND_PX:W - _BAND_PX] = True
    split = images_rgb is not None and not whole
    regions = [cylinder_region(K, t, (W, H), vol.radius_mm, vol.height_mm) for t in T_cam_table]
    room_colours = None
    if split and images_rgb is not None:
        # the room's colours (as the silhouettes saw them): a pixel of a piece in front of the room with none of
        # them is the object's, whatever its flood meets first (a white figure's lit head on a grey wall, joined
        # to the wall through its shaded side, went with the wall in 29 views of 36)
        room_colours = room_colour_set(np.asarray(images_rgb), K, T_cam_table, vol.radius_mm,
                                       np.any(regions, axis=0))
        if not plain_room(room_colours):
            room_colours = None
    close = np.ones((moved_window_px((W, H)),) * 2, np.uint8)
    drop = np.zeros_like(unknown)
    in_piece = np.zeros((H, W), np.int32) if split else None
    kept = np.zeros((H, W), np.int32) if split else None
    for i in range(V):
        doubt = unknown[i] & ~masks[i]
        if not doubt.any():
            continue
        region = regions[i].astype(np.uint8)
        band = (region > 0) & (cv2.erode(region, kernel, iterations=_BAND_PX) == 0) & inner
        n, lab = cv2.connectedComponents(doubt.astype(np.uint8), connectivity=8)
        hit = np.unique(lab[band & doubt])
        hit = hit[hit > 0]
        if not len(hit):
            continue
        pieces = np.isin(lab, hit)
        seeds = None
        if room_colours is not None and images_rgb is not None:
            # off the table top (the paper is not the room's) and blobs, not a pixel of noise
            off_disc = ~cylinder_region(K, T_cam_table[i], (W, H), vol.radius_mm + PLATE_BORDER_MM, 0.0)
            unlike = (pieces & off_disc & ~in_set(np.asarray(images_rgb[i]), room_colours)).astype(np.uint8)
            seeds = cv2.morphologyEx(unlike, cv2.MORPH_OPEN, kernel) > 0
        drop[i] = _wall_side(images_rgb[i], masks[i], pieces, band, seeds) if split and masks[i].any() else pieces
        if split and moved is not None:
            closed = cv2.morphologyEx((pieces & moved[i]).astype(np.uint8), cv2.MORPH_CLOSE, close)
            drop[i] &= ~(pieces & (cv2.erode(closed, close) > 0))
        if split:
            in_piece += pieces
            kept += pieces & ~drop[i]
    if split:
        # a pixel the split gives the object in most of the views whose pieces hold it stays in every view: a part
        # static in the image (a vase's neck) is the same pixels in each frame, and one view whose flood crossed
        # a faint stretch of its outline first would carve it away alone
        held = (in_piece >= _SPLIT_MIN_VIEWS) & (2 * kept >= in_piece)
        drop &= ~held
    if drop.any():  # a dropped pixel that would leave a pinhole through which the view alone carves stays
        holds = masks | (unknown & ~drop)
        pins = np.stack([doubt_pinholes(h) & d for h, d in zip(holds, drop, strict=True)])
        drop &= ~carved_alone(pins, holds, K, T_cam_table, vol.radius_mm, vol.height_mm)
    views = [i for i in range(V) if drop[i].any()]
    return unknown & ~drop, views


def given_paper_share(given: np.ndarray, images_rgb, K: np.ndarray, T_cam_table: np.ndarray,
                      vol: WorkingVolume) -> float:
    """The share of the pixels ``given`` (V, H, W) bool that show the paper as the other views saw it
    (:func:`recon.silhouettes.paper_pixels`, in the working volume ``vol``); 0 where none is given.

    What a split of the doubt off the outline gives back to the object (the pixels
    its pieces keep) should be the object's: its shaded side or neck, joined to a
    wall of its grey. Where it is mostly the target's lit paper, the split followed
    the target's ink instead of the object's outline.
    """
    from recon.silhouettes import paper_pixels

    n = int(np.count_nonzero(given))
    if n == 0:
        return 0.0
    paper = paper_pixels(np.stack(list(images_rgb)), K, T_cam_table, vol.radius_mm, vol.height_mm)
    return float(np.count_nonzero(given & paper)) / n


def _wall_side(img: np.ndarray, mask: np.ndarray, pieces: np.ndarray, band: np.ndarray,
               seeds: np.ndarray | None = None) -> np.ndarray:
    """The pixels of ``pieces`` that a watershed of the image's colour gradient floods from the outline ``band``
    before the mask's flood (and that of the object's ``seeds`` in the pieces) reaches them (on the bounding box
    of the pieces and the mask)."""
    from skimage.segmentation import watershed

    from recon.silhouette_doubt import colour_gradient

    ys, xs = np.nonzero(pieces | mask)
    y0, y1 = max(ys.min() - 2, 0), min(ys.max() + 3, mask.shape[0])
    x0, x1 = max(xs.min() - 2, 0), min(xs.max() + 3, mask.shape[1])
    box = np.s_[y0:y1, x0:x1]
    # the largest channel's gradient: an edge in any colour. Smoothed little: at sigma 1 px the faint corner where
    # a white vase's shaded neck meets its rim blurred shut and the wall's flood leaked into the neck in most views
    # (vase on a light wall, 640x480, seed 2: 1.21 -> 0.47 % of the diagonal at 0.5 px)
    grad = colour_gradient(img[box], sigma=_SPLIT_SIGMA_PX)
    markers = np.zeros(grad.shape, np.int32)
    markers[mask[box]] = 1
    if seeds is not None:
        markers[seeds[box] & pieces[box]] = 1
    markers[pieces[box] & band[box]] = 2
    flooded = watershed(grad, markers, mask=(pieces | mask)[box])
    wall = np.zeros_like(pieces)
    wall[box] = (flooded == 2) & pieces[box]
    return wall
