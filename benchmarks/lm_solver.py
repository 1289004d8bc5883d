"""calib's Levenberg-Marquardt (:mod:`calib.lm`) against ``scipy.optimize.least_squares``: a markdown table.

Single-threaded BLAS: ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``,
``MKL_NUM_THREADS`` and ``VECLIB_MAXIMUM_THREADS`` are set to 1 by this script
before numpy is imported (threadpoolctl is not installed here), so neither
solver gains or loses from BLAS threads on a shared machine.

Two problems, both solvers given the same residual and Jacobian callables and
the same start:

* **single view**: the paper's view (f = 3000 px, R = 50 / 28 mm, 1280x960, as
  ``benchmarks/calib_noise.py``), 1000 centre-line points per ring, 0.5 px noise
  and 2 % gross outliers (+-5 px); parameters ``[f, a1, a2, t]`` (the normal
  ``N(n0 + a1 e1 + a2 e2)``), scaled as ``calib.refine`` scales them; residuals
  ``calib.refine.edge_residuals``, Jacobian from ``calib.refine.edge_linearisation``;
  ours solves the dense normal equations (:class:`calib.lm.DenseSystem`), damping from
  ``calib.refine.LM_LAMBDA0`` as ``refine_view`` does;
* **sequence**: a turntable of N frames (default 36), f = 750 px, 4 edges x 140
  points per frame, 0.15 px noise and 1 % outliers, marks on every frame, started
  1 % off in f, 1 mm off in t, 0.6 deg off in every angle;
  :class:`calib.sequence_model.JointProblem` with f and the stroke free (the
  joint fit's first stage); ours on the blocked normal equations (Schur
  complement), scipy on the dense Jacobian (:func:`calib.sequence_model.dense_jacobian`),
  ``tr_solver="exact"``; ours from the default damping 1e-3, as the joint fit.

Robust rows: soft-L1, scale 1 px (``loss="soft_l1", f_scale=1.0``; scipy
``method="trf"``, as ``"lm"`` takes no robust loss); L2 rows: ``"trf"`` and
``"lm"`` (MINPACK). Tolerances: ours ``rtol = 1e-9``; scipy ``ftol = 1e-9``,
``xtol`` and ``gtol`` at their default 1e-8. Times: best of ``--repeats``, the
two solvers run alternately. "cost rel. diff": ``(C_scipy - C_ours) / C_ours``
(C as :func:`calib.lm.robust_cost`, i.e. twice scipy's ``cost``); "max |dx| / sigma":
the largest parameter difference in units of its 1-sigma (``s^2 (J^T J)^-1`` at
our solution).

    nice .venv/bin/python benchmarks/lm_solver.py [--frames 36] [--repeats 7]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.camera import circle_points_table, look_at, make_T, project_points, rotation_from_normal  # noqa: E402
from calib.lm import DenseSystem, dense_covariance, levenberg_marquardt, robust_cost  # noqa: E402
from calib.refine import LM_LAMBDA0, edge_linearisation, edge_residuals  # noqa: E402
from calib.sequence_model import FitState, FrameEdges, JointProblem, dense_jacobian, rot_y  # noqa: E402
from calib.types import EdgePoints, TargetObservation  # noqa: E402

RTOL = 1e-9


def _noisy(uv, rng, sigma, outliers):
    uv = uv + rng.normal(0, sigma, uv.shape)
    bad = rng.random(len(uv)) < outliers
    uv[bad] += rng.uniform(-5, 5, (int(bad.sum()), 2))
    return uv


# --------------------------------------------------------------------------- the single view
class SingleView:
    """``x`` scaled like calib.refine: ``[f, a1, a2, t] = scale * x``; normal ``N(n0 + E a)``, no re-basing."""

    def __init__(self, rng):
        f, W, H = 3000.0, 1280, 960
        self.K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
        n = -np.array([-0.07, 0.93, 0.34])
        T = make_T(rotation_from_normal(n / np.linalg.norm(n)), [-4.3, 41.0, 750.0])
        self.edges = tuple(EdgePoints(_noisy(project_points(self.K, T, circle_points_table(R, 1000)), rng, 0.5,
                                             0.02), R, 0) for R in (50.0, 28.0))
        n0 = T[:3, 1] + np.radians(1.0) * np.array([0.3, 0.0, 0.95])  # 1 deg off
        self.n0 = n0 / np.linalg.norm(n0)
        a = np.array([1.0, 0.0, 0.0]) if abs(self.n0[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = np.cross(self.n0, a)
        e1 /= np.linalg.norm(e1)
        self.E = np.column_stack([e1, np.cross(self.n0, e1)])
        self.scale = np.concatenate([[0.01 * f, 0.01, 0.01], np.full(3, 0.01 * np.linalg.norm(T[:3, 3]))])
        self.x0 = np.concatenate([[1.02 * f, 0.0, 0.0], T[:3, 3] + [2.0, -2.0, 2.0]]) / self.scale

    def _pose(self, x):
        p = x * self.scale
        m = self.n0 + self.E @ p[1:3]
        K = self.K.copy()
        K[0, 0] = K[1, 1] = p[0]
        return K, make_T(rotation_from_normal(m / np.linalg.norm(m)), p[3:6]), np.linalg.norm(m)

    def residuals(self, x):
        K, T, _ = self._pose(x)
        return edge_residuals(K, T, 0.0, self.edges)

    def jacobian(self, x):
        K, T, norm_m = self._pose(x)
        L = edge_linearisation(K, T, 0.0, self.edges)
        J = np.column_stack([L.d_focal, L.d_normal @ self.E / norm_m, L.d_t])  # d_normal is tangent: no projection
        return J * self.scale

    def normal_equations(self, x, r, weights):
        return DenseSystem.from_jacobian(self.jacobian(x), r, weights)

    def accept(self, x):
        return x


# --------------------------------------------------------------------------- the sequence
def sequence_problem(rng, n_frames):
    K = np.array([[750.0, 0.0, 319.5], [0.0, 750.0, 239.5], [0.0, 0.0, 1.0]])
    T_ca = look_at(np.array([0.0, 225.0, -390.0]), np.zeros(3))
    d = np.array([2.0, 0.0, -1.5])
    theta = np.radians(np.arange(n_frames) * 360.0 / n_frames)
    frames = []
    for th in theta:
        T = T_ca @ make_T(rot_y(th), rot_y(th) @ d)
        edges = tuple(EdgePoints(_noisy(project_points(K, T, circle_points_table(r + s * 1.5, 140)), rng, 0.15, 0.01),
                                 r, s) for r in (80.0, 50.0) for s in (-1, 1))
        frames.append(FrameEdges.from_observation(TargetObservation(edges, 640, 480), 140))
    st = FitState(K=K * [[1.01], [1.01], [1]], dist=np.zeros(5), stroke=3.2, R_cam_axis=T_ca[:3, :3],
                  t_cam_axis=T_ca[:3, 3] + 1.0, d_xz=np.zeros(2), theta=theta + np.radians(0.6))
    mark_R = [T_ca[:3, :3] @ rot_y(th) for th in theta]
    return JointProblem(frames, st, ("f",), True, "turntable", free_theta=np.arange(n_frames) > 0,
                        free_yaw=True, mark_R=mark_R, mark_w=np.full(n_frames, 50.0))


class DenseJac:
    """scipy's view of a JointProblem: its residuals and its Jacobian made dense."""

    def __init__(self, p: JointProblem):
        self.p = p

    def residuals(self, x):
        return self.p.residuals(x)

    def jacobian(self, x):
        return dense_jacobian(self.p, self.p.jacobian(x))


