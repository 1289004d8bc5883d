"""benchmarks/viewer_check.py (with viewer_glb.py, viewer_usd.py): a reconstruction's GLB in three.js (headless
Chromium) and its USDZ in usd-core.

The reconstruction is a small synthetic one (a vase with the synthetic
renderer's procedural texture, 8 frames 320x240, true cameras and masks,
``--resolution 32 --no-fusion --texture-size 256``), drawn from two azimuths
at 480x360. The GLB checks must pass on it and fail on each broken copy
(upside down, texture removed, texture black, out of frame, texture flipped on
the surface: only the comparison with model.ply's photo colours can see that);
the USDZ checks must pass on it and fail on a copy with Z up in centimetres,
one whose diffuseColor reads no texture, one with a prim type AR Quick Look
does not draw, one wound inside out and one whose st is not the GLB's
(u, 1 - v). The GLB part skips without Chromium or three.js
(``benchmarks/viewer_check.py --install-three`` installs it with npm into
~/.cache/turntable-viewer; nothing in ``make test`` needs npm); the USDZ
part skips without usd-core.
"""

import shutil
import sys
import zipfile
from pathlib import Path

import pytest

from turntable.cli import main

ROOT = Path(__file__).resolve().parents[1]
# the scripts' folder, as when viewer_check.py runs as a script: it and its siblings import each other by name;
# appended, not first: benchmarks/ holds names as plain as texture.py and batch.py
sys.path.append(str(ROOT / "benchmarks"))
import viewer_check as vc  # noqa: E402
import viewer_glb as vg  # noqa: E402
import viewer_usd as vu  # noqa: E402


@pytest.fixture(scope="module")
def recon(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("viewer_check")
    seq, out = work / "S", work / "R"
    assert main(["synth", str(seq), "--object", "vase", "--frames", "8", "--size", "320x240", "--focal-px", "380",
                 "--elevation-deg", "35", "--distance-mm", "430", "--supersample", "1"]) == 0
    assert main(["reconstruct", str(seq / "images"), "--cameras", str(seq / "cameras_gt.json"), "--masks",
                 str(seq / "masks"), "--resolution", "32", "--no-fusion", "--texture-size", "256", "--out", str(out),
                 "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")  # module scope, as recon's, so that it is set up (and skips) first
def three() -> Path:
    """three.js's folder; skips (before the reconstruction is made) without it or Chromium."""
    if not Path(vc.CHROMIUM).exists():
        pytest.skip(f"{vc.CHROMIUM} not found (apt-get install chromium)")
    three = vc.find_three()
    if three is None:
        why = "node/npm not installed" if shutil.which("npm") is None else \
            "run benchmarks/viewer_check.py --install-three (npm) or set TURNTABLE_THREE"
        pytest.skip(f"three.js not found: {why}")
    return three


def _failed(rows, model: str) -> set[str]:
    return {r.check for r in rows if r.model == model and r.ok is False}


def test_glb_passes_in_three_js_and_broken_copies_fail(three, recon, tmp_path):
    glb = (recon / "model.glb").read_bytes()
    models = {"model": glb, **vg.negative_models(glb)}
    reference = vg.photo_reference(recon / "model.glb")
    assert reference is not None and reference.path.name == "model.ply"
    rows = vc.check_models(models, three, screenshots=tmp_path, azimuths=(0, 180), reference=reference,
                           window=(480, 360))
    vc.print_table(rows)
    ok = {r.check for r in rows if r.model == "model" and r.ok}
    assert _failed(rows, "model") == set()
    assert {"loads", "textured", "on table", "in frame", "lit", "shading varies", "colour", "texture detail",
            "photo colours", "upright"} <= ok  # the procedural texture varies: the correlations are measured
    assert {"upright", "on table"} <= _failed(rows, "upside_down")
    assert "textured" in _failed(rows, "no_texture")
    assert "lit" in _failed(rows, "black_texture")
    assert "in frame" in _failed(rows, "out_of_frame")
    assert _failed(rows, "flipped_v") == {"photo colours"}  # consistent with its own UVs, not with the photos
    assert sorted(p.name for p in tmp_path.glob("model_az*.png")) == ["model_az000.png", "model_az180.png"]


def _repackaged(usdz: Path, work: Path, edit) -> Path:
    """A copy of the USDZ whose layer ``edit(stage)`` changed, packaged again with usd-core."""
    from pxr import Sdf, Usd, UsdUtils

    work.mkdir()
    with zipfile.ZipFile(usdz) as z:
        z.extractall(work)
        layer = work / z.namelist()[0]
    stage = Usd.Stage.Open(str(layer))
    edit(stage)
    stage.GetRootLayer().Save()
    out = work / "broken.usdz"
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(layer)), str(out))
    return out


def test_usdz_checks_pass_and_broken_copies_fail(recon, tmp_path):
    pytest.importorskip("pxr", reason="usd-core not installed (pip install usd-core, the extra turntable[usd])")
    from pxr import UsdGeom, UsdShade

    glb = (recon / "model.glb").read_bytes()
    rows = vu.usdz_rows("usdz", recon / "model.usdz", glb)
    assert [r.check for r in rows if not r.ok] == []
    assert {"usd validators", "ARKit rules", "up axis", "metres per unit", "texture binding", "surface",
            "bounds"} <= {r.check for r in rows}
    assert "st vs (u, 1 - v)" in next(r.value for r in rows if r.check == "surface")  # compared, not skipped

    def z_up_cm(stage):
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, 0.01)

    def no_texture(stage):
        surface = next(UsdShade.Shader(p) for p in stage.Traverse()
                       if p.GetTypeName() == "Shader" and UsdShade.Shader(p).GetIdAttr().Get() == "UsdPreviewSurface")
        surface.GetInput("diffuseColor").DisconnectSource()

    def failed(edit, folder: str) -> set[str]:
        rows = vu.usdz_rows(folder, _repackaged(recon / "model.usdz", tmp_path / folder, edit), glb)
        return {r.check for r in rows if r.ok is False}

    def curves(stage):  # a prim type AR Quick Look does not draw
        UsdGeom.BasisCurves.Define(stage, "/model/hair")

    def inside_out(stage):
        mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
        mesh.GetOrientationAttr().Set(UsdGeom.Tokens.leftHanded)

    def t_not_flipped(stage):  # st = (u, v): the texture upside down on the surface in USD
        mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
        st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
        st.Set([(s, 1.0 - t) for s, t in st.Get()])

    assert {"up axis", "metres per unit"} <= failed(z_up_cm, "z")
    assert failed(no_texture, "t") == {"texture binding"}
    assert failed(curves, "c") == {"ARKit rules"}
    assert failed(inside_out, "o") == {"surface"}
    assert failed(t_not_flipped, "f") == {"surface"}


def test_bad_input_is_a_clear_error(tmp_path, capsys):
    assert vc.main([str(tmp_path / "missing")]) == 2
    assert "no such file or folder" in capsys.readouterr().err
    (tmp_path / "model.glb").write_bytes(b"not a glb at all")
    assert vc.main([str(tmp_path)]) == 2
    assert "not a binary glTF" in capsys.readouterr().err
    (tmp_path / "model.glb").write_bytes(vg.write_glb({"asset": {"version": "2.0"}}, b""))  # a GLB without a mesh
    assert vc.main([str(tmp_path)]) == 2
    assert "no mesh with POSITION" in capsys.readouterr().err
    (tmp_path / "model.txt").write_text("hello")
    assert vc.main([str(tmp_path / "model.txt")]) == 2
    assert "expected a .glb, a .usdz or a reconstruction folder" in capsys.readouterr().err
