"""Procedural test objects with ground-truth geometry and colour.

Every object is a :class:`trimesh.Trimesh` in its own object frame, which is the
table frame of the scene it stands in: millimetres, +Y up, the base on the plane
Y = 0, centred on the Y axis. Colours are per-vertex RGBA uint8
(``mesh.visual.vertex_colors``) sampled from a procedural texture in object
coordinates (value-noise fBm, stripes and a checker, blended), so multi-view
stereo has something to match. The texture itself rides along in
``mesh.metadata["albedo"]`` (a :class:`ProceduralTexture`): the renderer
evaluates it at every ray hit, so images keep sub-millimetre texture detail
while the GT mesh (edges <= 2.5 mm) stays small; meshes without it are
rendered from their interpolated vertex colours.

Built-in objects (:data:`OBJECT_NAMES`):

``vase``
    Smooth, convex-ish closed body of revolution, ~70 mm across, 110 mm tall.
``cup``
    Open cup with a 3 mm wall: its inside is a concavity that no silhouette sees
    (visible from above at 30 deg elevation).
``chair``
    Four legs and two back posts 5 mm thick: thin parts for silhouette carving.
``figure``
    A stylised standing figure with 4-5 mm thick arms and a thin staff standing on the
    table: one body (head and arms sunk into the torso).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from calib.types import as_points

__all__ = ["OBJECT_NAMES", "ProceduralTexture", "make_object", "load_object", "procedural_colors", "fit_to_footprint"]

OBJECT_NAMES = ("vase", "cup", "chair", "figure")

_MAX_EDGE_MM = 2.5


# --------------------------------------------------------------------------- texture
def _value_noise(pts: np.ndarray, perm: np.ndarray, values: np.ndarray, scale_mm: float) -> np.ndarray:
    """Smooth 3-D value noise in [0, 1] at ``pts`` (N, 3) mm, lattice ``scale_mm``."""
    p = pts / scale_mm
    i0 = np.floor(p).astype(np.int64)
    f = p - i0
    f = f * f * (3.0 - 2.0 * f)  # smoothstep
    m = len(perm) - 1

    def lattice(dx, dy, dz):
        h = perm[(i0[:, 0] + dx) & m]
        h = perm[(h + i0[:, 1] + dy) & m]
        h = perm[(h + i0[:, 2] + dz) & m]
        return values[h]

    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1.0 - f[:, 0]
        for dy in (0, 1):
            wy = f[:, 1] if dy else 1.0 - f[:, 1]
            for dz in (0, 1):
                wz = f[:, 2] if dz else 1.0 - f[:, 2]
                out += wx * wy * wz * lattice(dx, dy, dz)
    return out


@dataclass(frozen=True)
class ProceduralTexture:
    """Albedo as a function of object coordinates (mm): call it on (N, 3) points.

    Two base colours blended by multi-scale value noise (lattices of 14, 6 and
    2.5 mm); horizontal stripes and a faint 4 mm checker add structure at a few
    millimetres. Drawn once from a generator by :meth:`random`.
    """

    perm: np.ndarray  # (256,) int64 lattice hash
    values: np.ndarray  # (256,) float64 lattice values in [0, 1)
    base_a: np.ndarray  # (3,) float64 RGB in [0, 1] (sRGB)
    base_b: np.ndarray  # (3,)
    offset_mm: np.ndarray  # (3,) shifts the noise lattice
    stripe_mm: float

    @classmethod
    def random(cls, rng: np.random.Generator) -> ProceduralTexture:
        hue = rng.random()
        return cls(perm=rng.permutation(256).astype(np.int64), values=rng.random(256),
                   base_a=_hsv_to_rgb(hue, 0.55 + 0.3 * rng.random(), 0.8),
                   base_b=_hsv_to_rgb((hue + 0.35 + 0.3 * rng.random()) % 1.0, 0.65, 0.45),
                   offset_mm=rng.uniform(-1000, 1000, 3), stripe_mm=float(rng.uniform(9.0, 15.0)))

    def __call__(self, pts_obj: np.ndarray) -> np.ndarray:
        """sRGB colours (N, 3) float32 in [0, 1] at object points ``pts_obj`` (N, 3) mm."""
        pts = as_points(pts_obj, 3, "pts_obj")
        q = pts + self.offset_mm
        n = (0.5 * _value_noise(q, self.perm, self.values, 14.0) + 0.3 * _value_noise(q, self.perm, self.values, 6.0)
             + 0.2 * _value_noise(q, self.perm, self.values, 2.5))
        t = np.clip((n - 0.5) * 2.2 + 0.5, 0.0, 1.0)
        rgb = (1.0 - t)[:, None] * self.base_a + t[:, None] * self.base_b
        stripes = 0.5 + 0.5 * np.sin(2 * np.pi * pts[:, 1] / self.stripe_mm)
        rgb *= (0.8 + 0.2 * stripes)[:, None]
        checker = (np.floor(q[:, 0] / 4.0) + np.floor(q[:, 1] / 4.0) + np.floor(q[:, 2] / 4.0)) % 2
        rgb *= (0.92 + 0.08 * checker)[:, None]
        return np.clip(rgb, 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class UniformAlbedo:
    """One sRGB albedo ``rgb`` (3,) in [0, 1] everywhere: a white ceramic, a plain 3D print."""

    rgb: tuple[float, float, float]

    def __call__(self, pts_obj: np.ndarray) -> np.ndarray:
        """sRGB colours (N, 3) float32 in [0, 1] at object points ``pts_obj`` (N, 3) mm."""
        n = len(as_points(pts_obj, 3, "pts_obj"))
        return np.tile(np.asarray(self.rgb, np.float32), (n, 1))


def with_uniform_albedo(mesh: trimesh.Trimesh, rgb) -> trimesh.Trimesh:
    """A copy of ``mesh`` coloured by one sRGB albedo ``rgb`` (3,) in [0, 1] (vertex colours and renderer)."""
    rgb = tuple(float(c) for c in rgb)
    if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
        raise ValueError(f"albedo: expected three values in [0, 1], got {rgb}")
    out = mesh.copy()
    byte = np.round(np.asarray(rgb) * 255.0).astype(np.uint8)
    out.visual = trimesh.visual.ColorVisuals(out, vertex_colors=np.tile(np.append(byte, 255), (len(out.vertices), 1)))
    out.metadata["albedo"] = UniformAlbedo(rgb)
    return out


def procedural_colors(pts_obj: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Colours (N, 3) uint8 of a fresh :class:`ProceduralTexture` drawn from ``rng``."""
    return np.round(ProceduralTexture.random(rng)(pts_obj) * 255.0).astype(np.uint8)


