"""The USDZ side of benchmarks/viewer_check.py: usdchecker --arkit, usd-core's validators, the ARKit rules.

``usdz_rows`` checks a model.usdz with usd-core (and, given the GLB of the
same reconstruction, its texture, UVs and bounds against the GLB's); what it
checks is described in ``benchmarks/viewer_check.py``'s docstring.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2
import numpy as np
from viewer_glb import Albedo, Row, accessor, glb_albedo, read_glb

ARKIT_PRIM_TYPES = {"", "Scope", "Xform", "Camera", "Shader", "Material", "Mesh", "Sphere", "Cube", "Cylinder",
                    "Cone", "Capsule", "GeomSubset", "Points", "SkelRoot", "Skeleton", "SkelAnimation",
                    "BlendShape", "SpatialAudio"}
ARKIT_SHADER_IDS = {"UsdPreviewSurface", "UsdUVTexture", "UsdTransform2d"} | {
    f"UsdPrimvarReader_{t}" for t in ("float", "float2", "float3", "float4", "int", "string", "normal", "point",
                                      "vector", "matrix")}
ARKIT_EXTENSIONS = {"usdc", "usd", "usda", "png", "jpg", "jpeg", "m4a", "mp3", "wav"}


#: What ``usdchecker --arkit`` runs (USD <= 25.x: UsdUtils.ComplianceChecker), for an interpreter whose usd-core has it.
_LEGACY_USDCHECKER = """
import json, sys
from pxr import Sdr, Tf, UsdUtils
if not hasattr(UsdUtils, "ComplianceChecker"):
    print(json.dumps(None)); sys.exit()
missing = []
for sid in ("UsdPreviewSurface", "UsdUVTexture", "UsdPrimvarReader_float2"):
    try:  # usd-core wheels lack the usdShaders plugin: no Sdr definitions of the preview shaders
        node = Sdr.Registry().GetShaderNodeByIdentifier(sid)
    except Tf.ErrorException:
        node = None
    if node is None:
        missing.append(sid)
c = UsdUtils.ComplianceChecker(arkit=True, skipARKitRootLayerCheck=False, rootPackageOnly=False, skipVariants=False,
                               verbose=False)
c.CheckCompliance(sys.argv[1])
from pxr import Usd
print(json.dumps({"version": ".".join(map(str, Usd.GetVersion()[1:])), "errors": c.GetErrors(),
                  "failed": c.GetFailedChecks(), "warnings": c.GetWarnings(), "rules": len(c._rules),
                  "no_definition": missing}))
