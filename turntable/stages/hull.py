"""Stage 4, hull: visual-hull carving in a working volume grown until the object fits (``recon.carving``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import UserError
from .cache import stage_key
from .options import MIN_VIEWS, max_rejections
from .silhouettes import (
    GREY,
    Silhouettes,
    describe,
    is_greyscale,
    silhouettes_stage,
    verdicts,
)

JOIN_MORE_REJECTIONS = 2  # a hull standing in several pieces: carving tolerates up to this many more views ...
JOIN_MAX_GROWTH = 1.5  # ... where that makes it one piece at most this much larger
MIN_BODY_FRACTION = 0.01  # a body of the hull counts as a piece from this share of the largest (the mesh's specks)


class GridTooLarge(UserError):
    """``--resolution`` asks for a grid that does not fit in memory (refused before it is allocated)."""


def volume_text(mm3: float) -> str:
    """A carved or dropped volume for a note: cm³ from 0.1 cm³, mm³ to a tenth below (never "0.0 cm³")."""
    return f"{mm3 / 1000.0:.1f} cm³" if mm3 >= 100.0 else f"{mm3:.1f} mm³"


def carve_hull(masks, K, Ts, opts, cache, key, progress, vol, rejections: int | None = None, images=None,
               held=None):
    """The visual hull of ``masks`` in the working volume ``vol`` (cached under ``key``); a voxel is carved where
    more than ``rejections`` views see background there (default: :func:`max_rejections` of ``opts``).

    Given the frames (``images``, automatic silhouettes), also where one view fewer sees the background round
    the object: past the edge its outline sits on (:func:`recon.carving.held_past_edges` of ``held``, default
    ``masks``; with its holes and narrow bays filled)."""
    from recon.types import VoxelHull

    fields = {"values": ("f", (None, None, None)), "origin": ("f", (3,)), "voxel_mm": ("f", ()),
              "touches": ("iu", (2,))}
    hit = cache.load("hull", key, fields)
    if hit is not None:
        progress.note("hull: reused")
        meta = {"touches_side": int(hit["touches"][0]), "touches_top": int(hit["touches"][1])}
        return VoxelHull(values=hit["values"], origin_table=hit["origin"], voxel_mm=float(hit["voxel_mm"]), meta=meta)
    from recon.carving import HullTooLarge, carve_hull

    outer = None
    if images is not None:  # automatic silhouettes: the background round the object carves alone
        from recon.carving import held_past_edges, outer_band_px
        from recon.image_edges import edge_thresholds

        band, thresholds = outer_band_px(masks.shape[2], masks.shape[1]), edge_thresholds(images, Ts)
        outer = np.array([held_past_edges(m, im, band, thresholds) for m, im in
                          zip(masks if held is None else held, images, strict=True)])
    with progress.stage("carving") as tick:
        try:
            hull = carve_hull(masks, K, Ts, radius_mm=vol.radius_mm, height_mm=vol.height_mm,
                              resolution=opts.resolution,
                              max_rejections=min(max_rejections(opts) if rejections is None else rejections,
                                                 len(masks) - 1),
                              outer_masks=outer, progress=tick)
        except HullTooLarge as exc:  # not the silhouettes' fault: say only what to change
            raise GridTooLarge(f"{opts.input}: --resolution {opts.resolution}: {exc}") from None
        except ValueError as exc:
            raise UserError(f"{opts.input}: carving: {exc}") from None
    cache.save("hull", key, values=hull.values, origin=hull.origin_table, voxel_mm=np.array(hull.voxel_mm),
               touches=np.array([hull.meta["touches_side"], hull.meta["touches_top"]]))
    return hull


@dataclass(frozen=True)
class HullStage:
    """The silhouettes and the hull carved from the views they kept."""

    silhouettes: Silhouettes
    keep: list[int]  # indices of the views whose silhouettes are used
    rejected: dict[str, str]  # frame name -> why its silhouette was dropped
    conservative: dict[str, str]  # frame name -> why its silhouette was kept with every doubtful pixel
    hull: object | None  # recon.carving.VoxelHull; None when fewer than MIN_VIEWS silhouettes are usable
    volume: object  # turntable.stages.volume.WorkingVolume, as grown
    report: dict  # summary.json's "working_volume"


def _fits(hull) -> bool:
    """The carved hull stays off the working volume's side and top."""
    return not (hull.meta["touches_side"] > 0 or hull.meta["touches_top"] > 0)