def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    i = int(h * 6.0) % 6
    f = h * 6.0 - int(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


# --------------------------------------------------------------------------- geometry
def _resample_polyline(pts: np.ndarray, step: float) -> np.ndarray:
    """Points along a 2-D polyline (N, 2) at about ``step`` spacing, keeping the ends."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(np.ceil(s[-1] / step)), 2)
    si = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(si, s, pts[:, 0]), np.interp(si, s, pts[:, 1])])


def _revolve(profile_ry: np.ndarray, n_theta: int = 160) -> trimesh.Trimesh:
    """Closed surface of revolution about +Y of a profile (r, y) from axis to axis.

    The profile (N, 2) starts and ends on the axis (r = 0); it runs so that the
    solid is on its left when walking from the first to the last point with r
    to the right and y up (bottom centre -> outside -> top centre).
    """
    prof = _resample_polyline(np.asarray(profile_ry, float), 0.6 * _MAX_EDGE_MM)
    r, y = prof[:, 0], prof[:, 1]
    r[0] = r[-1] = 0.0
    th = np.linspace(0.0, 2 * np.pi, n_theta, endpoint=False)
    inner = prof[1:-1]
    ring = np.stack([inner[:, 0:1] * np.cos(th), np.repeat(inner[:, 1:2], n_theta, 1),
                     inner[:, 0:1] * np.sin(th)], axis=-1).reshape(-1, 3)
    bottom, top = len(ring), len(ring) + 1
    V = np.vstack([ring, [[0.0, y[0], 0.0]], [[0.0, y[-1], 0.0]]])
    m = len(inner)
    j = np.arange(n_theta)
    jn = (j + 1) % n_theta
    F = [np.column_stack([np.full(n_theta, bottom), jn, j])]
    for i in range(m - 1):
        a, b = i * n_theta + j, i * n_theta + jn
        c, d = (i + 1) * n_theta + j, (i + 1) * n_theta + jn
        F.append(np.column_stack([a, b, d]))
        F.append(np.column_stack([a, d, c]))
    last = (m - 1) * n_theta
    F.append(np.column_stack([np.full(n_theta, top), last + j, last + jn]))
    mesh = trimesh.Trimesh(V, np.vstack(F), process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _vase() -> trimesh.Trimesh:
    y = np.linspace(0.0, 110.0, 120)
    r = 22.0 + 13.0 * np.sin(np.pi * np.clip(y / 78.0, 0, 1)) ** 1.3
    neck = y > 70.0
    r[neck] = 12.5 + 4.0 * ((y[neck] - 70.0) / 40.0) ** 2 + 9.5 * np.exp(-((y[neck] - 70.0) / 9.0) ** 2)
    r = np.convolve(np.pad(r, 4, mode="edge"), np.ones(9) / 9, mode="valid")
    prof = np.vstack([[0.0, 0.0], np.column_stack([r, y]), [0.0, 110.0]])
    return _revolve(prof)


def _cup() -> trimesh.Trimesh:
    # bottom centre -> foot -> outer wall -> rounded rim -> inner wall -> inner floor centre
    h, wall, floor = 68.0, 3.0, 5.0
    y_out = np.linspace(2.0, h, 60)
    r_out = 27.0 + 11.0 * (y_out / h) ** 1.4
    rim = np.linspace(0.0, np.pi, 9)
    r_rim = r_out[-1] - wall / 2 + wall / 2 * np.cos(rim)
    y_rim = h + wall / 2 * np.sin(rim)
    y_in = np.linspace(h, floor, 60)
    r_in = 27.0 + 11.0 * (y_in / h) ** 1.4 - wall
    prof = np.vstack([[0.0, 0.0], [25.0, 0.0], [27.0, 2.0], np.column_stack([r_out, y_out]),
                      np.column_stack([r_rim, y_rim])[1:-1], np.column_stack([r_in, y_in]),
                      [r_in[-1] - 3.0, floor], [0.0, floor]])
    return _revolve(prof)


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def _chair() -> trimesh.Trimesh:
    half, leg, seat_y, seat_t = 27.0, 5.0, 45.0, 6.0
    parts = []
    for sx in (-1, 1):
        for sz in (-1, 1):
            x0, z0 = sx * (half - leg / 2), sz * (half - leg / 2)
            parts.append(_box([x0 - leg / 2, 0.0, z0 - leg / 2], [x0 + leg / 2, seat_y, z0 + leg / 2]))
    parts.append(_box([-half, seat_y, -half], [half, seat_y + seat_t, half]))
    top = seat_y + seat_t
    for sx in (-1, 1):  # back posts on the -Z side
        x0 = sx * (half - leg / 2)
        parts.append(_box([x0 - leg / 2, top, -half], [x0 + leg / 2, top + 52.0, -half + leg]))
    for yb in (top + 22.0, top + 42.0):  # slats
        parts.append(_box([-half + leg, yb, -half + 0.5], [half - leg, yb + 7.0, -half + 3.5]))
    return trimesh.util.concatenate(parts)


def _capsule(p0, p1, radius: float, n_theta: int = 24) -> trimesh.Trimesh:
    """Closed capsule of ``radius`` (mm) between the points ``p0`` and ``p1`` (3,)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.linalg.norm(p1 - p0))
    a = np.linspace(-np.pi / 2, 0.0, 8)
    bottom = np.column_stack([radius * np.cos(a), radius * np.sin(a)])
    top = np.column_stack([radius * np.cos(-a[::-1]), length + radius * np.sin(-a[::-1])])
    cap = _revolve(np.vstack([bottom, top]), n_theta=n_theta)
    T = trimesh.geometry.align_vectors([0, 1, 0], (p1 - p0) / length)
    T[:3, 3] = p0
    cap.apply_transform(T)
    return cap


