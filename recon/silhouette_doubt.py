"""What one frame of a sequence cannot be sure of: the doubtful pixels of :mod:`recon.silhouettes`.

Colours are compared with a background plate per channel, in 0..255 units;
``tau`` is the sequence's agreement threshold. A pixel outside the mask is
*confident background* only where the object cannot fake what it shows:

* a colour the object does not show (its colour set, 8-DN bins grown by one)
  that a trusted plate matches closely, ``max_c |I_c - P_c| < 2 tau`` against
  the plate's own colour (not only within its 3 x 3 range, which at an edge of
  the backdrop spans many colours); or
* the table plate's printed texture reproduced: normalised cross-correlation
  ``NCC(I, P) > 0.8`` over 3 x 3 where the plate's grey-level variance exceeds
  ``(2 tau)^2``, the pixel within ``3 tau`` of the plate's range.

Everything else in the working volume's image is doubtful: white on white
paper, a mere shadow of the plate (the dull side of a pale object), a colour
only within a plate edge's range. Carving with ``mask | unknown`` then keeps
what a view cannot rule out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import binary_dilation

__all__ = ["Plate", "Evidence", "channel_max", "channel_sum", "doubtful_pixels", "texture_match", "colour_dist",
           "colour_gradient", "colour_range", "plate_envelope", "range_dist", "shadow_dist", "colour_set", "in_set",
           "major_colours", "MAJOR_SHARE", "doubt_joined", "blend_behind", "blend_alpha", "window_mean", "doubt_across",
           "doubt_unlike", "doubt_enclosed", "doubt_pinholes", "reach", "PINHOLE_SHARE"]


@dataclass(frozen=True)
class Plate:
    """A background plate in the box of one frame: median, 3x3 envelope, where it is trusted."""

    mid: np.ndarray  # (h, w, 3) uint8
    lo: np.ndarray
    hi: np.ndarray
    trust: np.ndarray  # (h, w) bool
    strong: np.ndarray  # (h, w) bool: background in nearly every frame


@dataclass(frozen=True)
class Evidence:
    """What the plates say about the pixels (h, w) of one frame's box."""

    labels: np.ndarray  # uint8 GrabCut labels
    explained: np.ndarray  # bool: a trusted plate matches the pixel's colour (its 3x3 envelope)
    tight: np.ndarray  # bool: ... and the plate's own colour there, within 2 tau (not loosely, at an edge)
    shadow: np.ndarray  # bool: a darker copy of a trusted plate matches it
    trusted: np.ndarray  # bool: some plate is trusted here
    disagrees: np.ndarray  # bool: a trusted plate contradicts the pixel
    background: np.ndarray  # (h, w, 3) uint8: the trusted plate's colour
    usable: np.ndarray  # bool: where ``background`` is meaningful


def channel_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=-1)`` of colours (..., 3): the same values (NaN where a channel is NaN, as there), ~10 x
    faster: numpy reduces a last axis of three one element at a time (15 of the 58 s of a sequence's
    silhouettes, 36 frames of 640 x 480, went to such maxima)."""
    if a.ndim == 0 or a.shape[-1] != 3:
        return a.max(axis=-1)
    return np.maximum(np.maximum(a[..., 0], a[..., 1]), a[..., 2])


def channel_sum(a: np.ndarray) -> np.ndarray:
    """``a.sum(axis=-1)`` of float colours (..., 3), added in the same order, so the same values; ~10 x faster
    for the same reason as :func:`channel_max`. Integer colours are summed by numpy (its wider result type)."""
    if a.ndim == 0 or a.shape[-1] != 3 or not np.issubdtype(a.dtype, np.floating):
        return a.sum(axis=-1)
    return a[..., 0] + a[..., 1] + a[..., 2]


def colour_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Largest per-channel difference (..., ) float32 between RGB arrays (..., 3), 0..255 units."""
    return channel_max(np.abs(a.astype(np.int16) - b.astype(np.int16))).astype(np.float32)


