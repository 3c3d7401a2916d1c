"""Error analysis of elevation differences on stable terrain (Hugonnet et al. 2022, IEEE JSTARS
15; xdem ``spatialstats``): heteroscedasticity, spatial correlation, σ of area means.

1. :func:`heteroscedasticity` — NMAD of ``dh`` binned by slope and maximum curvature (1-D and
   2-D, quantile bins), interpolated to a per-cell σ_dh; optionally compared with a per-cell σ
   from the sensor models (first-order propagation) and the share it explains.
2. :func:`variogram` — the empirical (Matheron) variogram of (standardised) ``dh``: all pairs of
   scattered samples (``scipy.spatial.distance.pdist``) or, on a grid, random pairs whose
   separations are drawn log-uniformly so that short and long lags are sampled alike;
   :func:`fit_variogram` — a sum of spherical (or exponential) models
   γ(d) = nugget + Σ s_k·f(d; r_k), weighted least squares on the bins.
3. :func:`area_mean_sigma` — σ of the mean of ``dh`` over an area,
   σ² = (1/N²) Σ_i Σ_j σ_i σ_j ρ(d_ij), by sampling cell pairs of the area (the diagonal
   exactly), not σ/√N.

Distances are metres (east/north of :func:`stereodem.post.coreg.local_metric_coords`).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from scipy import optimize
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial.distance import pdist

from stereodem.core.blocks import default_threads, each_item
from stereodem.core.errors import InputError
from stereodem.core.stats import nmad

from . import warp
from .coreg import local_metric_coords

#: scattered samples up to which :func:`variogram` uses every pair
ALL_PAIRS_MAX = 6000


# ----------------------------------------------------------------------------- models


def spherical(d, r):
    """Spherical correlation-free shape: 1.5 d/r − 0.5 (d/r)³ below ``r``, 1 beyond."""
    x = np.minimum(np.asarray(d, float) / r, 1.0)
    return 1.5 * x - 0.5 * x**3


def exponential(d, r):
    """Exponential shape with practical (95 %) range ``r``: 1 − exp(−3 d / r)."""
    return 1.0 - np.exp(-3.0 * np.asarray(d, float) / r)


_SHAPES = {"spherical": spherical, "exponential": exponential}


@dataclass
class VariogramModel:
    """γ(d) = nugget + Σ sills[k]·shape(d; ranges[k]) (d in metres)."""

    ranges: np.ndarray
    sills: np.ndarray
    nugget: float = 0.0
    model: str = "spherical"

    @property
    def sill(self) -> float:
        """Total sill (nugget + partial sills): the variance."""
        return float(self.nugget + np.sum(self.sills))

    def gamma(self, d):
        d = np.asarray(d, float)
        f = _SHAPES[self.model]
        g = np.full(d.shape, 0.0) + np.where(d > 0, self.nugget, 0.0)
        for r, s in zip(self.ranges, self.sills):
            g = g + s * f(d, r)
        return g

    def covariance(self, d):
        """C(d) = sill − γ(d); C(0) = sill."""
        return self.sill - self.gamma(d)

    def correlation(self, d):
        return self.covariance(d) / self.sill

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "nugget": float(self.nugget),
            "ranges_m": [float(r) for r in self.ranges],
            "sills": [float(s) for s in self.sills],
            "sill": self.sill,
        }


@dataclass
class EmpiricalVariogram:
    """Binned semivariances: ``edges`` (m), ``lag`` (mean pair distance per bin, m),
    ``gamma``, ``count`` (pairs per bin)."""

    edges: np.ndarray
    lag: np.ndarray
    gamma: np.ndarray
    count: np.ndarray

    def to_dict(self) -> dict:
        ok = self.count > 0
        return {
            "edges_m": self.edges.tolist(),
            "lag_m": self.lag[ok].tolist(),
            "gamma": self.gamma[ok].tolist(),
            "count": self.count[ok].astype(int).tolist(),
        }


# ----------------------------------------------------------------------------- empirical


def _bin(d, sq, edges):
    k = np.searchsorted(edges, d, side="right") - 1
    ok = (k >= 0) & (k < edges.size - 1)
    n = edges.size - 1
    cnt = np.bincount(k[ok], minlength=n).astype(float)
    ssum = np.bincount(k[ok], weights=sq[ok], minlength=n)
    dsum = np.bincount(k[ok], weights=d[ok], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        gamma = 0.5 * ssum / cnt
        lag = dsum / cnt
    return lag, gamma, cnt


def default_edges(min_lag, max_lag, n_bins=30):
    """Log-spaced bin edges from ``min_lag`` to ``max_lag`` metres, with 0 first."""
    return np.concatenate([[0.0], np.geomspace(min_lag, max_lag, n_bins)])


def variogram(
    values,
    coords=None,
    *,
    transform=None,
    crs=None,
    edges=None,
    n_pairs: int = 2_000_000,
    max_lag: float | None = None,
    seed: int = 0,
    max_points: int = ALL_PAIRS_MAX,
) -> EmpiricalVariogram:
    """Empirical (Matheron) variogram of ``values``.

    Either scattered: ``values`` 1-D and ``coords`` (n, 2) metres — every pair when n ≤
    ``max_points`` (else a random subset of that many points); or gridded: ``values`` 2-D
    (NaN = not stable) with ``transform``/``crs`` — ``n_pairs`` random pairs whose separation
    is log-uniform between one pixel and ``max_lag`` (default half the grid's diagonal).
    """
    rng = np.random.default_rng(seed)
    v = np.asarray(values, float)
    if coords is not None:
        xy = np.asarray(coords, float)
        ok = np.isfinite(v) & np.all(np.isfinite(xy), axis=1)
        xy, v = xy[ok], v[ok]
        if v.size < 10:
            raise InputError(f"variogram: only {v.size} valid samples")
        if v.size > max_points:
            pick = rng.choice(v.size, max_points, replace=False)
            xy, v = xy[pick], v[pick]
        d = pdist(xy)
        sq = pdist(v[:, None], "sqeuclidean")
        if edges is None:
            edges = default_edges(max(np.min(d[d > 0]), 1e-6), max_lag or d.max() / 2)
        lag, gamma, cnt = _bin(d, sq, np.asarray(edges, float))
        return EmpiricalVariogram(np.asarray(edges, float), lag, gamma, cnt)

    if v.ndim != 2 or transform is None:
        raise InputError(
            "variogram: give coords for scattered values or a 2-D grid with its transform"
        )
    fx, fy = warp.metres_per_unit(transform, crs, v.shape)
    px, py = abs(transform.a) * fx, abs(transform.e) * fy
    rows, cols = v.shape
    valid = np.flatnonzero(np.isfinite(v))
    if valid.size < 10:
        raise InputError(f"variogram: only {valid.size} valid cells")
    diag = np.hypot(rows * py, cols * px)
    max_lag = float(max_lag or diag / 2)
    first = rng.choice(valid, n_pairs)
    r0, c0 = np.divmod(first, cols)
    dist = np.exp(rng.uniform(np.log(min(px, py)), np.log(max_lag), n_pairs))
    ang = rng.uniform(0, 2 * np.pi, n_pairs)
    r1 = np.rint(r0 + dist * np.sin(ang) / py).astype(np.int64)
    c1 = np.rint(c0 + dist * np.cos(ang) / px).astype(np.int64)
    inside = (r1 >= 0) & (r1 < rows) & (c1 >= 0) & (c1 < cols) & ((r1 != r0) | (c1 != c0))
    r0, c0, r1, c1 = r0[inside], c0[inside], r1[inside], c1[inside]
    z0, z1 = v[r0, c0], v[r1, c1]
    ok = np.isfinite(z1)
    d = np.hypot((r1[ok] - r0[ok]) * py, (c1[ok] - c0[ok]) * px)
    sq = (z1[ok] - z0[ok]) ** 2
    if edges is None:
        edges = default_edges(min(px, py) * 0.999, max_lag)
    lag, gamma, cnt = _bin(d, sq, np.asarray(edges, float))
    return EmpiricalVariogram(np.asarray(edges, float), lag, gamma, cnt)


# ----------------------------------------------------------------------------- fit


def fit_variogram(
    emp: EmpiricalVariogram,
    *,
    n_models: int = 2,
    model: str = "spherical",
    nugget: bool = False,
    min_count: int = 30,
    max_range: float | None = None,
) -> VariogramModel:
    """Fit a sum of ``n_models`` spherical (or exponential) models (+ a nugget) to the binned
    variogram by weighted least squares (weights √count), ranges ordered short to long,
    several starts; bins with fewer than ``min_count`` pairs are ignored."""
    if model not in _SHAPES:
        raise InputError(f"unknown variogram model {model!r}; choose from {', '.join(_SHAPES)}")
    ok = (emp.count >= min_count) & np.isfinite(emp.gamma)
    if ok.sum() < 2 * n_models + int(nugget) + 1:
        raise InputError(f"variogram fit: only {int(ok.sum())} populated lag bins")
    d, g, w = emp.lag[ok], emp.gamma[ok], np.sqrt(emp.count[ok])
    f = _SHAPES[model]
    rmax = float(max_range or emp.edges[-1])
    rmin = float(max(d.min() * 0.5, 1e-9))
    gmax = float(np.nanmax(g))

    def unpack(p):
        # ranges as cumulative log increments: r_1 < r_2 < ...
        lr = np.cumsum(p[:n_models])
        return np.exp(lr), p[n_models : 2 * n_models], (p[-1] if nugget else 0.0)

    def resid(p):
        r, s, c0 = unpack(p)
        m = c0 + sum(s[k] * f(d, r[k]) for k in range(n_models))
        return w * (m - g)

    best = None
    lo = [np.log(rmin)] + [0.0] * (n_models - 1) + [0.0] * n_models + ([0.0] if nugget else [])
    hi = (
        [np.log(rmax)]
        + [np.log(rmax / rmin)] * (n_models - 1)
        + [10 * gmax] * n_models
        + ([gmax] if nugget else [])
    )
    # starts: ranges spread over the lags (each model's range from the shortest lag to the
    # longest), equal partial sills
    grid = np.geomspace(max(rmin * 2, d.min()), max(d.max(), rmin * 4), 5)
    starts = [np.array(c) for c in _increasing_combinations(grid, n_models)]
    for r0 in starts:
        p0 = np.concatenate(
            [
                [np.log(r0[0])],
                np.diff(np.log(r0)) + 1e-3,
                np.full(n_models, gmax / n_models),
                [0.05 * gmax] if nugget else [],
            ]
        )
        p0 = np.clip(p0, np.array(lo) + 1e-9, np.array(hi) - 1e-9)
        try:
            sol = optimize.least_squares(resid, p0, bounds=(lo, hi), x_scale="jac")
        except ValueError:
            continue
        if best is None or sol.cost < best.cost:
            best = sol
    if best is None:
        raise InputError("variogram fit failed")
    r, s, c0 = unpack(best.x)
    return VariogramModel(np.asarray(r), np.asarray(s), float(c0), model)


def _increasing_combinations(values, k):
    """Strictly increasing k-tuples of ``values`` (few: 5 values, k ≤ 3)."""
    return list(combinations(sorted(values), k))


# ----------------------------------------------------------------------------- area mean


def area_mean_sigma(
    model: VariogramModel,
    area,
    transform=None,
    crs=None,
    *,
    sigma=1.0,
    n_samples: int = 3000,
    seed: int = 0,
) -> dict:
    """σ of the mean over an area of a field with correlation ``model`` and per-cell σ.

    ``area``: bool array on the grid of ``transform``/``crs`` (the cells of the polygon) or
    (n, 2) coordinates in metres. ``sigma``: scalar or per-cell σ (same grid; multiplies the
    model, which is then a variogram of standardised values). σ² = (1/N²) Σ_i Σ_j σ_i σ_j
    C(d_ij): the diagonal (1/N²)·Σσ_i²·C(0) exactly, the N(N−1) off-diagonal terms by the mean
    over the pairs of a random subset of ``n_samples`` cells.

    Returns ``{"sigma_mean", "n_cells", "n_effective", "sigma_naive"}``: ``n_effective`` the
    number of independent samples with the same σ of the mean (σ̄²·C(0)/σ_mean²), ``sigma_naive``
    the σ/√N that ignores correlation.
    """
    rng = np.random.default_rng(seed)
    if transform is not None:
        a = np.asarray(area, bool)

        e, n = local_metric_coords(transform, crs, a.shape)
        sig = _sigma_on(sigma, a.shape, "area")
        keep = a & np.isfinite(sig)
        xy = np.column_stack([e[keep], n[keep]])
        s = sig[keep]
    else:
        xy = np.asarray(area, float)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise InputError(
                f"area mean: area must be a bool grid (with its transform) or (n, 2) "
                f"coordinates in metres, got shape {xy.shape}"
            )
        s = _sigma_on(sigma, (xy.shape[0],), "area's points").copy()
    n_cells = xy.shape[0]
    if n_cells == 0:
        raise InputError("area mean: the area holds no cell")
    c0 = model.sill
    diag = np.sum(s**2) * c0 / n_cells**2
    if n_cells == 1:
        var = diag
    else:
        if n_cells > n_samples:
            pick = rng.choice(n_cells, n_samples, replace=False)
            xs, ss = xy[pick], s[pick]
        else:
            xs, ss = xy, s
        d = pdist(xs)
        prod = _pair_products(ss)
        off_mean = float(np.mean(prod * model.covariance(d)))
        var = diag + off_mean * (n_cells - 1) / n_cells
    mean_var = float(np.mean(s**2)) * c0
    sigma_mean = float(np.sqrt(max(var, 0.0)))
    return {
        "sigma_mean": sigma_mean,
        "n_cells": int(n_cells),
        "n_effective": float(mean_var / var) if var > 0 else float("inf"),
        "sigma_naive": float(np.sqrt(mean_var / n_cells)),
    }


def _sigma_on(sigma, shape, what):
    """``sigma`` (scalar or per cell) broadcast to ``shape``; an :class:`InputError` naming
    both shapes when it does not fit (numpy's broadcast ValueError before)."""
    sig = np.asarray(sigma, float)
    try:
        return np.broadcast_to(sig, shape)
    except ValueError:
        raise InputError(
            f"area mean: sigma of shape {sig.shape} does not fit the {what} {tuple(shape)}"
        ) from None


def _pair_products(s):
    """σ_i σ_j for the pairs i < j in ``pdist`` order."""
    i, j = np.triu_indices(s.size, k=1)
    return s[i] * s[j]


# ----------------------------------------------------------------------------- heteroscedasticity


def _quantile_edges(x, n_bins):
    e = np.unique(np.nanquantile(x, np.linspace(0, 1, n_bins + 1)))
    return e if e.size >= 2 else np.array([np.nanmin(x), np.nanmax(x) + 1e-9])


#: values per piece of the per-value work of :func:`heteroscedasticity` (bin indices, the
#: interpolation at each cell) spread over threads: a few MB of temporaries each
CHUNK = 1 << 20


def _bin_index(edges, x, threads=None):
    """The bin of each value of ``x`` (1-D) between ``edges`` (outer values in the outer bins),
    in chunks of :data:`CHUNK` values on ``threads`` threads."""
    out = np.empty(x.shape, np.intp)

    def one(i0):
        v = x[i0 : i0 + CHUNK]
        out[i0 : i0 + CHUNK] = np.clip(
            np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2
        )

    each_item(one, range(0, x.size, CHUNK), threads=threads)
    return out


def _binned_nmad(d, k, n, x=None, threads=None):
    """NMAD of ``d`` in each of the ``n`` bins ``k`` holding 20 values or more (NaN in the
    others) and the count per bin; with ``x``, also the median of ``x`` per non-empty bin. The
    bins (tens) are worked out on ``threads`` threads, the same numbers on any number."""
    out = np.full(n, np.nan)
    cnt = np.bincount(k, minlength=n)
    cen = np.full(n, np.nan)

    def one(i):
        sel = k == i
        return (nmad(d[sel]) if cnt[i] >= 20 else np.nan), (
            np.median(x[sel]) if x is not None else np.nan
        )

    bins = np.flatnonzero(cnt >= 20) if x is None else np.flatnonzero(cnt)
    for i, (v, c) in zip(bins, each_item(one, bins, threads=threads)):
        out[i], cen[i] = v, c
    return (out, cnt) if x is None else (out, cnt, cen)


def heteroscedasticity(
    dh, slope, curvature, *, n_bins: int = 8, sigma_model=None, threads: int | None = None
) -> dict:
    """Dispersion of ``dh`` (m, NaN outside stable terrain) against slope (deg) and maximum
    curvature (1/100 m; its absolute value is binned).

    Returns a dict: ``slope`` and ``curvature`` (1-D: bin edges, centres, NMAD, count, and
    the quadratic fitted to NMAD against the bin centre), ``table`` (2-D NMAD on slope ×
    |curvature| quantile bins) and ``sigma`` — the per-cell σ_dh (array, grid shape)
    interpolated in the 2-D table (nearest beyond the outer bin centres). With
    ``sigma_model`` (per-cell σ from the sensor models, m), also ``sensor_model``: the RMS model
    σ per slope bin, ``explained_variance_share`` = mean(σ_model²)/mean(σ_dh²) over the stable
    cells (σ_dh the binned, heteroscedastic dispersion above), the Pearson r of
    binned NMAD against binned RMS σ_model over the 2-D bins, and NMAD(dh/σ_model); and
    ``sigma_sensor``: the per-cell σ built on the sensor model, √(σ_model² + σ_u²) with σ_u² the
    variance the model leaves unexplained in the cell's 2-D bin.

    The bins and the per-cell interpolation are worked out on ``threads`` threads (default:
    the process's budget, :func:`stereodem.core.blocks.default_threads`); the numbers do not
    depend on it.
    """
    threads = default_threads() if threads is None else int(threads)
    dh = np.asarray(dh, float)
    s = np.asarray(slope, float)
    c = np.abs(np.asarray(curvature, float))
    ok = np.isfinite(dh) & np.isfinite(s) & np.isfinite(c)
    if ok.sum() < 100:
        raise InputError(f"heteroscedasticity: only {int(ok.sum())} stable cells")
    d = dh[ok] - np.median(dh[ok])
    out = {}
    for name, x, unit in (("slope", s[ok], "deg"), ("curvature", c[ok], "1/(100 m), absolute")):
        edges = _quantile_edges(x, n_bins)
        k = _bin_index(edges, x, threads)
        nm, cnt, cen = _binned_nmad(d, k, edges.size - 1, x=x, threads=threads)
        good = np.isfinite(nm) & np.isfinite(cen)
        coef = np.polyfit(cen[good], nm[good], 2).tolist() if good.sum() >= 3 else []
        out[name] = {
            "unit": unit,
            "edges": edges.tolist(),
            "centre": cen.tolist(),
            "nmad": nm.tolist(),
            "count": cnt.tolist(),
            "quadratic_fit": coef,
        }
    es, ec = np.asarray(out["slope"]["edges"]), np.asarray(out["curvature"]["edges"])
    ks = _bin_index(es, s[ok], threads)
    kc = _bin_index(ec, c[ok], threads)
    flat = ks * (ec.size - 1) + kc
    nm2, cnt2 = _binned_nmad(d, flat, (es.size - 1) * (ec.size - 1), threads=threads)
    table = nm2.reshape(es.size - 1, ec.size - 1)
    # fill empty 2-D bins from the 1-D slope curve, then interpolate at each cell
    fill = np.asarray(out["slope"]["nmad"], float)[:, None] * np.ones((1, ec.size - 1))
    table_f = np.where(np.isfinite(table), table, fill)
    nmad_all = nmad(d)
    table_f = np.where(np.isfinite(table_f), table_f, nmad_all)
    cs = np.asarray(out["slope"]["centre"], float)
    cc = np.asarray(out["curvature"]["centre"], float)
    interp = RegularGridInterpolator(
        (_strict(cs), _strict(cc)), table_f, bounds_error=False, fill_value=None, method="linear"
    )
    sig = np.full(dh.shape, np.nan)
    fin = np.isfinite(s) & np.isfinite(c)
    flat_s, flat_c, flat_fin, flat_sig = (
        s.reshape(-1),
        c.reshape(-1),
        fin.reshape(-1),
        sig.reshape(-1),
    )

    def at_cells(i0):  # the table interpolated at the cells i0 : i0 + CHUNK (row-major)
        part = slice(i0, i0 + CHUNK)
        f = flat_fin[part]
        pts = np.column_stack(
            [
                np.clip(flat_s[part][f], cs.min(), cs.max()),
                np.clip(flat_c[part][f], cc.min(), cc.max()),
            ]
        )
        flat_sig[part][f] = interp(pts)

    each_item(at_cells, range(0, sig.size, CHUNK), threads=threads)
    out["table"] = {
        "nmad": np.where(np.isfinite(table), table, np.nan).tolist(),
        "count": cnt2.reshape(table.shape).tolist(),
    }
    out["nmad_all"] = nmad_all
    out["sigma"] = sig
    if sigma_model is not None:
        sm = np.asarray(sigma_model, float)
        if sm.shape != dh.shape:
            raise InputError(f"sensor-model σ map shape {sm.shape} differs from dh {dh.shape}")
        ok2 = ok & np.isfinite(sm) & (sm > 0)
        if ok2.sum() < 100:
            raise InputError("sensor-model σ map: fewer than 100 stable cells with a σ")
        smv = sm[ok2]
        dd = dh[ok2] - np.median(dh[ok2])
        ks2 = np.clip(np.searchsorted(es, s[ok2], side="right") - 1, 0, es.size - 2)
        kc2 = np.clip(np.searchsorted(ec, c[ok2], side="right") - 1, 0, ec.size - 2)
        f2 = ks2 * (ec.size - 1) + kc2
        nb = (es.size - 1) * (ec.size - 1)
        cnt = np.bincount(f2, minlength=nb)
        rms = np.sqrt(np.bincount(f2, weights=smv**2, minlength=nb) / np.maximum(cnt, 1))
        obs, _ = _binned_nmad(dd, f2, nb, threads=threads)
        g = np.isfinite(obs) & (cnt >= 20)
        r = float(np.corrcoef(obs[g], rms[g])[0, 1]) if g.sum() >= 3 else float("nan")
        rms_slope = np.sqrt(
            np.bincount(ks2, weights=smv**2, minlength=es.size - 1)
            / np.maximum(np.bincount(ks2, minlength=es.size - 1), 1)
        )
        out["sensor_model"] = {
            "rms_sigma_by_slope": rms_slope.tolist(),
            "rms_sigma": float(np.sqrt(np.mean(smv**2))),
            "explained_variance_share": float(np.mean(smv**2) / np.nanmean(sig[ok2] ** 2)),
            "binned_r": r,
            "nmad_standardised": nmad(dd / smv),
            "n": int(ok2.sum()),
        }
        # the sensor-model σ as the per-cell σ of the heteroscedastic model: σ² = σ_model² +
        # the dispersion it leaves unexplained in the cell's (slope, curvature) bin
        extra2 = np.where(np.isfinite(obs) & (cnt >= 20), np.maximum(obs**2 - rms**2, 0.0), np.nan)
        extra2 = np.where(
            np.isfinite(extra2), extra2, max(nmad(dd) ** 2 - float(np.mean(smv**2)), 0.0)
        )
        ksa = np.clip(np.searchsorted(es, s, side="right") - 1, 0, es.size - 2)
        kca = np.clip(np.searchsorted(ec, c, side="right") - 1, 0, ec.size - 2)
        with np.errstate(invalid="ignore"):
            sig_sm = np.sqrt(sm**2 + extra2[ksa * (ec.size - 1) + kca])
        sig_sm[~(fin & np.isfinite(sm))] = np.nan
        out["sensor_model"]["unexplained_rms"] = float(np.sqrt(np.mean(extra2)))
        out["sigma_sensor"] = sig_sm
    return out


def _strict(x):
    """Make bin centres strictly increasing (ties from quantile bins nudged)."""
    x = np.asarray(x, float).copy()
    for i in range(1, x.size):
        if not x[i] > x[i - 1]:
            x[i] = x[i - 1] + 1e-9 * max(1.0, abs(x[i - 1]))
    return x


#: standardised values further than this many NMADs from their median are blunders, left out
#: of the variogram (xdem's ``infer_spatial_correlation_from_stable``, Hugonnet et al. 2022)
OUTLIER_NMAD = 4.0


def drop_outliers(z, k: float = OUTLIER_NMAD):
    """``z`` (a copy) with the values further than ``k`` NMADs from its median set to NaN, and
    their number. A few blunders (0.3 % of a filtered stereo DEM's cells, at up to 400 σ) make
    a Matheron variogram's sill and range what they like (a sill of 336 for standardised
    values, a 200 km range, and a σ of an area mean of 58 m on a DEM of NMAD 2.3 m)."""
    z = np.array(z, float)
    ok = np.isfinite(z)
    if not ok.any():
        return z, 0
    spread = nmad(z[ok])
    if not spread > 0:  # a constant field (or a handful of values): nothing to call a blunder
        return z, 0
    out = ok & (np.abs(z - np.median(z[ok])) > k * spread)
    z[out] = np.nan
    return z, int(out.sum())


def standardise(dh, sigma):
    """``dh`` minus its median, divided by the per-cell σ (NaN where σ is not positive)."""
    dh = np.asarray(dh, float)
    sig = np.asarray(sigma, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (dh - np.nanmedian(dh)) / np.where(sig > 0, sig, np.nan)
    return z


# ----------------------------------------------------------------------------- simulation


def simulate_field(model: VariogramModel, shape, pixel_m, *, rng=None, n_fields: int = 1):
    """Gaussian random fields of covariance ``model`` on a grid of ``shape`` cells of
    ``pixel_m`` = (east, north) metres, by circulant embedding (FFT on a grid twice the size;
    negative eigenvalues, if any, set to zero). Returns an array (n_fields, rows, cols)."""
    rng = np.random.default_rng(rng)
    rows, cols = shape
    px, py = (pixel_m, pixel_m) if np.isscalar(pixel_m) else pixel_m
    R, C = 2 * rows, 2 * cols
    i = np.minimum(np.arange(R), R - np.arange(R)) * py
    j = np.minimum(np.arange(C), C - np.arange(C)) * px
    d = np.hypot(i[:, None], j[None, :])
    cov = model.covariance(d)
    cov[0, 0] = model.sill
    lam = np.clip(np.fft.fft2(cov).real, 0.0, None)
    amp = np.sqrt(lam / (R * C))
    out = np.empty((n_fields, rows, cols))
    k = 0
    while k < n_fields:
        w = rng.standard_normal((R, C)) + 1j * rng.standard_normal((R, C))
        z = np.fft.fft2(amp * w)
        out[k] = z.real[:rows, :cols]
        if k + 1 < n_fields:
            out[k + 1] = z.imag[:rows, :cols]
        k += 2
    return out
