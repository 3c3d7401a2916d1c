"""Iterated (nonlinear) Gauss–Markov least squares on a whitened system.

The caller supplies ``evaluate(x) -> (e, A)``: the whitened residuals ``e = W (f(x) - l)``
(every row of unit a-priori variance; parameter priors/constraints appended as fictitious
observations ``(x_k - x_k0) / sigma_k``) and their Jacobian ``A = de/dx``. The minimisation is
:func:`scipy.optimize.least_squares` with ``method="lm"`` (Levenberg–Marquardt, MINPACK's
``lmder``; parameters scaled by the Jacobian's column norms, so that radians, metres and
1/mm^4 are comparable); Tikhonov
regularisation, with its weight from the L-curve or GCV
(:mod:`stereodem.sensor.estimation.regularize`), enters as fictitious observations
``lam D (x - x0) = 0`` on the equilibrated parameters. Statistics come from the SVD of the
column-equilibrated design matrix at the solution.

Convergence criterion (stated in every result), checked at the solution: the Gauss–Newton
correction still to be applied, in units of each parameter's own standard deviation,
``max_k |dx_k| / sigma_k`` with ``sigma_k = sqrt((A^T A)^-1_kk)``, is below ``tolerance``
(default 0.01: a hundredth of a standard deviation); up to five further Gauss–Newton steps
are taken to meet it. A correction below ``STATIONARY_SIGMA`` (0.1 sigma) that no longer
lowers the weighted sum of squares also counts as converged: in ill-conditioned problems the
precision of a finite-difference Jacobian limits how small the predicted correction can get.
Such a solution is accepted but reported as ``status="stalled"`` (``converged`` false, the last
correction in ``max_correction``), not as converged.

Near-singular normal matrices (condition number of the equilibrated ``A^T A`` above
``max_condition``) raise :class:`stereodem.core.errors.SensorModelError` naming the condition
number and the parameters that cannot be separated (the largest components of the right
singular vector of the smallest singular value), unless regularisation with a positive weight
was asked for (a weight of 0 is no regularisation). Every solve goes through SVDs of the
(regularised) equilibrated design matrix, never an inverse of the normal matrix, so a
rank-deficient parameter set with a positive Tikhonov weight has finite statistics; any
:class:`numpy.linalg.LinAlgError` that still arises (an SVD that does not converge, or the
model's own linear algebra) is raised as :class:`~stereodem.core.errors.SensorModelError`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from stereodem.core.errors import ConvergenceError, InputError, SensorModelError
from stereodem.sensor.estimation import regularize

__all__ = ["GaussMarkovSolution", "solve", "inseparable", "equilibrated_svd", "MAX_CONDITION"]

#: condition number of the equilibrated normal matrix above which the solution is refused
MAX_CONDITION = 1e12
#: a Gauss-Newton correction below this many sigma that does not lower the sum of squares any
#: more is accepted as convergence (the Jacobian's own precision limits ill-conditioned problems)
STATIONARY_SIGMA = 0.1


@dataclass
class GaussMarkovSolution:
    """Result of :func:`solve` (all at the final parameters)."""

    x: np.ndarray  #: parameters
    e: np.ndarray  #: whitened residuals (m,)
    A: np.ndarray  #: whitened Jacobian (m, u)
    Qxx: np.ndarray  #: cofactor matrix of the parameters (u, u), (A^T A + R)^-1
    condition: float  #: condition number of the equilibrated A^T A
    iterations: int
    converged: bool  #: the stated criterion max |dx_k| / sigma_k < tolerance was met
    max_correction: float  #: last max |dx_k| / sigma_k
    regularization: float  #: Tikhonov weight used (0: none)
    #: "converged", or "stalled": the line search could no longer lower the sum of squares
    #: with a correction below STATIONARY_SIGMA (accepted, but the criterion was not met)
    status: str = "converged"


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


#: the most iterations an adjustment may be given (they converge in a few to a few tens;
#: 99999999999 overflowed MINPACK's C int in SciPy's least_squares)
MAX_ITERATIONS = 10_000


def check_max_iterations(value) -> int:
    """``value`` as a number of iterations: a whole number from 0 to :data:`MAX_ITERATIONS`
    (0: the statistics of the initial parameters, nothing estimated), else
    :class:`InputError` naming it (``--max-iterations -1`` was taken: one unchecked
    Gauss-Newton step, reported as an adjustment)."""
    try:
        n = int(value)
    except (TypeError, ValueError, OverflowError):
        n = -1
    if not 0 <= n <= MAX_ITERATIONS or n != value:
        raise InputError(
            f"max_iterations must be a whole number from 0 to {MAX_ITERATIONS} (0: the "
            f"initial model's statistics, nothing estimated), got {value}"
        )
    return n


def solve(
    evaluate,
    x0,
    names,
    *,
    residual=None,
    max_iterations: int = 20,
    tolerance: float = 1e-2,
    regularization=None,
    max_condition: float = MAX_CONDITION,
    what: str = "adjustment",
) -> GaussMarkovSolution:
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
        Non-finite residuals, a parameter without effect, a near-singular normal matrix
        (without a positive regularisation weight), a failed SVD or model linear algebra.
    ConvergenceError
        No convergence within ``max_iterations``.
    """
    max_iterations = check_max_iterations(max_iterations)
    try:
        return _solve(
            evaluate,
            x0,
            names,
            residual=residual,
            max_iterations=max_iterations,
            tolerance=tolerance,
            regularization=regularization,
            max_condition=max_condition,
            what=what,
        )
    except np.linalg.LinAlgError as exc:
        raise SensorModelError(
            f"{what}: linear algebra failed ({exc}) with parameters {', '.join(names)} — the set "
            "is probably rank-deficient: free fewer parameters, add priors, or regularise"
        ) from None


