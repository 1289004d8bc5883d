"""Rerun recording of a reconstruction: every stage, one file a person can open.

Layout (table frame, millimetres, +Y up — ``rr.ViewCoordinates.RIGHT_HAND_Y_UP``):

- ``world/target``: the two rings in 3D (static).
- ``world/camera``: on the ``frame`` timeline, the camera of that frame:
  ``Transform3D`` (parent-from-child, i.e. table-from-camera) and ``Pinhole``
  (OpenCV axes, RDF); ``world/camera/image`` the photo (JPEG-encoded),
  ``world/camera/image/ellipses`` the detected ring conics and
  ``world/camera/image/silhouette`` the silhouette outline.
- ``world/hull``, ``world/points``, ``world/mesh``: static results.

A blueprint puts the 3D view beside the current image.

The recording is kept in memory and written by :meth:`Recorder.save` with an
ordinary file write (whole or not at all): Rerun's own file sink blocked
forever in its flush when the disk filled (rerun-sdk 0.41), where a write of
ours fails at once with "no space left".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.camera import circle_points_table, invert_T
from calib.conics import conic_to_ellipse, ellipse_points

__all__ = ["Recorder", "record_reconstruction"]


class Recorder:
    """Records in memory; :meth:`save` writes the ``.rrd`` (as a context manager: to ``path`` on success)."""

    def __init__(self, path: str | Path | None = None, *, application_id: str = "turntable"):
        import rerun as rr

        self._rr = rr
        self.path = None if path is None else Path(path)
        self.rec = rr.RecordingStream(application_id)
        self._memory = self.rec.memory_recording()
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        self._send_blueprint()

    def _send_blueprint(self) -> None:
        import rerun.blueprint as rrb

        bp = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial3DView(origin="world", name="table frame (mm)"),
                rrb.Spatial2DView(origin="world/camera/image", name="current frame"),
                column_shares=[3, 2],
            ),
            rrb.TimePanel(expanded=False),
        )
        self.rec.send_blueprint(bp)

    # -- static scene -------------------------------------------------------------------
    def log_target(self, r_outer_mm: float, r_inner_mm: float) -> None:
        rr = self._rr
        strips = [np.vstack([c, c[:1]]) for c in (circle_points_table(r_outer_mm, 256),
                                                  circle_points_table(r_inner_mm, 256))]
        self.rec.log("world/target", rr.LineStrips3D(strips, colors=[[20, 20, 20], [20, 20, 20]], radii=0.6),
                     static=True)

    def log_mesh(self, entity: str, vertices_table, faces, normals=None, colors_rgb=None) -> None:
        rr = self._rr
        kw = {}
        if normals is not None:
            kw["vertex_normals"] = np.asarray(normals, np.float32)
        if colors_rgb is not None:
            kw["vertex_colors"] = np.asarray(colors_rgb, np.uint8)
        self.rec.log(f"world/{entity}", rr.Mesh3D(vertex_positions=np.asarray(vertices_table, np.float32),
                                                  triangle_indices=np.asarray(faces, np.uint32), **kw),
                     static=True)

    def log_points(self, entity: str, pts_table, colors_rgb=None, radius_mm: float = 0.4) -> None:
        rr = self._rr
        self.rec.log(f"world/{entity}", rr.Points3D(np.asarray(pts_table, np.float32), colors=colors_rgb,
                                                    radii=radius_mm), static=True)

    def log_text(self, entity: str, text: str) -> None:
        self.rec.log(entity, self._rr.TextDocument(text, media_type="text/markdown"), static=True)

    # -- per frame ----------------------------------------------------------------------
    def set_frame(self, index: int) -> None:
        self.rec.set_time("frame", sequence=int(index))

    def log_camera(self, index: int, K, width: int, height: int, T_cam_table, image_rgb=None,
                   image_plane_mm: float = 60.0) -> None:
        rr = self._rr
        self.set_frame(index)
        T_table_cam = invert_T(np.asarray(T_cam_table, float))
        self.rec.log("world/camera", rr.Transform3D(translation=T_table_cam[:3, 3], mat3x3=T_table_cam[:3, :3]))
        # Rerun puts pixel (0, 0)'s centre at (0.5, 0.5); ours is at (0, 0).
        K_rr = np.asarray(K, float).copy()
        K_rr[:2, 2] += 0.5
        self.rec.log("world/camera", rr.Pinhole(image_from_camera=K_rr, resolution=[width, height],
                                                camera_xyz=rr.ViewCoordinates.RDF,
                                                image_plane_distance=image_plane_mm))
        if image_rgb is not None:
            self.rec.log("world/camera/image", rr.Image(np.ascontiguousarray(image_rgb)).compress(jpeg_quality=85))

    def log_image_only(self, index: int, image_rgb) -> None:
        self.set_frame(index)
        self.rec.log("image", self._rr.Image(np.ascontiguousarray(image_rgb)).compress(jpeg_quality=85))

    def log_conics(self, index: int, conics: dict) -> None:
        rr = self._rr
        self.set_frame(index)
        strips = []
        for C in conics.values():
            try:
                p = ellipse_points(conic_to_ellipse(C), 256)
            except ValueError:
                continue
            strips.append(np.vstack([p, p[:1]]) + 0.5)  # rerun's pixel corners vs our centres
        if strips:
            self.rec.log("world/camera/image/ellipses", rr.LineStrips2D(strips, colors=[[0, 255, 255]] * len(strips)))

    def log_silhouette(self, index: int, mask) -> None:
        import cv2

        rr = self._rr
        self.set_frame(index)
        contours, _ = cv2.findContours(np.asarray(mask, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        strips = [np.vstack([c[:, 0, :], c[:1, 0, :]]).astype(np.float32) + 0.5 for c in contours if len(c) > 2]
        self.rec.log("world/camera/image/silhouette", rr.LineStrips2D(strips, colors=[[255, 80, 0]] * len(strips)))

    # -- lifetime -----------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write everything logged so far to ``path`` (atomically) and end the recording."""
        from recon.fileio import atomic_write_bytes

        self.rec.flush(timeout_sec=60.0)  # encoding into memory: no disk involved
        data = self._memory.drain_as_bytes()
        self.rec.disconnect()
        atomic_write_bytes(path, data)
        return Path(path)

    def close(self) -> None:
        """End the recording without writing anything."""
        self.rec.disconnect()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None and self.path is not None:
            self.save(self.path)
        else:
            self.close()


def record_reconstruction(rec: Recorder, opts, seq, names, images_rgb, masks, K, Ts, hull_mesh, fused, mesh, conics,
                          ws) -> None:
    """The recording shows the work images with their camera ``K`` and the rings mapped onto them."""
    if opts.spec is not None:
        rec.log_target(opts.spec.r_outer_mm, opts.spec.r_inner_mm)
    W, H = ws.work
    for i, n in enumerate(names):
        rec.log_camera(i, K, W, H, Ts[i], image_rgb=images_rgb[i])
        if n in conics:
            rec.log_conics(i, {k: ws.conic(C) for k, C in conics[n].items()})
        rec.log_silhouette(i, masks[i])
    rec.log_mesh("hull", hull_mesh.vertices_table, hull_mesh.faces, hull_mesh.normals_table)
    if fused is not None and len(fused.pts_table):
        rec.log_points("points", fused.pts_table, fused.colors_rgb)
    rec.log_mesh("mesh", mesh.vertices_table, mesh.faces, mesh.normals_table, mesh.colors_rgb)
