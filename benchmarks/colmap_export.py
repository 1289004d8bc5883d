"""The COLMAP export as COLMAP reads it: tracks on every image, reprojection, depth ranges, a moved OUT.

For each case, ``turntable reconstruct ... --export-colmap --export-nerfstudio``
runs as a user runs it (ground-truth cameras and masks, so that only the
export is judged), OUT is then moved to another folder (``mv OUT elsewhere``),
and the moved export is read by pycolmap (``pycolmap.Reconstruction``):

* **tracks**: points, observations, the fewest observations of any image,
  mean track length;
* **reprojection**: COLMAP's mean reprojection error after
  ``update_point_3d_errors`` (its own camera model, distortion and pixel
  convention), and the largest single observation's error;
* **paths**: how many image paths of ``colmap/images.txt`` (under
  ``OUT/images``) and ``transforms.json`` resolve after the move;
* **dense**: ``pycolmap.undistort_images`` on the moved export (what
  ``colmap image_undistorter`` does), then, on the undistorted model, the
  depth range of each image exactly as COLMAP's patch-match computes it
  (``mvs::Model::ComputeDepthRanges``: the 1st and 99th percentile of its
  tracks' depths, stretched by 0.75 / 1.25; -1 for an image without tracks,
  which patch-match refuses) and the source images it would pick
  (``GetMaxOverlappingImages``: images sharing points at a 75th-percentile
  triangulation angle >= 1 degree). ``covers`` says whether every image's
  range holds the true object's depths (synthetic cases: ``object_gt.ply``;
  real ones: the exported mesh). patch-match itself needs CUDA, which this
  pycolmap build lacks; the figures above are what it reads from the model.

Cases: the synthetic vase with barrel distortion (k1 = -0.05), visual hull
(``--no-fusion``: points sampled on the mesh) and fused (fused points); the
cup (concave: its inside is occluded in most views); with ``--data``, every
real sequence there (``images/ masks/ cameras.json``), hull only.

    nice .venv/bin/python benchmarks/colmap_export.py [--quick] [--data ../shared/realdata] [--keep DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from turntable.cli import main  # noqa: E402
from turntable.synth import SynthOptions, make_sequence  # noqa: E402

TRIANGULATION_MIN_DEG = 1.0  # PatchMatchOptions.min_triangulation_angle's default


def depth_ranges(rec) -> dict[int, tuple[float, float]]:
    """COLMAP's mvs::Model::ComputeDepthRanges on a pycolmap reconstruction (metres)."""
    depths: dict[int, list[float]] = {i: [] for i in rec.images}
    for p in rec.points3D.values():
        for el in p.track.elements:
            T = rec.images[el.image_id].cam_from_world().matrix()
            d = float(T[2, :3] @ p.xyz + T[2, 3])
            if d > 0:
                depths[el.image_id].append(d)
    out = {}
    for i, ds in depths.items():
        if not ds:
            out[i] = (-1.0, -1.0)
            continue
        ds.sort()
        out[i] = (ds[int(len(ds) * 0.01)] * 0.75, ds[int(len(ds) * 0.99)] * 1.25)
    return out


def source_images(rec) -> dict[int, int]:
    """How many source images COLMAP's GetMaxOverlappingImages would offer each image (before its cap)."""
    centres = {i: im.projection_center() for i, im in rec.images.items()}
    angles: dict[tuple[int, int], list[float]] = {}
    for p in rec.points3D.values():
        ids = [el.image_id for el in p.track.elements]
        for a in range(len(ids)):
            for b in range(a):
                u, v = centres[ids[a]] - p.xyz, centres[ids[b]] - p.xyz
                ang = np.degrees(np.arccos(np.clip(u @ v / np.linalg.norm(u) / np.linalg.norm(v), -1.0, 1.0)))
                angles.setdefault((ids[a], ids[b]), []).append(ang)
                angles.setdefault((ids[b], ids[a]), []).append(ang)
    n = dict.fromkeys(rec.images, 0)
    for (i, _), a in angles.items():
        n[i] += np.percentile(a, 75) >= TRIANGULATION_MIN_DEG
    return n


def true_depths(rec, pts_m: np.ndarray) -> dict[int, tuple[float, float]]:
    out = {}
    for i, im in rec.images.items():
        T = im.cam_from_world().matrix()
        d = pts_m @ T[2, :3] + T[2, 3]
        out[i] = (float(d.min()), float(d.max()))
    return out


def max_observation_error(rec) -> float:
    worst = 0.0
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        obs = [p for p in im.points2D if p.has_point3D()]
        if not obs:
            continue
        X = np.array([rec.points3D[p.point3D_id].xyz for p in obs])
        X_cam = X @ im.cam_from_world().rotation.matrix().T + im.cam_from_world().translation
        uv = np.array([cam.img_from_cam(x) for x in X_cam])
        worst = max(worst, float(np.linalg.norm(uv - np.array([p.xy for p in obs]), axis=1).max()))
    return worst


def resolving_paths(out: Path) -> tuple[int, int]:
    names = [ln.split()[9] for ln in (out / "colmap" / "images.txt").read_text().splitlines()[4::2]]
    doc = json.loads((out / "transforms.json").read_text())
    paths = [out / "images" / n for n in names] + [out / fr["file_path"] for fr in doc["frames"]]
    return sum(p.is_file() for p in paths), len(paths)


