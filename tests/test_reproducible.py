"""Two clean runs of `turntable reconstruct` on the same photos give the same bytes.

A small rendered sequence is reconstructed twice into two fresh output folders
(nothing cached); the model files and cameras.json must be byte-identical and
the automatic silhouettes (the stage cache's masks and unknown pixels) equal.
The first run cuts the silhouettes on four worker threads, the second on one:
a result that depends on which thread handled which frame (OpenCV's random
number generator is one per thread, and GrabCut starts its colour models
from it) then shows even when both runs would schedule their threads alike,
and on a one-core machine.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from turntable.cli import main
from turntable.synth import SynthOptions, make_sequence

MODEL_FILES = ("model.ply", "model.glb", "model.obj", "cameras.json")


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


def test_two_clean_runs_give_identical_files(scene, tmp_path, monkeypatch):
    for name, cores in (("a", 4), ("b", 1)):  # the silhouette stage runs one thread per core
        monkeypatch.setattr(os, "cpu_count", lambda cores=cores: cores)
        _reconstruct(scene, tmp_path / name)
    monkeypatch.undo()
    with np.load(tmp_path / "a" / ".turntable" / "silhouettes.npz") as sa, \
            np.load(tmp_path / "b" / ".turntable" / "silhouettes.npz") as sb:
        for field in ("masks", "unknown"):
            differ = (sa[field] != sb[field]).reshape(len(sa[field]), -1).sum(axis=1)
            assert not differ.any(), f"{field}: pixels differing per frame {differ.tolist()}"
    for name in MODEL_FILES:
        a, b = (tmp_path / "a" / name).read_bytes(), (tmp_path / "b" / name).read_bytes()
        assert a == b, f"{name} differs between the two runs"