def _bodies(hull) -> int:
    """The hull's bodies that its mesh keeps: 26-connected inside voxels (as
    :func:`recon.carving.drop_floating_bodies` counts) of at least ``MIN_BODY_FRACTION`` of the largest one's
    volume (:func:`recon.meshing.mesh_from_hull` drops smaller specks)."""
    from scipy import ndimage

    lab, n = ndimage.label(hull.values > 0, structure=np.ones((3, 3, 3), bool))
    if n <= 1:
        return int(n)
    size = np.bincount(lab.ravel(), minlength=n + 1)[1:]
    return int(np.count_nonzero(size >= MIN_BODY_FRACTION * size.max()))


def _kept(stack: np.ndarray | None, keep: list[int]) -> np.ndarray | None:
    """``stack[keep]``, or None where there is no stack."""
    return None if stack is None else stack[keep]


def _inside_mm3(hull) -> float:
    """The hull's volume (its grid is fitted to what it carves: compare in mm^3, not voxels)."""
    return float((hull.values > 0).sum()) * hull.voxel_mm ** 3


def _rejoined(joined: int) -> str:
    """The summary's words for :func:`recon.carving.rejoin_cut_off`'s count (empty for none)."""
    return "" if not joined else (f" ({joined} part(s) the split cut off the body joined to it again, where the "
                                  f"hull before the split held the gap)")


def _seen_back(cut, before, masks, unknown_before, unknown_cut, K, Ts, vol) -> tuple[object, float, float]:
    """The hull ``cut`` carved after a split of the doubt off the volume's outline, with what the views see inside
    the object back where the split took it: ``(hull, lost, mm^3 back)``.

    ``before``: the hull carved before the split; ``unknown_before``, ``unknown_cut``: the views' doubtful pixels
    before and after it (what the split took: in the first, not in the second, nor in ``masks``). ``lost`` is the
    largest share of a view's sure silhouette (``masks``) that ``before`` covers and the result does not
    (:func:`recon.faces.hull_uncovered_share`; where the split alone leaves at most ``SPLIT_MAX_UNCOVERED``, that
    of ``cut``: what comes back only covers more, and the callers only weigh it against that bound). Where the
    split alone leaves more than ``SPLIT_MAX_UNCOVERED`` uncovered, it took a part of the object with the wall,
    and :func:`recon.carving.keep_seen_inside` gives back the voxels more views see inside their silhouettes than
    hold them as the wall (a white chair's back on a light wall: 18 % of a view's silhouette uncovered, 0.01 %
    after, the fin of wall behind it still carved).
    Elsewhere it gives back only those of them that the views holding them as the wall hold from one side of
    the turn (``SEEN_ONE_SIDE``): a part of the object's shaded side, doubt that went with the wall in the views
    that see it at their outline (a white vase on a light wall: its shoulder, carved 7 mm deep all round while
    no view's sure silhouette lost its hull; 0.79 -> 0.48 % of the diagonal), not the wall's doubt round the
    object, which the views at both ends of the turn drop; none that a view saw past before the split, and only
    in parts ``SEEN_DEEP_MM`` deep (:func:`recon.carving.keep_seen_inside`). Where nothing comes back, ``cut``
    is returned as it was carved.
    """
    from recon.carving import SEEN_DEEP_MM, SEEN_ONE_SIDE, keep_seen_inside
    from recon.faces import hull_uncovered_share

    from .volume import SPLIT_MAX_UNCOVERED

    lost = hull_uncovered_share(before, cut, masks, K, Ts)
    dropped = unknown_before & ~unknown_cut & ~masks
    one_sided = lost <= SPLIT_MAX_UNCOVERED
    seen, back_mm3 = keep_seen_inside(cut, before, masks, dropped, K, Ts, vol.radius_mm, vol.height_mm,
                                      one_side=SEEN_ONE_SIDE if one_sided else None,
                                      held=masks | unknown_before if one_sided else None,
                                      min_depth_mm=SEEN_DEEP_MM if one_sided else None)
    if one_sided:  # under the bound already: not projected again
        return (cut, lost, 0.0) if back_mm3 <= 0 else (seen, lost, back_mm3)
    return seen, hull_uncovered_share(before, seen, masks, K, Ts), back_mm3


