"""The stage cache in ``OUT/.turntable``: reused only for the same bytes and options, never trusted when damaged.

The file-level checks drive :class:`turntable.stages.cache.StageCache` directly; the
end-to-end ones run ``turntable reconstruct`` on one small rendered sequence
(8 frames, 640x480, 32^3 hull, no fusion), edit an input in place (keeping its
size and modification time where the edit allows) or damage a cache file, and
check the re-run recomputes, says why when a file was damaged, and exits 0.
"""

from __future__ import annotations

import json
import os
import shutil
import zipfile

import cv2
import numpy as np
import pytest

from turntable.cli import main
from turntable.stages.cache import StageCache
from turntable.synth import SynthOptions, make_sequence

VOLUME_REL_TOL = 0.02  # automatic silhouettes recomputed: the model's volume may move this much


# --------------------------------------------------------------------------- the file
def _saved(tmp_path, notes):
    cache = StageCache(tmp_path, note=notes.append)
    rng = np.random.default_rng(0)
    masks = rng.random((3, 20, 30)) > 0.5
    cache.save("silhouettes", "k1", masks=masks, status=np.array(["ok", "ok", "rejected: empty"]))
    fields = {"masks": ("b", (3, 20, 30)), "status": ("U", (3,))}
    return cache, masks, fields


def test_round_trip_and_a_stale_key_is_not_a_fault(tmp_path):
    notes: list[str] = []
    cache, masks, fields = _saved(tmp_path, notes)
    hit = cache.load("silhouettes", "k1", fields)
    assert hit is not None and np.array_equal(hit["masks"], masks) and set(hit) == {"masks", "status"}
    assert cache.load("silhouettes", "k2", fields) is None  # other inputs: recomputed without a note
    assert cache.load("hull", "k1") is None
    assert notes == []


def _flip_in_member(path, member: str) -> None:
    """Rewrite the archive with one byte of ``member``'s array data changed (zip CRCs made to match)."""
    with zipfile.ZipFile(path) as z:
        items = {n: z.read(n) for n in z.namelist()}
    data = bytearray(items[member])
    data[-1] ^= 0x01  # the last byte of the array data, after the .npy header
    items[member] = bytes(data)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for n, b in items.items():
            z.writestr(n, b)


def _damage(path, how: str) -> None:
    data = path.read_bytes()
    if how == "empty":
        path.write_bytes(b"")
    elif how == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif how == "garbage":
        path.write_bytes(np.random.default_rng(1).integers(0, 256, len(data), dtype=np.uint8).tobytes())
    elif how == "flipped byte":  # inside the compressed data: the zip CRC catches it
        mid = bytearray(data)
        mid[len(mid) // 3] ^= 0xFF
        path.write_bytes(bytes(mid))
    elif how == "checksum":  # a valid archive whose array differs from what was saved
        _flip_in_member(path, "masks.npy")
    else:
        raise ValueError(how)


@pytest.mark.parametrize("how, says", [("empty", "unreadable (empty)"), ("truncated", "unreadable"),
                                       ("garbage", "unreadable"), ("flipped byte", ""),
                                       ("checksum", "checksum mismatch")])
def test_a_damaged_file_is_a_miss_with_a_note(tmp_path, how, says):
    notes: list[str] = []
    cache, _, fields = _saved(tmp_path, notes)
    _damage(cache.path("silhouettes"), how)
    assert cache.load("silhouettes", "k1", fields) is None
    assert len(notes) == 1 and "silhouettes.npz" in notes[0] and notes[0].endswith("recomputing"), notes
    assert says in notes[0]


def test_a_file_without_a_checksum_is_a_miss_with_a_note(tmp_path):
    notes: list[str] = []
    cache = StageCache(tmp_path, note=notes.append)
    cache.dir.mkdir()
    np.savez_compressed(cache.path("hull"), _key=np.array("k1"), values=np.zeros((2, 2, 2), np.float32))
    assert cache.load("hull", "k1") is None
    assert len(notes) == 1 and "no checksum" in notes[0], notes


@pytest.mark.parametrize("fields, says", [({"masks": ("b", (3, 20, 31))}, "shape"),
                                          ({"masks": ("f", (3, 20, 30))}, "kind"),
                                          ({"unknown": ("b", (3, 20, 30))}, "no field 'unknown'"),
                                          ({"masks": ("b", ("V", 20, 30)), "status": ("U", ("V", 1))}, "status")])
def test_fields_of_the_wrong_shape_or_kind_are_a_miss_with_a_note(tmp_path, fields, says):
    notes: list[str] = []
    cache, _, _ = _saved(tmp_path, notes)
    assert cache.load("silhouettes", "k1", fields) is None
    assert len(notes) == 1 and says in notes[0], notes


# --------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    opts = SynthOptions(object="vase", frames=8, step_deg=45.0, width=640, height=480, focal_px=760.0,
                        elevation_deg=35.0, distance_mm=430.0, noise=1.5, jpeg=95, backdrop="dark", seed=3,
                        supersample=1)
    make_sequence(root / "seq", opts)
    return root / "seq"


