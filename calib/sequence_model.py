"""The joint least-squares problem behind :mod:`calib.sequence`.

Parameters: the free intrinsics (``f`` as a relative change, ``cx, cy`` in
pixels, ``k1, k2``), the stroke width ``w`` and either

* turntable: ``T_cam_table_k = T_cam_axis . RotY(theta_k) . Trans(d_x, 0, d_z)``
  with ``R_cam_axis = Exp(w) R0`` (``w`` on ``R0``'s X and Z axes, and on its Y
  axis when the marks fix the yaw), ``t_cam_axis``, ``d`` and ``theta_k``;
* handheld: ``R_k = R0_k Exp((a, 0, b))`` (the normal; the rings do not see the
  rotation about it) and ``t_k``.

Residuals: each edge point's distance (pixels) from its projected edge circle,
:func:`calib.refine.edge_residuals` on points undistorted with the current
``K, dist`` (:func:`calib.distortion.undistort_px`); for a turntable, one row per
frame whose marks were read: the yaw between the model's pose and the marks'
pose, scaled to pixels by ``noise_px / std``. Solved by Levenberg-Marquardt on
the normal equations, built block by block (a frame's rows touch the global
parameters and its own).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .camera import make_T
from .distortion import undistort_px
from .refine import edge_residuals
from .types import CalibrationError, EdgePoints, TargetObservation

__all__ = ["rot_y"]


# --------------------------------------------------------------------------- small geometry
def rot_y(theta: float) -> np.ndarray:
    """Right-handed rotation (3, 3) by ``theta`` radians about +Y."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _exp_so3(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-12:
        return np.eye(3) + W
    return np.eye(3) + math.sin(th) / th * W + (1.0 - math.cos(th)) / th**2 * (W @ W)


def _yaw_of(R: np.ndarray) -> float:
    """Angle (rad) of the rotation about +Y closest to ``R`` (3, 3)."""
    return math.atan2(R[0, 2] - R[2, 0], R[0, 0] + R[2, 2])


def _project_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def _wrap(a: np.ndarray | float):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# --------------------------------------------------------------------------- edge data
@dataclass(frozen=True)
class _FrameEdges:
    """Edge points of one frame, packed for vectorised residuals."""

    uv_px: np.ndarray  # (N, 2) raw (distorted) pixels
    groups: tuple  # ((slice, ring_radius_mm, side), ...)

    @classmethod
    def from_observation(cls, obs: TargetObservation, max_per_edge: int) -> "_FrameEdges":
        uvs, groups, n = [], [], 0
        for e in obs.edges:
            uv = e.uv_px
            if len(uv) < 5:
                continue
            if len(uv) > max_per_edge:
                uv = uv[np.linspace(0, len(uv) - 1, max_per_edge).round().astype(int)]
            uvs.append(uv)
            groups.append((slice(n, n + len(uv)), float(e.ring_radius_mm), int(e.side)))
            n += len(uv)
        if not uvs:
            raise CalibrationError("no edge points")
        return cls(np.concatenate(uvs), tuple(groups))

    def select(self, keep: np.ndarray) -> "_FrameEdges":
        uvs, groups, n = [], [], 0
        for sl, r, side in self.groups:
            uv = self.uv_px[sl][keep[sl]]
            if len(uv) < 5:
                continue
            uvs.append(uv)
            groups.append((slice(n, n + len(uv)), r, side))
            n += len(uv)
        return _FrameEdges(np.concatenate(uvs), tuple(groups))

    @property
    def has_stroke(self) -> bool:
        return any(side != 0 for _, _, side in self.groups)


def _edge_residuals(K: np.ndarray, dist: np.ndarray, T_cam_table: np.ndarray, stroke_mm: float,
                    fe: _FrameEdges) -> np.ndarray:
    """Distances (N,) px of ``fe``'s undistorted points from their projected edge circles.

    The single-view residual of :func:`calib.refine.edge_residuals`, on points
    undistorted with the current ``K, dist``.
    """
    uv = undistort_px(fe.uv_px, K, dist) if np.any(dist) else fe.uv_px
    edges = tuple(EdgePoints(uv[sl], r, side) for sl, r, side in fe.groups)
    return edge_residuals(K, T_cam_table, stroke_mm, edges)


# --------------------------------------------------------------------------- the problem
_INTR_NAMES = ("f", "cx", "cy", "k1", "k2")