def _solve(
    evaluate, x0, names, *, residual, max_iterations, tolerance, regularization, max_condition, what
) -> GaussMarkovSolution:
    x_ref = np.asarray(x0, dtype=np.float64).copy()
    residual = residual or (lambda z: evaluate(z)[0])
    e, A = evaluate(x_ref)
    _check_finite(e, A, what)
    zero = np.flatnonzero(np.linalg.norm(A, axis=0) == 0)
    if zero.size:
        raise SensorModelError(
            f"{what}: parameter(s) {', '.join(names[k] for k in zero)} "
            "have no effect on the observations"
        )
    D, U, s, Vt = equilibrated_svd(A)
    cond = _condition(s)
    lam, D_reg = 0.0, None
    if regularization is not None:
        lam = _weight(regularization, A / D, -e)
        if lam > 0:  # a zero weight is no regularisation: the condition check applies
            D_reg = D.copy()
    if D_reg is None and cond > max_condition:
        raise SensorModelError(
            f"{what}: near-singular normal matrix (condition number {cond:.3g}"
            + (f", regularisation weight {lam:g}" if regularization is not None else "")
            + f"); cannot separate {', '.join(inseparable(Vt, s, names)) or 'the parameters'} — "
            "free fewer parameters, add priors, or regularise"
        )

    # Tikhonov as fictitious observations lam * D (x - x0) = 0 (equilibrated units)
    def fun(z):
        r = residual(z)
        return r if D_reg is None else np.concatenate([r, lam * D_reg * (z - x_ref)])

    def jac(z):
        _, J = evaluate(z)
        return J if D_reg is None else np.vstack([J, lam * np.diag(D_reg)])

    x, iterations = x_ref.copy(), 0
    if max_iterations > 0:
        with np.errstate(all="ignore"):
            try:
                sol = least_squares(
                    fun,
                    x_ref,
                    jac=jac,
                    method="lm",
                    x_scale="jac",
                    xtol=1e-10,
                    ftol=1e-12,
                    gtol=1e-12,
                    max_nfev=4 * max_iterations + 10,
                )
            except ValueError as exc:  # residuals not finite at the start
                raise SensorModelError(f"{what}: {exc}") from None
        x, iterations = sol.x, int(sol.njev or sol.nfev)

    # the stated criterion, checked at the solution with Gauss-Newton steps
    worst, dx, stationary = np.inf, np.zeros_like(x), False
    for _ in range(6 if max_iterations > 0 else 1):
        e, A = evaluate(x)
        _check_finite(e, A, what)
        Ab = A if D_reg is None else np.vstack([A, lam * np.diag(D_reg)])
        eb = e if D_reg is None else np.concatenate([e, lam * D_reg * (x - x_ref)])
        D, U, s, Vt = equilibrated_svd(Ab)
        cond = _condition(equilibrated_svd(A)[2]) if D_reg is not None else _condition(s)
        Q = (Vt.T / s**2) @ Vt / np.outer(D, D)
        sigma = np.sqrt(np.maximum(np.diag(Q), 1e-300))
        dx = (Vt.T @ ((U.T @ -eb) / s)) / D
        worst = float(np.max(np.abs(dx) / sigma))
        if max_iterations == 0 or worst < tolerance:
            break
        xn = x + dx
        en = fun(xn)
        if not (np.all(np.isfinite(en)) and float(en @ en) <= float(eb @ eb) * (1 + 1e-9)):
            # the correction no longer lowers the weighted sum of squares: stationary to the
            # precision of the (finite-difference) Jacobian
            stationary = worst < STATIONARY_SIGMA
            break
        x, iterations = xn, iterations + 1
    converged = max_iterations == 0 or worst < tolerance
    if not (converged or stationary):
        raise ConvergenceError(
            f"{what}: no convergence in {iterations} iteration(s) (last correction {worst:.3g} "
            f"sigma of {names[int(np.argmax(np.abs(dx) / sigma))]}; criterion "
            f"max |dx|/sigma < {tolerance:g}; condition number {cond:.3g}"
            + (f", weakly separable: {', '.join(inseparable(Vt, s, names))}" if cond > 1e8 else "")
            + ") — check the initial model and the points, or free fewer parameters"
        )
    return GaussMarkovSolution(
        x, e, A, Q, cond, iterations, converged, worst, lam, "converged" if converged else "stalled"
    )


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
        raise SensorModelError(
            f"{what}: the model gives non-finite image coordinates or "
            "derivatives at some points (outside its validity range?)"
        )
