"""Faults a trusted tool must survive: a full disk, kills, signals, two runs at once, stale files.

The rule under test (``turntable.outdir``): OUT shows either the previous
run's files or the new run's, whole — never a mix, never nothing where there
was something — and nothing a run leaves behind survives the next run.

Runs use known cameras and masks on a small rendered sequence, so each takes a
few seconds; ``benchmarks/faults.py`` runs the heavier cases (automatic
calibration and silhouettes, fusion).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from disk_full import model_digests, published_digests, run_leftovers, tmpfs_prefix

from turntable.cli import main
from turntable.errors import UserError
from turntable.outdir import OutputFolder
from turntable.synth import SynthOptions, make_sequence

HERE = Path(__file__).parent


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("faults")
    opts = SynthOptions(object="vase", frames=8, step_deg=45.0, width=320, height=240, focal_px=380.0,
                        elevation_deg=35.0, distance_mm=430.0, noise=1.0, jpeg=95, backdrop="dark", seed=5,
                        supersample=1)
    make_sequence(root / "seq", opts)
    return root / "seq"


def _args(scene: Path, out: Path, *extra: str) -> list[str]:
    return ["reconstruct", str(scene / "images"), "--cameras", str(scene / "cameras_gt.json"),
            "--masks", str(scene / "masks"), "--out", str(out), "--resolution", "32", "--max-faces", "2000",
            "--no-fusion", "--quiet", *extra]


@pytest.fixture(scope="module")
def good(scene, tmp_path_factory):
    """A finished OUT (exit 0) and its published files' hashes."""
    out = tmp_path_factory.mktemp("good") / "scan"
    assert main(_args(scene, out)) == 0
    return out, published_digests(out)


def _copy(good, tmp_path) -> Path:
    out = tmp_path / "scan"
    shutil.copytree(good[0], out)
    return out


def _cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "turntable", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


# --------------------------------------------------------------------------- the switch itself
def _stage(folder: OutputFolder, files: dict[str, str]) -> None:
    for name, text in files.items():
        p = folder.staging / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)


def _contents(out: Path) -> dict[str, str]:
    return {str(p.relative_to(out)): p.read_text() for p in sorted(out.rglob("*"))
            if p.is_file() and p.relative_to(out).parts[0] != ".turntable"}


OLD = {"model.glb": "old glb", "cameras.json": "old cams", "colmap/images.txt": "old colmap",
       "transforms.json": "old nerf"}
NEW = {"model.glb": "new glb", "cameras.json": "new cams", "summary.json": "new summary"}


def _publish(out: Path, files: dict[str, str]) -> None:
    with OutputFolder(out) as folder:
        _stage(folder, files)
        folder.publish()


def test_publish_replaces_the_whole_set_and_removes_what_the_new_run_does_not_write(tmp_path):
    out = tmp_path / "scan"
    _publish(out, OLD)
    (out / "my notes.txt").write_text("the user's")  # not ours: never touched
    _publish(out, NEW)
    assert _contents(out) == {**NEW, "my notes.txt": "the user's"}
    assert run_leftovers(out) == []
    assert json.loads((out / ".turntable" / "published.json").read_text())["files"] == sorted(NEW)


def test_an_output_folder_of_an_older_version_has_its_known_files_replaced(tmp_path):
    out = tmp_path / "scan"
    for name, text in {**OLD, "my notes.txt": "the user's"}.items():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(text)
    (out / ".recording.4242.rrd").write_text("orphan of a killed run")
    (out / ".model.glb.x1y2.tmp").write_text("orphan of an atomic write")
    _publish(out, NEW)
    assert _contents(out) == {**NEW, "my notes.txt": "the user's"}
    assert run_leftovers(out) == []


def test_leaving_without_publishing_changes_nothing(tmp_path):
    out = tmp_path / "scan"
    _publish(out, OLD)
    with pytest.raises(RuntimeError), OutputFolder(out) as folder:
        _stage(folder, NEW)
        raise RuntimeError("a stage failed")
    assert _contents(out) == OLD and run_leftovers(out) == []


