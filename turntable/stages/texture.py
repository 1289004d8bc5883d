"""Stage 6b, texture: the UV atlas and the photo texture of the final mesh and its levels of detail
(:func:`recon.texture.texture_mesh`), kept in the stage cache.

The key is everything the bake reads: the views (``sil_key``: the frames' bytes, cameras, masks, work
size; ``names``: the views kept), the final mesh's arrays (vertices, faces, normals, vertex colours: a
re-run whose mesh differs by one bit bakes again), ``--texture-size``, ``--lods`` and
``TEXTURE_VERSION`` (bumped when the atlas or the bake changes, so an older cache is not reused).
"""

from __future__ import annotations

import numpy as np

from .cache import StageCache, stage_key

#: Bumped whenever recon.texture's atlas or bake changes what it makes.
TEXTURE_VERSION = 2


def texture_key(sil_key: str, names: list[str], mesh, opts) -> str:
    return stage_key(sil_key, names, "texture", TEXTURE_VERSION, np.asarray(mesh.vertices_table),
                     np.asarray(mesh.faces), None if mesh.normals_table is None else np.asarray(mesh.normals_table),
                     None if mesh.colors_rgb is None else np.asarray(mesh.colors_rgb), opts.texture_size,
                     list(opts.lods))


def textured_model(mesh, images_rgb, K, Ts, masks, opts, cache: StageCache, key: str, progress):
    """The :class:`recon.texture.TexturedMesh` of ``mesh`` (with ``opts.lods``), from the cache or baked."""
    from recon.texture import TexturedMesh, texture_mesh
    from recon.types import TableMesh

    n_lods = len(opts.lods)
    fields = {"texture": ("u", ("S", "S", 3))}
    for i in range(n_lods + 1):
        fields |= {f"v{i}": ("f", (f"n{i}", 3)), f"f{i}": ("iu", (None, 3)), f"n{i}": ("f", (f"n{i}", 3)),
                   f"uv{i}": ("f", (f"n{i}", 2)), f"src{i}": ("iu", (f"n{i}",))}
    hit = cache.load("texture", key, fields | {"levels": ("iu", ())})
    if hit is not None and 0 <= int(hit["levels"]) <= n_lods + 1:
        progress.note("texture: reused")
        tex = hit["texture"]
        colors = None if mesh.colors_rgb is None else np.asarray(mesh.colors_rgb, np.uint8)[hit["src0"]]
        levels = [TexturedMesh(TableMesh(hit[f"v{i}"], hit[f"f{i}"], hit[f"n{i}"],
                                         colors if i == 0 else None), hit[f"uv{i}"], tex, hit[f"src{i}"])
                  for i in range(int(hit["levels"]))]
        return TexturedMesh(levels[0].mesh, levels[0].texcoords, tex, levels[0].source_vertex, tuple(levels[1:]))
    with progress.stage("texture"):
        textured = texture_mesh(mesh, images_rgb, K, Ts, masks=masks, size=opts.texture_size, lods=opts.lods)
    arrays: dict[str, np.ndarray] = {"texture": textured.texture_rgb, "levels": np.array(1 + len(textured.lods))}
    for i, lv in enumerate((textured, *textured.lods)):
        arrays |= {f"v{i}": np.asarray(lv.mesh.vertices_table), f"f{i}": np.asarray(lv.mesh.faces),
                   f"n{i}": np.asarray(lv.mesh.normals_table), f"uv{i}": np.asarray(lv.texcoords),
                   f"src{i}": np.asarray(lv.source_vertex)}
    for i in range(1 + len(textured.lods), n_lods + 1):  # a level left out (the mesh had too few faces): empty
        arrays |= {f"v{i}": np.zeros((0, 3)), f"f{i}": np.zeros((0, 3), np.int64), f"n{i}": np.zeros((0, 3)),
                   f"uv{i}": np.zeros((0, 2)), f"src{i}": np.zeros(0, np.int64)}
    cache.save("texture", key, **arrays)
    return textured
