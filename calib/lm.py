"""Levenberg-Marquardt: the one non-linear least-squares solver of :mod:`calib`.

Both maximum-likelihood fits use it: the single view (:mod:`calib.refine`, 6 to
8 parameters, a dense Jacobian) and the whole sequence
(:mod:`calib.sequence_model`, a block-sparse Jacobian solved through the Schur
complement). A problem supplies its residuals and its normal equations in
whatever form suits it (:class:`LeastSquaresProblem`); this module owns the
cost, the damping and the stopping rule.

Cost, with the robust soft-L1 loss of scale ``c`` (pixels), or plain squares
when no scale is given::

    C(x) = sum_i 2 c^2 (sqrt(1 + (r_i / c)^2) - 1)        (c given)
    C(x) = sum_i r_i^2                                     (L2)

minimised by iteratively reweighted Gauss-Newton: at each linearisation the
rows get the weights ``w_i = 1 / sqrt(1 + (r_i / c)^2)`` (``w = 1`` for L2),
``A = J^T W J``, ``g = J^T W r``, and the step solves::

    (A + lam D) dx = -g,     D = max(diag(A), 1e-12 max(diag(A)))   (Marquardt's scaling)

Damping: ``lam`` starts at ``lam0`` (1e-3 by default; the single view, which starts at
a closed-form solution, takes 1e-6), is divided by 10 after an accepted
step (down to 1e-9) and multiplied by 10 after a rejected one (one that does not
lower ``C``, or a singular system); past 1e10 the solver stops.

Stopping (``rtol``): the Gauss-Newton model's predicted decrease
``-(2 g.dx + dx^T A dx) = -g.dx + lam dx^T D dx`` is at most ``rtol C``; or an
accepted step lowered ``C`` by less than ``rtol C``; or a rejected step raised it
by at most ``rtol C`` (the minimum, to rounding); or ``max_iter`` steps.

Uncertainty: after a plain least-squares fit, ``cov = s^2 (J^T J)^-1`` with
``s^2 = sum r^2 / (N - p)`` (:attr:`LMResult.sigma2`, :func:`dense_covariance`);
a problem with a sparse Jacobian computes its own blocks of it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = [
    "LinearSystem",
    "LeastSquaresProblem",
    "DenseSystem",
    "LMIteration",
    "LMResult",
    "levenberg_marquardt",
    "robust_cost",
    "robust_weights",
    "dense_covariance",
]

LAMBDA_MIN = 1e-9
LAMBDA_MAX = 1e10
#: floor of the Marquardt scaling, relative to the largest diagonal entry of ``A``
DIAGONAL_FLOOR = 1e-12


class LinearSystem(Protocol):
    """The weighted normal equations ``A = J^T W J``, ``g = J^T W r`` at one point, in any storage.

    Vectors are flat, in the problem's parameter order: ``gradient`` (p,) is
    ``g``, ``diagonal()`` (p,) is ``diag(A)``, and ``solve(d)`` returns ``x``
    (p,) with ``(A + diag(d)) x = g`` (raises ``numpy.linalg.LinAlgError``
    when singular).
    """

    @property
    def gradient(self) -> np.ndarray: ...

    def diagonal(self) -> np.ndarray: ...

    def solve(self, damping: np.ndarray) -> np.ndarray: ...


class LeastSquaresProblem(Protocol):
    """What :func:`levenberg_marquardt` needs of a problem.

    ``residuals(x)`` (N,) pixels (non-finite where ``x`` is outside the valid
    region); ``normal_equations(x, r, weights)`` the system at ``x`` with row
    weights ``weights`` (N,) (``r = residuals(x)``, given to save a pass);
    ``accept(x)`` is called with every accepted point and returns the same
    point in the problem's parameters from then on (a problem that re-bases a
    local parametrisation, e.g. the plane normal's tangent coordinates, does it
    here; others return ``x``).
    """

    def residuals(self, x: np.ndarray) -> np.ndarray: ...

    def normal_equations(self, x: np.ndarray, r: np.ndarray, weights: np.ndarray) -> LinearSystem: ...

    def accept(self, x: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class DenseSystem:
    """:class:`LinearSystem` of a dense Jacobian ``J`` (N, p): ``A = J^T W J``, ``g = J^T W r`` formed directly.

    For a few parameters and thousands of rows the normal equations are far
    cheaper than a QR or SVD of ``J`` (``scipy.optimize.least_squares``); the
    problem keeps its columns of comparable size (it is then well conditioned).
    """

    A: np.ndarray
    gradient: np.ndarray

    @classmethod
    def from_jacobian(cls, J: np.ndarray, r: np.ndarray, weights: np.ndarray) -> DenseSystem:
        Jw = J * weights[:, None]
        return cls(A=J.T @ Jw, gradient=Jw.T @ r)

    def diagonal(self) -> np.ndarray:
        return np.diag(self.A).copy()

    def solve(self, damping: np.ndarray) -> np.ndarray:
        return np.linalg.solve(self.A + np.diag(damping), self.gradient)


@dataclass(frozen=True)
class LMIteration:
    """One progress report: ``iteration`` steps taken (0: the start), ``cost`` ``C(x)``, ``rows`` N;
    ``done`` on the last report of a solve."""

    iteration: int
    cost: float
    rows: int
    done: bool = False


@dataclass(frozen=True)
class LMResult:
    """Outcome of :func:`levenberg_marquardt`.

    Attributes
    ----------
    x : (p,) float64
        The solution, in the problem's parameters after its last ``accept``.
    residuals : (N,) float64
        ``r(x)``, pixels.
    cost : float
        ``C(x)`` (soft-L1 or squares), px^2.
    iterations : int
        Accepted steps.
    converged : bool
        Stopped by ``rtol``; False when ``max_iter`` steps were taken or the
        damping ran past its bound (no step lowers the cost).
    """

    x: np.ndarray
    residuals: np.ndarray
    cost: float
    iterations: int
    converged: bool

    @property
    def sigma2(self) -> float:
        """``s^2 = sum r^2 / max(N - p, 1)``, the residual variance (px^2) of a least-squares fit."""
        return _sum_sq(self.residuals) / max(len(self.residuals) - len(self.x), 1)


def _sum_sq(r: np.ndarray) -> float:
    """``sum(r**2)`` by numpy's pairwise sum: ``r @ r`` is BLAS's ddot, which splits a long vector over
    its threads, so the sum (and every std derived from it) would depend on their number."""
    return float(np.sum(r * r))


def robust_cost(r: np.ndarray, scale: float | None) -> float:
    """``C`` of residuals ``r`` (N,): soft-L1 of ``scale`` (> 0), or ``sum r^2`` when ``scale`` is None.

    Matches ``scipy.optimize.least_squares(loss="soft_l1", f_scale=scale)``'s cost times 2.
    """
    if scale is None:
        return _sum_sq(r)
    z = (r / scale) ** 2
    return float(np.sum(np.sqrt(1.0 + z) - 1.0)) * 2.0 * scale * scale


def robust_weights(r: np.ndarray, scale: float | None) -> np.ndarray:
    """IRLS row weights (N,) of the cost: ``1 / sqrt(1 + (r / scale)^2)``, or ones (L2)."""
    if scale is None:
        return np.ones_like(r)
    return 1.0 / np.sqrt(1.0 + (r / scale) ** 2)


def _cost_at(r: np.ndarray, scale: float | None) -> float:
    return robust_cost(r, scale) if np.all(np.isfinite(r)) else np.inf


def levenberg_marquardt(
    problem: LeastSquaresProblem,
    x0: np.ndarray,
    *,
    loss_scale: float | None,
    rtol: float = 1e-9,
    max_iter: int = 40,
    lam0: float = 1e-3,
    report: Callable[[LMIteration], None] | None = None,
) -> LMResult:
    """Minimise ``C(x)`` (module docstring) from ``x0`` (p,).

    Parameters
    ----------
    problem : LeastSquaresProblem
    x0 : (p,) float64
        Start; passed through ``problem.accept`` first.
    loss_scale : float or None
        Soft-L1 scale (pixels); None for plain least squares.
    rtol : float
        Relative cost change below which the solve stops.
    max_iter : int
        Most accepted steps.
    lam0 : float
        Initial damping.
    report : callable, optional
        Told the cost at the start, after every accepted step and at the end.

    Returns
    -------
    LMResult
    """
    x = problem.accept(np.array(x0, dtype=np.float64))
    r = problem.residuals(x)
    cost = _cost_at(r, loss_scale)
    lam = lam0
    steps, converged = 0, False

    def tell(done: bool = False) -> None:
        if report is not None:
            report(LMIteration(steps, cost, len(r), done))

    tell()
    while steps < max_iter and not converged:
        system = problem.normal_equations(x, r, robust_weights(r, loss_scale))
        g, d = system.gradient, system.diagonal()
        d = np.maximum(d, DIAGONAL_FLOOR * max(float(np.max(d, initial=0.0)), 1e-300))
        accepted = False
        while lam <= LAMBDA_MAX:
            try:
                dx = -system.solve(lam * d)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            predicted = -float(g @ dx) + lam * float(dx @ (d * dx))
            if predicted <= rtol * cost:
                converged = True  # the model promises nothing worth a step
                break
            r_new = problem.residuals(x + dx)
            cost_new = _cost_at(r_new, loss_scale)
            if cost_new < cost:
                accepted = True
                break
            if cost_new - cost <= rtol * cost:
                converged = True  # at the minimum, to rounding
                break
            lam *= 10.0
        if not accepted:
            break
        converged = cost - cost_new < rtol * cost
        x, r, cost = problem.accept(x + dx), r_new, cost_new
        lam = max(lam / 10.0, LAMBDA_MIN)
        steps += 1
        tell()
    tell(done=True)
    return LMResult(x=x, residuals=r, cost=cost, iterations=steps, converged=converged)


def dense_covariance(J: np.ndarray, sigma2: float) -> np.ndarray:
    """``sigma2 (J^T J)^-1`` (p, p) for a dense Jacobian ``J`` (N, p).

    Computed on the column-normalised ``J`` (unit diagonal of ``J^T J``) by an
    eigen-decomposition whose eigenvalues are floored at ``1e-14`` of the
    largest: an unconstrained parameter gets a huge variance, never a
    negative or NaN one. All-inf when the decomposition fails.
    """
    norms = np.linalg.norm(J, axis=0)
    norms[norms == 0] = 1.0
    Js = J / norms
    M = np.einsum("ij,ik->jk", Js, Js, optimize=False)
    try:
        w, V = np.linalg.eigh(M)
    except np.linalg.LinAlgError:
        return np.full((J.shape[1], J.shape[1]), np.inf)
    if w[0] <= w[-1] * 1e-14:
        w = np.where(w <= w[-1] * 1e-14, w[-1] * 1e-14, w)
    cov_s = (V / w) @ V.T
    return cov_s * sigma2 / np.outer(norms, norms)
