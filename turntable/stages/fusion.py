"""The point-fusion stage: per-view stereo depth -> fused points -> hull-aware surface.

Wires :mod:`recon.stereo`, :mod:`recon.fusion`, :mod:`recon.surface` and
:mod:`recon.regions`:

1. stereo depth for every view, fused into consistent points (all views);
2. the hull's grid carved by those points as seen from the even views only
   (:func:`recon.surface.fused_field`: carving needs several views that saw
   free space, the cavity prior an observed opening);
3. each carved region judged on the odd views' stereo depth, which step 2
   did not use (:func:`recon.regions.choose_regions`); unconfirmed or
   unjudged regions keep the hull;
4. enclosed voids filled, carved-off fragments dropped
   (:func:`recon.regions.supported_field`);
5. the inside under an opening its rim outlines hollowed, where stereo did
   not see it (:mod:`recon.openings`: a plain white cup); then meshed like
   the hull, and every vertex clipped back into the hull
   (:func:`recon.meshing.clip_to_hull`).
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np

from recon.types import FusedPoints, TableMesh, VoxelHull

from .hull import volume_text

log = logging.getLogger(__name__)

__all__ = ["FusionResult", "run_fusion"]


class FusionResult(NamedTuple):
    """What the fusion stage gives the next: a named tuple, so ``mesh, points, note = run_fusion(...)`` reads too.

    Attributes
    ----------
    mesh : TableMesh
        The mesh to colour and export: the hull mesh unless some region of
        the fused surface was confirmed by held-out views.
    points : FusedPoints
        The fused stereo points (table frame, mm).
    note : str
        One line for the summary: what was kept and why.
    """

    mesh: TableMesh
    points: FusedPoints
    note: str


def run_fusion(images_rgb, masks, K: np.ndarray, T_cam_table: np.ndarray, hull: VoxelHull, hull_mesh: TableMesh,
               opts, progress, swept=None) -> FusionResult:
    """The mesh to colour and export, the fused points and a note for the summary (:class:`FusionResult`).

    Check :func:`recon.meshing.mesh_stats` for watertightness and bodies of
    the mesh either way. ``swept``: :func:`recon.faces.sweep` of these views,
    where the caller has it (the openings read it).
    """
    from recon.fusion import fuse_depths
    from recon.meshing import clip_to_hull, mesh_from_hull, mesh_stats
    from recon.openings import find_openings
    from recon.regions import choose_regions, supported_field
    from recon.stereo import depth_maps, hull_depth_range
    from recon.surface import fused_field

    H, W = images_rgb[0].shape[:2]
    with progress.stage("openings"):  # a vessel's rim outlined all round: the inside no view sees (recon.openings)
        openings = find_openings(images_rgb, masks, K, T_cam_table, hull, swept)
    with progress.stage("stereo") as tick:
        depth_range = hull_depth_range(hull, K, T_cam_table, (W, H), margin_mm=2.0, scale=0.5)
        depths = depth_maps(images_rgb, K, T_cam_table, depth_range, masks=masks, progress=tick)
    with progress.stage("fusion") as tick:
        fused = fuse_depths(depths, images_rgb, K, T_cam_table, progress=tick)
    n_pts = len(fused.pts_table)
    why = None
    if n_pts == 0:
        why = "stereo found no consistent points"
    elif len(T_cam_table) < 4:
        why = "too few views to hold any out for judging the fused surface"
    else:
        with progress.stage("surface") as tick:
            F = fused_field(fused, hull, K, T_cam_table[0::2], depths[0::2], size=(W, H), progress=tick)
            choice = choose_regions(hull, F, depths[1::2], K, T_cam_table[1::2], masks[1::2])
            if choice.n_kept:
                values = supported_field(hull.values, choice.values)
        if choice.n_kept == 0:
            carved = ("stereo carved nothing" if choice.n_regions == 0 else
                      f"none of {choice.n_regions} carved regions ({volume_text(choice.rejected_mm3)}) was "
                      f"confirmed by held-out views ({choice.n_unjudged} too little seen to judge)")
            why = f"{n_pts} fused points; {carved}"
    if why is not None:
        if not openings:
            return FusionResult(hull_mesh, fused, f"hull kept: {why}")
        values = np.asarray(hull.values, np.float32)
    values, hollow_note = _hollow(values, openings, hull, masks, K, T_cam_table, fused, progress)
    if why is not None and hollow_note is None:
        return FusionResult(hull_mesh, fused, f"hull kept: {why}")
    with progress.stage("fused mesh"):
        mesh = mesh_from_hull(VoxelHull(values=values, origin_table=hull.origin_table, voxel_mm=hull.voxel_mm),
                              max_faces=opts.max_faces)
        mesh = clip_to_hull(mesh, hull)
    st, sh = mesh_stats(mesh), mesh_stats(hull_mesh)
    if not st.watertight:
        log.warning("the fused mesh is not watertight; keeping the hull mesh")
        return FusionResult(hull_mesh, fused,
                            f"hull kept: the fused mesh could not be made watertight ({n_pts} fused points)")
    ratio = f"volume {st.volume_mm3 / max(sh.volume_mm3, 1e-9):.2f} x the hull's"
    if why is not None:  # only the openings changed the hull
        return FusionResult(mesh, fused, f"hull kept but for the openings ({why}); {hollow_note}; {ratio}")
    share = 100.0 * choice.kept_mm3 / max(choice.kept_mm3 + choice.rejected_mm3, 1e-9)
    note = (f"fused surface kept in {choice.n_kept} of {choice.n_regions} carved regions "
            f"({volume_text(choice.kept_mm3)} carved, {share:.0f} % of what stereo carved), hull elsewhere "
            f"({choice.n_unjudged} regions too little seen to judge); on {choice.n_pixels} held-out stereo pixels "
            f"there, error {choice.fused_err_mm:.2f} mm fused vs {choice.hull_err_mm:.2f} mm hull; "
            + (f"{hollow_note}; " if hollow_note else "") + f"{ratio}; {n_pts} fused points")
    return FusionResult(mesh, fused, note)


def _hollow(values, openings, hull: VoxelHull, masks, K, T_cam_table, fused: FusedPoints, progress):
    """``values`` with the insides of ``openings`` hollowed (:func:`recon.openings.hollow_openings`), and a note
    for the summary (None where none was)."""
    if not openings:
        return values, None
    from recon.openings import hollow_openings

    with progress.stage("hollow openings"):
        values, done = hollow_openings(hull, values, openings, masks, K, T_cam_table, fused.pts_table)
    if not done:
        return values, None
    texts = []
    for op, mm3 in done:
        down = (f"down to the floor the views outline {op.floor_mm:.1f} mm above the table" if op.floor_mm is not None
                else "down to a floor as thick as the wall")
        text = (f"an opening {op.height_mm:.1f} mm above the table ({op.area_mm2:.0f} mm², its rim outlined all round "
                f"in the views): the inside no view sees hollowed as a vessel's, walls {op.wall_mm:.1f} mm, {down} "
                f"({volume_text(mm3)}; --no-fusion keeps the hull)")
        progress.note(f"fusion: {text}")
        texts.append(text)
    return values, "; ".join(texts)