def _figure() -> trimesh.Trimesh:
    """A standing figure on a plinth, holding a staff that stands on the table: one body, as every real
    object on a turntable is (the pipeline drops hull pieces floating above the table). Its head sinks 1 mm
    into the torso's top (a 4 mm neck), its arms 1.5 mm into the torso's shoulders."""
    parts = [
        _box([-22.0, 0.0, -16.0], [22.0, 5.0, 16.0]),  # plinth
        _capsule([-7.0, 8.0, 0.0], [-6.0, 45.0, 0.0], 4.5),  # legs
        _capsule([7.0, 8.0, 0.0], [6.0, 45.0, 0.0], 4.5),
        _capsule([0.0, 50.0, 0.0], [0.0, 78.0, 0.0], 10.0),  # torso, top at 88 mm
        _capsule([-9.5, 84.0, 0.0], [-25.0, 62.0, 6.0], 2.5),  # thin arms
        _capsule([9.5, 84.0, 0.0], [26.0, 98.0, 4.0], 2.5),
        _capsule([27.0, 2.0, 5.0], [27.0, 112.0, 5.0], 2.0),  # staff, 4 mm thick, standing on the table
    ]
    head = trimesh.creation.icosphere(subdivisions=3, radius=9.0)
    head.apply_translation([0.0, 96.0, 0.0])  # from 87 mm: resting on the torso
    parts.append(head)
    return trimesh.util.concatenate(parts)


