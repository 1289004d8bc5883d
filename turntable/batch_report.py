"""The report of a ``turntable batch``: ``OUT/batch.json``, ``batch.csv``, ``index.html`` and the thumbnails.

One row per object (:class:`BatchResult`); ``batch.csv`` has the main figures and the stage times as
``time_<stage>_s`` columns; ``index.html`` is one self-contained page, a card per object with its
thumbnail (``OUT/thumbnails/<object>.png``), rendered from its model by ray casting on the CPU
(:func:`render_thumbnail`). Also the names OUT holds besides the objects' folders (:data:`RESERVED_NAMES`).
"""

from __future__ import annotations

import csv
import html
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.camera import camera_centre_table

from .cameras_io import atomic_write_text

__all__ = ["BatchResult", "write_reports", "overview_html", "load_model", "thumbnail_camera", "render_thumbnail",
           "write_thumbnail", "STATUSES", "CSV_COLUMNS", "RESERVED_NAMES", "BATCH_DIR", "THUMB_DIR", "THUMB_PX"]

#: What a job ended as. ``ok``: exit 0; ``warning``: finished, some frames unreadable (reconstruct's 1);
#: ``check_failed``: finished, the model failed a check (3); ``failed``: no model (bad input, a worker
#: that died every attempt, an internal error); ``not_run``: the batch was interrupted first.
STATUSES = ("ok", "warning", "check_failed", "failed", "not_run")

BATCH_DIR = ".batch"  # OUT/.batch: one record per finished object, the running markers
THUMB_DIR = "thumbnails"
THUMB_PX = 192
#: What OUT holds besides the objects' folders: no object may be named so
RESERVED_NAMES = ("batch.json", "batch.csv", "index.html", THUMB_DIR, BATCH_DIR)


# --------------------------------------------------------------------------- what a batch gives


@dataclass
class BatchResult:
    """What :func:`turntable.batch.run_batch` gives: a report row per object, the wall time, and the report files."""

    rows: list[dict]
    wall_s: float
    interrupted: bool = False
    files: dict[str, Path] = field(default_factory=dict)

    @property
    def not_ok(self) -> list[dict]:
        return [r for r in self.rows if r["status"] != "ok"]


# --------------------------------------------------------------------------- the report

CSV_COLUMNS = ("object", "status", "reason", "attempts", "resumed", "node", "frames_used", "focal_px",
               "focal_std_px", "rms_px", "mesh_faces", "volume_cm3", "watertight", "wall_s")


def write_reports(out: Path, res: BatchResult) -> dict[str, Path]:
    """``OUT/batch.json``, ``OUT/batch.csv`` (stage times as ``time_<stage>_s`` columns) and ``OUT/index.html``."""
    counts = {s: sum(r["status"] == s for r in res.rows) for s in STATUSES}
    doc = {"objects": len(res.rows), "counts": counts, "wall_s": round(res.wall_s, 2), "interrupted": res.interrupted,
           "rows": res.rows}
    atomic_write_text(out / "batch.json", json.dumps(doc, indent=1, default=str) + "\n")
    stages: list[str] = []
    for r in res.rows:
        stages += [k for k in r.get("time_s") or {} if k not in stages]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*CSV_COLUMNS, *(f"time_{s.replace(' ', '_')}_s" for s in stages)])
    for r in res.rows:
        w.writerow([("" if r.get(c) is None else r.get(c)) for c in CSV_COLUMNS] +
                   [(r.get("time_s") or {}).get(s, "") for s in stages])
    atomic_write_text(out / "batch.csv", buf.getvalue())
    atomic_write_text(out / "index.html", overview_html(res.rows, counts))
    return {"json": out / "batch.json", "csv": out / "batch.csv", "html": out / "index.html"}


_COLOURS = {"ok": "#2e7d32", "warning": "#b26a00", "check_failed": "#c62828", "failed": "#c62828",
            "not_run": "#616161"}


_CARD = {"warning": "warn", "check_failed": "bad", "failed": "bad", "not_run": "idle"}  # a card's frame


def _fmt(v, spec: str = "") -> str:
    return "–" if v is None else format(v, spec)