def _seen(back_mm3: float) -> str:
    """The summary's words for what :func:`_seen_back` gave back (empty for nothing)."""
    return "" if back_mm3 <= 0 else (f" ({back_mm3 / 1000:.1f} cm³ of what it took, inside the object's sure "
                                     f"silhouette in more views than held it as the wall, given back)")


def join_pieces(hull, floating: list[float], carve_at, k0: int, k_max: int) -> tuple[object, list[float], str | None]:
    """The hull in one piece where tolerating a few more views' background makes it one: ``(hull, floating, note)``.

    An object standing on the turntable is one piece. Where the hull stands on the table in several
    (:func:`_bodies`), a few views' doubtful "background" may have cut it: a white figure's plinth, whose lit
    top looks like the paper behind it from 40 deg, was carved thin and parted from the legs (two pieces,
    exit 3). ``carve_at(k)`` carves again where more than ``k`` views see background and drops the floating
    bodies (:func:`recon.carving.drop_floating_bodies`: ``(hull, floating)``); from ``k0 + 1`` to ``k_max``,
    the first that is one piece and at most ``JOIN_MAX_GROWTH`` times the volume is kept, with a note for the
    summary. Otherwise (two objects apart stay apart; a hull that would only join as a blob) nothing changes
    and the note is None.
    """
    n = _bodies(hull)
    if n <= 1:
        return hull, floating, None
    for k in range(k0 + 1, k_max + 1):
        alt, alt_floating = carve_at(k)
        if _bodies(alt) == 1 and _inside_mm3(alt) <= JOIN_MAX_GROWTH * _inside_mm3(hull):
            grew = 100.0 * (_inside_mm3(alt) / max(_inside_mm3(hull), 1e-9) - 1.0)
            views = "view sees" if k == 1 else "views see"
            return alt, alt_floating, (f"the hull stood on the table in {n} pieces; carved only where more than {k} "
                                       f"{views} background (not {k0}), it is one, {grew:.1f} % larger: kept")
    return hull, floating, None


