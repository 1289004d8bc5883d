"""Phone inputs give the same cameras as upright PNGs (issue 9): a markdown table.

One rendered turntable sequence (``turntable synth``, portrait, PNG) is stored
as a phone would store it, and each copy goes through ``turntable
calibrate-sequence`` as a user would run it:

* ``png``: the upright photos (the reference);
* ``jpeg``: upright JPEG, quality 95 (what JPEG alone changes);
* ``jpeg6`` / ``jpeg8``: portrait JPEG as phones write it: landscape pixels
  turned 90° and EXIF orientation 6 / 8, quality 95;
* ``heic6``: HEIC (pillow-heif, quality 95), landscape pixels + orientation 6,
  which pillow-heif stores as a HEIF ``irot``;
* ``video``: an mp4v video of the landscape frames with "rotate 90°" in its
  track header (informational: mp4v at OpenCV's default bitrate is far lossier
  than a phone's HEVC).

Every photo copy carries an EXIF 35 mm equivalent focal length (the true f,
rounded to a whole mm, as phones write it). The table gives f, its error
against the truth, its difference from the PNG's, the frames used, and the
EXIF f in pixels (diagonal convention). Bar: JPEG 6/8 and HEIC within 0.05 %
of the PNG's f.

Usage: ``python benchmarks/phone_inputs.py [--frames 12] [--size 960x1280] [--quick] [--keep DIR]``.
"""

from __future__ import annotations

import argparse
import math
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from turntable.cameras_io import read_cameras  # noqa: E402

BAR_REL = 0.0005  # 0.05 %
F_TRUE_PX = 1400.0
STORED = {6: lambda a: np.rot90(a, 1), 8: lambda a: np.rot90(a, -1)}  # applying EXIF o gives the upright image


def _exif(orientation: int, f35: int):
    from PIL import Image

    ex = Image.Exif()
    ex[0x0112] = orientation
    ex.get_ifd(0x8769)[0xA405] = f35
    return ex


def _set_mp4_rotation(path: Path, degrees_cw: int) -> None:
    """A clockwise display rotation in the MP4 track header (tkhd matrix), as phones write it."""
    c, s = {90: (0, 1), 270: (0, -1), 180: (-1, 0)}[degrees_cw]
    data = bytearray(path.read_bytes())
    k = data.find(b"tkhd")
    off = k + 8 + (20 if data[k + 4] == 0 else 32) + 16
    data[off:off + 36] = struct.pack(">9i", c << 16, s << 16, 0, -s << 16, c << 16, 0, 0, 0, 1 << 30)
    path.write_bytes(bytes(data))


def store_variants(upright: list[np.ndarray], root: Path, f35: int) -> dict[str, Path]:
    """Each storage of the upright BGR photos; the name -> folder (or video file)."""
    import pillow_heif
    from PIL import Image

    dirs = {k: root / k for k in ("png", "jpeg", "jpeg6", "jpeg8", "heic6")}
    for d in dirs.values():
        d.mkdir(parents=True)
    for k, up in enumerate(upright):
        rgb = up[..., ::-1]
        cv2.imwrite(str(dirs["png"] / f"frame_{k:03d}.png"), up)
        Image.fromarray(np.ascontiguousarray(rgb)).save(dirs["jpeg"] / f"IMG_{k:03d}.JPG", "JPEG", quality=95,
                                                        exif=_exif(1, f35))
        for o in (6, 8):
            stored = np.ascontiguousarray(STORED[o](rgb))
            Image.fromarray(stored).save(dirs[f"jpeg{o}"] / f"IMG_{k:03d}.JPG", "JPEG", quality=95,
                                         exif=_exif(o, f35))
        stored = np.ascontiguousarray(STORED[6](rgb))
        pillow_heif.from_bytes("RGB", (stored.shape[1], stored.shape[0]), stored.tobytes()).save(
            dirs["heic6"] / f"IMG_{k:03d}.HEIC", quality=95, exif=_exif(6, f35).tobytes())
    video = root / "phone.mp4"
    h, w = upright[0].shape[:2]
    vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10, (h, w))  # landscape frames
    if vw.isOpened():
        for up in upright:
            vw.write(np.ascontiguousarray(np.rot90(up, 1)))  # shown rotated 90° clockwise: upright
        vw.release()
        _set_mp4_rotation(video, 90)
        dirs["video"] = video
    return dirs