"""


def legacy_usdchecker_row(name: str, usdz: Path, python: str) -> Row | None:
    """``usdchecker --arkit``'s checks (ComplianceChecker, arkit=True) run by ``python``; None if it has none.

    A failure of ShaderPropertyTypeConformanceChecker ("has invalid shader node") for a shader whose
    Sdr definition that usd-core lacks is the wheel's gap, not the asset's: it is listed, not counted.
    """
    r = subprocess.run([python, "-c", _LEGACY_USDCHECKER, str(usdz)], capture_output=True, text=True, timeout=300)
    try:
        out = json.loads(r.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        return Row(name, "usdchecker --arkit", f"{python} failed: {r.stderr.strip()[-160:]}", False)
    if out is None:
        return None
    excused = [f for f in out["failed"] if "invalid shader node" in f and "ShaderPropertyTypeConformance" in f
               and out["no_definition"]]
    real = [f for f in out["failed"] if f not in excused] + out["errors"]
    value = (f"ComplianceChecker(arkit=True) of usd-core {out['version']}: {out['rules']} rules, "
             f"{len(out['errors'])} errors, {len(out['failed'])} failed checks, {len(out['warnings'])} warnings")
    if excused:
        value += (f"; {len(excused)} 'invalid shader node' not counted: that usd-core has no Sdr definition of "
                  f"{', '.join(out['no_definition'])}")
    if real:
        value += "; " + "; ".join(real)[:200]
    return Row(name, "usdchecker --arkit", value, not real)


def usdchecker_rows(name: str, usdz: Path, legacy_python: str | None = None) -> list[Row]:
    """usdchecker --arkit where it exists; usd-core's validators and the ARKit profile's rules always."""
    exe = shutil.which("usdchecker") or shutil.which("usdchecker", path=str(Path(sys.executable).parent))
    rows = []
    if exe:
        r = subprocess.run([exe, "--arkit", str(usdz)], capture_output=True, text=True, timeout=120)
        text = (r.stdout + r.stderr).strip().splitlines()
        rows.append(Row(name, "usdchecker --arkit", f"exit {r.returncode}: {(text[-1] if text else '')[:120]}",
                        r.returncode == 0))
    else:
        row = legacy_usdchecker_row(name, usdz, legacy_python or sys.executable)
        if row is not None:
            rows.append(row)
    from pxr import Usd, UsdValidation

    stage = Usd.Stage.Open(str(usdz))
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = [e for e in UsdValidation.ValidationContext(validators).Validate(stage)
              if e.GetType() == UsdValidation.ValidationErrorType.Error]
    rows.append(Row(name, "usd validators", f"{len(validators)} validators of usd-core "
                    f"{'.'.join(map(str, Usd.GetVersion()[1:]))} (usdchecker's rules): {len(errors)} errors"
                    + (f": {errors[0].GetMessage()[:120]}" if errors else ""), not errors))
    problems = []
    with zipfile.ZipFile(usdz) as z:
        names = z.namelist()
    if not names or not names[0].endswith(".usdc"):
        problems.append(f"first file {names[:1]} is not a usdc layer")
    problems += [f"{n}: file type not allowed" for n in names if n.rsplit(".", 1)[-1].lower() not in ARKIT_EXTENSIONS]
    for prim in stage.Traverse():
        if prim.GetTypeName() not in ARKIT_PRIM_TYPES:
            problems.append(f"{prim.GetPath()}: prim type {prim.GetTypeName()}")
        if prim.GetTypeName() == "Shader":
            sid = prim.GetAttribute("info:id").Get()
            if sid not in ARKIT_SHADER_IDS:
                problems.append(f"{prim.GetPath()}: shader {sid}")
    layers = stage.GetUsedLayers()
    problems += [f"layer {ly.identifier} outside the package" for ly in layers
                 if "[" not in ly.identifier and not ly.anonymous and ly.identifier != str(usdz)]
    rows.append(Row(name, "ARKit rules", f"{len(names)} files {names}; " + ("; ".join(problems)[:160] or "no problem"),
                    not problems))
    return rows


def usdz_rows(name: str, usdz: Path, glb: bytes | None = None, legacy_python: str | None = None) -> list[Row]:
    """The USDZ checks; with the GLB of the same reconstruction, also its texture, UVs and bounds against that."""
    if importlib.util.find_spec("pxr") is None:
        return [Row(name, "usd-core", "not installed (pip install usd-core): USDZ not checked", None)]
    from pxr import Usd, UsdGeom

    albedo, glb_bounds, glb_mesh = None, None, None
    if glb is not None:
        gltf, binary = read_glb(glb)
        attributes = gltf["meshes"][0]["primitives"][0]["attributes"]
        acc = gltf["accessors"][attributes["POSITION"]]
        glb_bounds = np.array([acc["min"], acc["max"]], np.float64)
        albedo = glb_albedo(gltf, binary)
        uv = accessor(gltf, binary, attributes["TEXCOORD_0"]) if "TEXCOORD_0" in attributes else None
        glb_mesh = (accessor(gltf, binary, attributes["POSITION"]), uv)

    rows = usdchecker_rows(name, usdz, legacy_python)
    stage = Usd.Stage.Open(str(usdz))
    up = UsdGeom.GetStageUpAxis(stage)
    rows.append(Row(name, "up axis", str(up), up == UsdGeom.Tokens.y))
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    rows.append(Row(name, "metres per unit", f"{mpu:g}", abs(mpu - 1.0) < 1e-9))
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    rows.append(Row(name, "texture binding", *_texture_binding(stage, meshes, usdz, albedo)))
    if len(meshes) == 1:
        rows.append(Row(name, "surface", *_usd_surface(UsdGeom.Mesh(meshes[0]), glb_mesh)))
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_])
    rng = cache.ComputeWorldBound(stage.GetPseudoRoot()).ComputeAlignedRange()
    lo, hi = np.array(rng.GetMin()), np.array(rng.GetMax())
    value = f"min {np.round(lo, 4).tolist()} max {np.round(hi, 4).tolist()} m"
    if glb_bounds is not None:
        diff = float(np.abs(np.concatenate([lo, hi]) - glb_bounds.ravel()).max())
        rows.append(Row(name, "bounds", value + f"; vs GLB {1000 * diff:.2f} mm", diff <= 1e-3))
    else:
        rows.append(Row(name, "bounds", value, None))
    return rows


def _usd_surface(mesh, glb_mesh: tuple[np.ndarray, np.ndarray | None] | None) -> tuple[str, bool]:
    """Faces wound outward (positive signed volume: AR Quick Look culls back faces); st = the GLB's (u, 1 - v)."""
    from pxr import UsdGeom

    pts = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    if len(counts) == 0 or np.any(counts != 3):
        return "not a triangle mesh", False
    tri = pts[np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)]
    volume = float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        volume = -volume
    problems = [] if volume > 0 else ["faces wound inward"]
    value = f"{len(tri)} triangles, signed volume {1e6 * volume:.1f} cm3"
    if glb_mesh is not None:
        positions, uv = glb_mesh
        st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
        st_v = np.asarray(st.Get(), np.float64) if st and st.HasValue() else None
        if len(positions) != len(pts) or uv is None or st_v is None or len(st_v) != len(uv):
            value += "; vertices or UVs not one to one with the GLB's: st not compared"
        else:
            d_pos = float(np.abs(positions - pts).max())
            d_st = float(np.abs(st_v - np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])).max())
            value += f"; vs GLB: points {1000 * d_pos:.3f} mm, st vs (u, 1 - v) {d_st:.1e}"
            if d_pos > 1e-6 or d_st > 1e-5:
                problems.append("not the GLB's points/UVs")
    return value + ("; " + "; ".join(problems) if problems else ""), not problems


