"""Error statistics of height differences (DEM − reference), whole set and by class.

The metric set follows the usual DEM-accuracy block (xdem, demcompare, ASP ``geodiff``; see
``anchors-ecosystem.md`` §B): N, % valid, mean, median, std, RMSE, MAE, NMAD, P16/P84,
LE90/LE95 empirical (P90/P95 of |dh|) and Gaussian (1.6449 σ, 1.9600 σ), min and max.
"""

from __future__ import annotations

import numpy as np

from stereodem.core.errors import InputError
from stereodem.core.stats import NMAD_FACTOR

Z90 = 1.6448536269514722  #: standard normal quantile of 0.95 (two-sided 90 %)
Z95 = 1.959963984540054  #: standard normal quantile of 0.975 (two-sided 95 %)

#: default slope class edges, degrees (last class open-ended)
DEFAULT_SLOPE_BINS = (0.0, 5.0, 10.0, 20.0, 30.0, 45.0, 90.0)

STAT_KEYS = (
    "n",
    "n_total",
    "valid_pct",
    "mean",
    "median",
    "std",
    "rmse",
    "mae",
    "nmad",
    "p16",
    "p84",
    "le90",
    "le95",
    "le90_gauss",
    "le95_gauss",
    "min",
    "max",
)


def error_stats(dh, *, n_total: int | None = None) -> dict:
    """Statistics of height differences ``dh`` (metres; NaN = no comparison).

    Parameters
    ----------
    dh : array_like
        Differences, any shape; non-finite values are counted as invalid.
    n_total : int, optional
        Number of cells of the footprint for ``valid_pct`` (default ``dh.size``).

    Returns
    -------
    dict with the keys of :data:`STAT_KEYS` (floats, NaN when there is no valid value; ``n``
    and ``n_total`` ints). ``std`` uses the population form (ddof=0), so that
    ``rmse² = mean² + std²`` exactly.
    """
    a = np.asarray(dh, dtype=np.float64).ravel()
    total = int(a.size if n_total is None else n_total)
    x = a[np.isfinite(a)]
    n = int(x.size)
    out = dict.fromkeys(STAT_KEYS, float("nan"))
    out.update(n=n, n_total=total, valid_pct=(100.0 * n / total) if total else float("nan"))
    if n == 0:
        return out
    med = float(np.median(x))
    absx = np.abs(x)
    std = float(np.std(x))
    p16, p84 = np.percentile(x, [16.0, 84.0])
    le90, le95 = np.percentile(absx, [90.0, 95.0])
    out.update(
        mean=float(np.mean(x)),
        median=med,
        std=std,
        rmse=float(np.sqrt(np.mean(x * x))),
        mae=float(np.mean(absx)),
        nmad=float(NMAD_FACTOR * np.median(np.abs(x - med))),
        p16=float(p16),
        p84=float(p84),
        le90=float(le90),
        le95=float(le95),
        le90_gauss=Z90 * std,
        le95_gauss=Z95 * std,
        min=float(x.min()),
        max=float(x.max()),
    )
    return out


def _bin_label(lo, hi, unit, last):
    if last and not np.isfinite(hi):
        return f">{lo:g}{unit}"
    return f"{lo:g}-{hi:g}{unit}"


def bin_edges(bins, name: str = "bin") -> np.ndarray:
    """Class edges as a float64 array; :class:`InputError` unless at least two increasing."""
    edges = np.asarray(bins, dtype=np.float64)
    # edges compared, not subtracted (-1e308 .. 1e308 overflowed, a RuntimeWarning)
    if edges.ndim != 1 or edges.size < 2 or np.any(edges[1:] <= edges[:-1]):
        raise InputError(f"{name} bins must be at least two increasing edges, got {list(bins)}")
    return edges


def binned_stats(
    dh, variable, bins, *, unit: str = "", name: str = "bin", footprint=None
) -> list[dict]:
    """Statistics of ``dh`` in bins of ``variable`` (same shape).

    Bins are ``[edge_i, edge_{i+1})``, the last one closed; an upper edge of ``inf`` makes the
    last class open-ended. Each entry holds ``class`` (a label), ``lower``, ``upper``,
    ``<name>_mean`` (mean of the variable in the class) and the :func:`error_stats` keys, with
    ``n_total`` the number of cells of the class whatever ``dh`` (inside ``footprint``, a
    boolean array of the same shape, when given: ``valid_pct`` is then the class's share of
    valid cells within the DEM's footprint, not diluted by the class's cells outside it).
    """
    dh = np.asarray(dh, dtype=np.float64)
    v = np.asarray(variable, dtype=np.float64)
    if dh.shape != v.shape:
        raise InputError(f"differences {dh.shape} and {name} {v.shape} differ in shape")
    edges = bin_edges(bins, name)
    out = []
    fin = np.isfinite(v)
    for i in range(edges.size - 1):
        lo, hi = edges[i], edges[i + 1]
        last = i == edges.size - 2
        sel = fin & (v >= lo) & ((v <= hi) if last else (v < hi))
        st = error_stats(dh[sel], n_total=_count_in(sel, footprint))
        entry = {
            "class": _bin_label(lo, hi, unit, last),
            "lower": float(lo),
            "upper": float(hi) if np.isfinite(hi) else None,
            f"{name}_mean": float(np.mean(v[sel & np.isfinite(dh)])) if st["n"] else float("nan"),
        }
        entry.update(st)
        out.append(entry)
    return out