def silhouettes_and_hull(images_rgb, names, K, Ts, opts, cache, sil_key, progress, ws, intr=None) -> HullStage:
    """Silhouettes and hull in a working volume grown until the object fits (or the view ends)."""
    from recon.carving import drop_floating_bodies, rejoin_cut_off

    from .volume import (
        MIN_TOUCH_VIEWS,
        SPLIT_MAX_GROWTH,
        SPLIT_MAX_PAPER,
        SPLIT_MAX_UNCOVERED,
        doubt_off_the_outline,
        given_paper_share,
        initial_volume,
        mask_touches,
    )

    H, W = images_rgb[0].shape[:2]
    try:
        vol = initial_volume(K, Ts, (W, H), None if opts.spec is None else opts.spec.extent_mm)
    except ValueError as exc:
        raise UserError(f"{opts.cameras or opts.input}: {exc}") from None
    vol_key = stage_key(sil_key, vol.key(), opts.resolution, max_rejections(opts))
    hit = cache.load("volume", vol_key, {"size": ("f", (2,)), "grown": ("U", (None,))})
    grown: list[str] = [str(g) for g in hit["grown"]] if hit is not None else []
    if hit is not None:
        vol = replace(vol, radius_mm=float(hit["size"][0]), height_mm=float(hit["size"][1]))
    automatic = opts.masks_dir is None
    clipped: list[str] = []
    doubtful_wall: list[str] = []

    grey = automatic and is_greyscale(images_rgb)
    if grey:
        progress.note(f"silhouettes: {GREY}")

    def carve(sil, keep, key, vol, rejections=None):
        k = max_rejections(opts) if rejections is None else rejections
        hull_key = stage_key(key, keep, opts.resolution, k, vol.key(), "round the object")
        held = sil.masks[keep] | sil.unknown[keep]
        try:
            # the background round the object is judged on the silhouettes as estimated: what the wall's split
            # took off a view (doubt_off_the_outline) is doubt, not background (alone, one view's split cut a
            # white figure's hand off)
            return carve_hull(held, K, Ts[keep], opts, cache, hull_key, progress, vol, k,
                              images=[images_rgb[i] for i in keep] if automatic else None,
                              held=held | orig.masks[keep] | orig.unknown[keep])
        except GridTooLarge:
            raise
        except UserError as exc:  # nothing left: say what each view's silhouette was
            raise UserError(f"{exc}; {describe(names, sil)}" + (f"; {GREY}" if grey else "")) from None

    sil, sil_for = None, None
    for _ in range(32):  # each pass grows the volume or ends the loop; the bound is a safety net
        key = stage_key(sil_key, vol.key()) if automatic else sil_key  # user masks do not depend on it
        if key != sil_for:
            sil, sil_for = silhouettes_stage(images_rgb, names, K, Ts, opts, cache, key, progress, vol, ws,
                                              intr), key
            orig = sil  # as estimated, before any split
        keep, rejected, conservative = verdicts(names, sil.status)
        if len(keep) < MIN_VIEWS:
            return HullStage(sil, keep, rejected, conservative, None, vol, {})
        hull, why, touch = None, [], (False, False)
        if automatic:  # confined to the cylinder's image: an object larger than it touches that outline
            side, top = mask_touches(sil.masks[keep], K, Ts[keep], vol)
            touch = (len(side) >= MIN_TOUCH_VIEWS, len(top) >= MIN_TOUCH_VIEWS)
            why = [f"the silhouettes of {len(v)} views reach its {w}" for w, v, t in
                   zip(("side", "top"), (side, top), touch, strict=True) if t]
        if not why:  # the silhouettes fit: carve, and ask the hull
            hull = carve(sil, keep, key, vol)
            touch = (hull.meta["touches_side"] > 0, hull.meta["touches_top"] > 0)
            why = [f"the carved hull reaches its {w}" for w, t in zip(("side", "top"), touch, strict=True) if t]
            if automatic and why:
                # carved from masks | unknown: the doubtful pixels (carved only where a view is sure of the
                # background) reach the wall, not the object's own silhouette, which fits. Growing on them
                # would chase the doubt to the edge of the view: note it, and keep the volume.
                doubtful_wall = [f"doubtful silhouette pixels (not the object's sure silhouette) let the hull reach "
                                 f"its {w}" for w, t in zip(("side", "top"), touch, strict=True) if t]
                # and they ran there in the views: drop, per view, the doubt that reaches the volume's outline,
                # split from the object along the image's edges (the object keeps what its mask reaches first).
                # The split stands where its hull fits and is not much larger than the hull without those pieces
                # (the neck it gives back is a small part; a split that gives the object the paper and the disc
                # enclosed by the target's ink is not); otherwise the pieces go whole.
                first, tried = sil, {}
                for whole in (False, True):
                    unknown, pruned = doubt_off_the_outline(first.masks[keep], first.unknown[keep], K, Ts[keep],
                                                            vol, [images_rgb[k] for k in keep], whole=whole,
                                                            moved=_kept(first.moved, keep))
                    if not pruned:
                        break
                    cut = replace(first, unknown=first.unknown.copy())
                    cut.unknown[keep] = unknown
                    tried[whole] = (cut, carve(cut, keep, stage_key(key, "doubt off the outline", whole), vol), pruned)
                how, choice = "", None
                if False in tried and True in tried:
                    (cut_split, h_split, _), (cut_whole, h_whole, _) = tried[False], tried[True]
                    grows = _inside_mm3(h_split) / max(_inside_mm3(h_whole), 1e-9)
                    # a split that gives back much more than a neck stands only if what it gives back is not
                    # the paper: a white vase on a light wall whose whole shaded side joined the wall lost half
                    # its body dropped whole (3.7 % of the diagonal; its split, 1.88x, gave back 2 % paper),
                    # where an all-doubtful frame's split gives the object the paper and the disc the target's
                    # ink encloses (2.39x, 70 % paper)
                    paper = None if not _fits(h_split) or grows <= SPLIT_MAX_GROWTH else \
                        given_paper_share(cut_split.unknown[keep] & ~cut_whole.unknown[keep],
                                          [images_rgb[k] for k in keep], K, Ts[keep], vol)
                    if _fits(h_split) and (paper is None or paper <= SPLIT_MAX_PAPER):
                        choice, how = False, (f"split from the object along the image's edges (the hull {grows:.2f}x "
                                              f"the one without those pieces"
                                              + ("" if paper is None else f", {100 * paper:.0f} % of what the split "
                                                 "gives back the paper") + ")")
                    else:
                        choice, how = True, ("dropped whole (split along the image's edges, the hull "
                                             + ("still reached the outline" if not _fits(h_split) else
                                                f"was {grows:.2f}x the one without them and {100 * paper:.0f} % of "
                                                "what the split gives back the paper") + ")")
                if choice is not None:
                    unsplit = hull
                    sil, hull, pruned = tried[choice]
                    hull, joined = rejoin_cut_off(hull, unsplit)
                    hull, _, back_mm3 = _seen_back(hull, unsplit, sil.masks[keep], first.unknown[keep],
                                                   sil.unknown[keep], K, Ts[keep], vol)
                    doubtful_wall.append(f"WARNING: {len(pruned)} view(s) lost the doubtful pixels that ran to the "
                                         f"working volume's outline (a wall of the object's colour), {how}, and the "
                                         f"hull {'now fits' if _fits(hull) else 'still reaches it'}"
                                         f"{_rejoined(joined)}{_seen(back_mm3)}; parts of the object with the "
                                         f"wall's colour may be missing (a dark or coloured backdrop avoids this)")
                progress.note(f"working volume: {'; '.join(doubtful_wall)}")
                why = []
            elif automatic:
                # the hull fits, yet views whose doubt floods the wall up to the outline may hold a fin of it
                # that the views seeing it edge-on cannot carve (a cream figure on a light wall: a sheet from
                # its staff to its arm at the height of its head, 1.6 % of the diagonal): the same split
                unknown, pruned = doubt_off_the_outline(sil.masks[keep], sil.unknown[keep], K, Ts[keep], vol,
                                                        [images_rgb[k] for k in keep], moved=_kept(sil.moved, keep))
                if pruned:
                    cut = replace(sil, unknown=sil.unknown.copy())
                    cut.unknown[keep] = unknown
                    h_cut = carve(cut, keep, stage_key(key, "doubt off the outline", False), vol)
                    h_cut, joined = rejoin_cut_off(h_cut, hull)
                    # and where it leaves the views' sure silhouettes covered (what the views see inside given
                    # back, _seen_back): the pieces are the wall's fin, not a part of the object (a white figure on
                    # a light wall, seed 13: its head, of the wall's grey and joined to it on its shaded side, went
                    # with the wall in 19 views of 36, and 5 % of a view's mask lost its hull: 1.17 % of the
                    # diagonal; the splits made on 27 other renders left at most 1.9 % of a view's mask, the
                    # chair's legs on a light wall)
                    lost, back_mm3 = None, 0.0
                    if _fits(h_cut):  # (what comes back keeps off the volume's outline: it fits as it did)
                        h_cut, lost, back_mm3 = _seen_back(h_cut, hull, sil.masks[keep], sil.unknown[keep], unknown,
                                                           K, Ts[keep], vol)
                        lost = lost if _bodies(h_cut) <= _bodies(hull) else None
                    if lost is not None and lost <= SPLIT_MAX_UNCOVERED:
                        sil, hull = cut, h_cut
                        doubtful_wall.append(f"{len(pruned)} view(s) lost the doubtful pixels that ran to the "
                                             f"working volume's outline (a wall of the object's colour), split "
                                             f"from the object along the image's edges{_rejoined(joined)}"
                                             f"{_seen(back_mm3)}")
                        progress.note(f"working volume: {doubtful_wall[-1]}")
                    elif lost is not None:
                        doubtful_wall.append(f"the doubtful pixels of {len(pruned)} view(s) run to the working "
                                             f"volume's outline (a wall of the object's colour); split off along the "
                                             f"image's edges they would take {100 * lost:.0f} % of a view's sure "
                                             f"silhouette with them, so they stay (a fin of the wall may remain; a "
                                             f"dark or coloured backdrop avoids this)")
                        progress.note(f"working volume: {doubtful_wall[-1]}")
        if not why:
            break
        bigger = vol.grown(*touch)
        if bigger is None:  # the cameras' view ends here: carve what there is, and say so
            clipped.append(f"the object reaches past the working volume ({vol.describe()}): {' and '.join(why)}; "
                           f"the cameras do not see further, so the model is cut there")
            progress.note(f"WARNING: {clipped[-1]}")
            break
        grown.append(f"{vol.describe()} -> {bigger.describe()}: {' and '.join(why)}")
        progress.note(f"working volume grows: {grown[-1]}")
        vol = bigger
    if hull is None:
        hull = carve(sil, keep, key, vol)
    # an object on the table is one body resting on it: a body of the hull floating above the table is a phantom
    hull, floating = drop_floating_bodies(hull)
    if automatic:  # ... and stands in one piece (join_pieces)
        def carve_at(k: int):
            return drop_floating_bodies(carve(sil, keep, stage_key(key, "joined", sil.unknown), vol, k))

        k0 = min(max_rejections(opts), len(keep) - 1)
        hull, floating, note = join_pieces(hull, floating, carve_at, k0, min(k0 + JOIN_MORE_REJECTIONS, len(keep) - 1))
        if note:
            doubtful_wall.append(note)
            progress.note(f"working volume: {note}")
    if floating:
        size = volume_text(sum(floating))
        doubtful_wall.append(f"{len(floating)} piece(s) of the hull float above the table, apart from the object "
                             f"({size}: space every view's silhouette left uncarved, which no object standing on "
                             f"the turntable can fill): dropped")
        progress.note(f"working volume: {doubtful_wall[-1]}")
    cache.save("volume", vol_key, size=np.array([vol.radius_mm, vol.height_mm]), grown=np.array(grown, dtype=str))
    report = {"radius_mm": round(vol.radius_mm, 1), "height_mm": round(vol.height_mm, 1),
              "first_guess": vol.source, "max_radius_mm": round(vol.max_radius_mm, 1),
              "max_height_mm": round(vol.max_height_mm, 1), "grown": grown, "clipped": clipped,
              "notes": doubtful_wall}
    return HullStage(sil, keep, rejected, conservative, hull, vol, report)


# --------------------------------------------------------------------------- main