def overview_html(rows: list[dict], counts: dict) -> str:
    """One self-contained page: a card per object (thumbnail, status, reason, the main figures)."""
    e = html.escape
    cards = []
    for r in rows:
        img = (f'<img src="{e(r["thumbnail"])}" alt="{e(r["object"])}">' if r.get("thumbnail")
               else '<div class="none">no model</div>')
        f = "" if r.get("focal_px") is None else (
            f"f {r['focal_px']:.1f}" + (f" ± {r['focal_std_px']:.2f}" if r.get("focal_std_px") is not None else "")
            + " px")
        facts = " · ".join(x for x in (f"{r['frames_used']} frames" if r.get("frames_used") is not None else "", f,
                                       f"edge RMS {r['rms_px']:.3f} px" if r.get("rms_px") is not None else "",
                                       f"{_fmt(r.get('mesh_faces'))} faces" if r.get("mesh_faces") else "",
                                       f"{r['volume_cm3']:.1f} cm³" if r.get("volume_cm3") is not None else "",
                                       f"{r['wall_s']:.1f} s" if r.get("wall_s") is not None else "") if x)
        kind = _CARD.get(r["status"], "")
        link = f'<a href="{e(r["output"])}/">{img}</a>' if r.get("thumbnail") else img  # no model: nothing to open
        cards.append(f'<div class="card {kind}" id="{e(r["object"])}">{link}'
                     f'<h2>{e(r["object"])}</h2>'
                     f'<p class="st" style="color:{_COLOURS.get(r["status"], "#000")}">{e(r["status"])}'
                     f'{" (resumed)" if r.get("resumed") else ""}</p><p>{e(facts)}</p>'
                     f'<p class="why">{e(r.get("reason") or "")}</p></div>')
    summary = e(", ".join(f"{v} {k}" for k, v in counts.items() if v))
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:  # the objects to look at, first: a link to each card
        summary += "<br>not ok: " + ", ".join(f'<a href="#{e(r["object"])}" style="color:'
                                               f'{_COLOURS.get(r["status"], "#000")}">{e(r["object"])}</a>'
                                               for r in bad)
    return ("<!doctype html><html><head><meta charset=\"utf-8\"><title>turntable batch</title><style>"
            "body{font:14px sans-serif;margin:1em}.card{display:inline-block;vertical-align:top;width:"
            f"{THUMB_PX + 24}px;margin:6px;padding:6px;border:1px solid #ccc;border-radius:4px}}"
            ".card.bad{border:4px solid #c62828;padding:3px;background:#fdecea}"
            ".card.warn{border:4px solid #b26a00;padding:3px;background:#fff3e0}"
            ".card.idle{border:4px dashed #9e9e9e;padding:3px;background:#f5f5f5}"
            "h2{font-size:14px;margin:4px 0}p{margin:2px 0}.st{font-weight:bold}.why{color:#c62828;font-size:12px}"
            f".none{{width:{THUMB_PX}px;height:{THUMB_PX}px;background:#eee;text-align:center;line-height:"
            f"{THUMB_PX}px;color:#888}}</style></head><body><h1>turntable batch: {len(rows)} objects</h1>"
            f"<p>{summary}</p>{''.join(cards)}</body></html>\n")


# --------------------------------------------------------------------------- thumbnails


