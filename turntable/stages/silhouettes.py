"""Stage 3, silhouettes: automatic (``recon.silhouettes``) or ``--masks``, with a verdict per view."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..progress import Progress
from ..worksize import WorkSize
from .frames import undistort_with


@dataclass(frozen=True)
class Silhouettes:
    masks: np.ndarray  # (V, H, W) bool: object
    unknown: np.ndarray  # (V, H, W) bool: neither object nor background for sure (carving keeps it)
    status: list[str]  # "ok", "conservative: <reason>" (kept) or "rejected: <reason>" (dropped)
    ground: tuple[float, float, float] | None = None  # a coloured printed ground's chromaticity, recognised
    moved: np.ndarray | None = None  # (V, H, W) bool: off the disc, not the still room (automatic silhouettes only)


def ground_name(chroma) -> str:
    """The hue of a printed ground's chromaticity (r, g, b summing to 1) in words: red, yellow, green, cyan,
    blue or magenta (what the camera saw: a printed green may photograph a little cyan)."""
    import colorsys

    hue = colorsys.rgb_to_hsv(*(float(c) for c in chroma))[0]
    names = ("red", "yellow", "green", "cyan", "blue", "magenta")
    return names[int(round(hue * 6.0)) % 6]


def describe_ground(chroma) -> str:
    """One line on a recognised coloured ground (the run's notes and the summary)."""
    r, g, b = (float(c) for c in chroma)
    return (f"the target's printed ground is coloured ({ground_name(chroma)}, chromaticity {r:.2f} {g:.2f} {b:.2f}): "
            "next to the object the paper is told by its colour")


EMPTY_SHARE = 0.25  # this share of the automatic silhouettes (nearly) empty: the run says what would help


def silhouette_advice(rejected: dict[str, str], conservative: dict[str, str], n_frames: int,
                      ground=None) -> str | None:
    """A hint when many automatic silhouettes came out (nearly) empty (``rejected`` and ``conservative``: the
    frames' reasons, :func:`verdicts`): the object looks like what is behind it, and what would tell them apart.
    None when few did (or with ``--masks``, whose empty masks say "the mask is empty")."""
    from recon.silhouette_checks import EMPTY

    empty = sum(EMPTY in why for why in (*rejected.values(), *conservative.values()))
    if n_frames <= 0 or empty < max(2, EMPTY_SHARE * n_frames):
        return None
    ground_tip = "" if ground is not None else \
        ", print the target on a coloured ground (turntable pattern --background green)"
    return (f"{empty} of {n_frames} automatic silhouettes came out (nearly) empty: the object looks like what "
            "is behind it (a white object on the white paper, before a light wall?). Photograph it before a dark "
            f"backdrop{ground_tip}, or give --masks (README: 'Scanning a white object')")


def read_masks(masks_dir: Path, names: list[str], ws: WorkSize,
                progress: Progress | None = None) -> tuple[np.ndarray, dict[str, str]]:
    """Masks matched to frames by file stem, as large as the photos (or their shape scaled, with a note); any
    image format; > 127 = object.

    A mask with transparency (a cut-out: the object on transparent pixels, as
    background removers write it) is its alpha channel, whatever its colours,
    with a note. A mask holding only 0 and one value up to 127 (a label image:
    0/1, 0/100) takes that value as the object, with a note. Returned at the work size
    (V, h, w) bool: each mask is reduced (area average, then > 0.5) as it is
    read; and for each mask with no object pixel, why (its brightest value).
    """
    import cv2

    from ..images import read_alpha, read_image
    from ..mask_checks import check_masks

    if not masks_dir.is_dir():
        raise UserError(f"--masks {masks_dir}: not a folder")
    (W, H), (w, h) = ws.full, ws.work
    out = np.zeros((len(names), h, w), bool)
    empty: dict[str, str] = {}
    labels: list[str] = []
    cutouts: list[str] = []
    scaled: list[str] = []
    for i, (n, p) in enumerate(zip(names, mask_files(masks_dir, names), strict=True)):
        if p is None:
            raise UserError(f"--masks {masks_dir}: no mask for frame {n} (expected {Path(n).stem}.png, or "
                            f"{Path(n).stem}_mask.png)")
        alpha = read_alpha(p)
        cutout = alpha is not None
        if alpha is not None:  # a cut-out's colours are the photo's: a dark part of it is no background
            cutouts.append(n)
            g = alpha
        else:
            g = read_image(p).max(axis=2)
        mh, mw = g.shape
        if (mh, mw) != (H, W):
            if abs(mw * H - W * mh) > 0.005 * W * mh:  # another shape, not the photo's scaled (a crop, turned)
                raise UserError(f"{p}: mask is {mw}x{mh}, frame {n} is {W}x{H} (not the same shape scaled either)")
            scaled.append(n)
        top = int(g.max())
        if 0 < top <= 127 and not np.any((g != 0) & (g != top)):  # two values, 0 and a low one: a label image
            labels.append(n)
            threshold = 0
        else:
            threshold = 127
        binary = np.where(g > threshold, np.uint8(255), np.uint8(0))
        if (mh, mw) == (H, W):
            out[i] = ws.reduce(binary) > 127
        else:  # the photo's shape at another size: scaled to the work size (pixel centres kept, as ws.reduce)
            out[i] = cv2.resize(binary, (w, h), interpolation=cv2.INTER_AREA if mw >= w else cv2.INTER_LINEAR) > 127
        if not out[i].any():
            if top > threshold:
                empty[n] = f"{p.name}: the object pixels vanish at the work size"
            elif cutout:
                empty[n] = f"{p.name} has no pixel with alpha above 127 (no opaque pixel)"
            else:
                empty[n] = f"{p.name} has no pixel above 127, the brightest is {top}"
    if scaled and progress is not None:
        progress.note(f"masks: {len(scaled)} mask(s) are not the photos' size but their shape scaled (e.g. "
                      f"{scaled[0]}): scaled to the photos")
    if cutouts and progress is not None:
        progress.note(f"masks: {len(cutouts)} mask(s) have transparency (cut-outs, e.g. {cutouts[0]}): "
                      f"their opaque pixels (alpha > 127) are taken as the object, not their colours")
    if labels and progress is not None:
        progress.note(f"masks: {len(labels)} mask(s) hold only 0 and one value up to 127 (label images, "
                      f"e.g. {labels[0]}): that value is taken as the object")
    check_masks(out, names, masks_dir)  # inverted, all-white, mostly empty: refused before any work
    return out, empty


#: A mask named after its frame with one of these around the stem is the frame's too (``IMG_0001_mask.png``,
#: ``mask_IMG_0001.png``), where no file has the frame's stem exactly.
MASK_SUFFIXES = ("_mask", "-mask", ".mask", "_alpha", "_matte")
MASK_PREFIXES = ("mask_", "mask-")


def mask_files(masks_dir: Path, names: list[str]) -> list[Path | None]:
    """The mask file of each frame, matched by file stem (None: no mask; no folder: all None).

    The stem itself first; then the stem with a common mask suffix or prefix
    (:data:`MASK_SUFFIXES`, :data:`MASK_PREFIXES`, any case)."""
    from ..frames import frame_name
    from ..images import IMAGE_SUFFIXES

    try:
        by_stem = {frame_name(p.stem): p for p in sorted(masks_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}
    except OSError:
        by_stem = {}
    lower: dict[str, Path] = {}
    for stem, p in by_stem.items():
        lower.setdefault(stem.lower(), p)

    def find(stem: str) -> Path | None:
        if stem in by_stem:
            return by_stem[stem]
        for cand in [stem + s for s in MASK_SUFFIXES] + [pre + stem for pre in MASK_PREFIXES]:
            if cand.lower() in lower:
                return lower[cand.lower()]
        return None

    return [find(Path(n).stem) for n in names]


def undistort_masks(masks: np.ndarray, intr, ws: WorkSize) -> np.ndarray:
    """``--masks`` (V, h, w) bool drawn on the photos, undistorted like the work images (the hull is carved
    with the undistorted camera): coverage resampled bilinearly, > 1/2 is object."""
    if intr is None or not intr.has_distortion:
        return masks
    m8 = undistort_with([m.astype(np.uint8) * 255 for m in masks], intr, ws)
    return np.stack([m > 127 for m in m8]) if len(m8) else masks


def silhouettes_stage(images_rgb, names, K, Ts, opts, cache, key, progress, vol, ws, intr=None) -> Silhouettes:
    V, (w, h) = len(names), ws.work
    fields = {"masks": ("b", (V, h, w)), "unknown": ("b", (V, h, w)), "status": ("U", (V,))}
    if opts.masks_dir is None:  # (a cache written before the moved pixels were kept is recomputed)
        fields["moved"] = ("b", (V, h, w))
    hit = cache.load("silhouettes", key, fields)
    if hit is not None:
        progress.note("silhouettes: reused")
        # (a cache written before the ground was kept has none: nothing recognised to report)
        kept = np.asarray(hit.get("ground", ()), float).ravel()
        ground = tuple(float(c) for c in kept) if kept.shape == (3,) and np.isfinite(kept).all() else None
        return Silhouettes(hit["masks"], hit["unknown"], [str(s) for s in hit["status"]], ground, hit.get("moved"))
    ground, moved = None, None
    with progress.stage("silhouettes") as tick:
        if opts.masks_dir is not None:
            masks, empty = read_masks(opts.masks_dir, names, ws, progress)
            masks = undistort_masks(masks, intr, ws)
            unknown = np.zeros_like(masks)
            status = ["ok" if m.any() else
                      f"rejected: the mask is empty ({empty.get(n, 'nothing left after undistortion')})"
                      for n, m in zip(names, masks, strict=True)]
        else:
            from recon.silhouettes import estimate_silhouettes

            try:
                res = estimate_silhouettes(images_rgb, K, Ts, opts.spec, radius_mm=vol.radius_mm,
                                           height_mm=vol.height_mm, progress=tick)
            except ValueError as exc:
                raise UserError(f"{opts.input}: silhouettes: {exc}") from None
            masks, status = np.asarray(res.masks, bool), list(res.status)
            unknown = np.asarray(res.unknown, bool)
            ground, moved = res.ground, res.moved
            if ground is not None:
                progress.note(f"silhouettes: {describe_ground(ground)}")
    extra = {} if moved is None else {"moved": moved}
    cache.save("silhouettes", key, masks=masks, unknown=unknown, status=np.array(status),
               ground=np.array(ground if ground is not None else (), float), **extra)
    return Silhouettes(masks, unknown, status, ground, moved)


GREY = ("the photos are greyscale: automatic silhouettes tell the object from the table and the background "
         "mostly by colour; photograph in colour, or give --masks")


def is_greyscale(images_rgb: list[np.ndarray]) -> bool:
    """Whether the (first few) photos carry no colour: R, G and B within 2 levels everywhere."""
    sample = images_rgb[:3]
    return bool(sample) and all(int(np.ptp(im.astype(np.int16), axis=2).max()) <= 2 for im in sample)


def describe(names: list[str], sil: Silhouettes, shown: int = 8) -> str:
    """Each view's silhouette, as its share of the image and its verdict (for an error that stops the run)."""
    share = sil.masks.reshape(len(names), -1).mean(axis=1)
    items = [f"{n} {100 * a:.1f} % {st}" for n, a, st in zip(names, share, sil.status, strict=True)]
    more = f" and {len(items) - shown} more" if len(items) > shown else ""
    return "silhouettes (share of the image, verdict): " + ", ".join(items[:shown]) + more


def verdicts(names, status) -> tuple[list[int], dict[str, str], dict[str, str]]:
    """Kept view indices, rejected frames and conservative (kept) frames, each with its reason."""
    keep, rejected, conservative = [], {}, {}
    for i, (n, s) in enumerate(zip(names, status, strict=True)):
        if s == "ok":
            keep.append(i)
        elif s.startswith("conservative"):
            keep.append(i)
            conservative[n] = s.partition(":")[2].strip() or s
        else:  # "rejected: <reason>" (or a bare reason from an older silhouettes module)
            rejected[n] = s.partition(":")[2].strip() if s.startswith("rejected") else s
    return keep, rejected, conservative
