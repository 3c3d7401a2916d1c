"""Tikhonov regularisation of linear least squares, and the choice of its weight.

For an over- or under-determined, ill-conditioned system ``A x ~ b`` the Tikhonov (ridge)
solution minimises

    ||A x - b||^2 + lam^2 ||x||^2,      x_lam = (A^T A + lam^2 I)^-1 A^T b,

(Bettemir 2006, §5.2, Eq. 5.20–5.23; Ok 2005, §6.2, who writes ``h`` for ``lam``). Everything
here works on the thin singular value decomposition ``A = U diag(s) V^T``, where the solution is
the filtered sum ``x_lam = sum_i f_i (u_i^T b / s_i) v_i`` with the Tikhonov filter factors
``f_i = s_i^2 / (s_i^2 + lam^2)`` (Hansen 1998, *Rank-Deficient and Discrete Ill-Posed Problems*,
§4.2; the filter ``s_i/(s_i + a^2)`` printed in Bettemir's Eq. 5.25 is an OCR/typesetting error).

The weight is chosen from the data being fitted only, never from independent check points:

* :func:`gcv_weight` — generalised cross-validation (Golub, Heath & Wahba 1979, *Technometrics*
  21(2)): minimise ``G(lam) = ||A x_lam - b||^2 / trace(I - H_lam)^2`` with the influence
  ("hat") matrix ``H_lam = A (A^T A + lam^2 I)^-1 A^T``, whose trace is ``sum_i f_i``.
* :func:`lcurve_weight` — the corner of the L-curve (Hansen & O'Leary 1993, *SIAM J. Sci.
  Comput.* 14(6)): the point of maximum curvature of ``(log ||A x_lam - b||, log ||x_lam||)``.

Both are reusable by any linear(ised) estimation, e.g. the rational-function fits of
:mod:`stereodem.sensor.models.generic` and, later, bundle adjustment (``sensor.adjust``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from stereodem.core.errors import InputError

__all__ = [
    "SVDSystem",
    "tikhonov_solve",
    "gcv_function",
    "gcv_weight",
    "lcurve",
    "lcurve_weight",
    "condition_number",
]


@dataclass(frozen=True)
class SVDSystem:
    """Thin SVD of a design matrix with the right-hand side projected onto it.

    Attributes
    ----------
    s : ndarray (k,)
        Singular values, descending.
    U, Vt : ndarray
        Left (m, k) and right (k, n) singular vectors.
    beta : ndarray (k,)
        ``U^T b``.
    resid0 : float
        ``||b - U U^T b||^2``, the part of ``b`` no solution can fit.
    m : int
        Number of equations.
    """

    s: np.ndarray
    U: np.ndarray
    Vt: np.ndarray
    beta: np.ndarray
    resid0: float
    m: int

    @classmethod
    def of(cls, A, b) -> SVDSystem:
        A = np.asarray(A, dtype=np.float64)
        b = np.asarray(b, dtype=np.float64)
        if A.ndim != 2 or b.shape != (A.shape[0],):
            raise InputError(
                f"regularize: design matrix {A.shape} and right-hand side {b.shape} do not match"
            )
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
            raise InputError(
                "regularize: non-finite values in the design matrix or right-hand side"
            )
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        beta = U.T @ b
        resid0 = max(float(b @ b - beta @ beta), 0.0)
        return cls(s, U, Vt, beta, resid0, A.shape[0])

    def filters(self, lam):
        """Tikhonov filter factors ``f_i`` for each weight in ``lam`` (shape (..., k))."""
        lam = np.asarray(lam, dtype=np.float64)[..., None]
        s2 = self.s**2
        with np.errstate(invalid="ignore", divide="ignore"):
            f = s2 / (s2 + lam**2)
        # lam == 0: plain (minimum-norm) least squares with numerically zero values dropped
        tiny = self.s <= self.s[0] * max(self.m, self.Vt.shape[1]) * np.finfo(float).eps
        return np.where(tiny & (lam == 0), 0.0, np.nan_to_num(f, nan=0.0))

    def residual_norm2(self, lam):
        """``||A x_lam - b||^2`` for each weight in ``lam``."""
        f = self.filters(lam)
        return np.sum(((1.0 - f) * self.beta) ** 2, axis=-1) + self.resid0

    def solution_norm2(self, lam):
        """``||x_lam||^2`` for each weight in ``lam``."""
        f = self.filters(lam)
        with np.errstate(invalid="ignore", divide="ignore"):
            xi = np.where(f > 0, f * self.beta / np.where(self.s > 0, self.s, 1.0), 0.0)
        return np.sum(xi**2, axis=-1)

    def solve(self, lam):
        f = self.filters(float(lam))
        coef = np.where(f > 0, f * self.beta / np.where(self.s > 0, self.s, 1.0), 0.0)
        return self.Vt.T @ coef

    def default_grid(self, n: int = 400, *, widen: float = 10.0):
        """Log-spaced weights from ``s_min / widen`` to ``s_max * widen`` (``s_min`` floored at
        ``s_max * 1e-14``); the L-curve uses ``widen = 1`` (Hansen's ``l_corner`` range)."""
        smax = float(self.s[0]) if self.s.size and self.s[0] > 0 else 1.0
        pos = self.s[self.s > smax * 1e-14]
        smin = float(pos[-1]) if pos.size else smax * 1e-14
        lo = max(smin / widen, smax * 1e-14)
        return np.logspace(np.log10(lo), np.log10(smax * widen), n)


def _system(A, b, svd):
    return svd if svd is not None else SVDSystem.of(A, b)


def tikhonov_solve(A, b, lam: float, *, svd: SVDSystem | None = None) -> np.ndarray:
    """Tikhonov-regularised least-squares solution ``(A^T A + lam^2 I)^-1 A^T b``.

    Parameters
    ----------
    A : ndarray (m, n)
        Design matrix (ideally of normalised coordinates, so that ``||x||`` is meaningful).
    b : ndarray (m,)
        Observations.
    lam : float
        Regularisation weight (``h`` in Ok 2005, ``alpha`` in Bettemir 2006), in the units of
        the singular values of ``A``; 0 gives the minimum-norm least-squares solution.
    svd : SVDSystem, optional
        A precomputed :class:`SVDSystem` of ``(A, b)``.

    Returns
    -------
    ndarray (n,)
    """
    if not np.isfinite(lam) or lam < 0:
        raise InputError(f"regularize: the Tikhonov weight must be finite and >= 0, got {lam}")
    return _system(A, b, svd).solve(float(lam))


def gcv_function(A, b, lams, *, svd: SVDSystem | None = None) -> np.ndarray:
    """GCV function ``||A x_lam - b||^2 / trace(I - H_lam)^2`` at each weight in ``lams``.

    (The customary factor ``m`` of Golub et al. does not move the minimum and is left out.)
    Where ``trace(I - H) <= 0`` (an interpolating fit) the value is ``inf``.
    """
    sv = _system(A, b, svd)
    lams = np.asarray(lams, dtype=np.float64)
    rn = sv.residual_norm2(lams)
    dof = sv.m - np.sum(sv.filters(lams), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = rn / dof**2
    return np.where(dof > 1e-9 * sv.m, g, np.inf)


def gcv_weight(A, b, *, lams=None, svd: SVDSystem | None = None) -> float:
    """Tikhonov weight minimising generalised cross-validation (Golub, Heath & Wahba 1979).

    The GCV function is evaluated on a log-spaced grid spanning the singular values of ``A``
    (or on ``lams``) and its minimum refined by a bounded scalar search in ``log lam``.

    Returns
    -------
    float
        The weight ``lam`` (> 0) to pass to :func:`tikhonov_solve`.
    """
    sv = _system(A, b, svd)
    grid = (
        sv.default_grid(500, widen=1e4)
        if lams is None
        else np.sort(np.asarray(lams, dtype=np.float64))
    )
    g = gcv_function(None, None, grid, svd=sv)
    if not np.any(np.isfinite(g)):
        raise InputError("regularize: GCV undefined (as many unknowns as observations?)")
    i = int(np.nanargmin(g))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    if hi <= lo:
        return float(grid[i])
    res = minimize_scalar(
        lambda t: float(gcv_function(None, None, np.exp(t), svd=sv)),
        bounds=(np.log(lo), np.log(hi)),
        method="bounded",
        options={"xatol": 1e-6},
    )
    best = float(np.exp(res.x))
    return best if float(gcv_function(None, None, best, svd=sv)) <= g[i] else float(grid[i])


def lcurve(A, b, lams, *, svd: SVDSystem | None = None):
    """Points of the L-curve: ``(log ||A x_lam - b||, log ||x_lam||)`` at each weight in
    ``lams``."""
    sv = _system(A, b, svd)
    lams = np.asarray(lams, dtype=np.float64)
    rho = 0.5 * np.log(np.maximum(sv.residual_norm2(lams), 1e-300))
    eta = 0.5 * np.log(np.maximum(sv.solution_norm2(lams), 1e-300))
    return rho, eta


def lcurve_weight(
    A, b, *, lams=None, svd: SVDSystem | None = None, min_curvature: float = 0.0
) -> float:
    """Tikhonov weight at the corner (maximum curvature) of the L-curve (Hansen & O'Leary 1993).

    The curve ``(rho, eta) = (log ||A x_lam - b||, log ||x_lam||)`` is sampled on a fine
    log-spaced grid of ``lam`` from the smallest to the largest singular value of ``A`` (or on
    ``lams``); its signed curvature ``(rho' eta'' - rho'' eta') / (rho'^2 + eta'^2)^(3/2)``
    (derivatives with respect to ``log lam``; positive where the curve turns from its steep
    branch, small ``lam``, to its flat branch, i.e. at the corner, as in Hansen's ``l_corner``)
    is maximised, the grid ends and stationary stretches excluded. A well-posed system has no
    corner (no curvature above ``min_curvature``): ``1e-3`` times the smallest weight of the
    grid (``s_min``) is then returned, a negligible damping (filter factors >= 1 - 1e-6).

    Returns
    -------
    float
        The weight ``lam`` (> 0).
    """
    sv = _system(A, b, svd)
    grid = (
        sv.default_grid(600, widen=1.0)
        if lams is None
        else np.sort(np.asarray(lams, dtype=np.float64))
    )
    if grid.size < 5:
        raise InputError("regularize: the L-curve needs at least 5 weights")
    t = np.log(grid)
    rho, eta = lcurve(None, None, grid, svd=sv)
    r1, e1 = np.gradient(rho, t), np.gradient(eta, t)
    r2, e2 = np.gradient(r1, t), np.gradient(e1, t)
    speed = np.hypot(r1, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = (r1 * e2 - r2 * e1) / speed**3
    # plateaus (the curve standing still) give round-off curvature: ignore them
    kappa[speed < 1e-3 * np.max(speed)] = -np.inf
    kappa[:2] = kappa[-2:] = -np.inf
    kappa[~np.isfinite(kappa)] = -np.inf
    i = int(np.argmax(kappa))
    if not np.isfinite(kappa[i]) or kappa[i] < min_curvature:
        # no corner: the system is well posed over the grid; damp negligibly (f_i >= 1 - 1e-6)
        return float(grid[0] * 1e-3)
    return float(grid[i])


def condition_number(A, lam: float = 0.0) -> float:
    """Condition number of the normal matrix ``A^T A + lam^2 I`` (2-norm), ``inf`` if singular.

    With the singular values ``s`` of ``A`` this is ``(s_max^2 + lam^2) / (s_min^2 + lam^2)``,
    bounded by ``(lam^2 + ||A^T A||) / lam^2`` (Neumaier 1998, quoted by Ok 2005).
    """
    A = np.asarray(A, dtype=np.float64)
    s = np.linalg.svd(A, compute_uv=False)
    n = A.shape[1]
    smin = s[-1] if s.size == n else 0.0
    den = smin**2 + lam**2
    return float((s[0] ** 2 + lam**2) / den) if den > 0 else float("inf")
