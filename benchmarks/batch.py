"""`turntable batch` against the same objects reconstructed one after the other, and the cost of one object.

Renders N objects (``turntable synth``: vase, cup, chair, figure on a dark and a light
backdrop, seeded; cached in ``--cache``), then

1. serial: one ``turntable reconstruct`` subprocess per object, one after the other, each with
   every core (the default threads), timed on its own (wall, CPU seconds, peak RSS);
2. batch: one ``turntable batch`` subprocess over the same objects (a local Ray, one core per
   job: ``--cpus-per-job 1``), timed end to end (Ray's start included);

and checks that every batch output equals its serial run: ``cameras.json`` (K, distortion and
every ``T_cam_table`` to 1e-9), the mesh (positions, faces, colours) and every file reconstruct
writes byte for byte (the models, the texture, ``points.ply``, ``cameras.json``; not
``summary.json``, whose times differ, nor ``recording.rrd``). The options are the defaults but
smaller (``--extra``): fusion and texture on. For reference the first object is reconstructed
again, the same command, and with ``--threads 1``: the batch's jobs run one thread each
(``--cpus-per-job 1``), the serial runs every core, so a thread-count dependence shows in both.
Bar (issue 14): batch wall <= 0.75 x the sum of the serial walls; outputs identical.

``--capacity MP ...``: the cost of one object at those sizes — ``data/sample`` (36 frames)
upscaled as ``benchmarks/resolution.py`` does, one ``reconstruct`` with default options: its
wall, CPU seconds (user + system, the process and its threads) and peak RSS.

    nice .venv/bin/python benchmarks/batch.py [--objects 8] [--size 640x480] [--frames 12]
        [--extra '--resolution 128 --max-faces 20000 --texture-size 512'] [--capacity 1.2 12]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

KINDS = [("vase", "dark"), ("cup", "dark"), ("chair", "dark"), ("figure", "dark"),
         ("vase", "light"), ("cup", "light"), ("chair", "light"), ("figure", "light")]
TARGET = ["--r-outer", "80", "--r-inner", "50", "--stroke", "3"]
POSE_TOL = 1e-9  # cameras.json: K, distortion, T_cam_table (mm and unitless)
SKIP = ("summary.json", "recording.rrd")  # times; the recording's own timestamps


def render(cache: Path, n: int, size: tuple[int, int], frames: int) -> list[Path]:
    from turntable.synth import SynthOptions, make_sequence

    folders = []
    for i in range(n):
        obj, backdrop = KINDS[i % len(KINDS)]
        folder = cache / f"{size[0]}x{size[1]}_{frames}" / f"{i:02d}_{obj}_{backdrop}"
        if not (folder / "cameras_gt.json").exists():
            make_sequence(folder, SynthOptions(object=obj, backdrop=backdrop, seed=i, frames=frames,
                                               step_deg=360.0 / frames, width=size[0], height=size[1],
                                               focal_px=1500.0 * size[0] / 1280), overwrite=True)
        folders.append(folder)
    return folders


def run(cmd: list[str], log: Path) -> tuple[float, float, float, int]:
    """(wall s, CPU s, peak RSS GB, exit code) of one subprocess (its own rusage, threads included)."""
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        p = subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT)
        _, status, ru = os.wait4(p.pid, 0)
    return (time.perf_counter() - t0, ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024 ** 2,
            os.waitstatus_to_exitcode(status))


def same_cameras(a: Path, b: Path) -> float:
    """Largest difference between two cameras.json (K, distortion, every T_cam_table)."""
    from turntable.cameras_io import read_cameras

    sa, sb = read_cameras(a), read_cameras(b)
    da, db = np.asarray(sa.intrinsics.dist, float), np.asarray(sb.intrinsics.dist, float)
    assert da.shape == db.shape, (da, db)
    d = [np.abs(sa.intrinsics.K - sb.intrinsics.K).max(), np.abs(da - db).max(initial=0.0)]
    assert [f.image for f in sa.frames] == [f.image for f in sb.frames]
    d += [np.abs(fa.T_cam_table - fb.T_cam_table).max() for fa, fb in zip(sa.frames, sb.frames, strict=True)
          if fa.ok and fb.ok]
    return float(max(d))


def mesh_digest(ply: Path) -> tuple[str, np.ndarray]:
    """sha256 of the mesh as geometry and colour (vertex positions, faces, vertex colours), and its normals."""
    import hashlib

    import trimesh

    m = trimesh.load(ply, process=False)
    h = hashlib.sha256()
    for a in (np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64), np.asarray(m.visual.vertex_colors)):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest(), np.asarray(m.vertex_normals, np.float64)


def _outputs(d: Path) -> set[str]:
    """Every file reconstruct wrote in OUT (not its stage cache ``.turntable``) but :data:`SKIP`."""
    return {p.relative_to(d).as_posix() for p in d.rglob("*")
            if p.is_file() and ".turntable" not in p.relative_to(d).parts and p.name not in SKIP}


def compare(serial: Path, batch: Path) -> tuple[float, bool, float, list[str]]:
    """Cameras' largest difference; same mesh digest; largest normal difference; the files (all that
    reconstruct writes but :data:`SKIP`) that are not byte-identical or not on both sides."""
    cams = same_cameras(serial / "cameras.json", batch / "cameras.json")
    (da, na), (db, nb) = mesh_digest(serial / "model.ply"), mesh_digest(batch / "model.ply")
    normals = float(np.abs(na - nb).max()) if na.shape == nb.shape else np.inf
    a, b = _outputs(serial), _outputs(batch)
    differ = sorted(a ^ b) + [n for n in sorted(a & b) if (serial / n).read_bytes() != (batch / n).read_bytes()]
    return cams, da == db, normals, differ


def _files(differ: list[str]) -> str:
    return "all identical" if not differ else "differ: " + ",".join(differ)


def capacity(sizes: list[float], work: Path) -> None:
    from resolution import _size_of, make_inputs

    print("\n# cost of one object: data/sample, 36 frames, upscaled (cv2 INTER_CUBIC, JPEG 92), default options")
    print(f"{'MP':>5} {'size':>10} {'wall s':>7} {'CPU s':>7} {'peak GB':>7} {'exit':>4}")
    for mp in sizes:
        size = _size_of(mp)
        images = work / f"cap_{mp:g}MP" / "images"
        make_inputs(ROOT / "data" / "sample", images, size, 36)
        out = work / f"cap_{mp:g}MP" / "out"
        wall, cpu, rss, rc = run([sys.executable, "-m", "turntable", "reconstruct", str(images), *TARGET,
                                  "--out", str(out), "--quiet"], work / f"cap_{mp:g}MP.log")
        print(f"{mp:5g} {size[0]:>4}x{size[1]:<5} {wall:7.1f} {cpu:7.1f} {rss:7.2f} {rc:4d}", flush=True)
        shutil.rmtree(images)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--objects", type=int, default=8, metavar="N")
    ap.add_argument("--size", default="640x480", metavar="WxH")
    ap.add_argument("--frames", type=int, default=12, metavar="N")
    ap.add_argument("--extra", default="--resolution 128 --max-faces 20000 --texture-size 512",
                    help="reconstruct options for both runs, one string")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "turntable-bench-batch"), metavar="DIR")
    ap.add_argument("--capacity", nargs="*", type=float, default=[], metavar="MP",
                    help="also measure one data/sample object at these sizes (e.g. 1.2 12)")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    cache, extra = Path(args.cache), args.extra.split()
    load = os.getloadavg()
    print(f"# {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {os.cpu_count()} cores, "
          f"load {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {args.objects} objects {size[0]}x{size[1]}, "
          f"{args.frames} frames; reconstruct {' '.join(TARGET + extra)}")
    folders = render(cache, args.objects, size, args.frames)
    work = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    try:
        root = work / "root"
        root.mkdir()
        for f in folders:  # the objects' photos only (batch reads OBJECT/images)
            (root / f.name).mkdir()
            (root / f.name / "images").symlink_to(f / "images")
        rows, serial_wall = [], 0.0
        print(f"{'object':<18} {'serial s':>8} {'CPU s':>7} {'peak GB':>7} {'exit':>4}")
        for f in folders:
            wall, cpu, rss, rc = run([sys.executable, "-m", "turntable", "reconstruct", str(f / "images"), *TARGET,
                                      "--out", str(work / "serial" / f.name), "--quiet", *extra],
                                     work / f"serial_{f.name}.log")
            serial_wall += wall
            rows.append((f.name, wall, cpu, rss, rc))
            print(f"{f.name:<18} {wall:8.1f} {cpu:7.1f} {rss:7.2f} {rc:4d}", flush=True)
        bwall, bcpu, brss, brc = run([sys.executable, "-m", "turntable", "batch", str(root), "--out",
                                      str(work / "batch"), *TARGET, "--cpus-per-job", "1", *extra],
                                     work / "batch.log")
        report = json.loads((work / "batch" / "batch.json").read_text())
        print(f"\nbatch: exit {brc}, {report['counts']}")
        print(f"{'object':<18} {'status':<13} {'job s':>6} {'cameras |d|':>11} {'mesh digest':>11} "
              f"{'normals |d|':>11}  files (all reconstruct writes but {', '.join(SKIP)})")
        worst, same_mesh, identical = 0.0, True, True
        for (name, *_, rc), r in zip(rows, report["rows"], strict=True):
            if rc == 2 or r["status"] == "failed":  # no model: the same failure on both sides is all to compare
                same_mesh &= rc == 2 and r["status"] == "failed"
                print(f"{name:<18} {r['status']:<13} serial exit {rc}; {r['reason'][:60]}")
                continue
            cams, same, normals, differ = compare(work / "serial" / name, work / "batch" / name)
            worst = max(worst, cams)
            same_mesh &= same and cams <= POSE_TOL
            identical &= not differ
            print(f"{name:<18} {r['status']:<13} {r['wall_s'] or 0:6.1f} {cams:11.1e} "
                  f"{'same' if same else 'DIFFER':>11} {normals:11.1e}  {_files(differ)}")
        # the same command again, and on one thread: what a separate run repeats byte for byte, for reference
        ref = next((i for i, r in enumerate(rows) if r[-1] in (0, 1, 3)), None)  # the first with a model
        for label, threads in () if ref is None else (("repeated", []), ("with --threads 1", ["--threads", "1"])):
            name = rows[ref][0]
            again = work / "again" / label.replace(" ", "_")
            run([sys.executable, "-m", "turntable", *threads, "reconstruct", str(folders[ref] / "images"), *TARGET,
                 "--out", str(again), "--quiet", *extra], work / "again.log")
            cams1, same1, normals1, differ1 = compare(work / "serial" / name, again)
            identical &= not differ1
            print(f"{name}, its serial run {label}: cameras |d| {cams1:.1e}, mesh digest "
                  f"{'same' if same1 else 'DIFFER'}, normals |d| {normals1:.1e}, files {_files(differ1)}")
        ratio = bwall / serial_wall
        print(f"\nsum of serial walls {serial_wall:.1f} s; batch wall {bwall:.1f} s (x{ratio:.2f}; bar <= 0.75: "
              f"{'met' if ratio <= 0.75 else 'NOT met'}); cameras to {worst:.1e}, mesh digests "
              f"{'all the same' if same_mesh else 'DIFFER'}, "
              f"files {'all byte-identical' if identical else 'not all byte-identical'} (batch and references)")
        serial_cpu = sum(r[2] for r in rows)
        print(f"serial CPU {serial_cpu:.1f} s = {serial_cpu / len(rows):.1f} s per object; "
              f"peak RSS {max(r[3] for r in rows):.2f} GB")
        if args.capacity:
            capacity(args.capacity, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