class _Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs (no ``finally``, no ``__exit__``)."""


def _switch_steps(tmp_path) -> int:
    """How many renames one publish of NEW over OLD makes."""
    calls = []
    out = tmp_path / "count"
    _publish(out, OLD)
    real = os.replace
    with OutputFolder(out) as folder:
        _stage(folder, NEW)
        os.replace = lambda *a: (calls.append(a), real(*a))[1]
        try:
            folder.publish()
        finally:
            os.replace = real
    return len(calls)


def test_a_run_killed_at_any_step_of_the_switch_leaves_one_whole_set(tmp_path, monkeypatch):
    import turntable.outdir as outdir

    n = _switch_steps(tmp_path)
    assert n >= 6  # the manifest, the commit, old files aside, new files in, the record
    real = os.replace
    for k in range(n):
        out = tmp_path / f"scan{k}"
        _publish(out, OLD)
        folder = OutputFolder(out).__enter__()
        _stage(folder, NEW)
        calls = []

        def dying_replace(*a, k=k, calls=calls):
            if len(calls) == k:
                raise _Killed
            calls.append(a)
            return real(*a)

        monkeypatch.setattr(outdir.os, "replace", dying_replace)
        with pytest.raises(_Killed):
            folder.publish()
        monkeypatch.setattr(outdir.os, "replace", real)
        folder._lock.release()  # the kernel does this for a killed process
        with OutputFolder(out) as again:  # the next run: finishes or drops the killed one's switch
            pass
        assert _contents(out) in (OLD, NEW), (k, _contents(out))
        assert _contents(out) == (NEW if k >= 2 else OLD), k  # committed once the staging folder was renamed
        assert run_leftovers(out) == [], k
        assert again.cleaned, k  # the killed run's traces were found and cleared (and said so)


def test_a_second_run_into_the_same_out_is_refused_with_the_holder_s_pid(tmp_path):
    out = tmp_path / "scan"
    with OutputFolder(out), pytest.raises(UserError, match=rf"in use by pid {os.getpid()}"):
        OutputFolder(out).__enter__()
    with OutputFolder(out):  # released on leaving
        pass


def test_a_killed_holder_s_lock_and_staging_folder_do_not_outlive_it(tmp_path):
    out = tmp_path / "scan"
    code = ("import sys, time; from turntable.outdir import OutputFolder; f = OutputFolder(sys.argv[1]).__enter__(); "
            "(f.staging / 'model.glb').write_text('half'); print('held', flush=True); time.sleep(60)")
    p = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "held"
    with pytest.raises(UserError, match=rf"in use by pid {p.pid}"):
        OutputFolder(out).__enter__()
    p.kill()
    p.wait()
    assert list((out / ".turntable").glob("staging.*"))
    with OutputFolder(out) as folder:
        assert folder.cleaned
    assert run_leftovers(out) == [] and _contents(out) == {}


# --------------------------------------------------------------------------- whole runs
def test_a_failed_run_leaves_the_previous_output_as_it_was(good, tmp_path, capsys):
    out = _copy(good, tmp_path)
    blank = tmp_path / "blank"
    blank.mkdir()
    import cv2

    for i in range(4):
        cv2.imwrite(str(blank / f"f{i}.png"), np.full((240, 320, 3), 90 + i, np.uint8))
    code = main(["reconstruct", str(blank), "--r-outer", "80", "--r-inner", "50", "--out", str(out), "--quiet"])
    assert code == 2 and "no ring" in capsys.readouterr().err
    assert published_digests(out) == good[1] and run_leftovers(out) == []


def test_exports_a_re_run_does_not_ask_for_are_removed(scene, tmp_path):
    out = tmp_path / "scan"
    assert main(_args(scene, out, "--export-colmap", "--export-nerfstudio")) == 0
    assert (out / "colmap" / "images.txt").is_file() and (out / "transforms.json").is_file()
    assert main(_args(scene, out)) == 0
    assert not (out / "colmap").exists() and not (out / "transforms.json").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert sorted(Path(p).name for p in summary["files"].values()) == sorted(published_digests(out))


def test_a_concurrent_run_is_refused_and_changes_nothing(good, scene, tmp_path, capsys):
    out = _copy(good, tmp_path)
    with OutputFolder(out):  # another run holds OUT
        code = main(_args(scene, out, "--overwrite"))
    err = capsys.readouterr().err
    assert code == 2 and f"is in use by pid {os.getpid()}" in err and "Traceback" not in err
    assert published_digests(out) == good[1]


def _stop_mid_run(out: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Leave ``proc`` stopped (SIGSTOP) at a moment its staging folder exists: mid-run, whatever the load.

    Looking for the folder while the run goes on races its end on a busy machine (the run can publish
    between the look and the signal); a stopped run cannot.
    """
    t0 = time.monotonic()
    while True:
        proc.send_signal(signal.SIGSTOP)
        if list((out / ".turntable").glob(f"staging.{proc.pid}")):
            return
        proc.send_signal(signal.SIGCONT)
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout
        time.sleep(0.02)