_BUILDERS = {"vase": _vase, "cup": _cup, "chair": _chair, "figure": _figure}


# --------------------------------------------------------------------------- public
def _finish(mesh: trimesh.Trimesh, rng: np.random.Generator, keep_colors: bool = False) -> trimesh.Trimesh:
    """Subdivide to ~1 mm edges, stand on Y = 0, colour procedurally (unless kept)."""
    V, F = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    colors = None
    if keep_colors and mesh.visual.kind == "vertex":
        colors = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(np.float64)
    for _ in range(12):
        edges = np.linalg.norm(V[F[:, [1, 2, 0]]] - V[F], axis=2)
        long_faces = np.flatnonzero(edges.max(axis=1) > _MAX_EDGE_MM)
        if len(long_faces) == 0:
            break
        attrs = None if colors is None else {"rgb": colors}
        out = trimesh.remesh.subdivide(V, F, face_index=long_faces, vertex_attributes=attrs)
        V, F = out[0], out[1]
        if colors is not None:
            colors = out[2]["rgb"]
    V = V - [0.0, V[:, 1].min(), 0.0]
    result = trimesh.Trimesh(V, F, process=False)
    if colors is None:
        texture = ProceduralTexture.random(rng)
        rgb = np.round(texture(V) * 255.0).astype(np.uint8)
        result.metadata["albedo"] = texture
    else:
        rgb = np.clip(np.round(colors), 0, 255).astype(np.uint8)
    result.visual = trimesh.visual.ColorVisuals(result, vertex_colors=np.column_stack(
        [rgb, np.full(len(V), 255, np.uint8)]))
    return result


def make_object(name: str, rng: np.random.Generator) -> trimesh.Trimesh:
    """A built-in textured test object (see the module docstring for the list).

    Parameters
    ----------
    name : str
        One of :data:`OBJECT_NAMES`.
    rng : numpy.random.Generator
        Draws the texture (palette, noise lattice); the geometry is fixed.

    Returns
    -------
    trimesh.Trimesh
        Vertices (N, 3) float64 in mm in the table frame, base on Y = 0, centred
        on the Y axis; per-vertex RGBA uint8 colours.
    """
    if name not in _BUILDERS:
        raise ValueError(f"unknown object {name!r}; built-in objects: {', '.join(OBJECT_NAMES)}")
    return _finish(_BUILDERS[name](), rng)


def fit_to_footprint(mesh: trimesh.Trimesh, max_radius_mm: float, max_height_mm: float) -> trimesh.Trimesh:
    """Uniformly scaled copy standing on Y = 0, centred on the Y axis, inside a cylinder."""
    V = np.asarray(mesh.vertices, float)
    lo, hi = V.min(axis=0), V.max(axis=0)
    centre = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    V = V - centre
    r = np.hypot(V[:, 0], V[:, 2]).max()
    s = min(max_radius_mm / max(r, 1e-12), max_height_mm / max(V[:, 1].max(), 1e-12))
    out = mesh.copy()
    out.vertices = V * s
    return out


def load_object(path: str, rng: np.random.Generator, max_radius_mm: float = 40.0,
                max_height_mm: float = 120.0) -> trimesh.Trimesh:
    """Any mesh file trimesh can read, +Y up, scaled to fit and coloured.

    The mesh is centred on the Y axis, stood on Y = 0 and scaled uniformly so it
    fits in a cylinder of ``max_radius_mm`` and ``max_height_mm``. Its vertex
    colours are kept when it has them, otherwise procedural ones are drawn.
    Raises ``ValueError`` when the file holds no triangles.
    """
    try:
        mesh = trimesh.load_mesh(path, process=True)
    except Exception as exc:  # trimesh raises many kinds for unreadable files
        raise ValueError(f"cannot load mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError("file holds no triangle mesh")
    mesh = fit_to_footprint(mesh, max_radius_mm, max_height_mm)
    return _finish(mesh, rng, keep_colors=True)
