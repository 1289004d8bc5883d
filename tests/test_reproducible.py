"""Two clean runs of `turntable reconstruct` on the same photos give the same bytes.

A small rendered sequence is reconstructed twice into two fresh output folders
(nothing cached), with the default fusion and texture; every file but the
summary and the recording must be byte-identical and the automatic silhouettes
(the stage cache's masks and unknown pixels) equal. The first run cuts the
silhouettes on four worker threads, the second on one and with ``--threads 1``
(OpenCV, BLAS and OpenMP on one thread, as a `turntable batch` job with
``--cpus-per-job 1`` runs): a result that depends on which thread handled which
frame (OpenCV's random number generator is one per thread, and GrabCut starts
its colour models from it) or on how many threads a library used then shows
even when both runs would schedule their threads alike, and on a one-core
machine.

Found this way (2026-12-02): OpenCV's precise distance transform, which the
hull's silhouette distances use, takes IPP's code on one thread and its own on
more; they agree to an ulp, not to the bit, and the hull, the fused mesh and
the texture followed (benchmarks/batch.py: a batch job on one core against a
separate run on two). ``recon.carving.silhouette_sdf_px`` now snaps them to
``sqrt`` of their integer square; ``test_silhouette_distances_ignore_opencv_threads``
checks that function alone.
"""

from __future__ import annotations

import os
from contextlib import contextmanager

import cv2
import numpy as np
import pytest

from turntable.cli import _THREAD_VARS, main
from turntable.synth import SynthOptions, make_sequence

SKIP = ("summary.json", "recording.rrd")  # times; the recording's own timestamps


@contextmanager
def _opencv_threads(n: int):
    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def _sdf_thread_dependent() -> bool:
    """Whether the hull's silhouette distances still differ between one OpenCV thread and two."""
    from recon.carving import silhouette_sdf_px

    v, u = np.mgrid[:360, :480]
    mask = ((u - 230) / 150.0) ** 2 + ((v - 190) / 120.0) ** 2 < 1.0  # a crop of 2^14 pixels or more
    mask[150:230, 300:330] = False  # and a notch: distances of every direction
    with _opencv_threads(1):
        one = silhouette_sdf_px(mask)
    with _opencv_threads(2):
        two = silhouette_sdf_px(mask)
    return not np.array_equal(one, two)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    opts = SynthOptions(object="vase", frames=12, step_deg=30.0, width=480, height=360, focal_px=570.0,
                        elevation_deg=35.0, distance_mm=430.0, noise=1.5, jpeg=95, backdrop="dark", seed=3,
                        supersample=2)
    make_sequence(root / "seq", opts)
    return root / "seq"


def _reconstruct(scene, out) -> None:
    code = main(["reconstruct", str(scene / "images"), "--r-outer", "80", "--r-inner", "50", "--stroke", "3",
                 "--out", str(out), "--resolution", "48", "--max-faces", "20000", "--quiet"])
    assert code == 0


def _reconstruct_one_thread(scene, out, monkeypatch) -> None:
    """``turntable --threads 1 reconstruct``, in this process: the thread settings put back afterwards."""
    for var in _THREAD_VARS:
        monkeypatch.setenv(var, os.environ.get(var, ""))  # undone by monkeypatch: --threads sets them
    with _opencv_threads(cv2.getNumThreads()):
        code = main(["--threads", "1", "reconstruct", str(scene / "images"), "--r-outer", "80", "--r-inner", "50",
                     "--stroke", "3", "--out", str(out), "--resolution", "48", "--max-faces", "20000", "--quiet"])
    assert code == 0


@pytest.mark.skipif(not cv2.ipp.useIPP(), reason="OpenCV without IPP: one code path at any thread count")
def test_silhouette_distances_ignore_opencv_threads():
    assert not _sdf_thread_dependent()


def test_two_clean_runs_give_identical_files(scene, tmp_path, monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 4)  # the silhouette stage runs one thread per core
    _reconstruct(scene, tmp_path / "a")
    monkeypatch.setattr(os, "cpu_count", lambda: 1)
    _reconstruct_one_thread(scene, tmp_path / "b", monkeypatch)
    monkeypatch.undo()
    with np.load(tmp_path / "a" / ".turntable" / "silhouettes.npz") as sa, \
            np.load(tmp_path / "b" / ".turntable" / "silhouettes.npz") as sb:
        for field in ("masks", "unknown"):
            differ = (sa[field] != sb[field]).reshape(len(sa[field]), -1).sum(axis=1)
            assert not differ.any(), f"{field}: pixels differing per frame {differ.tolist()}"
    files = {p.name for p in (tmp_path / "a").iterdir() if p.is_file() and p.name not in SKIP}
    assert {"model.ply", "model.glb", "model_albedo.png", "points.ply", "cameras.json"} <= files  # fusion, texture
    assert files == {p.name for p in (tmp_path / "b").iterdir() if p.is_file() and p.name not in SKIP}
    differ = sorted(n for n in files if (tmp_path / "a" / n).read_bytes() != (tmp_path / "b" / n).read_bytes())
    assert not differ, f"{', '.join(differ)} differ between the two runs"
