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
``K, dist`` (:func:`calib.distortion.undistort_px`), all frames' points in one
vectorised pass (each point with its frame's plane); for a turntable, one row per
frame whose marks were read: the yaw between the model's pose and the marks'
pose, scaled to pixels by ``noise_px / std``. Solved by Levenberg-Marquardt
(:func:`calib.lm.levenberg_marquardt`) on the normal equations, which are block sparse: a frame's rows (its edge points
and its mark row) touch the ``g`` global parameters and its own ``l`` (0, 1 or
5) only, so with ``J_k = [G_k | L_k]``::

    [ U    W ] [dx_g]   [b_g]      U = sum_k G_k^T G_k   (g, g)
    [ W^T  V ] [dx_l] = [b_l]      W_k = G_k^T L_k (g, l),  V = diag(V_k),  V_k = L_k^T L_k (l, l)

is solved through the Schur complement over the per-frame blocks,
``(U - sum_k W_k V_k^-1 W_k^T) dx_g = b_g - sum_k W_k V_k^-1 b_k``, then
``dx_k = V_k^-1 (b_k - W_k^T dx_g)``: time and memory linear in the frames
(a dense ``J`` and ``J^T J`` grow with their square, the solve with their cube).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np

from .camera import make_T
from .distortion import undistort_px
from .lm import LMIteration, dense_covariance, levenberg_marquardt
from .refine import edge_geometry
from .types import CalibrationError, TargetObservation

__all__ = [
    "rot_y",
    "exp_so3",
    "yaw_of",
    "project_rotation",
    "wrap_angle",
    "FrameEdges",
    "FitState",
    "JointProblem",
    "BlockJacobian",
    "JointFit",
    "FitStep",
    "FitReport",
    "fit_joint",
    "solve_joint",
    "global_std",
    "dense_jacobian",
    "param_std",
    "ROBUST_SCALE_PX",
]

#: soft-L1 scale (px) of the robust stage of the joint fit
ROBUST_SCALE_PX = 1.0


# --------------------------------------------------------------------------- small geometry
def rot_y(theta: float) -> np.ndarray:
    """Right-handed rotation (3, 3) by ``theta`` radians about +Y."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) of the rotation vector ``w`` (3,) radians (Rodrigues)."""
    th = float(np.linalg.norm(w))
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-12:
        return np.eye(3) + W
    return np.eye(3) + math.sin(th) / th * W + (1.0 - math.cos(th)) / th**2 * (W @ W)


def yaw_of(R: np.ndarray) -> float:
    """Angle (rad) of the rotation about +Y closest to ``R`` (3, 3)."""
    return math.atan2(R[0, 2] - R[2, 0], R[0, 0] + R[2, 2])


