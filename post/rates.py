"""Elevation-change rates per cell: weighted least squares in time with iterative rejection
of outliers (what a cloud or a blunder leaves), vectorised over cells.

For one cell with heights ``h_i`` (m) at times ``t_i`` (decimal years) and standard deviations
``σ_i`` (m), the line ``h = a + b (t − t̄_w)`` is fitted with weights ``w_i = 1/σ_i²``
(``t̄_w`` the weighted mean time):

    b = Σ w (t − t̄_w) h / Σ w (t − t̄_w)²,   σ_b = 1 / √(Σ w (t − t̄_w)²)   (m/yr)

``σ_b`` is the formal standard deviation of the rate given the ``σ_i`` (no a-posteriori
scaling: with five dates the χ² of one cell says little). Outliers are rejected one per cell
and per iteration: the observation with the largest internally studentised residual
``|r_i| / (σ_i √(1 − H_ii))`` (``H`` the hat matrix of the weighted fit; it picks a blunder at
the end of the series, where the raw residuals of it and of its neighbour are equal), when that
exceeds ``k``, while more than ``min_keep`` observations remain. Before that, observations
farther than ``max_deviation`` metres from the cell's temporal median are dropped (gross
blunders, e.g. cloud tops, that would otherwise bend every fit).

Everything works on arrays ``(T, ...)`` (time first), so a dask/xarray block of cells is one
call (:func:`fit_block`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereodem.core.errors import InputError
from stereodem.core.stats import nanmedian


@dataclass(frozen=True)
class RateSettings:
    """Settings of :func:`fit_rates`.

    Attributes
    ----------
    k : float
        Rejection threshold on the studentised residual (default 4).
    max_iterations : int
        Rejection passes (at most one observation per cell and pass).
    min_keep : int
        No rejection leaves fewer observations than this (default 3).
    min_obs : int
        Cells with fewer valid observations get no rate (NaN); at least 2.
    max_deviation : float
        Metres from the cell's temporal median beyond which an observation is dropped before
        the fit (default 150 m; ``inf`` turns it off). Real change over the stack's span must
        stay below it.
    """

    k: float = 4.0
    max_iterations: int = 3
    min_keep: int = 3
    min_obs: int = 2
    max_deviation: float = 150.0

    def __post_init__(self):
        if not self.k > 0:
            raise InputError(f"rate rejection threshold k must be positive, got {self.k}")
        if self.min_obs < 2:
            raise InputError(f"a rate needs at least 2 observations (min_obs={self.min_obs})")
        if not self.max_deviation > 0:
            raise InputError(f"max_deviation must be positive, got {self.max_deviation}")


def _weighted_line(h, t, w):
    """Weighted line fit per cell. ``h, w`` (T, N) (w = 0 where invalid), ``t`` (T, 1).
    Returns slope, intercept at t̄_w, t̄_w, Sxx, S (all (N,)), all NaN-free (Sxx may be 0)."""
    s = w.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        tbar = (w * t).sum(0) / s
        dt = t - tbar
        sxx = (w * dt * dt).sum(0)
        hbar = (w * np.where(w > 0, h, 0)).sum(0) / s
        b = (w * dt * np.where(w > 0, h - hbar, 0)).sum(0) / sxx
    return b, hbar, tbar, sxx, s


def fit_rates(heights, times, sigma, *, settings: RateSettings = RateSettings(), valid=None):
    """Rates of elevation change per cell.

    Parameters
    ----------
    heights : ndarray (T, ...) float
        Heights (m), NaN where there is no observation.
    times : ndarray (T,)
        Decimal years.
    sigma : ndarray (T,) or (T, ...)
        Standard deviation of each observation (m), > 0.
    valid : ndarray bool (T, ...), optional
        Observations allowed in the fit (masks: clouds, ...); default all finite heights.

    Returns
    -------
    dict of arrays of the cell shape: ``rate`` (m/yr), ``rate_sigma`` (m/yr), ``intercept``
    (m, the fitted height at ``t_mean``), ``t_mean`` (decimal year), ``n_obs`` (int16,
    observations kept), ``n_rejected`` (int16), and ``kept`` (T, ...) bool.
    """
    h = np.asarray(heights, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    if h.ndim < 1 or h.shape[0] != t.size:
        raise InputError(f"heights have {h.shape[0] if h.ndim else 0} dates, times {t.size}")
    if len(np.unique(t)) != t.size:
        raise InputError("repeated dates in the stack")
    cell_shape = h.shape[1:]
    T = t.size
    h = h.reshape(T, -1)
    sig = np.broadcast_to(
        np.asarray(sigma, np.float64).reshape((T,) + (1,) * (h.ndim - 1))
        if np.ndim(sigma) == 1
        else np.asarray(sigma, np.float64).reshape(T, -1),
        h.shape,
    )
    if not np.all(np.isfinite(sig) & (sig > 0) | ~np.isfinite(h)):
        raise InputError("observation standard deviations must be finite and positive")
    ok = np.isfinite(h)
    if valid is not None:
        ok &= np.asarray(valid, bool).reshape(T, -1)
    n_in = ok.sum(0)
    if np.isfinite(settings.max_deviation):
        med = nanmedian(np.where(ok, h, np.nan), axis=0)  # NaN: no observation
        with np.errstate(invalid="ignore"):
            ok &= ~(np.abs(h - med) > settings.max_deviation)
    tt = t[:, None]
    w0 = 1.0 / (sig * sig)
    rejected = np.zeros(h.shape[1], np.int16)
    for _ in range(settings.max_iterations):
        w = np.where(ok, w0, 0.0)
        b, a, tbar, sxx, s = _weighted_line(h, tt, w)
        n = ok.sum(0)
        can = (n > settings.min_keep) & (sxx > 0)
        if not can.any():
            break
        with np.errstate(invalid="ignore", divide="ignore"):
            r = h - (a + b * (tt - tbar))
            lev = w * (1.0 / s + (tt - tbar) ** 2 / sxx)
            z = np.abs(r) * np.sqrt(w0) / np.sqrt(np.clip(1.0 - lev, 1e-12, None))
        z = np.where(ok, z, -1.0)
        worst = np.argmax(z, axis=0)
        zmax = np.take_along_axis(z, worst[None], 0)[0]
        drop = can & (zmax > settings.k)
        if not drop.any():
            break
        cols = np.flatnonzero(drop)
        ok[worst[cols], cols] = False
        rejected[cols] += 1
    w = np.where(ok, w0, 0.0)
    b, a, tbar, sxx, s = _weighted_line(h, tt, w)
    n = ok.sum(0)
    good = (n >= settings.min_obs) & (sxx > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rate_sigma = 1.0 / np.sqrt(sxx)
    nan = np.float32(np.nan)
    out = dict(
        rate=np.where(good, b, nan).astype(np.float32),
        rate_sigma=np.where(good, rate_sigma, nan).astype(np.float32),
        intercept=np.where(good, a, nan).astype(np.float32),
        t_mean=np.where(good, tbar, nan).astype(np.float32),
        n_obs=n.astype(np.int16),
        n_rejected=(n_in - n).astype(np.int16),
    )
    out = {k: v.reshape(cell_shape) for k, v in out.items()}
    out["kept"] = ok.reshape((T,) + cell_shape)
    return out


RATE_LAYERS = ("rate", "rate_sigma", "intercept", "n_obs", "n_rejected")


def fit_block(heights, valid, times, sigma, settings: RateSettings):
    """:func:`fit_rates` for one block (``heights``/``valid`` with time last, as
    ``xarray.apply_ufunc`` hands core dimensions): returns the :data:`RATE_LAYERS` arrays
    stacked on a new last axis (float32)."""
    h = np.moveaxis(np.asarray(heights), -1, 0)
    v = np.moveaxis(np.asarray(valid), -1, 0)
    res = fit_rates(h, times, sigma, settings=settings, valid=v)
    return np.stack([res[k].astype(np.float32) for k in RATE_LAYERS], axis=-1)


def noise_limit(times, sigma) -> float:
    """Rate standard deviation (m/yr) that noise alone leaves in a cell observed at every one of
    ``times`` (decimal years) with independent errors ``sigma`` (m, per date): the formal
    ``1/√(Σ w (t − t̄_w)²)``."""
    t = np.asarray(times, np.float64)
    w = 1.0 / np.asarray(sigma, np.float64) ** 2 * np.ones_like(t)
    tbar = (w * t).sum() / w.sum()
    return float(1.0 / np.sqrt((w * (t - tbar) ** 2).sum()))
