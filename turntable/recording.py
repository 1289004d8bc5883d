"""Rerun recording of a reconstruction: every stage, one file a person can open.

Layout (table frame, millimetres, +Y up — ``rr.ViewCoordinates.RIGHT_HAND_Y_UP``):

- ``world/target``: the two rings in 3D (static).
- ``world/mesh``: the final coloured mesh (static); ``world/hull`` (the carved
  visual hull) and ``world/points`` (the fused stereo points), static, present
  but hidden in the default blueprint (tick them in the blueprint panel).
- ``world/cameras/frame_000`` …: every used frame's camera, static — ``Transform3D``
  (parent-from-child, i.e. table-from-camera) and ``Pinhole`` (OpenCV axes, RDF)
  for a small copy of the photo, ``…/image``, drawn inside the frustum. The
  number is the frame's index on the ``frame`` timeline.
- ``world/camera``: on the ``frame`` timeline, the current frame's camera, drawn
  larger: ``world/camera/image`` the photo (work size, JPEG-encoded),
  ``world/camera/image/ellipses`` the detected ring conics and
  ``world/camera/image/silhouette`` the silhouette outline.
- ``calibration/edge_rms_px``, ``calibration/angle_deg``: on the ``frame``
  timeline, what calibration measured for each frame (``rr.Scalars``; frames
  where it is unknown, e.g. cameras given with ``--cameras``, have no value).

The default blueprint: the 3D view (mesh, rings, all cameras, its eye set by
:meth:`Recorder.frame_view` to frame the object) beside the current photo with
its ellipses and silhouette, and under it the two per-frame plots.

The recording is kept in memory and written by :meth:`Recorder.save` with an
ordinary file write (whole or not at all): Rerun's own file sink blocked
forever in its flush when the disk filled (rerun-sdk 0.41), where a write of
ours fails at once with "no space left".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calib.camera import circle_points_table, invert_T
from calib.conics import conic_to_ellipse, ellipse_points

__all__ = ["HIDDEN_BY_DEFAULT", "SCALARS", "Recorder", "camera_entity", "record_reconstruction"]

#: Entities logged but hidden in the default blueprint.
HIDDEN_BY_DEFAULT = ("world/hull", "world/points")
#: The per-frame plots: entity -> plot title.
SCALARS = {"calibration/edge_rms_px": "edge RMS (px)", "calibration/angle_deg": "turntable angle (deg)"}
#: Long side of the photo drawn in every camera's frustum, pixels.
THUMBNAIL_PX = 160
#: Colour of the current frame's frustum (the others are drawn in the viewer's default colour).
CURRENT_CAMERA_RGB = (255, 120, 0)
#: Largest side of a mesh texture in the recording, texels (a 2048² texture would add 12 MB, raw).
TEXTURE_PX = 1024
#: The 3D view's eye, in farthest-camera distances from the object (:func:`eye_for`).
EYE_DISTANCE = 2.0


def camera_entity(index: int) -> str:
    """The static camera of frame ``index``: ``world/cameras/frame_000``."""
    return f"world/cameras/frame_{int(index):03d}"


def _pinhole_K(K, sx: float = 1.0, sy: float = 1.0) -> np.ndarray:
    """Our K (pixel (0, 0)'s centre at (0, 0)) in Rerun's convention (centre at (0.5, 0.5)), scaled by (sx, sy)."""
    K_rr = np.asarray(K, float).copy()
    K_rr[:2, 2] += 0.5
    return np.diag([sx, sy, 1.0]) @ K_rr


class Recorder:
    """Records in memory; :meth:`save` writes the ``.rrd`` (as a context manager: to ``path`` on success)."""

    def __init__(self, path: str | Path | None = None, *, application_id: str = "turntable"):
        import rerun as rr

        self._rr = rr
        self.path = None if path is None else Path(path)
        self.rec = rr.RecordingStream(application_id)
        self._memory = self.rec.memory_recording()
        self._eye: tuple[np.ndarray, np.ndarray] | None = None
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        self.rec.log("world/camera", rr.TransformAxes3D(0.0), static=True)  # its coloured frustum marks it

    # -- the default layout -------------------------------------------------------------
    def frame_view(self, eye_table, look_target_table) -> None:
        """Where the 3D view's eye starts (table frame, mm), looking at ``look_target_table``."""
        self._eye = (np.asarray(eye_table, float).reshape(3), np.asarray(look_target_table, float).reshape(3))

    def blueprint(self):
        """The default blueprint (see the module docstring)."""
        import rerun.blueprint as rrb

        eye = None
        if self._eye is not None:
            eye = rrb.EyeControls3D(position=self._eye[0], look_target=self._eye[1], eye_up=[0.0, 1.0, 0.0])
        hidden = {e: rrb.EntityBehavior(visible=False) for e in HIDDEN_BY_DEFAULT}
        view3d = rrb.Spatial3DView(origin="world", name="table frame (mm)", overrides=hidden, eye_controls=eye)
        plots = [rrb.TimeSeriesView(origin=e, name=title) for e, title in SCALARS.items()]
        return rrb.Blueprint(
            rrb.Horizontal(
                view3d,
                rrb.Vertical(rrb.Spatial2DView(origin="world/camera/image", name="current frame"),
                             rrb.Horizontal(*plots), row_shares=[3, 2]),
                column_shares=[3, 2],
            ),
            rrb.BlueprintPanel(state="collapsed"),
            rrb.SelectionPanel(state="collapsed"),
            rrb.TimePanel(state="collapsed"),
        )

    # -- static scene -------------------------------------------------------------------
    def log_target(self, r_outer_mm: float, r_inner_mm: float) -> None:
        rr = self._rr
        strips = [np.vstack([c, c[:1]]) for c in (circle_points_table(r_outer_mm, 256),
                                                  circle_points_table(r_inner_mm, 256))]
        self.rec.log("world/target", rr.LineStrips3D(strips, colors=[[20, 20, 20], [20, 20, 20]], radii=0.6),
                     static=True)

    def log_mesh(self, entity: str, vertices_table, faces, normals=None, colors_rgb=None, texcoords=None,
                 texture_rgb=None) -> None:
        """A mesh (table frame, mm) with vertex colours, or a texture (``texcoords`` (N, 2), top-left origin as
        glTF and Rerun; ``texture_rgb`` (S, S, 3) uint8 sRGB, logged at most ``TEXTURE_PX`` on a side)."""
        rr = self._rr
        kw = {}
        if normals is not None:
            kw["vertex_normals"] = np.asarray(normals, np.float32)
        if texture_rgb is not None:
            import cv2

            tex = np.asarray(texture_rgb, np.uint8)
            if max(tex.shape[:2]) > TEXTURE_PX:
                tex = cv2.resize(tex, (TEXTURE_PX, TEXTURE_PX), interpolation=cv2.INTER_AREA)
            kw["vertex_texcoords"] = np.asarray(texcoords, np.float32)
            kw["albedo_texture"] = tex
        elif colors_rgb is not None:
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

    def log_static_camera(self, index: int, K, width: int, height: int, T_cam_table, image_rgb=None,
                          image_plane_mm: float = 40.0) -> None:
        """Frame ``index``'s camera, static, at :func:`camera_entity`; the photo reduced to :data:`THUMBNAIL_PX`."""
        import cv2

        rr = self._rr
        entity = camera_entity(index)
        T_table_cam = invert_T(np.asarray(T_cam_table, float))
        self.rec.log(entity, rr.Transform3D(translation=T_table_cam[:3, 3], mat3x3=T_table_cam[:3, :3]),
                     rr.TransformAxes3D(0.0), static=True)
        s = min(1.0, THUMBNAIL_PX / max(width, height))
        w, h = max(1, round(width * s)), max(1, round(height * s))
        self.rec.log(entity, rr.Pinhole(image_from_camera=_pinhole_K(K, w / width, h / height), resolution=[w, h],
                                        camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=image_plane_mm),
                     static=True)
        if image_rgb is not None:
            small = cv2.resize(np.ascontiguousarray(image_rgb), (w, h), interpolation=cv2.INTER_AREA)
            self.rec.log(f"{entity}/image", rr.Image(small).compress(jpeg_quality=80), static=True)

    # -- per frame ----------------------------------------------------------------------
    def set_frame(self, index: int) -> None:
        self.rec.set_time("frame", sequence=int(index))

    def log_camera(self, index: int, K, width: int, height: int, T_cam_table, image_rgb=None,
                   image_plane_mm: float = 60.0) -> None:
        """The current frame's camera (``world/camera``) and photo, on the ``frame`` timeline."""
        rr = self._rr
        self.set_frame(index)
        T_table_cam = invert_T(np.asarray(T_cam_table, float))
        self.rec.log("world/camera", rr.Transform3D(translation=T_table_cam[:3, 3], mat3x3=T_table_cam[:3, :3]))
        self.rec.log("world/camera", rr.Pinhole(image_from_camera=_pinhole_K(K), resolution=[width, height],
                                                camera_xyz=rr.ViewCoordinates.RDF,
                                                image_plane_distance=image_plane_mm, color=CURRENT_CAMERA_RGB))
        if image_rgb is not None:
            self.rec.log("world/camera/image", rr.Image(np.ascontiguousarray(image_rgb)).compress(jpeg_quality=85))

    def log_image_only(self, index: int, image_rgb) -> None:
        self.set_frame(index)
        self.rec.log("image", self._rr.Image(np.ascontiguousarray(image_rgb)).compress(jpeg_quality=85))

    def log_scalar(self, index: int, entity: str, value: float) -> None:
        """One per-frame value (a plot of the default blueprint when ``entity`` is in :data:`SCALARS`)."""
        if math.isfinite(value):
            self.set_frame(index)
            self.rec.log(entity, self._rr.Scalars(float(value)))

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
        """Write everything logged so far, and the default blueprint, to ``path`` (atomically); end the recording."""
        from recon.fileio import atomic_write_bytes

        self.rec.send_blueprint(self.blueprint())
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


def eye_for(vertices_table, Ts) -> tuple[np.ndarray, np.ndarray]:
    """A 3D eye that shows the whole object with the cameras around it: (eye, look target), table frame, mm.

    It looks at the centre of the object's bounding box from 45° above the
    table, from the side the cameras are on (their mean direction; the first
    camera's where they go all round), at twice the farthest camera's distance,
    so the object is whole in the middle of the view and the cameras' arc in
    front of it.
    """
    V = np.asarray(vertices_table, float).reshape(-1, 3)
    target = 0.5 * (V.min(axis=0) + V.max(axis=0)) if len(V) else np.zeros(3)
    centres = np.array([invert_T(np.asarray(T, float))[:3, 3] for T in Ts]).reshape(-1, 3)
    if not len(centres):
        return target + np.array([0.0, 500.0, 500.0]), target
    d = centres - target
    dist = float(np.max(np.linalg.norm(d, axis=1)))
    side = d.mean(axis=0)
    if np.hypot(side[0], side[2]) < 0.25 * dist:  # cameras all round: the mean says nothing
        side = d[0]
    az = math.atan2(side[0], side[2])
    elev = math.radians(45.0)
    direction = np.array([math.cos(elev) * math.sin(az), math.sin(elev), math.cos(elev) * math.cos(az)])
    return target + EYE_DISTANCE * dist * direction, target


@dataclass(frozen=True)
class RecordedViews:
    """The views a run used, as the recording shows them: names, work images (V, H, W, 3) and masks,
    the work-size camera ``K``, poses ``T_cam_table`` (V, 4, 4), ring conics per name (full-size pixels,
    mapped by ``work_size``) and the :class:`turntable.worksize.WorkSize`."""

    names: list[str]
    images_rgb: list[np.ndarray]
    masks: np.ndarray
    K: np.ndarray
    T_cam_table: np.ndarray
    conics: dict
    work_size: Any


@dataclass(frozen=True)
class RecordedModels:
    """What a run made: the hull's mesh, the fused points (or None), the final mesh and its texture (or None)."""

    hull_mesh: Any
    fused: Any
    mesh: Any
    textured: Any = None


def record_reconstruction(rec: Recorder, spec, seq, views: RecordedViews, models: RecordedModels) -> None:
    """The recording shows the work images with their camera ``K`` and the rings mapped onto them; the final
    mesh with its texture when ``models.textured`` (a :class:`recon.texture.TexturedMesh`) is given.
    ``spec``: the printed target (its rings drawn), or None."""
    names, images_rgb, masks, K, Ts, conics, ws = (views.names, views.images_rgb, views.masks, views.K,
                                                   views.T_cam_table, views.conics, views.work_size)
    hull_mesh, fused, mesh, textured = models.hull_mesh, models.fused, models.mesh, models.textured
    if spec is not None:
        rec.log_target(spec.r_outer_mm, spec.r_inner_mm)
    W, H = ws.work
    by_name = {fp.image: fp for fp in seq.frames}
    eye, target = eye_for(mesh.vertices_table, Ts)
    dist = float(np.linalg.norm(eye - target)) / EYE_DISTANCE
    for i, n in enumerate(names):
        rec.log_static_camera(i, K, W, H, Ts[i], image_rgb=images_rgb[i], image_plane_mm=0.1 * dist)
        rec.log_camera(i, K, W, H, Ts[i], image_rgb=images_rgb[i], image_plane_mm=0.2 * dist)
        if n in conics:
            rec.log_conics(i, {k: ws.conic(C) for k, C in conics[n].items()})
        rec.log_silhouette(i, masks[i])
        fp = by_name.get(n)
        if fp is not None:
            rec.log_scalar(i, "calibration/edge_rms_px", fp.rms_px)
            rec.log_scalar(i, "calibration/angle_deg", fp.angle_deg)
    rec.log_mesh("hull", hull_mesh.vertices_table, hull_mesh.faces, hull_mesh.normals_table)
    if fused is not None and len(fused.pts_table):
        rec.log_points("points", fused.pts_table, fused.colors_rgb)
    if textured is None:
        rec.log_mesh("mesh", mesh.vertices_table, mesh.faces, mesh.normals_table, mesh.colors_rgb)
    else:
        m = textured.mesh
        rec.log_mesh("mesh", m.vertices_table, m.faces, m.normals_table, texcoords=textured.texcoords,
                     texture_rgb=textured.texture_rgb)
    rec.frame_view(eye, target)