def _texture_binding(stage, meshes: list, usdz: Path, albedo: Albedo | None) -> tuple[str, bool]:
    from pxr import UsdGeom, UsdShade

    if len(meshes) != 1:
        return f"{len(meshes)} meshes (expected 1)", False
    mesh = meshes[0]
    material, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
    if not material:
        return f"{mesh.GetPath()} has no bound material", False
    surface = material.ComputeSurfaceSource()[0]
    if not surface or surface.GetIdAttr().Get() != "UsdPreviewSurface":
        return "the material's surface is not a UsdPreviewSurface", False
    diffuse = surface.GetInput("diffuseColor")
    src = diffuse.GetConnectedSources()[0] if diffuse and diffuse.HasConnectedSource() else []
    if not src or UsdShade.Shader(src[0].source.GetPrim()).GetIdAttr().Get() != "UsdUVTexture":
        return "diffuseColor is not fed by a UsdUVTexture", False
    tex = UsdShade.Shader(src[0].source.GetPrim())
    asset = tex.GetInput("file").Get()
    space = tex.GetInput("sourceColorSpace").Get() if tex.GetInput("sourceColorSpace") else None
    st_in = tex.GetInput("st")
    reader = st_in.GetConnectedSources()[0] if st_in and st_in.HasConnectedSource() else []
    varname = UsdShade.Shader(reader[0].source.GetPrim()).GetInput("varname").Get() if reader else None
    primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar(str(varname)) if varname else None
    with zipfile.ZipFile(usdz) as z:
        inside = asset.path in z.namelist()
        data = z.read(asset.path) if inside else b""
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    problems = []
    if bgr is None:
        problems.append(f"texture {asset.path!r} not a PNG/JPEG inside the package")
    if space != "sRGB":
        problems.append(f"sourceColorSpace {space}")
    if not primvar or not primvar.IsDefined() or str(primvar.GetTypeName()) != "texCoord2f[]":
        problems.append(f"st reader's varname {varname!r} is no texCoord2f[] primvar of the mesh")
    same = ""
    if bgr is not None and albedo is not None and albedo.texture is not None:
        usd_mean = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).reshape(-1, 3).mean(axis=0)
        d = float(np.abs(usd_mean - albedo.texture.reshape(-1, 3).mean(axis=0)).max()) \
            if bgr.shape == albedo.texture.shape else float("inf")
        same = f", mean colour vs the GLB's texture {d:.2f} DN"
        if d > 1.0:
            problems.append("not the GLB's texture")
    value = (f"UsdPreviewSurface.diffuseColor <- UsdUVTexture({asset.path}, {space}) <- primvar {varname}"
             + (f" {bgr.shape[1]}x{bgr.shape[0]}" if bgr is not None else "") + same)
    return value + ("; " + "; ".join(problems) if problems else ""), not problems
