"""The run's verdict and its summary: one :class:`ReconstructSummary`, written to ``summary.json``
(:meth:`ReconstructSummary.to_json`) and printed (:meth:`ReconstructSummary.lines`) from the same fields."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from .silhouettes import describe_ground, ground_name, silhouette_advice

__all__ = ["MeshSummary", "ReconstructSummary", "failed_checks", "summarise"]


def failed_checks(stats, vol_report: dict) -> list[str]:
    """What is wrong with the finished model, one line each (empty: it passed)."""
    failed = []
    if not stats.watertight:
        failed.append("the mesh is not watertight")
    if stats.n_bodies != 1:
        failed.append(f"the mesh is {stats.n_bodies} separate pieces, not one")
    failed += vol_report["clipped"]
    return failed


@dataclass(frozen=True)
class MeshSummary:
    """The final model: size, closedness, volume (cm³) and extent (mm, table frame X, Y, Z)."""

    vertices: int
    faces: int
    watertight: bool
    volume_cm3: float
    extent_mm: list[float]
    pieces: int = 1


@dataclass(frozen=True)
class ReconstructSummary:
    """What a run made and how it went: the same in ``summary.json`` and on screen.

    ``working_volume`` is the hull stage's report (radius, height, how it grew, what was clipped),
    ``silhouettes`` the frames ``rejected`` and kept ``conservative`` with their reasons (and
    ``printed_ground``, its hue and chromaticity, where a coloured printed ground was recognised, and
    ``advice`` where many automatic silhouettes came out empty: :func:`silhouette_advice`),
    ``exif_focal`` the photos' EXIF focal length against the calibrated one (or None),
    ``work_size`` the size the stages after calibration ran at, ``time_s`` each stage's wall time
    and the ``total``, ``files`` what OUT holds (paths as published), ``texture`` the photo texture's
    side and file and the textured models, finest first (file, faces, vertices; None: ``--no-texture``).
    """

    out: str
    frames_used: int
    frames_skipped: dict[str, str]
    focal_px: float
    focal_std_px: float | None
    principal_point_px: list[float]
    mode: str
    rms_px: float | None
    mesh: MeshSummary
    fusion: str
    warnings: list[str] = field(default_factory=list)
    time_s: dict[str, float] = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)
    working_volume: dict = field(default_factory=dict)
    silhouettes: dict = field(default_factory=dict)
    failed_checks: list[str] = field(default_factory=list)
    exif_focal: dict | None = None
    work_size: dict | None = None
    texture: dict | None = None

    def to_json(self) -> dict:
        """The content of ``summary.json``: every field but ``out``, in field order (strict JSON: no NaN,
        paths as strings)."""
        return {k: v for k, v in asdict(self).items() if k != "out"}

    @classmethod
    def from_json(cls, d: dict, out: str = "") -> ReconstructSummary:
        """Read a ``summary.json`` back (keys missing from older files take their defaults)."""
        m = d["mesh"]
        return cls(out=out, frames_used=int(d["frames_used"]), frames_skipped=dict(d.get("frames_skipped", {})),
                   focal_px=float(d["focal_px"]), focal_std_px=d.get("focal_std_px"),
                   principal_point_px=list(d.get("principal_point_px", [])), mode=str(d.get("mode", "")),
                   rms_px=d.get("rms_px"),
                   mesh=MeshSummary(int(m["vertices"]), int(m["faces"]), bool(m["watertight"]),
                                    float(m["volume_cm3"]), list(m["extent_mm"]), int(m.get("pieces", 1))),
                   fusion=str(d.get("fusion", "")), warnings=list(d.get("warnings", [])),
                   working_volume=d.get("working_volume") or {}, silhouettes=d.get("silhouettes") or {},
                   failed_checks=list(d.get("failed_checks", [])), exif_focal=d.get("exif_focal"),
                   work_size=d.get("work_size"), time_s=dict(d.get("time_s", {})), files=dict(d.get("files", {})),
                   texture=d.get("texture"))

    def lines(self) -> list[str]:
        """The summary as ``turntable reconstruct`` prints it, one line each."""
        from ..images import focal_warning

        out = [f"turntable reconstruct: {self.out}", f"  frames used     {self.frames_used}"]
        out += [f"  skipped         {name}: {why}" for name, why in self.frames_skipped.items()]
        sf = f" ± {self.focal_std_px:.2f}" if self.focal_std_px is not None else ""
        out.append(f"  focal length    {self.focal_px:.2f}{sf} px   ({self.mode} mode)")
        ex = self.exif_focal
        if ex:
            out.append(f"  EXIF focal      {ex['focal_35mm']:g} mm equivalent = {ex['focal_px']:.1f} px "
                       f"(calibrated {ex['calibrated_vs_exif_pct']:+.1f} %)")
            out += [f"  warning         {line}" for line in (ex.get("note"), focal_warning(self.focal_px, ex)) if line]
        out += [f"  warning         {line}" for line in self.warnings]
        if self.rms_px is not None:
            out.append(f"  edge RMS        {self.rms_px:.3f} px")
        ws = self.work_size
        if ws:
            full = ("full size" if (ws["width"], ws["height"]) == (ws["full_width"], ws["full_height"]) else
                    f"{ws['scale']:.3f} of {ws['full_width']} x {ws['full_height']}")
            out.append(f"  work size       {ws['width']} x {ws['height']} px ({full}; {ws['why']}); rings and "
                       "calibration at full size")
        m = self.mesh
        ext = " x ".join(f"{v:.1f}" for v in m.extent_mm)
        out.append(f"  mesh            {m.vertices} vertices, {m.faces} faces, "
                   f"{'watertight' if m.watertight else 'NOT watertight'}, {m.pieces} piece(s), "
                   f"{m.volume_cm3:.1f} cm³, {ext} mm")
        t = self.texture
        if t:
            out.append(f"  texture         {t['size_px']} x {t['size_px']} px, {t['file']}")
            out += [f"  {'model' if i == 0 else f'LOD {i}':<15} {lv['file']}: {lv['faces']} faces, "
                    f"{lv['vertices']} vertices (seams split)" for i, lv in enumerate(t["levels"])]
        else:
            out.append("  texture         none (--no-texture): vertex colours")
        v = self.working_volume
        if v:
            out.append(f"  working volume  radius {v['radius_mm']:.0f} mm, height {v['height_mm']:.0f} mm "
                       f"(first guess: {v['first_guess']}; the cameras allow {v['max_radius_mm']:.0f} x "
                       f"{v['max_height_mm']:.0f})")
            out += [f"  grown           {g}" for g in v.get("grown", [])]
            out += [f"  note            {note}" for note in v.get("notes", [])]
        out += [f"  conservative    {name}: {why}"
                for name, why in (self.silhouettes or {}).get("conservative", {}).items()]
        advice = (self.silhouettes or {}).get("advice")
        if advice:
            out.append(f"  hint            {advice}")
        ground = (self.silhouettes or {}).get("printed_ground")
        if ground:
            out.append(f"  printed ground  {describe_ground(ground['chromaticity'])}")
        out.append(f"  fusion          {self.fusion}")
        out.append("  time            " + ", ".join(f"{k} {t:.1f} s" for k, t in self.time_s.items()))
        out += [f"  {k:<15} {p}" for k, p in sorted(self.files.items())]
        out += [f"  !! CHECK FAILED {why}" for why in self.failed_checks]
        return out


def summarise(*, out, seq, names, skipped, mesh, stats, fusion_note, carved, failed, exif, work_size, times_s,
              files, textured=None) -> ReconstructSummary:
    """The summary of a finished run, from what the stages returned (``textured``: the
    :class:`recon.texture.TexturedMesh` exported, None without a texture)."""
    from ..frames import frame_name

    diagnostics = seq.diagnostics
    std_f = diagnostics.focal_std_px if diagnostics is not None else None
    rms = [fp.rms_px for fp in seq.frames if fp.ok and not math.isnan(fp.rms_px)]
    lo, hi = mesh.vertices_table.min(axis=0), mesh.vertices_table.max(axis=0)
    advice = silhouette_advice(carved.rejected, carved.conservative, len(carved.keep) + len(carved.rejected),
                               carved.silhouettes.ground)
    return ReconstructSummary(
        out=frame_name(str(out)), frames_used=len(names), frames_skipped=dict(skipped),
        focal_px=float(seq.intrinsics.focal_px),
        focal_std_px=None if std_f is None or math.isnan(std_f) else float(std_f),
        principal_point_px=[float(v) for v in seq.intrinsics.principal_point_px], mode=str(seq.mode),
        rms_px=float(np.sqrt(np.mean(np.square(rms)))) if rms else None,
        mesh=MeshSummary(vertices=int(len(mesh.vertices_table)), faces=int(len(mesh.faces)),
                         watertight=bool(stats.watertight), volume_cm3=float(stats.volume_mm3) / 1000.0,
                         extent_mm=[float(v) for v in hi - lo], pieces=int(stats.n_bodies)),
        fusion=fusion_note, warnings=list(diagnostics.warnings) if diagnostics is not None else [],
        working_volume=carved.report,
        silhouettes={"rejected": dict(carved.rejected), "conservative": dict(carved.conservative),
                     **({} if advice is None else {"advice": advice}),
                     **({} if carved.silhouettes.ground is None else
                        {"printed_ground": {"colour": ground_name(carved.silhouettes.ground),
                                            "chromaticity": [round(float(c), 4) for c in carved.silhouettes.ground]}})},
        failed_checks=list(failed), exif_focal=exif, work_size=work_size,
        time_s={k: round(v, 2) for k, v in times_s.items()},
        files={k: frame_name(str(v)) for k, v in files.items()},  # strict JSON whatever the path
        texture=None if textured is None else texture_summary(textured),
    )


def texture_summary(textured) -> dict:
    """The texture's side and file, and each textured model (``model.glb``, ``model_lod1.glb``, ...)."""
    from recon.export import lod_stem

    levels = [{"file": f"{lod_stem('model', i)}.glb", "faces": int(len(lv.mesh.faces)),
               "vertices": int(len(lv.mesh.vertices_table))} for i, lv in enumerate((textured, *textured.lods))]
    return {"size_px": int(textured.texture_rgb.shape[0]), "file": "model_albedo.png", "levels": levels}