def test_sigterm_ends_the_run_like_ctrl_c(good, scene, tmp_path):
    out = _copy(good, tmp_path)
    p = _cli(*_args(scene, out, "--overwrite"))
    _stop_mid_run(out, p)
    p.send_signal(signal.SIGTERM)  # pending until the run goes on
    p.send_signal(signal.SIGCONT)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 128 + signal.SIGTERM and "terminated" in err and "Traceback" not in err, err
    assert published_digests(out) == good[1] and run_leftovers(out) == []


@pytest.mark.parametrize("library", ["swallows", "makes_a_keyboard_interrupt"])
def test_a_sigterm_a_library_swallows_still_ends_the_run_and_publishes_nothing(good, scene, tmp_path, capsys,
                                                                               monkeypatch, library):
    """trimesh wraps small steps in ``except BaseException: pass``; a SIGTERM landing there must still count.

    Before the handler kept the signal, such a run went on, published and exited 0 (the SIGTERM test's rare
    failure under load, with --quiet's empty stderr). Ray's ``ray.wait`` instead raises a plain KeyboardInterrupt
    of its own for it (its signal check catches KeyboardInterrupt, which Terminated is): that run said
    "interrupted", exit 130 (the batch SIGTERM test under load).
    """
    import recon.meshing

    swallowed = []
    real = recon.meshing.mesh_from_hull

    def library_step(*a, **kw):
        try:  # what trimesh does around, e.g., keeping vertex normals
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(200):
                time.sleep(0.01)  # the handler runs here, in the main thread
        except BaseException as exc:
            swallowed.append(type(exc).__name__)
            if library == "makes_a_keyboard_interrupt":
                raise KeyboardInterrupt from None
        return real(*a, **kw)

    monkeypatch.setattr(recon.meshing, "mesh_from_hull", library_step)
    out = _copy(good, tmp_path)
    before = signal.signal(signal.SIGTERM, signal.SIG_DFL)  # as in a fresh process: main() installs its own
    try:
        code = main(_args(scene, out, "--overwrite"))
        after = signal.getsignal(signal.SIGTERM)
    finally:
        signal.signal(signal.SIGTERM, before)
    err = capsys.readouterr().err
    assert swallowed == ["Terminated"]
    assert code == 128 + signal.SIGTERM and "terminated (signal 15)" in err, err
    assert published_digests(out) == good[1] and run_leftovers(out) == []
    assert after == signal.SIG_DFL  # main() put back what it found
    monkeypatch.undo()
    assert main(_args(scene, out, "--overwrite")) == 0  # the next run starts with no signal remembered


@pytest.mark.parametrize("fraction", [0.15, 0.5, 0.85])
def test_sigkill_at_any_point_then_a_re_run_gives_the_same_model(good, scene, tmp_path, fraction):
    out = _copy(good, tmp_path)
    t0 = time.monotonic()
    ref = _cli(*_args(scene, tmp_path / "ref", "--overwrite"))
    ref.communicate(timeout=120)
    full = time.monotonic() - t0
    p = _cli(*_args(scene, out, "--overwrite"))
    time.sleep(fraction * full)
    p.kill()
    p.wait()
    before = published_digests(out)
    assert before == good[1] or model_digests(out) == model_digests(good[0])  # whole old set, or a finished new one
    assert main(_args(scene, out)) == 0
    assert model_digests(out) == model_digests(good[0]) and run_leftovers(out) == []