def _run(capsys, *args) -> tuple[int, str, float]:
    """Exit code, stderr and the model's volume (cm³) of one ``reconstruct`` run."""
    capsys.readouterr()
    code = main(["reconstruct", *map(str, args), "--resolution", "32", "--max-faces", "5000", "--no-fusion"])
    err = capsys.readouterr().err
    out = args[args.index("--out") + 1]
    vol = json.loads((out / "summary.json").read_text())["mesh"]["volume_cm3"] if code == 0 else float("nan")
    return code, err, vol


def _known(seq, out, cameras=None):
    """Given cameras and masks; the radii make the first working volume the target's, whatever the cameras."""
    return (seq / "images", "--cameras", cameras or seq / "cameras_gt.json", "--masks", seq / "masks", "--out", out,
            "--r-outer", "80", "--r-inner", "50")


def _auto(seq, out, *extra):
    return (seq / "images", "--r-outer", "80", "--r-inner", "50", "--out", out, *extra)


def _keep_time(path, edit) -> None:
    """Edit a file in place and give it back its modification time."""
    st = path.stat()
    edit(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_a_mask_edited_in_place_recomputes_the_silhouettes(scene, tmp_path, capsys):
    seq = tmp_path / "seq"
    shutil.copytree(scene, seq)
    out = tmp_path / "scan"
    code, _, before = _run(capsys, *_known(seq, out))
    assert code == 0

    def cut_top(p):  # the object's upper half goes from one view: the hull loses it
        m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        rows = np.nonzero(m.reshape(m.shape[0], -1).max(axis=1))[0]
        m[: (rows[0] + rows[-1]) // 2] = 0
        cv2.imwrite(str(p), m)

    _keep_time(seq / "masks" / "frame_002.png", cut_top)
    code, err, after = _run(capsys, *_known(seq, out))
    assert code == 0 and "silhouettes: reused" not in err and "hull: reused" not in err, err
    _, _, fresh = _run(capsys, *_known(seq, tmp_path / "fresh"))
    assert after == pytest.approx(fresh, rel=1e-9) and after < 0.95 * before, (before, after, fresh)


def test_a_new_camera_matrix_in_the_cameras_file_recomputes_the_hull(scene, tmp_path, capsys):
    cams = tmp_path / "cameras.json"
    shutil.copy(scene / "cameras_gt.json", cams)
    out = tmp_path / "scan"
    code, _, before = _run(capsys, *_known(scene, out, cams))
    assert code == 0

    def other_camera(p):  # small enough to leave the working volume as it was: only K says it changed
        d = json.loads(p.read_text())
        K = d["intrinsics"]["K"]
        K[0][0], K[1][1], K[0][2] = 1.01 * K[0][0], 1.01 * K[1][1], K[0][2] + 6.0
        p.write_text(json.dumps(d))

    _keep_time(cams, other_camera)
    code, err, after = _run(capsys, *_known(scene, out, cams))
    assert code == 0 and "hull: reused" not in err, err
    _, _, fresh = _run(capsys, *_known(scene, tmp_path / "fresh", cams))
    assert after == pytest.approx(fresh, rel=1e-9) and after != pytest.approx(before, rel=1e-3), (before, after)


def test_a_frame_edited_in_place_is_new_input(scene, tmp_path, capsys):
    seq = tmp_path / "seq"
    shutil.copytree(scene, seq)
    out = tmp_path / "scan"
    assert _run(capsys, *_known(seq, out))[0] == 0

    def flip_a_byte(p):  # same size, same time: only the content says it changed
        data = bytearray(p.read_bytes())
        data[len(data) * 3 // 4] ^= 0x10
        p.write_bytes(bytes(data))

    _keep_time(seq / "images" / "frame_005.jpg", flip_a_byte)
    code, err, _ = _run(capsys, *_known(seq, out))
    assert code == 0 and "silhouettes: reused" not in err, err
    code, err, _ = _run(capsys, *_known(seq, out))  # and the same bytes again are the same input
    assert code == 0 and "silhouettes: reused" in err and "hull: reused" in err, err


@pytest.fixture(scope="module")
def auto_scan(scene, tmp_path_factory):
    """An OUT with every stage file, from automatic cameras and silhouettes; its model's volume."""
    out = tmp_path_factory.mktemp("auto") / "scan"
    assert main(["reconstruct", *map(str, _auto(scene, out)), "--resolution", "32", "--max-faces", "5000",
                 "--no-fusion", "--quiet"]) == 0
    assert sorted(p.name for p in (out / ".turntable").glob("*.npz")) == \
        ["detections.npz", "hull.npz", "silhouettes.npz", "texture.npz", "volume.npz"]
    # beside the stages: the cached calibration, the lock and the record of the published set, nothing else
    assert sorted(p.name for p in (out / ".turntable").iterdir() if p.suffix != ".npz") == \
        ["cameras.json", "lock", "published.json"]
    return out, json.loads((out / "summary.json").read_text())["mesh"]["volume_cm3"]


def test_damaged_cache_files_are_recomputed_with_a_note(scene, tmp_path, capsys, auto_scan):
    out = tmp_path / "scan"
    shutil.copytree(auto_scan[0], out)
    damage = {"detections": "empty", "silhouettes": "truncated", "hull": "garbage", "volume": "flipped byte"}
    for name, how in damage.items():
        _damage(out / ".turntable" / f"{name}.npz", how)
    code, err, vol = _run(capsys, *_auto(scene, out))
    assert code == 0 and "internal error" not in err, err
    for name in damage:
        assert f"cache: {out / '.turntable' / name}.npz unreadable" in err, (name, err)
    assert "reusing cameras.json" not in err and "silhouettes: reused" not in err and "hull: reused" not in err
    assert vol == pytest.approx(auto_scan[1], rel=VOLUME_REL_TOL)
    code, err, _ = _run(capsys, *_auto(scene, out))  # the files written again are reused
    assert code == 0 and "reusing cameras.json" in err and "hull: reused" in err and "cache:" not in err, err


def test_a_checksum_mismatch_recomputes(scene, tmp_path, capsys, auto_scan):
    out = tmp_path / "scan"
    shutil.copytree(auto_scan[0], out)
    _damage(out / ".turntable" / "silhouettes.npz", "checksum")
    code, err, vol = _run(capsys, *_auto(scene, out))
    assert code == 0 and "silhouettes.npz checksum mismatch, recomputing" in err, err
    assert "reusing cameras.json" in err and "silhouettes: reused" not in err
    assert vol == pytest.approx(auto_scan[1], rel=VOLUME_REL_TOL)


def test_an_edited_intrinsics_file_recalibrates(scene, tmp_path, capsys):
    intr = tmp_path / "camera.json"
    K = [[760.0, 0.0, 319.5], [0.0, 760.0, 239.5], [0.0, 0.0, 1.0]]
    intr.write_text(json.dumps({"camera_matrix": K, "distortion_coefficients": [], "image_width": 640,
                                "image_height": 480}))
    out = tmp_path / "scan"
    assert _run(capsys, *_auto(scene, out, "--intrinsics", intr))[0] == 0
    before = json.loads((out / "cameras.json").read_text())["intrinsics"]["K"][0][0]

    def longer_focal(p):
        d = json.loads(p.read_text())
        d["camera_matrix"][0][0] = d["camera_matrix"][1][1] = 766.0
        p.write_text(json.dumps(d))

    _keep_time(intr, longer_focal)
    code, err, _ = _run(capsys, *_auto(scene, out, "--intrinsics", intr))
    assert code == 0 and "reusing cameras.json" not in err, err
    after = json.loads((out / "cameras.json").read_text())["intrinsics"]["K"][0][0]
    assert before == pytest.approx(760.0) and after == pytest.approx(766.0), (before, after)
