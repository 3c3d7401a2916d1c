"""Gaussian-process rates (optional; Hugonnet et al. 2021 fit per-pixel GPs with pyddem).

Each cell's series is modelled as a linear trend plus a Gaussian process and noise,

    h(t) = c + b (t − t̄) + f(t) + ε,   f ~ GP(0, σ_f² exp(−(t − t')² / 2ℓ²)),   ε_i ~ N(0, σ_i²),

and the trend is the generalised-least-squares (universal-kriging) estimate under the
covariance ``K = K_f + diag(σ_i²)``: ``[c, b] = (XᵀK⁻¹X)⁻¹ XᵀK⁻¹ h`` with ``X = [1, t − t̄]``,
its covariance ``(XᵀK⁻¹X)⁻¹``. The non-linear part ``f`` (a surge, a change of regime) no
longer biases the rate and widens its σ; without it (σ_f = 0) this is
:func:`stereodem.post.rates.fit_rates` without rejection.

Cells observed at the same dates share one weight vector, so the fit is one small solve per
observation pattern and a matrix product over the cells (vectorised). Outliers should be
removed first (pass the ``kept`` mask of :func:`~stereodem.post.rates.fit_rates`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereodem.core.errors import InputError


@dataclass(frozen=True)
class GPSettings:
    """Settings of :func:`gp_rates`.

    Attributes
    ----------
    sigma_f : float
        Standard deviation of the non-linear part (m; default 3).
    length : float
        Its correlation time ℓ (years; default 4).
    min_obs : int
        Fewest observations for a rate (default 3).
    """

    sigma_f: float = 3.0
    length: float = 4.0
    min_obs: int = 3


def gp_rates(heights, times, sigma, *, valid=None, settings: GPSettings = GPSettings()) -> dict:
    """Rates with the Gaussian-process model (module docstring).

    ``heights`` (T, ...) m, ``times`` (T,) decimal years, ``sigma`` (T,) m; ``valid`` (T, ...)
    bool. Returns ``rate``, ``rate_sigma`` (m/yr) and ``n_obs`` with the cell shape."""
    h = np.asarray(heights, np.float64)
    t = np.asarray(times, np.float64)
    T = t.size
    if h.shape[0] != T:
        raise InputError(f"heights have {h.shape[0]} dates, times {T}")
    cell_shape = h.shape[1:]
    h = h.reshape(T, -1)
    ok = np.isfinite(h)
    if valid is not None:
        ok &= np.asarray(valid, bool).reshape(T, -1)
    sig = np.broadcast_to(np.asarray(sigma, np.float64), (T,))
    tc = t - t.mean()
    kf = settings.sigma_f**2 * np.exp(-0.5 * (tc[:, None] - tc[None, :]) ** 2 / settings.length**2)
    rate = np.full(h.shape[1], np.nan, np.float32)
    rsig = np.full(h.shape[1], np.nan, np.float32)
    n_obs = ok.sum(0).astype(np.int16)
    patterns, inverse = np.unique(ok.T, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    for p, pat in enumerate(patterns):
        if pat.sum() < max(settings.min_obs, 2):
            continue
        idx = np.flatnonzero(pat)
        K = kf[np.ix_(idx, idx)] + np.diag(sig[idx] ** 2)
        X = np.column_stack([np.ones(idx.size), tc[idx]])
        Ki_X = np.linalg.solve(K, X)
        cov = np.linalg.inv(X.T @ Ki_X)
        w = (cov @ Ki_X.T)[1]  # rate = w · h
        cells = np.flatnonzero(inverse == p)
        rate[cells] = w @ h[np.ix_(idx, cells)]
        rsig[cells] = np.sqrt(cov[1, 1])
    return dict(
        rate=rate.reshape(cell_shape),
        rate_sigma=rsig.reshape(cell_shape),
        n_obs=n_obs.reshape(cell_shape),
    )
