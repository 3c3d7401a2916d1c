"""PNG figures of an assessment (matplotlib, Agg backend): hillshade, difference map,
histogram of differences, error against slope."""
from __future__ import annotations


import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from affine import Affine  # noqa: E402

from stereodem.sensor.io.raster import check_writable  # noqa: E402

from . import terrain  # noqa: E402
from .stats import error_stats  # noqa: E402


def _save(fig, path, overwrite):
    path = check_writable(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.part.png")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return path


#: longest side (cells) of an array drawn in a figure; the figures are ~700 px wide, so larger
#: rasters are decimated first (drawing a 5000² raster costs seconds and GBs for nothing)
DISPLAY_CELLS = 1400


def _decimation(shape) -> int:
    """Stride that brings the longest side of ``shape`` to at most :data:`DISPLAY_CELLS`."""
    return max(1, int(np.ceil(max(shape) / DISPLAY_CELLS)))


def hillshade_png(heights, transform, crs, path, *, title="DEM hillshade", overwrite=False):
    """Hillshade of a DEM (NW light, 45°) with voids in red (large DEMs decimated for display)."""
    k = _decimation(np.shape(heights))
    if k > 1:
        heights, transform = np.asarray(heights)[::k, ::k], transform @ Affine.scale(k)
    hs = terrain.hillshade(heights, transform, crs)
    fig, ax = plt.subplots(figsize=(6, 6))
    cmap = plt.get_cmap("gray").with_extremes(bad="red")
    ax.imshow(np.ma.masked_invalid(hs), cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
    ax.set_title(title)
    ax.set_axis_off()
    return _save(fig, path, overwrite)


def difference_map_png(dh, path, *, title="DEM − reference (m)", overwrite=False):
    """Map of differences with a diverging colour scale symmetric about 0 (± P98 of |dh|)."""
    a = np.asarray(dh)
    k = _decimation(a.shape)
    a = a[::k, ::k].astype(np.float64)
    fin = a[np.isfinite(a)]
    lim = float(np.percentile(np.abs(fin), 98)) if fin.size else 1.0
    lim = lim if lim > 0 else 1.0
    fig, ax = plt.subplots(figsize=(6.5, 6))
    cmap = plt.get_cmap("RdBu_r").with_extremes(bad="0.8")
    im = ax.imshow(np.ma.masked_invalid(a), cmap=cmap, vmin=-lim, vmax=lim, interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.8, label="m")
    ax.set_title(title)
    ax.set_axis_off()
    return _save(fig, path, overwrite)


def histogram_png(dh, path, *, title="Histogram of DEM − reference", overwrite=False):
    """Histogram of differences with the mean, median and ±NMAD marked."""
    a = np.asarray(dh, dtype=np.float64)
    a = a[np.isfinite(a)]
    s = error_stats(a)
    lo, hi = (np.percentile(a, [0.5, 99.5]) if a.size else (-1, 1))
    fig, ax = plt.subplots(figsize=(6.5, 4))
    ax.hist(a, bins=100, range=(lo, hi) if hi > lo else None, color="steelblue")
    for x, lab, c in ((s["mean"], "mean", "k"), (s["median"], "median", "orange")):
        if np.isfinite(x):
            ax.axvline(x, color=c, label=f"{lab} {x:.2f} m")
    if np.isfinite(s["nmad"]):
        for sign in (-1, 1):
            ax.axvline(s["median"] + sign * s["nmad"], color="orange", ls="--")
    ax.set_xlabel("dh (m)")
    ax.set_ylabel("cells")
    ax.set_title(f"{title}\nN={s['n']} RMSE={s['rmse']:.2f} NMAD={s['nmad']:.2f} LE90={s['le90']:.2f} m")
    ax.legend()
    return _save(fig, path, overwrite)


def error_vs_slope_png(dh, slope, by_slope, path, *, overwrite=False):
    """Per-slope-class NMAD, std and LE90 against class mean slope, with a cell scatter."""
    a = np.asarray(dh, dtype=np.float64).ravel()
    s = np.asarray(slope, dtype=np.float64).ravel()
    ok = np.isfinite(a) & np.isfinite(s)
    fig, ax = plt.subplots(figsize=(6.5, 4))
    if ok.any():
        idx = np.flatnonzero(ok)
        idx = idx[np.random.default_rng(0).choice(idx.size, min(idx.size, 20000), replace=False)]
        ax.scatter(s[idx], np.abs(a[idx] - np.median(a[ok])), s=1, alpha=0.15, color="0.5",
                   label="|dh − median| (cells)")
    x = [e["slope_mean"] for e in by_slope]
    for key, c in (("nmad", "C0"), ("std", "C1"), ("le90", "C3")):
        ax.plot(x, [e[key] for e in by_slope], "o-", color=c, label=key)
    ax.set_xlabel("slope of the reference (deg)")
    ax.set_ylabel("error (m)")
    ax.set_title("Error against slope")
    fin = np.abs(a[ok] - np.median(a[ok])) if ok.any() else np.array([1.0])
    ax.set_ylim(0, max(float(np.percentile(fin, 99)), 1e-3) * 1.1)
    ax.legend(fontsize=8)
    return _save(fig, path, overwrite)