@dataclass
class _State:
    """Everything the joint fit estimates (plain arrays; internal)."""

    K: np.ndarray
    dist: np.ndarray  # (5,)
    stroke: float
    # turntable
    R_cam_axis: np.ndarray | None = None
    t_cam_axis: np.ndarray | None = None
    d_xz: np.ndarray | None = None
    theta: np.ndarray | None = None  # (n_frames,) rad
    # handheld
    R: list | None = None  # per-frame (3, 3)
    t: list | None = None  # per-frame (3,)

    def poses(self) -> list[np.ndarray]:
        if self.R is not None:
            return [make_T(R, t) for R, t in zip(self.R, self.t)]
        Ts = []
        for th in self.theta:
            R = self.R_cam_axis @ rot_y(th)
            Ts.append(make_T(R, R @ np.array([self.d_xz[0], 0.0, self.d_xz[1]]) + self.t_cam_axis))
        return Ts


class _Problem:
    """Parameter packing, residuals and a block-sparse finite-difference Jacobian.

    Global parameters (free intrinsics, stroke, turntable geometry) touch every
    frame; local ones (theta_k, or a handheld frame's 5) touch one frame, so
    the Jacobian costs (n_global + n_local_per_frame) residual evaluations.
    """

    def __init__(self, frames: list[_FrameEdges], state: _State, free_intr: tuple[str, ...],
                 free_stroke: bool, model: str, free_theta: np.ndarray | None = None,
                 free_yaw: bool = True, mark_R: list | None = None, mark_w: np.ndarray | None = None):
        self.frames, self.s0, self.model = frames, state, model
        self.free_intr, self.free_stroke = free_intr, free_stroke
        self.free_theta = free_theta if free_theta is not None else np.zeros(len(frames), bool)
        self.free_yaw = free_yaw
        self.mark_R = mark_R or [None] * len(frames)
        self.mark_w = mark_w if mark_w is not None else np.zeros(len(frames))
        n_g = len(free_intr) + int(free_stroke)
        if model == "turntable":
            n_g += 2 + int(free_yaw) + 3 + 2
            self.n_local = self.free_theta.astype(int)
        else:
            self.n_local = np.full(len(frames), 5)
        self.n_global = n_g
        self.local_start = n_g + np.concatenate([[0], np.cumsum(self.n_local)[:-1]]).astype(int)
        self.n_params = n_g + int(self.n_local.sum())
        self.n_edge = np.array([len(f.uv_px) for f in frames])
        self.row_start = np.concatenate([[0], np.cumsum(self.n_edge)]).astype(int)
        self.has_mark = np.array([m is not None and w > 0 for m, w in zip(self.mark_R, self.mark_w)])
        self.n_rows = int(self.row_start[-1] + self.has_mark.sum())

    # -- packing ------------------------------------------------------------
    def unpack(self, x: np.ndarray) -> _State:
        s0, i = self.s0, 0
        K, dist = s0.K.copy(), s0.dist.copy()
        for name in self.free_intr:
            if name == "f":
                K[0, 0] = K[1, 1] = s0.K[0, 0] * (1.0 + x[i])
            elif name in ("cx", "cy"):
                j = 0 if name == "cx" else 1
                K[j, 2] = s0.K[j, 2] + x[i]
            else:
                j = 0 if name == "k1" else 1
                dist[j] = s0.dist[j] + x[i]
            i += 1
        stroke = s0.stroke
        if self.free_stroke:
            stroke = s0.stroke + x[i]
            i += 1
        st = _State(K=K, dist=dist, stroke=stroke)
        if self.model == "turntable":
            R0 = s0.R_cam_axis
            w = x[i] * R0[:, 0] + x[i + 1] * R0[:, 2]
            i += 2
            if self.free_yaw:
                w = w + x[i] * R0[:, 1]
                i += 1
            st.R_cam_axis = _exp_so3(w) @ R0
            st.t_cam_axis = s0.t_cam_axis + x[i:i + 3]
            st.d_xz = s0.d_xz + x[i + 3:i + 5]
            theta = s0.theta.copy()
            idx = np.flatnonzero(self.free_theta)
            theta[idx] += x[self.local_start[idx]]
            st.theta = theta
        else:
            st.R, st.t = [], []
            for k in range(len(self.frames)):
                j = self.local_start[k]
                st.R.append(s0.R[k] @ _exp_so3(np.array([x[j], 0.0, x[j + 1]])))
                st.t.append(s0.t[k] + x[j + 2:j + 5])
        return st

    # -- residuals ----------------------------------------------------------
    def _mark_residual(self, k: int, R_model: np.ndarray) -> float:
        return self.mark_w[k] * _yaw_of(R_model.T @ self.mark_R[k])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        st = self.unpack(x)
        Ts = st.poses()
        out = np.empty(self.n_rows)
        for k, fe in enumerate(self.frames):
            out[self.row_start[k]:self.row_start[k + 1]] = _edge_residuals(st.K, st.dist, Ts[k], st.stroke, fe)
        m = self.row_start[-1]
        for k in np.flatnonzero(self.has_mark):
            out[m] = self._mark_residual(k, Ts[k][:3, :3])
            m += 1
        return out

    def _frame_rows(self, st: _State, T: np.ndarray, k: int) -> tuple[np.ndarray, float | None]:
        r = _edge_residuals(st.K, st.dist, T, st.stroke, self.frames[k])
        return r, (self._mark_residual(k, T[:3, :3]) if self.has_mark[k] else None)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Forward differences, block by block (a local parameter re-evaluates its frame only).

        Not the analytic ``calib.refine.edge_linearisation``: it freezes the
        residual's weight ``1 / |grad rho|``, and Gauss-Newton then converges
        where ``J~^T r = 0``, which is biased by ``sum e^2 d log|grad rho| / dp``:
        with k1, k2 and the principal point free that moved the principal point
        by ~15 px and f by ~1 % at 0.15 px noise (exact differences: 0.6 px, 0.09 %).
        """
        J = np.zeros((self.n_rows, self.n_params))
        r0 = self.residuals(x)
        mark_row = np.full(len(self.frames), -1)
        mark_row[self.has_mark] = self.row_start[-1] + np.arange(self.has_mark.sum())
        for j in range(self.n_global):
            h = 1e-6 * max(1.0, abs(x[j]))
            xp = x.copy()
            xp[j] += h
            J[:, j] = (self.residuals(xp) - r0) / h
        for k in range(len(self.frames)):
            rows = slice(self.row_start[k], self.row_start[k + 1])
            for c in range(self.n_local[k]):
                j = self.local_start[k] + c
                h = 1e-6 * max(1.0, abs(x[j]))
                xp = x.copy()
                xp[j] += h
                st = self.unpack(xp)
                T = self._pose_k(st, k)
                r, m = self._frame_rows(st, T, k)
                J[rows, j] = (r - r0[rows]) / h
                if m is not None:
                    J[mark_row[k], j] = (m - r0[mark_row[k]]) / h
        return J

    @staticmethod
    def _pose_k(st: _State, k: int) -> np.ndarray:
        if st.R is not None:
            return make_T(st.R[k], st.t[k])
        R = st.R_cam_axis @ rot_y(st.theta[k])
        return make_T(R, R @ np.array([st.d_xz[0], 0.0, st.d_xz[1]]) + st.t_cam_axis)

    def blocks(self) -> list[tuple[slice, np.ndarray]]:
        """(rows, columns) of the Jacobian's non-zero blocks: one per frame, one for the mark rows."""
        out = []
        g = np.arange(self.n_global)
        for k in range(len(self.frames)):
            loc = self.local_start[k] + np.arange(self.n_local[k])
            out.append((slice(self.row_start[k], self.row_start[k + 1]), np.concatenate([g, loc]).astype(int)))
        if self.has_mark.any():
            out.append((slice(self.row_start[-1], self.n_rows), np.arange(self.n_params)))
        return out

    def edge_rms_per_frame(self, r: np.ndarray) -> np.ndarray:
        return np.array([np.sqrt(np.mean(r[self.row_start[k]:self.row_start[k + 1]] ** 2))
                         for k in range(len(self.frames))])


