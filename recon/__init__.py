"""recon: silhouettes, visual-hull carving, stereo depth and point fusion, meshing, export.

All geometry is in the table frame, millimetres (see the README's conventions);
exports convert to metres. Public names are imported lazily.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "types": ["VoxelHull", "TableMesh", "DepthMap", "FusedPoints"],
    "silhouettes": ["SilhouetteResult", "estimate_silhouettes"],
    "carving": ["carve_hull"],
    "stereo": ["StereoOptions", "depth_maps", "hull_depth_range"],
    "fusion": ["FusionOptions", "fuse_depths"],
    "surface": ["SurfaceOptions", "fused_field", "fused_surface", "compare_to_hull", "HullComparison"],
    "regions": ["RegionOptions", "RegionChoice", "choose_regions", "supported_field"],
    "raycast": ["raycasting_scene", "render_depth"],
    "meshing": ["mesh_from_hull", "finalize_mesh", "remesh_watertight", "mesh_stats", "MeshStats"],
    "colorize": ["color_vertices", "visible_vertices"],
    "texture": ["TexturedMesh", "texture_mesh", "bake_texture", "uv_atlas", "render_albedo"],
    "export": ["export_mesh", "export_colmap", "export_nerfstudio"],
}
_WHERE = {name: mod for mod, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    mod = _WHERE.get(name)
    if mod is None:
        raise AttributeError(f"module 'recon' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{mod}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