def calibrate(src: Path, out: Path) -> tuple[dict, float]:
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "turntable", "calibrate-sequence", str(src), "--r-outer", "80", "--r-inner", "50",
           "--out", str(out)]
    run = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if run.returncode not in (0, 1):
        return {"error": (run.stderr.strip().splitlines() or ["?"])[-1]}, wall
    seq = read_cameras(out)
    return {"f": seq.intrinsics.focal_px, "size": (seq.intrinsics.width, seq.intrinsics.height),
            "used": sum(fr.ok for fr in seq.frames), "n": len(seq.frames),
            "exif": ((seq.diagnostics.exif_focal if seq.diagnostics else None) or {}).get("focal_px")}, wall


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--size", default="960x1280", help="upright (portrait) image size WxH")
    ap.add_argument("--quick", action="store_true", help="8 frames at 600x800")
    ap.add_argument("--keep", metavar="DIR", help="keep the images here")
    opt = ap.parse_args()
    frames, size = (8, "600x800") if opt.quick else (opt.frames, opt.size)
    w, h = (int(v) for v in size.split("x"))
    f_true = F_TRUE_PX * w / 960
    f35 = round(f_true / math.hypot(w, h) * math.hypot(36, 24))
    root = Path(opt.keep) if opt.keep else Path(tempfile.mkdtemp(prefix="phone_inputs_"))
    synth = root / "synth"
    subprocess.run([sys.executable, "-m", "turntable", "synth", str(synth), "--frames", str(frames),
                    "--step-deg", f"{360 / frames:g}", "--size", size, "--focal-px", f"{f_true:g}",
                    "--jpeg", "0", "--seed", "9", "--overwrite"], check=True, capture_output=True)
    upright = [cv2.imread(str(p)) for p in sorted((synth / "images").glob("*.png"))]
    variants = store_variants(upright, root / "stored", f35)
    print(f"{frames} frames, {w}x{h} portrait, true f {f_true:.1f} px, EXIF {f35} mm equivalent "
          f"(= {f35 / math.hypot(36, 24) * math.hypot(w, h):.1f} px, diagonal convention)\n")
    print("| input | f px | f error | vs PNG | frames used | EXIF f px | time s |")
    print("|---|---|---|---|---|---|---|")
    results = {}
    for name, src in variants.items():
        r, wall = calibrate(src, root / f"{name}.json")
        results[name] = r
        if "error" in r:
            print(f"| {name} | failed: {r['error']} | | | | | {wall:.1f} |")
            continue
        ref = results["png"].get("f")
        vs = f"{100 * (r['f'] / ref - 1):+.4f} %" if ref else "-"
        exif = f"{r['exif']:.1f}" if r["exif"] else "-"
        print(f"| {name} | {r['f']:.2f} | {100 * (r['f'] / f_true - 1):+.3f} % | {vs} | {r['used']}/{r['n']} | "
              f"{exif} | {wall:.1f} |")
    ref = results["png"].get("f")
    worst = max((abs(results[k]["f"] / ref - 1) if "f" in results[k] else math.inf)
                for k in ("jpeg6", "jpeg8", "heic6")) if ref else math.inf
    print(f"\nbar: JPEG 6/8 and HEIC within {100 * BAR_REL:.2f} % of the PNG's f: worst {100 * worst:.4f} % -> "
          f"{'met' if worst <= BAR_REL else 'NOT MET'}")
    if not opt.keep:
        import shutil

        shutil.rmtree(root, ignore_errors=True)
    return 0 if worst <= BAR_REL else 1


if __name__ == "__main__":
    sys.exit(main())