def plate_envelope(plate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel 3x3 min and max of a plate: agreement tolerates a pixel of blur or misregistration."""
    k = np.ones((3, 3), np.uint8)
    return cv2.erode(plate, k), cv2.dilate(plate, k)


def range_dist(img: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Largest per-channel distance (..., ) float32 from ``img`` to the interval [lo, hi]."""
    i = img.astype(np.int16)
    d = np.maximum(lo.astype(np.int16) - i, i - hi.astype(np.int16))
    return np.maximum(channel_max(d), 0).astype(np.float32)


def shadow_dist(img: np.ndarray, plate: np.ndarray) -> np.ndarray:
    """Distance (..., ) from ``img`` to the darkened plate ``g * plate`` (0.25 <= g <= 0.95) that fits it best."""
    i = img.astype(np.float32)
    p = plate.astype(np.float32)
    g = np.clip((i * p).sum(-1) / np.maximum((p * p).sum(-1), 1.0), 0.25, 0.95)
    return channel_max(np.abs(i - g[..., None] * p))


MAJOR_SHARE = 0.002  # an object colour fills at least this share of the object's pixels (one bin)
_BIN = 8  # colour-set bins: 8 DN per channel (32^3 bins), one bin of slack around each seen colour


def colour_gradient(img: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """(h, w) float32: the largest channel's Sobel gradient magnitude of ``img`` (h, w, C) after a Gaussian blur
    of ``sigma`` pixels: an edge in any colour."""
    smooth = cv2.GaussianBlur(np.asarray(img, np.float32), (0, 0), sigma)
    grad = np.zeros(smooth.shape[:2], np.float32)
    for c in range(smooth.shape[2]):
        grad = np.maximum(grad, cv2.magnitude(cv2.Sobel(smooth[..., c], cv2.CV_32F, 1, 0),
                                              cv2.Sobel(smooth[..., c], cv2.CV_32F, 0, 1)))
    return grad


def rim_counts(lab: np.ndarray, n: int, parts: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the labelled ``parts`` (``lab`` (h, w), labels 1 .. n - 1 on ``parts``, 0 elsewhere): the pixels of each
    one's outer rim (next to it, 8-connected, not of ``parts``) in ``sel`` (h, w) bool, and all of them, (n,) each."""
    grown = cv2.dilate(lab.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.int64)
    rim = (grown > 0) & ~parts
    return np.bincount(grown[rim & sel], minlength=n), np.bincount(grown[rim], minlength=n)


def colour_range(img: np.ndarray) -> np.ndarray:
    """(h, w) int16: the largest channel's 3 x 3 range (max - min) of ``img`` (h, w, C) uint8: an edge
    where it reaches ``2 tau`` (:func:`doubt_joined`, :func:`doubt_enclosed`)."""
    k3 = np.ones((3, 3), np.uint8)
    return channel_max(cv2.dilate(img, k3).astype(np.int16) - cv2.erode(img, k3))


_RAMP_WIN = 9  # shading_ramp's window, pixels
_RAMP_RESIDUAL = 0.5  # ... a plane fits the window's colours within this share of tau (RMS)
_RAMP_RISE = 2.0  # ... and rises across it by at least this many tau


def _plane_fit(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A tilted plane in x, y fitted to each channel of ``img`` (h, w, C) over a 9 x 9 window: the worst
    channel's residual variance and the largest rise across the window, (h, w) float32 each."""
    k = _RAMP_WIN
    r = np.arange(k, dtype=np.float32) - (k - 1) / 2
    kx = np.tile(r, (k, 1)) / (k * k)
    sxx = float((r ** 2).mean())
    worst = np.zeros(img.shape[:2], np.float32)
    rise = np.zeros(img.shape[:2], np.float32)
    for c in range(img.shape[2]):
        ch = img[..., c].astype(np.float32)
        mean = cv2.blur(ch, (k, k), borderType=cv2.BORDER_REFLECT)
        sq = cv2.blur(ch * ch, (k, k), borderType=cv2.BORDER_REFLECT)
        # filter2D correlates: the window's mean of x * I, x relative to its centre; / mean(x^2): the slope
        gx = cv2.filter2D(ch, -1, kx, borderType=cv2.BORDER_REFLECT) / sxx
        gy = cv2.filter2D(ch, -1, kx.T, borderType=cv2.BORDER_REFLECT) / sxx
        worst = np.maximum(worst, sq - mean * mean - (gx * gx + gy * gy) * sxx)
        rise = np.maximum(rise, np.hypot(gx, gy) * (k - 1))
    return worst, rise


def shading_ramp(img: np.ndarray, tau: float) -> np.ndarray:
    """(h, w) bool: where a tilted plane in x, y fits ``img`` over a 9 x 9 window: within ``tau / 2`` RMS in each
    channel, rising by ``2 tau`` or more across the window in one of them.

    A lit curved surface shades smoothly (the ramp of a sphere's grey from its
    lit cap to its shaded side); a texture (wood grain, clutter) or a step (an
    outline, the horizon) leaves a residual the size of its contrast, and a
    plain wall has no rise.
    """
    worst, rise = _plane_fit(img)
    return (worst < (_RAMP_RESIDUAL * tau) ** 2) & (rise >= _RAMP_RISE * tau)


def plane_fits(img: np.ndarray, tau: float) -> np.ndarray:
    """(h, w) bool: where a tilted plane fits ``img`` over a 9 x 9 window within ``tau / 2`` RMS in each channel,
    whatever its rise (:func:`shading_ramp` without the rise): smooth shading, or a plain stretch."""
    return _plane_fit(img)[0] < (_RAMP_RESIDUAL * tau) ** 2


def no_edge(img: np.ndarray, tau: float) -> np.ndarray:
    """(h, w) bool: pixels on no edge: a 3 x 3 colour range under ``2 tau`` (:func:`colour_range`) or a smooth
    ramp of shading (:func:`shading_ramp`), through which the doubt grows (:func:`doubt_joined`,
    :func:`doubt_enclosed`)."""
    return (colour_range(img) < 2.0 * tau) | shading_ramp(img, tau)


def colour_set(samples: np.ndarray, min_count: int = 2) -> np.ndarray:
    """(32, 32, 32) bool: the colours seen at least ``min_count`` times in ``samples`` (..., 3) uint8,
    grown by one bin (noise, a little shading)."""
    q = (samples.reshape(-1, 3) // _BIN).astype(np.intp)
    n = 256 // _BIN
    hist = np.bincount((q[:, 0] * n + q[:, 1]) * n + q[:, 2], minlength=n ** 3).reshape(n, n, n)
    seen = (hist >= min_count).astype(np.uint8)
    return binary_dilation(seen, np.ones((3, 3, 3), bool))


def major_colours(img: np.ndarray, sel: np.ndarray) -> np.ndarray | None:
    """:func:`colour_set` of the pixels of ``img`` at ``sel`` that fill at least ``MAJOR_SHARE`` of them
    (not a few dark crevices), or None where fewer than 50 are selected."""
    n = int(sel.sum())
    return colour_set(img[sel], min_count=max(3, int(MAJOR_SHARE * n))) if n >= 50 else None


HUE_BINS = 64  # hue_unlike: chromaticity (r, g over r + g + b) in bins this fine, ...
HUE_SLACK = 2  # ... grown by this many bins (0.03: a white body's warmer lit side and cooler shade) ...
HUE_MIN_SUM = 120  # ... for pixels with r + g + b at least this (a dark pixel's hue is noise)


def chromaticity(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) float32 chromaticity ``rgb / (r + g + b)`` of ``img`` (..., 3) and the sum (...) float32."""
    f = np.asarray(img, np.float32)
    total = channel_sum(f)
    return f / np.maximum(total, 1.0)[..., None], total


def _hue_bins(px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (r, g) chromaticity bins (``HUE_BINS`` each) of the pixels ``px`` (..., 3)."""
    q = np.clip((chromaticity(px)[0][..., :2] * HUE_BINS).astype(np.intp), 0, HUE_BINS - 1)
    return q[..., 0], q[..., 1]


def hue_unlike(img: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """(h, w) bool: bright pixels whose hue (chromaticity, whatever their brightness) is none of the hues
    filling at least ``MAJOR_SHARE`` of the bright pixels of ``img`` at ``sel`` (grown by ``HUE_SLACK`` bins).

    Shading changes an object's brightness, hardly its hue: a white body's shaded side is a grey of its
    lit side's chromaticity, a brown table's grain is not (all False where ``sel`` has fewer than 50 bright
    pixels)."""
    bright = img.astype(np.int32).sum(axis=-1) >= HUE_MIN_SUM
    pick = sel & bright
    n = int(pick.sum())
    if n < 50:
        return np.zeros(img.shape[:2], bool)
    r, g = _hue_bins(img[pick])
    hist = np.bincount(r * HUE_BINS + g, minlength=HUE_BINS ** 2).reshape(HUE_BINS, HUE_BINS)
    seen = cv2.dilate((hist >= max(3, int(MAJOR_SHARE * n))).astype(np.uint8),
                      np.ones((2 * HUE_SLACK + 1,) * 2, np.uint8)) > 0
    r, g = _hue_bins(img)
    return bright & ~seen[r, g]


def in_set(img: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """(...) bool: whether each pixel of ``img`` (..., 3) uint8 has a colour of the set."""
    q = (img // _BIN).astype(np.intp)
    return colours[q[..., 0], q[..., 1], q[..., 2]]


_INK_CONTRAST = 1.0 / 3.0  # the image reproduces the plate's ink with at least this share of its contrast


def texture_match(img, plate: Plate, tau) -> np.ndarray:
    """(h, w) bool: the pixel's 3 x 3 neighbourhood reproduces the trusted table plate's texture there.

    Where the plate has texture (printed ink: its 3 x 3 grey-level spread is
    above ``2 tau``), a normalised cross-correlation above 0.8 between the
    image and the plate says the ray reaches the paper: an object in front
    of it (white on white paper included) cannot draw the ink's pattern, nor
    its contrast (the image's 3 x 3 spread must be a third of the plate's or
    more: a white object's faint shading correlates by chance). The
    pixel itself must lie within ``3 tau`` of the plate's 3 x 3 range (the
    plate, resampled twice, is blurrier than the photo: thin ink is lighter
    in it), so an object pixel next to visible ink is not taken for it.
    """
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)
    p = cv2.cvtColor(plate.mid, cv2.COLOR_RGB2GRAY).astype(np.float32)

    def box(a):
        return cv2.blur(a, (3, 3), borderType=cv2.BORDER_REPLICATE)

    mg, mp = box(g), box(p)
    vg, vp = box(g * g) - mg * mg, box(p * p) - mp * mp
    cov = box(g * p) - mg * mp
    ncc = cov / np.sqrt(np.maximum(vg * vp, 1e-6))
    near = range_dist(img, plate.lo, plate.hi) < 3.0 * tau  # the pixel itself within the plate's range
    # and the image must draw the ink with a contrast of its own (its 3 x 3 spread at least a third of the
    # plate's): a white object's faint shading in front of a ring's edge correlates with it by chance
    drawn = vg > (_INK_CONTRAST ** 2) * vp
    return plate.trust & near & (vp > (2.0 * tau) ** 2) & drawn & (ncc > 0.8)


def doubtful_pixels(img, mask, region, ev: Evidence, ink: np.ndarray, plates_only: bool,
                    static: np.ndarray | None = None) -> np.ndarray:
    """(h, w) bool: pixels of the region outside the mask that are not confidently background.

    Confident background is what the object cannot fake: a colour none of the
    object's that a trusted plate matches closely (its own colour, not just
    the range of a plate pixel's neighbourhood, which at an edge of the
    backdrop spans many colours), or the table plate's printed texture
    reproduced (``ink``, see :func:`texture_match`). A colour of the object's that
    matches a plate is doubtful (white object on white paper), and so is a
    mere darker copy of the plate (a shadow: it could be the dull side of a
    pale object). Where no plate is trusted, a colour none of the object's is
    confident too, unless ``plates_only`` (a frame whose mask is in doubt:
    then the object's colours are also those of every pixel of the region
    that no plate explains). The object's colours are those filling at least
    0.2 % of its pixels: a few dark crevices do not make a dark room doubtful.
    ``static``: where the room plate is trusted but does not vouch for the room
    (a static object over the axis, see :class:`recon.silhouette_plates.Plates`):
    no plate speaks for the background there either, and a static figure's dark
    crease under its head (a colour its mask rarely shows) is no background.
    With ``plates_only`` a pixel is confident all the same where its hue is none
    of the mask's (:func:`hue_unlike`) and a trusted plate explains it, or none
    is trusted there: shading turns a white object grey, not brown, and taking
    every colour no plate explained for the object's let a wooden table's grain
    beside a white chair's seat into the unknown of every view (a slab above
    the seat no view carved: 1.52 -> 1.16 % of the diagonal on a light wall).
    """
    # a frame in doubt may have missed most of the object: what no plate explains may be it too
    obj = mask | (region & ~ev.explained) if plates_only else mask
    # the object's colours: those of at least 0.2 % of its pixels (not a few dark crevices)
    object_colours = major_colours(img, obj)
    if object_colours is None:
        object_colours = np.zeros((32,) * 3, bool)
    known = ev.tight if plates_only else ev.tight | (~ev.trusted if static is None else ~ev.trusted & ~static)
    confident = ~in_set(img, object_colours) & known
    if plates_only:  # ... but not in a hue the mask never shows, where a plate explains it or none is trusted
        confident |= (ev.explained | ~ev.trusted) & hue_unlike(img, mask)
    confident |= ink
    return region & ~mask & ~confident


def doubt_joined(img: np.ndarray, mask: np.ndarray, doubtful: np.ndarray, paper: np.ndarray, tau: float,
                 background: np.ndarray | None = None, usable: np.ndarray | None = None,
                 on_plate: np.ndarray | None = None) -> np.ndarray:
    """(h, w) bool: the doubtful pixels joined to the mask without crossing an edge: a frame's unknown pixels.

    A white object's shaded side against a wall of its own grey is doubtful, and
    so is that whole wall; what tells them apart is the edge. The mask's outline
    sits on one wherever the object's colour differs from the wall's, while the
    object's part the mask missed joins it through smooth shading. So the
    doubtful pixels are grown from the mask through pixels without an edge (their
    3 x 3 colour range under ``2 tau``, or a smooth ramp of shading,
    :func:`shading_ramp`: the dark underside of a white ball lit from above falls
    by ~6 grey levels a pixel, and cut off there it was carved in every view of
    the static body, a cone under it, 1.14 % of the diagonal; 8-connected), then one pixel further (the
    edge's own blended pixels; given the plates' colour, ``background`` and
    ``usable`` as in :class:`Evidence`, only those more object than background,
    :func:`blend_behind`, but any in a pinhole, :func:`doubt_pinholes`: the
    shaded line under a static vase's lip has a verified room plate of its own
    colour, and judged it cut a notch through the lip). Not through ``paper``,
    the pixels the table plate matches closely (the plane's own colour at that
    point, not a shadow of it): from an object part of the paper's colour resting on it there is no edge,
    and a grown region flooded the paper up to the printed rings. So a white
    object's part that looks exactly like the paper where it stands stays to
    the other views (a plinth's top is not ``paper``: the table plate there is
    an untrusted island, see :func:`recon.silhouette_plates.untrust_enclosed`;
    the paper round a vase's foot, which such an island also holds, is
    ``paper`` in the views its plate comes from:
    :meth:`recon.silhouette_plates.TablePlate.in_arc`),
    like a doubtful part behind an edge
    (a figure's head, its colour a plate's, beyond a shaded neck). Joining
    those across edges as well kept the head but let the unknown run over a
    cluttered wall of the object's colours (rendered chair, hull Chamfer 1.83
    -> 1.97 % of the diagonal; white figure on a light wall 3.55 -> 2.28 %).
    On the paper (``on_plate``: where the ray meets the plane on the table
    plate's disc) a stretch is joined only where the mask next to it (its
    5 x 5 mean) has the stretch's colour: a mask a pixel too fat ends on the
    paper's colour past the outline's edge, and from there the unknown took
    the shadowed paper round a white vase's foot, a skirt in the hull (vase
    on a light wall, 1280 x 960, seed 2: 0.78 -> 0.34 %; seen from 45 deg in
    a dark room 1.35 -> 1.07 %). Off the paper the wall's split
    (:func:`turntable.stages.volume.doubt_off_the_outline`) takes a flood of
    the wall off whole; stopped there too, part of it stayed, held (figure on
    a light wall, seed 3: 0.66 -> 0.70 %).
    """
    k3 = np.ones((3, 3), np.uint8)
    smooth = doubtful & ~paper & no_edge(img, tau)
    n, lab = cv2.connectedComponents(smooth.astype(np.uint8), connectivity=8)
    seeds = (cv2.dilate(mask.astype(np.uint8), k3) > 0) & smooth
    if on_plate is not None and (seeds & on_plate).any():  # ... on the paper, in the mask's colour next to it
        m = mask.astype(np.float32)
        near = cv2.boxFilter(m, -1, (5, 5), normalize=False)
        local = cv2.boxFilter(img.astype(np.float32) * m[..., None], -1, (5, 5), normalize=False)
        local = local / np.maximum(near, 1.0)[..., None]
        seeds &= ~on_plate | (channel_max(np.abs(img.astype(np.float32) - local)) < 2.0 * tau)
    keep = np.unique(lab[seeds])
    held = np.isin(lab, keep[keep > 0]) | mask
    ring = (cv2.dilate(held.astype(np.uint8), k3) > 0) & ~held & doubtful
    if background is not None and usable is not None:  # not in a pinhole: a crack in the object's shading
        ring &= ~(blend_behind(img, held, ring, background, usable, tau) & ~doubt_pinholes(held))
    return (held & doubtful) | ring


def blend_behind(img: np.ndarray, held: np.ndarray, ring: np.ndarray, background: np.ndarray, usable: np.ndarray,
                 tau: float) -> np.ndarray:
    """(h, w) bool: the ``ring`` pixels (the layer just outside ``held``, or the outer layer of what a
    frame holds) that are more background than object.

    A blended outline pixel's colour is ``alpha F + (1 - alpha) B``, with ``B`` the
    trusted plate's colour (``background``, where ``usable``; elsewhere the mean
    colour of the pixels two or more outside, within 7 x 7) and ``F`` the
    object's colour at the outline (the mean of the ``held`` pixels next to the
    ring, within 7 x 7). Where the two differ by more than ``3 tau`` the pixel
    goes to the side that covers most of it (``alpha < 1/2``: background, the
    ground truth's convention); elsewhere it cannot be told and is not returned.
    ``F`` is taken at the outline, not further in: a curved body's shading turns
    towards its limb, and the colour of its lit middle made a shaded limb's own
    pixels look like the background (a fifth of a shaded sphere's outline on a
    dark wall; a tenth of it next to the ring). A limb whose shade turns to the
    backdrop's within the outermost pixel still reads as the backdrop there.
    """
    f_img = img.astype(np.float32)
    k3 = np.ones((3, 3), np.uint8)
    # the object's colour at the outline: the held pixels next to the ring (further in, a curved body's
    # shading turns: its lit middle made the shaded limb's own pixels look like the background)
    F, has_F = window_mean(f_img, held & (cv2.dilate(ring.astype(np.uint8), k3) > 0))
    # where no plate is trusted, the colour just beyond the ring (the held pixels' outside, two pixels off)
    B_out, has_B = window_mean(f_img, cv2.dilate((held | ring).astype(np.uint8), k3) == 0)
    alpha, decidable = blend_alpha(f_img, F, np.where(usable[..., None], background.astype(np.float32), B_out), tau)
    return ring & has_F & (usable | has_B) & decidable & (alpha < 0.5)


def window_mean(img: np.ndarray, sel: np.ndarray, size: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Mean colour (h, w, 3) float32 of the ``sel`` pixels (h, w) bool of ``img`` (h, w, 3) within ``size`` x
    ``size`` of each pixel, and where there is any (h, w) bool."""
    weight = cv2.boxFilter(sel.astype(np.float32), -1, (size, size), normalize=False)
    mean = cv2.boxFilter(img.astype(np.float32) * sel[..., None], -1, (size, size), normalize=False)
    return mean / np.maximum(weight, 1e-6)[..., None], weight > 0.5


def blend_alpha(img: np.ndarray, F: np.ndarray, B: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """A blended pixel's coverage ``alpha = (I - B).(F - B) / |F - B|^2`` (h, w) float32 between the object's
    colour ``F`` and the background's ``B`` (h, w, 3) float32, and where it can be told (h, w) bool: the two
    colours more than ``3 tau`` apart in some channel."""
    fb = F - B
    alpha = channel_sum((img - B) * fb) / np.maximum(channel_sum(fb * fb), 1e-6)
    return alpha, channel_max(np.abs(fb)) > 3.0 * tau


def doubt_across(mask: np.ndarray, joined: np.ndarray, doubtful: np.ndarray, unvouched: np.ndarray,
                 gap_px: int = 1) -> np.ndarray:
    """(h, w) bool: doubtful pixels that no plate vouches for, in components reaching ``mask | joined``.

    :func:`doubt_joined` stops at edges. Beyond one, what the room plate
    explains only because it covers the same pixels in every frame (a static
    object part: the lip of a body of revolution, a head over the axis, lit
    brighter than any colour of the room) is not vouched for: ``unvouched``
    is where no table plate is trusted (the ray misses the table plate's disc,
    or meets it where the plate's colour and its shadow's are not the pixel's:
    a head seen against the table behind the turntable from higher up) and
    the room plate is trusted only in the room's own colours (see
    :class:`recon.silhouette_plates.Plates`). Such components within
    ``gap_px`` of what the frame already holds, or of components so reached
    (:func:`reach`: a head's lit half across a shaded neck of the wall's grey,
    its top across the terminator's band), are candidates;
    :func:`recon.silhouettes.estimate_silhouettes` keeps them where a fifth
    of the views or more agree, or four in five counting those whose mask
    holds them: a static part reaches the object in every view (or is in
    its mask, where it turns off the axis), a poster behind it only while
    the object turns past it.
    """
    cand = doubtful & unvouched & ~joined & ~mask
    return reach(cand, joined | mask, gap_px)


def doubt_unlike(mask: np.ndarray, held: np.ndarray, doubtful: np.ndarray, unlike: np.ndarray) -> np.ndarray:
    """(h, w) bool: doubtful pixels unlike the background, in components touching ``mask | held``.

    :func:`doubt_joined` grows only through smooth pixels, so a thin part of a
    white object (an arm: its shading turns across a few pixels, every one an
    edge) or a plinth beyond the shaded line where it meets the legs stays out,
    and every view that misses it carves it off: the white figure on a light
    wall lost both arms. ``unlike`` is where the pixel is not the background's
    own colour: a trusted plate there whose colour it does not have (within
    ``2 tau``), or no trusted plate and not the room plate's median colour (what
    the pixel shows in most frames). The wall or the paper the object's colour
    matches is the background's colour, so these components stop at it, as the
    smooth growth stops at edges; they are not grown further.
    """
    return reach(doubtful & unlike & ~held & ~mask, held | mask, 1, rounds=1)


def doubt_enclosed(img: np.ndarray, held: np.ndarray, doubtful: np.ndarray, tau: float,
                   smooth_share: float = 0.5, moved: np.ndarray | None = None) -> np.ndarray:
    """(h, w) bool: holes of ``held`` (a frame's mask and unknown pixels) that are doubtful throughout and
    joined to it through smooth shading.

    :func:`doubt_joined` does not grow through ``paper`` (it would flood the
    paper up to the rings), so a white body's lit side that looks exactly
    like the paper behind it stays out, even where the mask and the unknown
    surround it. A static body of revolution shows the same pixels in every
    view, and with none of them carving it a groove was cut round a white
    vase's belly (40 deg elevation, light wall: ~480 pixels a frame, 3.9 %
    of the bounding box diagonal). Such a hole is unknown when no pixel of
    it is confident background and at least ``smooth_share`` of its rim
    (its pixels next to ``held``) is smooth, no edge in the sense of
    :func:`doubt_joined` (3 x 3 colour range under ``2 tau``, or a ramp of
    shading): the missed
    part of a surface continues the held part's shading. A view through the
    object (between a figure's arm and its body, a cup's handle) is ringed
    by the object's outline, an edge nearly all round (measured: a fifth of
    the rim smooth against all of it for the belly), or shows the
    background's own evidence (the printed ink, a colour none of the
    object's), and stays. Holes are 4-connected (the held pixels
    8-connected) and do not touch the box's border.

    With ``moved`` ((h, w) bool: the pixels that are not the still room,
    :func:`recon.silhouette_plates.moved_pixels`), a hole the held pixels round
    which mostly moved, and whose inside (two pixels in from them) mostly did not, stays
    too: the still room seen through a part that turns, not a static body's
    surface (neither moves). A white chair's back from 20 deg up, before a
    light wall of its grey: the wall between its rails, its edges as faint
    as the rails', was filled in 26 views of 36 (over 1000 pixels each;
    1.02 -> 1.28 % of the diagonal once the rails were held).
    """
    free = ~held
    lab, fill, _ = _doubtful_holes(held, doubtful)
    n = len(fill)
    rim = free & (cv2.dilate(held.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    n_rim = np.bincount(lab[rim], minlength=n)
    n_smooth = np.bincount(lab[rim & no_edge(img, tau)], minlength=n)
    fill &= n_smooth >= smooth_share * np.maximum(n_rim, 1)
    if moved is not None and fill.any():
        # the held pixels round each hole (labelled by the hole they touch), and the hole's inside
        around = cv2.dilate(np.where(fill[lab], lab, 0).astype(np.float32), np.ones((3, 3), np.uint8))
        around = np.where(held, around, 0).astype(np.int64)
        n_around = np.bincount(around[around > 0], minlength=n)
        rim_moved = np.bincount(around[(around > 0) & moved], minlength=n) > 0.5 * n_around
        inside = free & (cv2.dilate(held.astype(np.uint8), np.ones((5, 5), np.uint8)) == 0)
        n_inside = np.bincount(lab[inside], minlength=n)
        inside_still = (n_inside > 0) & (np.bincount(lab[inside & moved], minlength=n) < 0.5 * n_inside)
        fill &= ~(rim_moved & inside_still)
    return fill[lab]


PINHOLE_SHARE = 0.01  # doubt_pinholes: a hole of at most this share of what the frame holds (16 px at least)


def doubt_pinholes(held: np.ndarray, doubtful: np.ndarray | None = None, share: float = PINHOLE_SHARE) -> np.ndarray:
    """(H, W) bool: the pinholes of ``held`` (a frame's mask and unknown pixels).

    A pinhole is a 4-connected hole of ``held`` that does not touch the image's
    border, of at most ``max(16, share * held pixels)`` pixels, and no pixel of
    it confident background (all ``doubtful``, where given). Whether it is a
    view through the object or a few pixels of its surface that look like the
    paper behind it, the frame alone cannot tell: :func:`recon.silhouettes.carved_alone`
    asks the other views.
    """
    held = np.asarray(held, bool)
    lab, fill, area = _doubtful_holes(held, doubtful)
    fill &= area <= max(16.0, share * float(np.count_nonzero(held)))
    return fill[lab]


def _doubtful_holes(held: np.ndarray, doubtful: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 4-connected holes of ``held`` (h, w) bool: their labels (h, w) (0: the held pixels), which labels (n,)
    are holes that do not touch the border and have no confident pixel (none not ``doubtful``; any hole where
    ``doubtful`` is None), and their areas (n,) in pixels."""
    free = ~held
    n, lab, stats, _ = cv2.connectedComponentsWithStats(free.astype(np.uint8), connectivity=4)
    fill = np.ones(n, bool)
    fill[0] = False  # the held pixels
    fill[np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]])] = False  # open to the border
    if doubtful is not None:
        fill[lab[free & ~np.asarray(doubtful, bool)]] = False  # some pixel of it is confident background
    return lab, fill, stats[:, cv2.CC_STAT_AREA]


def reach(cand: np.ndarray, base: np.ndarray, gap_px: int, rounds: int = 4) -> np.ndarray:
    """(h, w) bool: the components of ``cand`` within ``gap_px`` of ``base`` or of components so reached."""
    n, lab = cv2.connectedComponents(cand.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(cand)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * gap_px + 1, 2 * gap_px + 1))
    kept = np.zeros(n, bool)
    front = base
    for _ in range(rounds):
        near = cv2.dilate(front.astype(np.uint8), k) > 0
        new = np.unique(lab[near & cand])
        new = new[(new > 0) & ~kept[new]]
        if not len(new):
            break
        kept[new] = True
        front = np.isin(lab, new)
    return kept[lab]