def run_case(name: str, images: Path, cameras: Path, masks: Path, truth_m: Path | None, work: Path,
             extra: list[str]) -> dict:
    import pycolmap
    import trimesh

    out = work / name / "scan"
    args = ["reconstruct", str(images), "--cameras", str(cameras), "--masks", str(masks), "--out", str(out),
            "--export-colmap", "--export-nerfstudio", "--quiet", *extra]
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):  # the run's summary: the table says what matters here
        code = main(args)
    wall = time.perf_counter() - t0
    summary = json.loads((out / "summary.json").read_text())
    moved = work / name / "moved" / "scan"
    moved.parent.mkdir(parents=True)
    shutil.move(str(out), str(moved))
    ok_paths, n_paths = resolving_paths(moved)

    rec = pycolmap.Reconstruction(str(moved / "colmap"))
    per_image = [im.num_points3D for im in rec.images.values()]
    rec.update_point_3d_errors()
    row = {"case": name, "exit": code, "wall_s": wall, "export_s": summary["time_s"].get("export", float("nan")),
           "points": rec.num_points3D(), "obs": rec.compute_num_observations(), "min_obs_image": min(per_image),
           "track": rec.compute_mean_track_length(), "reproj_mean_px": rec.compute_mean_reprojection_error(),
           "reproj_max_px": max_observation_error(rec), "paths": f"{ok_paths}/{n_paths}"}

    t0 = time.perf_counter()
    dense = work / name / "dense"
    pycolmap.undistort_images(str(dense), str(moved / "colmap"), str(moved / "images"))
    row["undistort_s"] = time.perf_counter() - t0
    und = pycolmap.Reconstruction(str(dense / "sparse"))
    ranges = depth_ranges(und)
    pts = (trimesh.load(truth_m, process=False).vertices if truth_m is not None else
           trimesh.load(moved / "model.ply", process=False).vertices)
    pts = np.asarray(pts, float) / (1000.0 if truth_m is not None else 1.0)  # object_gt.ply is in mm
    truth = true_depths(und, pts)
    row["no_range"] = sum(lo < 0 for lo, _ in ranges.values())
    row["range_m"] = (min(lo for lo, _ in ranges.values()), max(hi for _, hi in ranges.values()))
    row["covers"] = all(lo <= truth[i][0] and truth[i][1] <= hi for i, (lo, hi) in ranges.items())
    row["min_sources"] = min(source_images(und).values())
    return row


def synth_case(work: Path, name: str, opts: SynthOptions) -> Path:
    root = work / name / "seq"
    make_sequence(root, opts)
    return root


def main_(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the hull cases only, 12 frames")
    ap.add_argument("--data", type=Path, help="folder of real sequences (images/ masks/ cameras.json)")
    ap.add_argument("--keep", type=Path, help="work here and keep the files (default: a temporary folder)")
    a = ap.parse_args(argv)
    try:
        import pycolmap
    except ImportError:
        print("pycolmap is not installed: pip install '.[colmap]'", file=sys.stderr)
        return 2
    work = a.keep or Path(tempfile.mkdtemp(prefix="colmap_export_"))
    work.mkdir(parents=True, exist_ok=True)
    n = 12 if a.quick else 24
    common = {"frames": n, "step_deg": 360.0 / n, "width": 960, "height": 720, "focal_px": 1100.0,
              "elevation_deg": 30.0, "distance_mm": 450.0, "k1": -0.05, "jpeg": 92, "supersample": 1}
    cases = []
    vase = synth_case(work, "vase", SynthOptions(object="vase", **common))
    cup = synth_case(work, "cup", SynthOptions(object="cup", **common))
    base = ["--resolution", "64", "--max-faces", "20000"]
    cases.append(("vase hull", vase, base + ["--no-fusion"]))
    cases.append(("cup hull", cup, base + ["--no-fusion"]))
    if not a.quick:
        cases.append(("vase fused", vase, base))
        cases.append(("cup fused", cup, base))
    rows = []
    for name, seq, extra in cases:
        rows.append(run_case(name.replace(" ", "_"), seq / "images", seq / "cameras_gt.json", seq / "masks",
                             seq / "object_gt.ply", work, extra))
        rows[-1]["case"] = name
    if a.data:
        for d in sorted(p for p in a.data.iterdir() if (p / "cameras.json").is_file()):
            rows.append(run_case(f"{d.name}_hull", d / "images", d / "cameras.json", d / "masks", None, work,
                                 base + ["--no-fusion"]))
            rows[-1]["case"] = f"{d.name} hull (real)"

    print(f"\n{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.node()}, "
          f"pycolmap {pycolmap.__version__}, {n} synthetic frames 960x720, k1 -0.05\n")
    print("| case | exit | points | observations | min obs/image | mean track | reproj mean px | reproj max px "
          "| paths after mv | depth range m | images without range | covers truth | min sources | export s "
          "| undistort s | run s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|---|---:|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['case']} | {r['exit']} | {r['points']} | {r['obs']} | {r['min_obs_image']} | {r['track']:.2f} "
              f"| {r['reproj_mean_px']:.1e} | {r['reproj_max_px']:.1e} | {r['paths']} "
              f"| {r['range_m'][0]:.3f}–{r['range_m'][1]:.3f} | {r['no_range']} | {'yes' if r['covers'] else 'NO'} "
              f"| {r['min_sources']} | {r['export_s']:.2f} | {r['undistort_s']:.1f} | {r['wall_s']:.0f} |")
    if not a.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main_())
