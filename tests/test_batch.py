"""`turntable batch` on Ray: four small rendered objects, one broken on purpose.

Each job is an 8-frame 320x240 sequence with its true cameras and masks, carved at
32^3 without fusion (a few seconds). One batch run is shared by most tests: it runs
on a simulated two-node cluster (``ray.cluster_utils.Cluster``, one core a node,
joined through --address), so the jobs must spread over both nodes; while it runs,
the test kills the worker of one object with SIGKILL, and Ray's retry must still
finish it. A second run, on a local Ray started by the command (the default), lists
the same jobs in a manifest with --resume: it redoes only what changed (the
manifest's jobs are the same jobs as ROOT's). Then a batch interrupted by SIGINT (a
subprocess, as Ctrl-C reaches it), and manifests with bad rows (exit 2 before any
job runs).
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from turntable.batch import THUMB_PX, read_manifest, read_settings, render_thumbnail
from turntable.cli import main
from turntable.cli.batch import settings_types
from turntable.errors import UserError
from turntable.synth import SynthOptions, make_sequence

JOB_FLAGS = ["--cameras", "cameras_gt.json", "--masks", "masks", "--resolution", "32", "--no-fusion", "--no-texture"]
KILL_AFTER_S = 0.05  # into the job: the marker is written before the reconstruction, which takes 0.3 s or more
# (at 0.5 s a quick job on a quiet machine had sometimes already finished, and another job's worker was killed)


def _render(folder: Path, obj: str, seed: int) -> None:
    make_sequence(folder, SynthOptions(object=obj, frames=8, step_deg=45.0, width=320, height=240, focal_px=375.0,
                                       supersample=1, seed=seed))


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    base = tmp_path_factory.mktemp("batch")
    src = base / "src"
    _render(src / "vase", "vase", 1)
    _render(src / "cup", "cup", 2)
    root = base / "root"
    shutil.copytree(src / "vase", root / "a")
    shutil.copytree(src / "cup", root / "b")
    (root / "b" / "turntable.toml").write_text("resolution = 48  # a longer job: the test kills it mid-way\n")
    shutil.copytree(src / "vase", root / "c")
    (root / "c" / "turntable.toml").write_text("resolution = 40  # this object's own setting\n")
    broken = root / "d"  # two frames: too few to reconstruct
    shutil.copytree(src / "vase", broken)
    for p in sorted((broken / "images").iterdir())[2:]:
        p.unlink()
    return root


def _kill_first_attempt(marker: Path, killed: list, stop: threading.Event) -> None:
    """SIGKILL the worker that runs ``marker``'s job, once, mid-job (a worker lost as a node or OOM loses it).

    Watches until the batch returns (``stop``), not for a fixed time: on a loaded machine the first workers
    can take a minute to start."""
    while not stop.is_set():
        try:
            line = marker.read_text().split()
        except OSError:
            line = []
        if line:
            time.sleep(KILL_AFTER_S)
            os.kill(int(line[0]), signal.SIGKILL)
            killed.append(int(line[0]))
            return
        time.sleep(0.05)


@pytest.fixture(scope="module")
def first(root, tmp_path_factory):
    from ray.cluster_utils import Cluster

    out = tmp_path_factory.mktemp("out") / "batch"
    killed: list[int] = []
    stop = threading.Event()
    killer = threading.Thread(target=_kill_first_attempt, args=(out / ".batch" / "b.running", killed, stop),
                              daemon=True)
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        killer.start()
        code = main(["batch", str(root), "--out", str(out), *JOB_FLAGS, "--retries", "1", "--address",
                     cluster.address, "-q"])
        stop.set()
        killer.join(timeout=5)
    finally:
        cluster.shutdown()
    rows = {r["object"]: r for r in json.loads((out / "batch.json").read_text())["rows"]}
    return code, out, rows, killed


def test_statuses_and_exit_code(first):
    code, out, rows, _ = first
    assert code == 1  # d failed
    assert {k: r["status"] for k, r in rows.items()} == {"a": "ok", "b": "ok", "c": "ok", "d": "failed"}
    assert "only 2 frame(s) could be calibrated" in rows["d"]["reason"]
    assert rows["d"]["attempts"] == 1  # bad input is not retried
    for k in "abc":
        assert (out / k / "model.glb").is_file() and (out / k / "summary.json").is_file()
    assert not (out / "d").exists() or not (out / "d" / "model.glb").exists()
    assert not list((out / ".batch").glob("*.running"))


def test_killed_worker_is_retried(first):
    _, _, rows, killed = first
    assert len(killed) == 1, "the test never saw b's job start"
    assert rows["b"]["status"] == "ok"
    assert rows["b"]["attempts"] == 2  # the killed attempt and the retry


def test_object_settings_override_the_command_line(first, tmp_path):
    _, out, rows, _ = first
    assert rows["c"]["mesh_faces"] != rows["a"]["mesh_faces"]  # same photos, its resolution 40 not 32
    (tmp_path / "turntable.toml").write_text("colour = 1\n")
    with pytest.raises(UserError, match="turntable.toml.*unknown setting 'colour'"):
        read_settings(tmp_path, settings_types())
    (tmp_path / "turntable.toml").write_text("resolution = '64'\n")
    with pytest.raises(UserError, match="expected int"):
        read_settings(tmp_path, settings_types())
    (tmp_path / "turntable.toml").write_text("r-outer = 80\nfusion = false\nmasks = 'm'\nwork_size = 1600\n")
    assert read_settings(tmp_path, settings_types()) == {"r_outer": 80, "no_fusion": True, "masks": str(tmp_path / "m"),
                                                         "work_size": "1600"}


def test_report_files(first):
    _, out, rows, _ = first
    doc = json.loads((out / "batch.json").read_text())
    assert doc["counts"]["ok"] == 3 and doc["counts"]["failed"] == 1
    with open(out / "batch.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [r["object"] for r in table] == ["a", "b", "c", "d"]
    a = next(r for r in table if r["object"] == "a")
    assert int(a["frames_used"]) == 8 and float(a["focal_px"]) == pytest.approx(375.0)
    assert int(a["mesh_faces"]) > 100 and float(a["volume_cm3"]) > 0 and float(a["time_total_s"]) > 0
    page = (out / "index.html").read_text()
    for k in "abcd":
        assert f"<h2>{k}</h2>" in page
    assert "no model" in page and "only 2 frame(s)" in page
    for k in "abc":
        img = cv2.imread(str(out / rows[k]["thumbnail"]))
        assert img.shape == (THUMB_PX, THUMB_PX, 3)
        assert (np.abs(img.astype(int) - 245).sum(2) > 30).mean() > 0.05  # the object covers part of the picture


def test_thumbnail_shows_the_texture(tmp_path):
    """A textured model's thumbnail is its texture (as the GLB shows it), not the PLY's vertex colours: a
    standing square, grey vertex colours, a texture red on its top half and blue below."""
    import trimesh

    from recon.export import glb_bytes, png_bytes

    V = np.array([[-40.0, 0, 0], [40, 0, 0], [40, 80, 0], [-40, 80, 0]]) / 1000  # metres, +Y up, facing +Z
    F = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.0, 1], [1, 1], [1, 0], [0, 0]])  # glTF: v down from the texture's top row
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[:32] = (220, 30, 30)
    tex[32:] = (30, 30, 220)
    (tmp_path / "model.glb").write_bytes(glb_bytes(V, F, np.tile([0.0, 0, 1], (4, 1)), texcoords=uv,
                                                   texture_png=png_bytes(tex)))
    (tmp_path / "model_albedo.png").write_bytes(png_bytes(tex))
    trimesh.Trimesh(V, F, vertex_colors=np.full((4, 3), 128, np.uint8), process=False).export(tmp_path / "model.ply")
    img = render_thumbnail(tmp_path).astype(int)
    red = (img[..., 0] > 120) & (img[..., 2] < 80)
    blue = (img[..., 2] > 120) & (img[..., 0] < 80)
    assert red.sum() > 500 and blue.sum() > 500, (red.sum(), blue.sum())
    assert np.nonzero(red)[0].mean() < np.nonzero(blue)[0].mean()  # red above blue: the picture upright
    (tmp_path / "model_albedo.png").unlink()  # not textured: the vertex colours
    img = render_thumbnail(tmp_path).astype(int)
    obj = np.abs(img - 245).sum(2) > 30
    assert obj.mean() > 0.05 and np.ptp(img[obj], axis=1).max() < 8  # grey, shaded


def test_batch_output_equals_a_separate_run(first, root, tmp_path):
    _, out, _, _ = first
    sep = tmp_path / "a"
    obj = root / "a"
    assert main(["reconstruct", str(obj / "images"), "--cameras", str(obj / "cameras_gt.json"), "--masks",
                 str(obj / "masks"), "--resolution", "32", "--no-fusion", "--no-texture", "--out", str(sep), "-q"]) == 0
    compared = [p.name for p in sep.iterdir() if p.is_file() and p.name not in ("summary.json", "recording.rrd")]
    assert {"model.ply", "model.glb", "cameras.json"} <= set(compared)  # and whatever else reconstruct writes
    for name in compared:
        assert (sep / name).read_bytes() == (out / "a" / name).read_bytes(), name


def test_resume_from_a_manifest_redoes_only_what_changed(first, root):
    _, out, _, _ = first
    before = {k: (out / k / "model.glb").stat().st_mtime_ns for k in "abc"}
    img = sorted((root / "a" / "images").iterdir())[0]
    os.utime(img, ns=(img.stat().st_atime_ns, img.stat().st_mtime_ns + 10**9))  # a's input changed
    # the same jobs as ROOT's, listed: c's own turntable.toml still applies; d named by default
    manifest = root.parent / "jobs.csv"
    manifest.write_text("name,input,resolution\na,root/a,\nb,root/b,48\nc,root/c,\n,root/d,\n")
    code = main(["batch", "--manifest", str(manifest), "--out", str(out), *JOB_FLAGS, "--resume", "-q"])
    assert code == 1  # d still fails
    rows = {r["object"]: r for r in json.loads((out / "batch.json").read_text())["rows"]}
    assert list(rows) == ["a", "b", "c", "d"]
    assert [k for k, r in rows.items() if r["resumed"]] == ["b", "c"]  # same options and inputs as ROOT's jobs
    assert (out / "b" / "model.glb").stat().st_mtime_ns == before["b"]
    assert (out / "c" / "model.glb").stat().st_mtime_ns == before["c"]
    assert (out / "a" / "model.glb").stat().st_mtime_ns != before["a"] and rows["a"]["status"] == "ok"
    assert rows["a"]["node"] not in {r["node"] for r in first[2].values()}  # a Ray of its own: not the cluster's


def _bad(tmp_path, manifest: str, text: str, capsys) -> str:
    (tmp_path / manifest).write_text(text)
    out = tmp_path / "out"
    assert main(["batch", "--manifest", str(tmp_path / manifest), "--out", str(out), *JOB_FLAGS]) == 2
    assert not out.exists()  # nothing ran, nothing written
    return capsys.readouterr().err


def test_manifest_rows_checked_before_any_job(root, tmp_path, capsys):
    for k in "ab":
        shutil.copytree(root / k, tmp_path / "objs" / k)
    csv_text = "name,input,r-outer,fusion\nvase,objs/a,80,false\ncup,objs/b,,\n"
    (tmp_path / "jobs.csv").write_text(csv_text)
    entries = read_manifest(tmp_path / "jobs.csv", settings_types())
    assert [(e.name, e.path, e.settings) for e in entries] == [
        ("vase", tmp_path / "objs" / "a", {"r_outer": 80, "no_fusion": True}), ("cup", tmp_path / "objs" / "b", {})]
    (tmp_path / "jobs.toml").write_text('[[jobs]]\nname = "vase"\ninput = "objs/a"\nr-outer = 80\nfusion = false\n'
                                        '[[jobs]]\nname = "cup"\ninput = "objs/b"\n')
    (tmp_path / "jobs.json").write_text('{"jobs": [{"name": "vase", "input": "objs/a", "r_outer": 80, '
                                        '"no-fusion": true}, {"name": "cup", "input": "objs/b"}]}')
    for f in ("jobs.toml", "jobs.json"):
        assert read_manifest(tmp_path / f, settings_types()) == [
            e.__class__(name=e.name, path=e.path, settings=e.settings, where=e.where.replace(
                f"jobs.csv: line {i + 2}", f"{f}: job {i + 1}")) for i, e in enumerate(entries)]
    head = "name,input,resolution\n"
    err = _bad(tmp_path, "m.csv", head + "a,objs/a,32\nb,objs/b,sixty\n", capsys)
    assert "m.csv: line 3 (b): resolution = 'sixty': expected int" in err
    err = _bad(tmp_path, "m.csv", head + "a,objs/a,32\nb,objs/b,8\n", capsys)  # reconstruct's own checks
    assert "m.csv: line 3 (b): --resolution must be between 16 and 1024, got 8" in err
    err = _bad(tmp_path, "m.csv", head + "a,objs/a,\nA,objs/b,\n", capsys)
    assert "m.csv: line 3 (A): name 'A' already used by line 2" in err
    err = _bad(tmp_path, "m.csv", head + "a,objs/missing,\n", capsys)
    assert "m.csv: line 2: input 'objs/missing'" in err and "not found" in err
    err = _bad(tmp_path, "m.csv", "name,input,colour\na,objs/a,red\n", capsys)
    assert "m.csv: line 2 (a): unknown setting 'colour'" in err
    err = _bad(tmp_path, "m.toml", '[[jobs]]\nname = "thumbnails"\ninput = "objs/a"\n', capsys)
    assert "m.toml: job 1: name 'thumbnails'" in err
    err = _bad(tmp_path, "m.json", '{"jobs": [{"name": "a", "input": "objs/a", "masks": 3}]}', capsys)
    assert "m.json: job 1 (a): masks = 3: expected str" in err
    assert main(["batch", str(root), "--manifest", str(tmp_path / "jobs.csv"), "--out", str(tmp_path / "o")]) == 2


def test_bad_arguments_exit_2(root, tmp_path):
    assert main(["batch", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert main(["batch", str(root), "--out", str(tmp_path / "o"), "--retries", "-1"]) == 2
    assert main(["batch", str(root), "--out", str(tmp_path / "o"), *JOB_FLAGS[:4], "--resolution", "5"]) == 2


def test_jobs_spread_over_two_nodes(first):
    _, _, rows, _ = first
    assert len({r["node"] for r in rows.values()}) == 2, [r["node"] for r in rows.values()]


def _ray_cpus() -> int:
    """The cores a local Ray gives itself here (cgroup quotas and affinity counted): a job asking more never runs."""
    try:
        from ray._private.utils import get_num_cpus

        return max(1, int(get_num_cpus()))
    except (ImportError, AttributeError):  # a Ray that moved it
        return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


@pytest.mark.parametrize("sig, code, said", [(signal.SIGINT, 130, "interrupted"),
                                             (signal.SIGTERM, 143, "terminated (signal 15)")])
def test_ctrl_c_or_sigterm_stops_cleanly_and_keeps_what_finished(root, tmp_path, sig, code, said):
    """Ctrl-C, or SIGTERM (ray.init puts in its own SIGTERM handler, ``sys.exit(15)``: exit 15, no message; the
    CLI's is put back after it)."""
    import subprocess
    import sys

    small = tmp_path / "root"
    for k in "abc":
        shutil.copytree(root / k, small / k)
    out = tmp_path / "out"
    # one job at a time (each takes every core): when the first has finished, one runs and one waits. With a
    # job per core an idle machine finished the other two (0.4-3 s each) before SIGINT landed: exit 0
    cmd = [sys.executable, "-m", "turntable", "batch", str(small), "--out", str(out), *JOB_FLAGS,
           "--cpus-per-job", str(_ray_cpus())]
    # Ctrl-C's default action in the child even when this run was started in the background of a script
    # (a non-interactive shell starts `cmd &` with SIGINT ignored, and a child inherits that)
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    first_line = proc.stderr.readline()
    while first_line and not first_line.startswith("[1/"):  # Ray's own lines first
        first_line = proc.stderr.readline()
    proc.send_signal(sig)  # one object finished, the others running or waiting
    err = proc.stderr.read()
    assert proc.wait(timeout=60) == code, err
    assert said in err and "Traceback" not in err, err
    doc = json.loads((out / "batch.json").read_text())
    done = [r["object"] for r in doc["rows"] if r["status"] == "ok"]
    assert doc["interrupted"] and len(done) >= 1
    assert any(r["status"] == "not_run" for r in doc["rows"])
    # what a re-run with --resume reads: a record for each finished object, none for the others
    assert sorted(p.stem for p in (out / ".batch").glob("*.json")) == sorted(done)
    assert not list((out / ".batch").glob("*.running"))