def _count_in(sel, footprint) -> int:
    """Cells of ``sel`` (inside ``footprint`` when given)."""
    return int(np.count_nonzero(sel if footprint is None else sel & footprint))


def class_stats(
    dh, classes, *, names: dict | None = None, nodata=None, footprint=None
) -> list[dict]:
    """Statistics of ``dh`` per integer class of ``classes`` (e.g. a land-cover raster).

    ``names`` maps class values to labels; ``nodata`` (and non-finite values) is skipped;
    ``footprint`` as :func:`binned_stats`' (a class with no cell in it is left out).
    """
    dh = np.asarray(dh, dtype=np.float64)
    c = np.asarray(classes)
    if dh.shape != c.shape:
        raise InputError(f"differences {dh.shape} and classes {c.shape} differ in shape")
    valid = np.isfinite(c) if np.issubdtype(c.dtype, np.floating) else np.ones(c.shape, bool)
    if nodata is not None and np.isfinite(nodata):
        valid &= c != nodata
    out = []
    for value in np.unique(c[valid]):
        sel = valid & (c == value)
        key = int(value) if float(value).is_integer() else float(value)
        n_total = _count_in(sel, footprint)
        if n_total == 0:  # only beyond the DEM
            continue
        entry = {"class": (names or {}).get(key, str(key)), "value": key}
        entry.update(error_stats(dh[sel], n_total=n_total))
        out.append(entry)
    return out


def default_elevation_bins(heights, *, n_bands: int = 5):
    """Edges of ``n_bands`` elevation bands over the range of ``heights``, rounded to 10 m."""
    h = np.asarray(heights, dtype=np.float64)
    h = h[np.isfinite(h)]
    if h.size == 0:
        raise InputError("no valid height to define elevation bands")
    lo, hi = np.floor(h.min() / 10.0) * 10.0, np.ceil(h.max() / 10.0) * 10.0
    if hi <= lo:
        hi = lo + 10.0
    return np.unique(np.round(np.linspace(lo, hi, n_bands + 1) / 10.0) * 10.0)


def error_vs_slope(dh, slope) -> dict:
    """Linear fit of the absolute error |dh − median(dh)| (m) against slope (deg).

    Returns ``{"slope_m_per_deg", "intercept_m", "r", "n"}``: the least-squares line and the
    Pearson correlation of the cell values (NaN when fewer than 3 cells or no slope spread).
    """
    dh = np.asarray(dh, dtype=np.float64).ravel()
    s = np.asarray(slope, dtype=np.float64).ravel()
    ok = np.isfinite(dh) & np.isfinite(s)
    out = {
        "slope_m_per_deg": float("nan"),
        "intercept_m": float("nan"),
        "r": float("nan"),
        "n": int(ok.sum()),
        "error": "abs(dh - median(dh))",
    }
    if ok.sum() < 3 or np.ptp(s[ok]) == 0:
        return out
    e = np.abs(dh[ok] - np.median(dh[ok]))
    b, a = np.polyfit(s[ok], e, 1)
    out.update(slope_m_per_deg=float(b), intercept_m=float(a), r=float(np.corrcoef(s[ok], e)[0, 1]))
    return out


def class_trend(entries, *, x_key: str = "slope_mean", y_key: str = "nmad") -> dict:
    """Pearson r and the line of a class statistic (``y_key``) against the class mean
    (``x_key``), the per-class correlation the Ok (2005) thesis reports (r = 0.99 for SD vs
    slope class)."""
    x = np.array([e.get(x_key, np.nan) for e in entries], dtype=float)
    y = np.array([e.get(y_key, np.nan) for e in entries], dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    out = {
        "x": x_key,
        "y": y_key,
        "r": float("nan"),
        "slope": float("nan"),
        "intercept": float("nan"),
        "n_classes": int(ok.sum()),
    }
    if ok.sum() >= 3 and np.ptp(x[ok]) > 0 and np.ptp(y[ok]) > 0:
        b, a = np.polyfit(x[ok], y[ok], 1)
        out.update(r=float(np.corrcoef(x[ok], y[ok])[0, 1]), slope=float(b), intercept=float(a))
    return out