# --------------------------------------------------------------------------- timing
def ours(problem, x0, loss, lam0):
    return levenberg_marquardt(problem, x0, loss_scale=loss, rtol=RTOL, max_iter=100, lam0=lam0)


def scipy_fit(fun, jac, x0, loss, method):
    kw = dict(loss="soft_l1", f_scale=loss) if loss is not None else {}
    if method == "trf":
        kw["tr_solver"] = "exact"
    return least_squares(fun, x0, jac=jac, method=method, ftol=RTOL, **kw)


def compare(label, problem, fun, jac, x0, loss, method, repeats, lam0):
    t_ours, t_scipy = [], []
    for _ in range(repeats):  # alternately, so that a busy moment hits both
        t0 = time.perf_counter()
        a = ours(problem, x0, loss, lam0)
        t1 = time.perf_counter()
        b = scipy_fit(fun, jac, x0, loss, method)
        t2 = time.perf_counter()
        t_ours.append(t1 - t0)
        t_scipy.append(t2 - t1)
    c_ours = robust_cost(fun(a.x), loss)
    c_scipy = robust_cost(fun(b.x), loss)
    J = jac(a.x)
    sigma = np.sqrt(np.maximum(np.diag(dense_covariance(J, a.sigma2)), 1e-300))
    dx = float(np.max(np.abs(a.x - b.x) / sigma))
    m, n = J.shape
    print(f"| {label} | {m} x {n} | {'soft_l1' if loss else 'L2'} | {method} | {1e3 * min(t_ours):.1f} "
          f"({a.iterations}) | {1e3 * min(t_scipy):.1f} ({b.nfev}/{b.njev}) | {min(t_scipy) / min(t_ours):.1f} | "
          f"{(c_scipy - c_ours) / c_ours:+.1e} | {dx:.1e} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=36)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    now = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    print(f"# calib.lm vs scipy.optimize.least_squares — {now}, {platform.machine()}, {os.cpu_count()} CPUs, "
          f"BLAS threads 1 (env), numpy {np.__version__}\n")
    print("| problem | rows x params | loss | scipy method | ours ms (steps) | scipy ms (nfev/njev) | "
          "scipy / ours | cost rel. diff | max |dx| / sigma |")
    print("|---|---|---|---|---|---|---|---|---|")
    sv = SingleView(np.random.default_rng(1))
    for loss, method in ((1.0, "trf"), (None, "trf"), (None, "lm")):
        compare("single view", sv, sv.residuals, sv.jacobian, sv.x0, loss, method, args.repeats, LM_LAMBDA0)
    jp = sequence_problem(np.random.default_rng(2), args.frames)
    dj = DenseJac(jp)
    x0 = np.zeros(jp.n_params)
    for loss, method in ((1.0, "trf"), (None, "trf"), (None, "lm")):
        compare(f"sequence, {args.frames} frames", jp, dj.residuals, dj.jacobian, x0, loss, method,
                max(2, args.repeats // 3), 1e-3)
    return 0


if __name__ == "__main__":
    sys.exit(main())