@dataclass(frozen=True)
class _Fit:
    state: _State
    std: dict  # parameter name -> 1 sigma (intrinsics, stroke)
    rms_px: float
    rms_per_frame: np.ndarray
    residuals: np.ndarray
    problem: _Problem


def _gram(Jw: np.ndarray, rw: np.ndarray, blocks) -> tuple[np.ndarray, np.ndarray]:
    """``Jw^T Jw`` and ``Jw^T rw`` summed over row blocks touching only their columns.

    The Jacobian is block sparse (a frame's rows touch the global parameters and
    its own); small per-block products also keep clear of multithreaded BLAS,
    which oversubscribes busy machines badly.
    """
    n = Jw.shape[1]
    A, g = np.zeros((n, n)), np.zeros(n)
    for rows, cols in blocks:
        B = Jw[rows][:, cols]
        A[np.ix_(cols, cols)] += np.einsum("ij,ik->jk", B, B, optimize=False)
        g[cols] += np.einsum("ij,i->j", B, rw[rows], optimize=False)
    return A, g


def _levenberg_marquardt(fun, jac, x0: np.ndarray, robust_px: float | None, blocks, max_iter: int = 40) -> np.ndarray:
    """Minimise ``sum rho(r_i^2)`` by Levenberg-Marquardt on the normal equations.

    ``robust_px``: soft-L1 loss of that scale (iteratively reweighted), else L2.
    The parameters are few (tens) and the rows many, so ``J^T J`` is solved
    directly instead of factoring ``J``.
    """

    def cost_of(r):
        if robust_px is None:
            return float(r @ r)
        z = (r / robust_px) ** 2
        return float(np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0))) * robust_px**2

    x = x0.copy()
    r = fun(x)
    cost = cost_of(r)
    lam = 1e-3
    for _ in range(max_iter):
        J = jac(x)
        w = np.ones_like(r) if robust_px is None else 1.0 / np.sqrt(np.sqrt(1.0 + (r / robust_px) ** 2))
        A, g = _gram(J * w[:, None], w * r, blocks)
        D = np.maximum(np.diag(A), 1e-12 * max(np.max(np.diag(A)), 1e-300))
        improved = False
        for _ in range(12):
            try:
                dx = -np.linalg.solve(A + lam * np.diag(D), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            r_new = fun(x + dx)
            c_new = cost_of(r_new)
            if c_new < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        rel = (cost - c_new) / max(cost, 1e-300)
        x, r, cost = x + dx, r_new, c_new
        lam = max(lam / 10.0, 1e-9)
        if rel < 1e-9:
            break
    return x


def _solve(problem: _Problem, robust: bool) -> _Fit:
    x0 = np.zeros(problem.n_params)
    x = _levenberg_marquardt(problem.residuals, problem.jacobian, x0, 1.0 if robust else None, problem.blocks())
    r = problem.residuals(x)
    J = problem.jacobian(x)
    n_e = int(problem.row_start[-1])
    dof = max(len(r) - problem.n_params, 1)
    s2 = float(r @ r) / dof
    std = _param_std(J, s2)
    names = list(problem.free_intr) + (["stroke"] if problem.free_stroke else [])
    st = problem.unpack(x)
    out = {}
    for i, name in enumerate(names):
        s = std[i]
        if name == "f":
            s *= problem.s0.K[0, 0]
        out[name] = float(s)
    return _Fit(state=st, std=out, rms_px=float(np.sqrt(np.mean(r[:n_e] ** 2))),
                rms_per_frame=problem.edge_rms_per_frame(r), residuals=r, problem=problem)


def _param_std(J: np.ndarray, s2: float) -> np.ndarray:
    """1-sigma of each parameter from ``s2 (J^T J)^-1``; inf where singular."""
    norms = np.linalg.norm(J, axis=0)
    norms[norms == 0] = 1.0
    Js = J / norms
    M = np.einsum("ij,ik->jk", Js, Js, optimize=False)
    try:
        w, V = np.linalg.eigh(M)
    except np.linalg.LinAlgError:
        return np.full(J.shape[1], np.inf)
    if w[0] <= w[-1] * 1e-14:
        w = np.where(w <= w[-1] * 1e-14, w[-1] * 1e-14, w)
    cov_s = (V / w) @ V.T
    return np.sqrt(np.maximum(np.diag(cov_s), 0.0) * s2) / norms


def _fit(frames: list[_FrameEdges], state: _State, model: str, free_intr: tuple[str, ...], free_stroke: bool,
         **kw) -> _Fit:
    """Robust fit (soft L1, 1 px), drop edge points beyond 5 robust sigmas, final least squares."""
    fit = _solve(_Problem(frames, state, free_intr, free_stroke, model, **kw), robust=True)
    r = fit.residuals
    n_e = int(fit.problem.row_start[-1])
    sigma = 1.4826 * float(np.median(np.abs(r[:n_e])))
    thr = max(5.0 * sigma, 0.5)
    kept = []
    for k, fe in enumerate(frames):
        rk = r[fit.problem.row_start[k]:fit.problem.row_start[k + 1]]
        keep = np.abs(rk) <= thr
        kept.append(fe if keep.all() else fe.select(keep))
    return _solve(_Problem(kept, fit.state, free_intr, free_stroke, model, **kw), robust=False)