def test_a_full_disk_at_any_stage_fails_fast_naming_the_file_and_keeps_the_previous_output(good, scene):
    """Free space from none to just short of a whole run's files: each run fails within seconds.

    A tmpfs that is really full where this machine lets a test mount one, otherwise files limited in size
    (RLIMIT_FSIZE), which fail the same write calls (EFBIG instead of ENOSPC).
    """
    prefix = tmpfs_prefix()
    sizes = sorted(p.stat().st_size for p in good[0].rglob("*") if p.is_file() and ".turntable" not in p.parts)
    if prefix is None:
        budgets = [0, 1000, sizes[len(sizes) // 2], sizes[-1] - 1]  # per file
    else:
        # the whole disk: a disk with less room than half the last run's files is refused at once; with more,
        # the run fails at the write that fills it
        budgets = [0, 16 << 10, int(0.6 * sum(sizes)), int(0.9 * sum(sizes))]
    reports = []
    # every stage recomputed (cache files, then the outputs); and a new grid only (the hull's cache file first)
    for run_budgets, extra in ((budgets, ["--overwrite"]), ([0], ["--resolution", "40"])):
        r = subprocess.run([*(prefix or []), sys.executable, str(HERE / "disk_full.py"), str(good[0]),
                            json.dumps(run_budgets), "--", *_args(scene, Path("OUT"), *extra)],
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        reports.append(json.loads(r.stdout))
    assert reports[1]["results"][0]["stderr"][0].count(".turntable/hull.npz") == 1 or \
        reports[0]["mode"] == "tmpfs", reports[1]  # a full tmpfs is refused before the hull is carved
    if reports[0]["mode"] == "tmpfs":
        said = [r["stderr"][0] for r in reports[0]["results"]]
        assert all("a run writes at least" in s for s in said[:2]), said  # refused up front
        assert not any("a run writes at least" in s for s in said[2:]), said  # failed at a write
    report = {"mode": reports[0]["mode"], "results": reports[0]["results"] + reports[1]["results"]}
    assert report["mode"] == ("RLIMIT_FSIZE" if prefix is None else "tmpfs")
    for res in report["results"]:
        assert res["exit"] == 2, res
        why = "no space left" if report["mode"] == "tmpfs" else "file too large"
        assert why in res["stderr"][0] and "cannot write" in res["stderr"][0] and "was left as it was" in \
            res["stderr"][0], res
        assert res["seconds"] < 60, res  # a hang would be killed at 120 s; a normal run here takes ~5 s
        assert res["previous_intact"] and res["leftovers"] == [], res


def test_file_names_that_are_not_utf8_give_strict_json_and_a_summary(scene, tmp_path, capsys):
    """Bytes that are not UTF-8 in a file name become the text \\xNN in every JSON file and on screen."""
    images, masks = tmp_path / "images", tmp_path / "masks"
    images.mkdir()
    masks.mkdir()
    odd = os.fsdecode(b"frame_\xff03")  # a lone surrogate in Python's view of the name
    cams = json.loads((scene / "cameras_gt.json").read_text())
    for p in sorted((scene / "images").iterdir()):
        stem = odd if p.stem == "frame_003" else p.stem
        shutil.copy(p, images / f"{stem}{p.suffix}")
        shutil.copy(scene / "masks" / f"{p.stem}.png", masks / f"{stem}.png")
    for fr in cams["frames"]:
        if Path(fr["image"]).stem == "frame_003":
            fr["image"] = "frame_\\xff03.jpg"
    (tmp_path / "cams.json").write_text(json.dumps(cams))
    out = tmp_path / "scan"
    args = _args(scene, out, "--export-nerfstudio")
    for flag, value in (("--masks", masks), ("--cameras", tmp_path / "cams.json")):
        args[args.index(flag) + 1] = str(value)
    args[1] = str(images)
    args.remove("--quiet")
    assert main(args) == 0
    printed = capsys.readouterr().out
    for name in ("cameras.json", "summary.json", "transforms.json"):
        text = (out / name).read_bytes().decode("utf-8")  # strict UTF-8
        assert "\\ud" not in text.lower(), name  # no escaped lone surrogate
        json.loads(text)
    names = [fr["image"] for fr in json.loads((out / "cameras.json").read_text())["frames"]]
    assert "frame_\\xff03.jpg" in names and len(names) == 8
    assert "frames used     8" in printed


def test_greyscale_photos_are_recognised_and_each_view_s_silhouette_is_listed():
    from turntable.stages.silhouettes import Silhouettes, describe, is_greyscale

    rng = np.random.default_rng(0)
    grey = np.repeat(rng.integers(0, 255, (20, 30, 1), dtype=np.uint8), 3, axis=2)
    colour = grey.copy()
    colour[5:9, 5:9, 0] = 255 - colour[5:9, 5:9, 1]
    assert is_greyscale([grey, grey]) and not is_greyscale([grey, colour])
    masks = np.zeros((10, 20, 30), bool)
    masks[0, :10] = True
    said = describe([f"f{i}.jpg" for i in range(10)], Silhouettes(masks, masks, ["ok"] * 10))
    assert said.startswith("silhouettes (share of the image, verdict): f0.jpg 50.0 % ok, f1.jpg 0.0 % ok")
    assert said.endswith("and 2 more")