def load_model(out_dir: Path):
    """What an object's OUT shows: ``(TableMesh, texcoords, texture_rgb)``, mm in the table frame. A textured
    model (``model.glb`` next to ``model_albedo.png``) is read from the GLB, its UVs in the pipeline's
    convention (``v`` down from the texture's top row); otherwise ``model.ply`` with its vertex colours and
    ``None, None``."""
    import trimesh

    from recon.types import TableMesh

    out_dir = Path(out_dir)
    glb, ply = out_dir / "model.glb", out_dir / "model.ply"
    if glb.is_file() and (out_dir / "model_albedo.png").is_file():
        m = trimesh.load(glb, force="mesh", process=False)
        tex = getattr(getattr(m.visual, "material", None), "baseColorTexture", None)
        uv = getattr(m.visual, "uv", None)
        if tex is not None and uv is not None and len(uv) == len(m.vertices):
            uv = np.asarray(uv, np.float64).copy()
            uv[:, 1] = 1.0 - uv[:, 1]  # trimesh turns glTF's v (down) into OpenGL's (up): back
            mesh = TableMesh(vertices_table=np.asarray(m.vertices, np.float64) * 1000.0,  # GLB: metres
                             faces=np.asarray(m.faces, np.int64))
            return mesh, uv, np.asarray(tex.convert("RGB"), np.uint8)
    m = trimesh.load(ply, process=False)
    colours = getattr(m.visual, "vertex_colors", None)
    mesh = TableMesh(vertices_table=np.asarray(m.vertices, np.float64) * 1000.0,  # PLY: metres, as the GLB
                     faces=np.asarray(m.faces, np.int64),
                     colors_rgb=None if colours is None else np.asarray(colours, np.uint8)[:, :3])
    return mesh, None, None


def thumbnail_camera(vertices: np.ndarray, size: int, elevation_deg: float = 25.0, azimuth_deg: float = 35.0,
                     fov_deg: float = 35.0) -> tuple[np.ndarray, np.ndarray]:
    """``K, T_cam_table`` of a square ``size`` view (OpenCV camera, pixel centres at integers) that looks at
    the bounding box's centre from ``elevation_deg`` above the table (+Y up), far enough for the box's
    sphere to fit ``fov_deg``."""
    V = np.asarray(vertices, np.float64)
    lo, hi = V.min(0), V.max(0)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    view = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    eye = centre + view * radius / np.sin(np.radians(fov_deg / 2)) * 1.05
    z = (centre - eye) / np.linalg.norm(centre - eye)
    x = np.cross([0.0, -1.0, 0.0], z)  # image y runs down the table's +Y
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ eye
    f = (size / 2) / np.tan(np.radians(fov_deg / 2))
    K = np.array([[f, 0.0, (size - 1) / 2], [0.0, f, (size - 1) / 2], [0.0, 0.0, 1.0]])
    return K, T


def render_thumbnail(out_dir: Path, size: int = THUMB_PX) -> np.ndarray:
    """A small picture of an object's model as its GLB shows it: the photo texture when the model is
    textured, else the vertex colours (:func:`load_model`), looked up by ray casting on the CPU
    (:func:`recon.texture.render_albedo`), shaded by the surface's angle to the eye so the shape reads.
    ``(size, size, 3)`` uint8 RGB on a light grey background."""
    import open3d as o3d

    from recon.raycast import raycasting_scene
    from recon.texture import render_albedo

    mesh, uv, tex = load_model(Path(out_dir))
    V, F = mesh.vertices_table, mesh.faces
    if len(F) == 0:
        raise ValueError(f"{out_dir}: the model has no faces")
    K, T = thumbnail_camera(V, size)
    rgb, hit = render_albedo(mesh, K, T, (size, size), texcoords=uv, texture_rgb=tex)
    img = np.full((size, size, 3), 245.0)
    if hit.any():
        # the same rays as render_albedo's: the hit face's normal against the ray gives a Lambert shade
        u, v = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64))
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T[:3, :3]
        rays = np.concatenate([np.broadcast_to(camera_centre_table(T), d.shape), d], -1).astype(np.float32)
        ans = raycasting_scene(V, F).cast_rays(o3d.core.Tensor(rays))  # type: ignore[call-overload]
        n = ans["primitive_normals"].numpy()[hit].astype(np.float64)
        d = d[hit] / np.linalg.norm(d[hit], axis=1, keepdims=True)
        shade = 0.45 + 0.55 * np.abs((n * d).sum(1))
        img[hit] = rgb[hit] * shade[:, None]
    return np.round(np.clip(img, 0, 255)).astype(np.uint8)


def write_thumbnail(out_dir: Path, png: Path) -> Path:
    """:func:`render_thumbnail` of the model in ``out_dir`` written (atomically) to ``png``."""
    import cv2

    from recon.fileio import atomic_write_bytes

    rgb = render_thumbnail(out_dir)
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"{png}: PNG encoding failed")
    png.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(png, data.tobytes())
    return png
