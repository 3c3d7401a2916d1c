"""Iterated (nonlinear) Gauss–Markov least squares on a whitened system.

The caller supplies ``evaluate(x) -> (e, A)``: the whitened residuals ``e = W (f(x) - l)``
(every row of unit a-priori variance; parameter priors/constraints appended as fictitious
observations ``(x_k - x_k0) / sigma_k``) and their Jacobian ``A = de/dx``. Each iteration
solves the linearised problem ``A dx ~ -e`` through the SVD of the column-equilibrated design
matrix (columns scaled to unit norm, so that parameters in radians, metres and 1/mm^4 are
comparable), optionally with Tikhonov regularisation whose weight comes from the L-curve or
GCV (:mod:`stereodem.sensor.estimation.regularize`), and halves the step while the weighted
sum of squares grows (a damped Gauss–Newton).

Convergence criterion (stated in every result): the largest correction, in units of the
parameter's own standard deviation, ``max_k |dx_k| / sigma_k`` with
``sigma_k = sqrt((A^T A)^-1_kk)``, falls below ``tolerance`` (default 1e-3).

Near-singular normal matrices (condition number of the equilibrated ``A^T A`` above
``max_condition``) raise :class:`stereodem.sensor.errors.SensorModelError` naming the condition
number and the parameters that cannot be separated (the largest components of the right
singular vector of the smallest singular value), unless regularisation was asked for.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereodem.sensor.errors import ConvergenceError, SensorModelError
from stereodem.sensor.estimation import regularize

__all__ = ["GaussMarkovSolution", "solve", "inseparable", "equilibrated_svd", "MAX_CONDITION"]

#: condition number of the equilibrated normal matrix above which the solution is refused
MAX_CONDITION = 1e12


@dataclass
class GaussMarkovSolution:
    """Result of :func:`solve` (all at the final parameters)."""

    x: np.ndarray            #: parameters
    e: np.ndarray            #: whitened residuals (m,)
    A: np.ndarray            #: whitened Jacobian (m, u)
    Qxx: np.ndarray          #: cofactor matrix of the parameters (u, u), (A^T A + R)^-1
    condition: float         #: condition number of the equilibrated A^T A
    iterations: int
    converged: bool
    max_correction: float    #: last max |dx_k| / sigma_k
    regularization: float    #: Tikhonov weight used (0: none)


def equilibrated_svd(A):
    """Column norms ``D`` of ``A`` and the thin SVD of ``A / D``."""
    D = np.linalg.norm(A, axis=0)
    D = np.where(D > 0, D, 1.0)
    U, s, Vt = np.linalg.svd(A / D, full_matrices=False)
    return D, U, s, Vt


def inseparable(Vt, s, names, *, share: float = 0.1):
    """Names of the parameters dominating the weakest direction (right singular vector of the
    smallest singular value), largest first."""
    v = Vt[-1] ** 2
    order = np.argsort(v)[::-1]
    return [names[k] for k in order if v[k] >= share]


def _condition(s):
    return float((s[0] / s[-1]) ** 2) if s[-1] > 0 else float("inf")


def solve(evaluate, x0, names, *, residual=None, max_iterations: int = 20,
          tolerance: float = 1e-3, regularization=None, max_condition: float = MAX_CONDITION,
          what: str = "adjustment") -> GaussMarkovSolution:
    """Damped Gauss–Newton on a whitened least-squares problem (see the module docstring).

    Parameters
    ----------
    evaluate : callable ``x -> (e, A)``
        Whitened residuals (m,) and Jacobian (m, u).
    x0 : array_like (u,)
        Initial parameters.
    names : list of str
        Parameter names (for messages).
    residual : callable ``x -> e``, optional
        Residuals only (cheaper line-search trials); default ``evaluate(x)[0]``.
    max_iterations : int
        0 evaluates the statistics at ``x0`` without iterating.
    tolerance : float
        Convergence when ``max |dx_k| / sigma_k < tolerance``.
    regularization : None, "lcurve", "gcv" or float
        Tikhonov weight on the equilibrated parameter corrections (chosen once, at the first
        iteration, for the string methods).

    Raises
    ------
    SensorModelError
        Non-finite residuals, a parameter without effect, a near-singular normal matrix.
    ConvergenceError
        No convergence within ``max_iterations``.
    """
    x = np.asarray(x0, dtype=np.float64).copy()
    residual = residual or (lambda z: evaluate(z)[0])
    e, A = evaluate(x)
    _check_finite(e, A, what)
    lam = 0.0
    it, converged, worst = 0, max_iterations == 0, 0.0
    while True:
        D, U, s, Vt = equilibrated_svd(A)
        zero = np.flatnonzero(np.linalg.norm(A, axis=0) == 0)
        if zero.size:
            raise SensorModelError(f"{what}: parameter(s) {', '.join(names[k] for k in zero)} "
                                   "have no effect on the observations")
        cond = _condition(s)
        if regularization is None and cond > max_condition:
            raise SensorModelError(
                f"{what}: near-singular normal matrix (condition number {cond:.3g}); cannot "
                f"separate {', '.join(inseparable(Vt, s, names)) or 'the parameters'} — free "
                "fewer parameters, add priors, or regularise")
        if regularization is not None and it == 0:
            lam = _weight(regularization, A / D, -e)
        filt = s / (s * s + lam * lam)
        Q = (Vt.T * filt ** 2) @ Vt / np.outer(D, D) if lam == 0 else \
            np.linalg.inv((A / D).T @ (A / D) + lam * lam * np.eye(len(x))) / np.outer(D, D)
        sigma = np.sqrt(np.maximum(np.diag(Q), 1e-300))
        if converged or it >= max_iterations:
            break
        dx = (Vt.T @ (filt * (U.T @ -e))) / D
        worst = float(np.max(np.abs(dx) / sigma))
        cost = float(e @ e)
        step, accepted = 1.0, False
        for _ in range(12):
            xn = x + step * dx
            en = residual(xn)
            if np.all(np.isfinite(en)) and float(en @ en) <= cost * (1 + 1e-9) + 1e-12:
                accepted = True
                break
            step *= 0.5
        it += 1
        if not accepted:   # no descent along the step: at the minimum to working precision
            converged = worst < 0.1
            if not converged:
                break
            continue
        x = xn
        e, A = evaluate(x)
        _check_finite(e, A, what)
        converged = worst < tolerance
    if not converged:
        raise ConvergenceError(
            f"{what}: no convergence in {it} iteration(s) (last correction {worst:.3g} sigma of "
            f"{names[int(np.argmax(np.abs(dx) / sigma))] if len(x) else '-'}; criterion "
            f"max |dx|/sigma < {tolerance:g}) — check the initial model and the points")
    return GaussMarkovSolution(x, e, A, Q, cond, it, True, worst, lam)


def _weight(method, A, b):
    if isinstance(method, str):
        if method == "lcurve":
            return float(regularize.lcurve_weight(A, b))
        if method == "gcv":
            return float(regularize.gcv_weight(A, b))
        raise SensorModelError(f"unknown regularisation {method!r} (lcurve, gcv or a weight)")
    lam = float(method)
    if not np.isfinite(lam) or lam < 0:
        raise SensorModelError(f"regularisation weight must be >= 0, got {method}")
    return lam


def _check_finite(e, A, what):
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(A))):
        raise SensorModelError(f"{what}: the model gives non-finite image coordinates or "
                               "derivatives at some points (outside its validity range?)")