def project_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) nearest ``M`` (3, 3) in the Frobenius norm (SVD, determinant +1)."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def wrap_angle(a: np.ndarray | float):
    """Angles (radians, any shape) wrapped into ``[-pi, pi)``."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# --------------------------------------------------------------------------- edge data
@dataclass(frozen=True)
class FrameEdges:
    """Edge points of one frame, packed for the joint fit's vectorised residuals.

    ``uv_px`` (N, 2) raw (distorted) pixels; ``groups``: one ``(rows slice, ring_radius_mm, side)``
    per edge set. :meth:`from_observation` keeps at most ``max_per_edge`` points per edge, evenly.
    """

    uv_px: np.ndarray  # (N, 2) raw (distorted) pixels
    groups: tuple  # ((slice, ring_radius_mm, side), ...)

    @classmethod
    def from_observation(cls, obs: TargetObservation, max_per_edge: int) -> FrameEdges:
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

    def select(self, keep: np.ndarray) -> FrameEdges:
        uvs, groups, n = [], [], 0
        for sl, r, side in self.groups:
            uv = self.uv_px[sl][keep[sl]]
            if len(uv) < 5:
                continue
            uvs.append(uv)
            groups.append((slice(n, n + len(uv)), r, side))
            n += len(uv)
        return FrameEdges(np.concatenate(uvs), tuple(groups))

    @property
    def has_stroke(self) -> bool:
        return any(side != 0 for _, _, side in self.groups)


# --------------------------------------------------------------------------- the problem
_INTR_NAMES = ("f", "cx", "cy", "k1", "k2")


@dataclass
class FitState:
    """Everything the joint fit estimates, in plain arrays (mm, radians).

    ``K`` (3, 3), ``dist`` (5,) OpenCV coefficients, ``stroke`` mm; a turntable's
    ``R_cam_axis`` (3, 3), ``t_cam_axis`` (3,), ``d_xz`` (2,) the pattern's offset from the
    axis and ``theta`` (n,) each frame's angle; or a hand-held sequence's per-frame ``R``, ``t``.
    """

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
            assert self.t is not None  # handheld: R and t are set together
            return [make_T(R, t) for R, t in zip(self.R, self.t, strict=True)]
        assert self.theta is not None and self.d_xz is not None  # turntable
        Ts = []
        for th in self.theta:
            R = self.R_cam_axis @ rot_y(th)
            Ts.append(make_T(R, R @ np.array([self.d_xz[0], 0.0, self.d_xz[1]]) + self.t_cam_axis))
        return Ts


class JointProblem:
    """The joint fit as a :class:`calib.lm.LeastSquaresProblem`: parameter packing (relative to the
    state ``state``), residuals and a block-sparse finite-difference Jacobian.

    Global parameters (free intrinsics, stroke, turntable geometry) touch every
    frame; local ones (theta_k, or a handheld frame's 5) touch one frame, so
    the Jacobian costs ``n_global + max(n_local) + 1`` evaluations of all rows.
    Parameters are ordered globals first, then each frame's locals in frame
    order (frame ``k``'s from ``local_start[k]``).
    """

    def __init__(self, frames: list[FrameEdges], state: FitState, free_intr: tuple[str, ...],
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
        self.has_mark = np.array([m is not None and w > 0 for m, w in zip(self.mark_R, self.mark_w, strict=True)])
        self.n_rows = int(self.row_start[-1] + self.has_mark.sum())
        self.mark_row = np.full(len(frames), -1)  # each frame's mark row, -1 where it has none
        self.mark_row[self.has_mark] = self.row_start[-1] + np.arange(self.has_mark.sum())
        # every frame's edge points stacked: raw pixels, ring radius, side, frame of each row
        self.uv_px = np.concatenate([f.uv_px for f in frames])
        self.ring_mm = np.concatenate([np.full(sl.stop - sl.start, r) for f in frames for sl, r, _ in f.groups])
        self.side = np.concatenate([np.full(sl.stop - sl.start, float(sd)) for f in frames for sl, _, sd in f.groups])
        self.row_frame = np.repeat(np.arange(len(frames)), self.n_edge)
        self.mark_frames = np.flatnonzero(self.has_mark)
        self.mark_R_stack = np.array([self.mark_R[k] for k in self.mark_frames]).reshape(-1, 3, 3)
        # (key, uv): the last K, dist's undistorted points
        self._undistorted: tuple[tuple[bytes, bytes] | None, np.ndarray | None] = (None, None)

    # -- packing ------------------------------------------------------------
    def unpack(self, x: np.ndarray) -> FitState:
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
        st = FitState(K=K, dist=dist, stroke=stroke)
        if self.model == "turntable":
            assert s0.R_cam_axis is not None and s0.theta is not None
            R0 = s0.R_cam_axis
            w = x[i] * R0[:, 0] + x[i + 1] * R0[:, 2]
            i += 2
            if self.free_yaw:
                w = w + x[i] * R0[:, 1]
                i += 1
            st.R_cam_axis = exp_so3(w) @ R0
            st.t_cam_axis = s0.t_cam_axis + x[i:i + 3]
            st.d_xz = s0.d_xz + x[i + 3:i + 5]
            theta = s0.theta.copy()
            idx = np.flatnonzero(self.free_theta)
            theta[idx] += x[self.local_start[idx]]
            st.theta = theta
        else:
            assert s0.R is not None and s0.t is not None
            st.R, st.t = [], []
            for k in range(len(self.frames)):
                j = self.local_start[k]
                st.R.append(s0.R[k] @ exp_so3(np.array([x[j], 0.0, x[j + 1]])))
                st.t.append(s0.t[k] + x[j + 2:j + 5])
        return st

    def _poses(self, st: FitState) -> np.ndarray:
        """Every frame's ``T_cam_table`` (n, 4, 4) of a full state."""
        if st.R is not None:
            return np.array(st.poses()).reshape(-1, 4, 4)
        assert st.theta is not None and st.R_cam_axis is not None and st.d_xz is not None  # turntable
        c, s = np.cos(st.theta), np.sin(st.theta)
        Ry = np.zeros((len(st.theta), 3, 3))
        Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 1, 1], Ry[:, 2, 0], Ry[:, 2, 2] = c, s, 1.0, -s, c
        Ts = np.zeros((len(st.theta), 4, 4))
        Ts[:, :3, :3] = np.einsum("ij,kjl->kil", st.R_cam_axis, Ry, optimize=False)
        d = np.array([st.d_xz[0], 0.0, st.d_xz[1]])
        Ts[:, :3, 3] = np.einsum("kij,j->ki", Ts[:, :3, :3], d, optimize=False) + st.t_cam_axis
        Ts[:, 3, 3] = 1.0
        return Ts

    def _undistort(self, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
        if not np.any(dist):
            return self.uv_px
        key = (K.tobytes(), dist.tobytes())
        if self._undistorted[0] != key:
            self._undistorted = (key, undistort_px(self.uv_px, K, dist))
        return cast(np.ndarray, self._undistorted[1])  # set for this key just above

    # -- residuals ----------------------------------------------------------
    def mark_residual(self, k: int, R_model: np.ndarray) -> float:
        """Frame ``k``'s mark row: the yaw (rad) between ``R_model`` (3, 3) and the marks', times its weight."""
        return self.mark_w[k] * yaw_of(R_model.T @ self.mark_R[k])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """All rows (n_rows,): every frame's edge residuals (px) in frame order, then the mark rows."""
        st = self.unpack(x)
        Ts = self._poses(st)
        uv = self._undistort(st.K, st.dist)
        n_e = int(self.row_start[-1])
        out = np.empty(self.n_rows)
        n, t = Ts[:, :3, 1][self.row_frame], Ts[:, :3, 3][self.row_frame]  # each row's plane normal, centre
        geo = edge_geometry(st.K[0, 0], st.K[0, 2], st.K[1, 2], n, t, uv)
        out[:n_e] = (geo.rho - (self.ring_mm + 0.5 * self.side * st.stroke)) / geo.g
        mk = self.mark_frames
        M = np.einsum("kji,kjl->kil", Ts[mk, :3, :3], self.mark_R_stack, optimize=False)  # R_model^T R_marks
        out[n_e:] = self.mark_w[mk] * np.arctan2(M[:, 0, 2] - M[:, 2, 0], M[:, 0, 0] + M[:, 2, 2])
        return out

    def jacobian(self, x: np.ndarray) -> BlockJacobian:
        """Forward differences, block by block.

        A frame's rows depend on the global parameters and its own only, so
        the ``c``-th local parameter of every frame is stepped at once and
        one evaluation gives that column of every frame's block: the Jacobian
        costs ``n_global + max(n_local) + 1`` evaluations of all rows.

        Not the analytic ``calib.refine.edge_linearisation``: it freezes the
        residual's weight ``1 / |grad rho|``, and Gauss-Newton then converges
        where ``J~^T r = 0``, which is biased by ``sum e^2 d log|grad rho| / dp``:
        with k1, k2 and the principal point free that moved the principal point
        by ~15 px and f by ~1 % at 0.15 px noise (exact differences: 0.6 px, 0.09 %).
        """
        n_l = int(self.n_local.max(initial=0))
        J = BlockJacobian(glob=np.zeros((self.n_rows, self.n_global)), local=np.zeros((self.n_rows, n_l)))
        r0 = self.residuals(x)
        for j in range(self.n_global):
            h = 1e-6 * max(1.0, abs(x[j]))
            xp = x.copy()
            xp[j] += h
            J.glob[:, j] = (self.residuals(xp) - r0) / h
        for c in range(n_l):
            frames = np.flatnonzero(self.n_local > c)
            cols = self.local_start[frames] + c
            h = np.zeros(len(self.frames))
            h[frames] = 1e-6 * np.maximum(1.0, np.abs(x[cols]))
            xp = x.copy()
            xp[cols] += h[frames]
            r = self.residuals(xp)
            rows = np.concatenate([np.flatnonzero(h[self.row_frame] > 0),
                                   self.mark_row[frames[self.has_mark[frames]]]]).astype(int)
            J.local[rows, c] = (r[rows] - r0[rows]) / h[np.concatenate([self.row_frame, self.mark_frames])[rows]]
        return J

    # -- calib.lm.LeastSquaresProblem ------------------------------------------
    def normal_equations(self, x: np.ndarray, r: np.ndarray, weights: np.ndarray) -> _BlockSystem:
        """The blocked ``J^T W J``, ``J^T W r`` at ``x`` (forward-difference Jacobian), row weights ``weights``."""
        return _BlockSystem(_normal_equations(self, self.jacobian(x), np.sqrt(weights), r))

    def accept(self, x: np.ndarray) -> np.ndarray:
        return x

    def edge_rms_per_frame(self, r: np.ndarray) -> np.ndarray:
        return np.array([np.sqrt(np.mean(r[self.row_start[k]:self.row_start[k + 1]] ** 2))
                         for k in range(len(self.frames))])


@dataclass(frozen=True)
class BlockJacobian:
    """The Jacobian (n_rows, n_params) in its block-sparse form, memory linear in the frames.

    ``glob`` (n_rows, n_global): every row's derivatives by the global
    parameters; ``local`` (n_rows, n_l), ``n_l = max(n_local)``: each row's by
    its own frame's parameters (column ``c`` is parameter ``local_start[k] + c``
    for a row of frame ``k``; zero for ``c >= n_local[k]``). Each other entry of
    the dense Jacobian is zero.
    """

    glob: np.ndarray
    local: np.ndarray


@dataclass(frozen=True)
class _Normal:
    """The normal equations ``J^T J dx = J^T r`` in blocks (see the module docstring).

    ``U`` (g, g), ``b_g`` (g,); per frame ``W`` (n, g, l), ``V`` (n, l, l),
    ``b_l`` (n, l), padded with zeros past each frame's ``n_local`` (``pad``
    (n, l) bool marks the padding).
    """

    U: np.ndarray
    b_g: np.ndarray
    W: np.ndarray
    V: np.ndarray
    b_l: np.ndarray
    pad: np.ndarray

    def diagonal(self) -> tuple[np.ndarray, np.ndarray]:
        """``diag(J^T J)``: the global part (g,) and the local part (n, l), 0 on the padding."""
        return np.diagonal(self.U).copy(), np.diagonal(self.V, axis1=1, axis2=2).copy()


def _normal_equations(problem: JointProblem, J: BlockJacobian, w: np.ndarray, r: np.ndarray) -> _Normal:
    """``(Jw)^T Jw`` and ``(Jw)^T (w r)`` in blocks, for row weights ``w`` (n_rows,) and residuals ``r``.

    Per-frame products of a few hundred rows by a few columns (``einsum``
    without BLAS: multithreaded BLAS oversubscribes busy machines badly).
    """
    G, L, rw = J.glob * w[:, None], J.local * w[:, None], w * r
    n, g, l = len(problem.frames), problem.n_global, L.shape[1]
    U = np.einsum("ij,ik->jk", G, G, optimize=False)
    b_g = np.einsum("ij,i->j", G, rw, optimize=False)
    W, V, b_l = np.zeros((n, g, l)), np.zeros((n, l, l)), np.zeros((n, l))
    if l:
        for k in range(n):
            rows = slice(problem.row_start[k], problem.row_start[k + 1])
            W[k] = np.einsum("ij,ik->jk", G[rows], L[rows], optimize=False)
            V[k] = np.einsum("ij,ik->jk", L[rows], L[rows], optimize=False)
            b_l[k] = np.einsum("ij,i->j", L[rows], rw[rows], optimize=False)
        mk = np.flatnonzero(problem.has_mark)  # one mark row per such frame
        m = problem.mark_row[mk]
        W[mk] += G[m][:, :, None] * L[m][:, None, :]
        V[mk] += L[m][:, :, None] * L[m][:, None, :]
        b_l[mk] += L[m] * rw[m][:, None]
    pad = np.arange(l)[None, :] >= problem.n_local[:, None]
    return _Normal(U=U, b_g=b_g, W=W, V=V, b_l=b_l, pad=pad)


def _schur_solve(N: _Normal, d_g: np.ndarray, d_l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``(J^T J + diag(d)) x = b`` by the Schur complement over the frames' blocks.

    ``d_g`` (g,) and ``d_l`` (n, l) are added to the diagonal (the padding's
    diagonal is set to 1, its ``b`` is 0, so its ``x`` is 0). Returns ``(x_g
    (g,), x_l (n, l))``; raises ``LinAlgError`` when a block or the reduced
    system is singular.
    """
    l = N.V.shape[1]
    Vd = N.V.copy()
    i = np.arange(l)
    Vd[:, i, i] += np.where(N.pad, 1.0, d_l)
    Vinv = np.linalg.inv(Vd) if l else Vd
    WVinv = np.einsum("kgl,klm->kgm", N.W, Vinv, optimize=False)  # (n, g, l)
    S = N.U + np.diag(d_g) - np.einsum("kgl,khl->gh", WVinv, N.W, optimize=False)
    x_g = np.linalg.solve(S, N.b_g - np.einsum("kgl,kl->g", WVinv, N.b_l, optimize=False))
    x_l = np.einsum("klm,km->kl", Vinv, N.b_l - np.einsum("kgl,g->kl", N.W, x_g, optimize=False), optimize=False)
    return x_g, x_l


@dataclass(frozen=True)
class FitStep:
    """One report of the joint fit, for progress displays (:func:`calib.sequence.calibrate_sequence`).

    ``stage``: which least-squares problem (e.g. "turntable, robust"); ``iteration``:
    Levenberg-Marquardt steps taken (0: the starting point); ``cost``: the
    sum of squared (soft-L1 when robust) residuals, px^2; ``rms_px``:
    ``sqrt(cost / rows)``; ``done``: the stage's last report.
    """

    stage: str
    iteration: int
    cost: float
    rms_px: float
    done: bool = False


#: ``report(step)``: called at each Levenberg-Marquardt iteration of each stage of the joint fit.
FitReport = Callable[[FitStep], None]


@dataclass(frozen=True)
class JointFit:
    """One solve of a :class:`JointProblem` (:func:`solve_joint`): the estimated ``state``, 1-sigma
    ``std`` by parameter name (intrinsics "f" in px, "cx", "cy", "k1", "k2", "stroke" mm), the edge
    RMS (px) overall and per frame, all ``residuals`` (n_rows,) and the ``problem`` solved."""

    state: FitState
    std: dict  # parameter name -> 1 sigma (intrinsics, stroke)
    rms_px: float
    rms_per_frame: np.ndarray
    residuals: np.ndarray
    problem: JointProblem


@dataclass(frozen=True)
class _BlockSystem:
    """:class:`calib.lm.LinearSystem` of the blocked normal equations: flat vectors in parameter order
    (globals, then each frame's locals), solved by :func:`_schur_solve`."""

    N: _Normal

    @property
    def gradient(self) -> np.ndarray:
        return np.concatenate([self.N.b_g, self.N.b_l[~self.N.pad]])

    def diagonal(self) -> np.ndarray:
        dg, dl = self.N.diagonal()
        return np.concatenate([dg, dl[~self.N.pad]])

    def solve(self, damping: np.ndarray) -> np.ndarray:
        g = len(self.N.b_g)
        d_l = np.zeros(self.N.pad.shape)
        d_l[~self.N.pad] = damping[g:]
        x_g, x_l = _schur_solve(self.N, damping[:g], d_l)
        return np.concatenate([x_g, x_l[~self.N.pad]])


def solve_joint(problem: JointProblem, robust: bool, report: FitReport | None = None, stage: str = "") -> JointFit:
    """Solve ``problem`` from its state (:func:`calib.lm.levenberg_marquardt`; soft-L1 of
    ``ROBUST_SCALE_PX`` when ``robust``, else least squares) and the global parameters' 1-sigma
    (:func:`global_std`). ``report`` is told every iteration, as ``stage``."""
    label = f"{stage}, robust" if robust and stage else stage

    def tell(it: LMIteration) -> None:
        if report is not None:
            report(FitStep(label, it.iteration, it.cost, math.sqrt(it.cost / max(it.rows, 1)), it.done))

    sol = levenberg_marquardt(problem, np.zeros(problem.n_params), loss_scale=ROBUST_SCALE_PX if robust else None,
                              rtol=1e-9, max_iter=40, report=tell)
    x, r = sol.x, sol.residuals
    J = problem.jacobian(x)
    n_e = int(problem.row_start[-1])
    std = global_std(problem, J, sol.sigma2)
    names = list(problem.free_intr) + (["stroke"] if problem.free_stroke else [])
    st = problem.unpack(x)
    out = {}
    for i, name in enumerate(names):
        s = std[i]
        if name == "f":
            s *= problem.s0.K[0, 0]
        out[name] = float(s)
    return JointFit(state=st, std=out, rms_px=float(np.sqrt(np.mean(r[:n_e] ** 2))),
                rms_per_frame=problem.edge_rms_per_frame(r), residuals=r, problem=problem)


#: below this eigenvalue of a (column-normalised) block, the covariance is taken from the whole matrix
_SCHUR_MIN_EIG = 1e-10


def global_std(problem: JointProblem, J: BlockJacobian, s2: float) -> np.ndarray:
    """1-sigma (n_global,) of the global parameters from ``s2 (J^T J)^-1``; inf where singular.

    On the column-normalised ``M = Js^T Js`` (unit diagonal): the global block
    of ``M^-1`` is the inverse of its Schur complement over the frames'
    blocks. Where a block or that complement is near singular (an
    unconstrained parameter) the whole ``M`` is assembled and its
    eigenvalues clamped, as :func:`param_std` does (memory ``n_params^2``).
    """
    N = _normal_equations(problem, J, np.ones(problem.n_rows), np.zeros(problem.n_rows))
    dg, dl = N.diagonal()
    ng, nl = np.sqrt(dg), np.sqrt(dl)
    ng[ng == 0] = 1.0
    nl[nl == 0] = 1.0
    U = N.U / np.outer(ng, ng)
    W = N.W / (ng[None, :, None] * nl[:, None, :])
    V = N.V / (nl[:, :, None] * nl[:, None, :])
    l = V.shape[1]
    V[:, np.arange(l), np.arange(l)] += N.pad  # padding: identity, no coupling
    try:
        ok = l == 0 or np.linalg.eigvalsh(V).min() > _SCHUR_MIN_EIG
        if ok:
            WVinv = np.einsum("kgl,klm->kgm", W, np.linalg.inv(V) if l else V, optimize=False)
            S = U - np.einsum("kgl,khl->gh", WVinv, W, optimize=False)
            e, Q = np.linalg.eigh(S)
            ok = e[0] > _SCHUR_MIN_EIG
    except np.linalg.LinAlgError:
        ok = False
    if not ok:
        return param_std(dense_jacobian(problem, J), s2)[:problem.n_global]
    cov = (Q / e) @ Q.T
    return np.sqrt(np.maximum(np.diag(cov), 0.0) * s2) / ng


def dense_jacobian(problem: JointProblem, J: BlockJacobian) -> np.ndarray:
    """The dense Jacobian (n_rows, n_params) of a blocked one (memory ``n_rows * n_params``: fallback only)."""
    D = np.zeros((problem.n_rows, problem.n_params))
    D[:, :problem.n_global] = J.glob
    for k in range(len(problem.frames)):
        cols = slice(problem.local_start[k], problem.local_start[k] + problem.n_local[k])
        for rows in (slice(problem.row_start[k], problem.row_start[k + 1]),
                     slice(problem.mark_row[k], problem.mark_row[k] + 1) if problem.has_mark[k] else slice(0, 0)):
            D[rows, cols] = J.local[rows, :problem.n_local[k]]
    return D


def param_std(J: np.ndarray, s2: float) -> np.ndarray:
    """1-sigma of each parameter from ``s2 (J^T J)^-1`` for a dense ``J`` (:func:`calib.lm.dense_covariance`)."""
    return np.sqrt(np.maximum(np.diag(dense_covariance(J, s2)), 0.0))


def fit_joint(frames: list[FrameEdges], state: FitState, model: str, free_intr: tuple[str, ...], free_stroke: bool,
              report: FitReport | None = None, **kw) -> JointFit:
    """Robust fit (soft L1, 1 px), drop edge points beyond 5 robust sigmas, final least squares."""
    fit = solve_joint(JointProblem(frames, state, free_intr, free_stroke, model, **kw), robust=True, report=report,
                      stage=model)
    r = fit.residuals
    n_e = int(fit.problem.row_start[-1])
    sigma = 1.4826 * float(np.median(np.abs(r[:n_e])))
    thr = max(5.0 * sigma, 0.5)
    kept = []
    for k, fe in enumerate(frames):
        rk = r[fit.problem.row_start[k]:fit.problem.row_start[k + 1]]
        keep = np.abs(rk) <= thr
        kept.append(fe if keep.all() else fe.select(keep))
    return solve_joint(JointProblem(kept, fit.state, free_intr, free_stroke, model, **kw), robust=False,
                       report=report, stage=model)
