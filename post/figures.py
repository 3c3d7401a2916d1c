"""PNG figures of an assessment (matplotlib, Agg backend): shaded relief, difference map,
histogram of differences, error against slope.

Maps are drawn in map coordinates (kilometres east/north on projected grids, degrees on
geographic ones) with a scale bar and a colour bar in metres; cells without data are
transparent and the view is cropped to the data. Every line has a legend entry; what a
figure leaves out (clipped colour scales, histogram tails, sparse classes) is written on it.
"""

from __future__ import annotations

import matplotlib

from .blockstats import StreamingStats

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from affine import Affine  # noqa: E402
from matplotlib.colors import Normalize  # noqa: E402

from stereodem.core.mapaxes import map_axes  # noqa: E402
from stereodem.core.png import save_png  # noqa: E402

from . import terrain  # noqa: E402
from .stats import error_stats  # noqa: E402

#: longest side (cells) of an array drawn in a figure; the figures are ~700 px wide, so larger
#: rasters are decimated first (drawing a 5000² raster costs seconds and GBs for nothing)
DISPLAY_CELLS = 1400

#: classes with fewer valid cells than this are drawn grey and left out of the class curves
MIN_CLASS_CELLS = 100

DPI = 110


def height_cmap():
    """Colour map of heights: matplotlib's hypsometric ``terrain`` without its sea part (its
    lowest quarter, blue): green lowlands to brown and white summits. ``gist_earth``, used
    before, starts at black then dark blue: the lowest cells of a mountain DEM looked like
    voids or water."""
    from matplotlib.colors import LinearSegmentedColormap

    base = plt.get_cmap("terrain")
    return LinearSegmentedColormap.from_list(
        "terrain_land", base(np.linspace(0.25, 1.0, 256)), N=256
    )


def diverging_cmap():
    """Colour map of height differences: ``RdBu_r`` (blue below, red above, white at 0),
    drawn with limits symmetric about 0; no data transparent."""
    return plt.get_cmap("RdBu_r").with_extremes(bad=(0, 0, 0, 0))


def _save(fig, path, overwrite):
    """Write ``fig`` to ``path`` cropped as ``bbox_inches="tight"``, in one draw
    (:func:`stereodem.core.png.save_png`)."""
    return save_png(fig, path, dpi=DPI, overwrite=overwrite, bbox_inches="tight")


def _decimation(shape) -> int:
    """Stride that brings the longest side of ``shape`` to at most :data:`DISPLAY_CELLS`."""
    return max(1, int(np.ceil(max(shape) / DISPLAY_CELLS)))


# ----------------------------------------------------------------------------- map helpers


def _crop_to_data(a, transform, margin=0.03):
    """Rows/cols window of the finite cells of ``a`` (plus a margin) and its transform."""
    fin = np.isfinite(a)
    if not fin.any():
        return a, transform
    rows, cols = np.flatnonzero(fin.any(axis=1)), np.flatnonzero(fin.any(axis=0))
    m = int(np.ceil(margin * max(a.shape)))
    r0, r1 = max(rows[0] - m, 0), min(rows[-1] + 1 + m, a.shape[0])
    c0, c1 = max(cols[0] - m, 0), min(cols[-1] + 1 + m, a.shape[1])
    return a[r0:r1, c0:c1], transform @ Affine.translation(c0, r0)


def _prepare(a, transform):
    """Decimate for display and crop to the data; returns (array, transform)."""
    a = np.asarray(a)
    k = _decimation(a.shape)
    if k > 1:
        a = a[::k, ::k]
        if transform is not None:
            transform = transform @ Affine.scale(k)
    a = a.astype(np.float64)
    if transform is None:
        return a, None
    return _crop_to_data(a, transform)


# ----------------------------------------------------------------------------- figures


def hillshade_png(
    heights,
    transform,
    crs,
    path,
    *,
    title="DEM shaded relief",
    overwrite=False,
    height_label="height (m)",
):
    """Shaded relief of a DEM: heights in colour (colour bar in metres) shaded by a hillshade
    (NW light, 45°), in map coordinates with a scale bar; cells without data transparent.

    Parameters
    ----------
    heights : ndarray (rows, cols)
        Heights (m), NaN where there is no data.
    transform, crs
        Grid georeferencing.
    height_label : str
        Colour-bar label (say the vertical reference, e.g. "height above the ellipsoid (m)").
    """
    z, transform = _prepare(heights, transform)
    hs = terrain.hillshade(z, transform, crs)
    fin = np.isfinite(z) & np.isfinite(hs)
    lo, hi = np.percentile(z[fin], [1, 99]) if fin.any() else (0.0, 1.0)
    hi = hi if hi > lo else lo + 1.0
    cmap = height_cmap()
    norm = Normalize(lo, hi)
    rgba = cmap(norm(np.where(fin, z, lo)))
    rgba[..., :3] *= (0.25 + 0.75 * np.where(fin, hs, 1.0))[..., None]
    rgba[..., 3] = fin  # no data: transparent
    fig, ax = plt.subplots(figsize=(6.5, 6))
    extent = map_axes(ax, transform, crs, z.shape)
    # as bytes: what matplotlib turns float colours into after its nearest-cell resampling
    ax.imshow((rgba * 255).astype(np.uint8), extent=extent, interpolation="nearest")
    sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=ax, shrink=0.8, extend="both", label=height_label)
    void = (~fin).sum()
    ax.set_title(
        f"{title}\n(hatched: no data, {100 * void / max(z.size, 1):.0f} % of the frame; "
        "colours span the 1st–99th height percentiles)",
        fontsize=10,
    )
    return _save(fig, path, overwrite)


def difference_map_png(
    dh,
    path,
    *,
    title="DEM − reference",
    overwrite=False,
    transform=None,
    crs=None,
    label="DEM − reference (m)",
    unit="m",
    what="dh",
):
    """Map of differences (m) with a diverging colour scale symmetric about 0, clipped at
    ± the 98th percentile of |dh| (said on the figure), in map coordinates with a scale bar
    when ``transform`` and ``crs`` are given; cells without a difference are hatched.
    ``label``: the colour bar's (with its unit), ``unit`` and ``what`` name the values in
    the clipping note (e.g. ``"m/yr"``, ``"rate"`` for a rate map)."""
    a, t = _prepare(dh, transform)
    fin = a[np.isfinite(a)]
    lim = float(np.percentile(np.abs(fin), 98)) if fin.size else 1.0
    lim = lim if lim > 0 else 1.0
    clipped = int((np.abs(fin) > lim).sum())
    fig, ax = plt.subplots(figsize=(6.5, 6))
    cmap = diverging_cmap()
    kw = {}
    if t is not None:
        kw["extent"] = map_axes(ax, t, crs, a.shape)
    else:
        ax.set_xlabel("column")
        ax.set_ylabel("row")
    im = ax.imshow(
        np.ma.masked_invalid(a), cmap=cmap, vmin=-lim, vmax=lim, interpolation="nearest", **kw
    )
    fig.colorbar(im, ax=ax, shrink=0.8, extend="both", label=label)
    ax.set_title(
        f"{title}; hatched: no data\ncolour scale clipped at ±{lim:.2f} {unit} (98th "
        f"percentile of |{what}|): {100 * clipped / max(fin.size, 1):.1f} % of cells beyond",
        fontsize=10,
    )
    return _save(fig, path, overwrite)


def histogram_png(dh, path, *, title="Histogram of DEM − reference", overwrite=False):
    """Histogram of differences with the mean, median and median ± NMAD marked; the x axis
    spans the 0.5–99.5 percentiles and the cells beyond are counted on the figure.

    ``dh`` is an array of differences (NaN ignored) or a
    :class:`~stereodem.post.blockstats.StreamingStats` of them (counts by its ~1 mm bins)."""
    if isinstance(dh, StreamingStats):
        s = dh.result()
        lo, hi = dh.quantile([0.005, 0.995]) if dh.n else (-1.0, 1.0)
        below, above = dh.count_outside(lo, hi) if dh.n else (0, 0)
        n_all = dh.n
        n_in = n_all - below - above
    else:
        a = np.asarray(dh, dtype=np.float64)
        a = a[np.isfinite(a)]
        s = error_stats(a)
        lo, hi = np.percentile(a, [0.5, 99.5]) if a.size else (-1.0, 1.0)
        inside = (a >= lo) & (a <= hi)
        n_all, n_in = a.size, int(inside.sum())
        below, above = int((a < lo).sum()), int((a > hi).sum())
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    label = f"cells ({n_in:,} of {n_all:,})"
    if isinstance(dh, StreamingStats):
        edges = np.linspace(lo, hi, 101) if hi > lo else np.array([lo - 0.5, lo + 0.5])
        ax.stairs(dh.histogram(edges), edges, fill=True, color="steelblue", label=label)
    else:
        ax.hist(
            a[inside], bins=100, range=(lo, hi) if hi > lo else None, color="steelblue", label=label
        )
    for x, lab, c, ls in (
        (s["mean"], "mean", "k", "-"),
        (s["median"], "median", "darkorange", "-"),
    ):
        if np.isfinite(x):
            ax.axvline(x, color=c, ls=ls, label=f"{lab} {x:+.2f} m")
    if np.isfinite(s["nmad"]):
        for k, sign in enumerate((-1, 1)):
            ax.axvline(
                s["median"] + sign * s["nmad"],
                color="darkorange",
                ls="--",
                label=f"median ± NMAD ({s['nmad']:.2f} m)" if k == 0 else None,
            )
    ax.set_ylim(0, ax.get_ylim()[1] * 1.45)  # room for the legend and the note
    ax.set_xlabel("DEM − reference (m)")
    ax.set_ylabel("cells per bin")
    ax.set_title(
        f"{title}\nN={s['n']:,}  RMSE={s['rmse']:.2f}  NMAD={s['nmad']:.2f}  "
        f"LE90={s['le90']:.2f} m",
        fontsize=10,
    )
    ax.text(
        0.01,
        0.98,
        f"x axis: 0.5–99.5 percentiles [{lo:.1f}, {hi:.1f}] m\nnot shown: "
        f"{below:,} cells below (min {s['min']:.1f} m),\n{above:,} above (max {s['max']:.1f} m)",
        transform=ax.transAxes,
        va="top",
        ha="left",
        fontsize=8,
        bbox=dict(boxstyle="round", fc="white", ec="0.7", alpha=0.9),
    )
    ax.legend(fontsize=8, loc="upper right")
    return _save(fig, path, overwrite)


def error_vs_slope_png(
    dh, slope, by_slope, path, *, overwrite=False, min_cells=MIN_CLASS_CELLS, centre=None
):
    """Per-slope-class NMAD, std and LE90 against the class mean slope, over a scatter of
    cells; each class's cell count is printed, classes with fewer than ``min_cells`` valid
    cells are grey and left out of the curves; the y axis holds every curve point.

    ``dh``/``slope`` may be decimated (the scatter draws 20 000 random cells of them);
    ``centre`` is the median the deviations are taken from (default: that of ``dh``)."""
    a = np.asarray(dh, dtype=np.float64).ravel()
    s = np.asarray(slope, dtype=np.float64).ravel()
    ok = np.isfinite(a) & np.isfinite(s)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ymax = 1e-3
    if ok.any():
        idx = np.flatnonzero(ok)
        idx = idx[np.random.default_rng(0).choice(idx.size, min(idx.size, 20000), replace=False)]
        e_cells = np.abs(a[idx] - (np.median(a[ok]) if centre is None else centre))
        ax.scatter(
            s[idx],
            e_cells,
            s=1,
            alpha=0.15,
            color="0.5",
            rasterized=True,
            label=f"|dh − median| of {idx.size:,} random cells",
        )
        ymax = max(ymax, float(np.percentile(e_cells, 99)))
    entries = [e for e in by_slope if e.get("n")]
    x = np.array([e["slope_mean"] for e in entries], dtype=float)
    n = np.array([e["n"] for e in entries])
    good = n >= min_cells
    for key, c, lab in (("nmad", "C0", "NMAD"), ("std", "C1", "std"), ("le90", "C3", "LE90")):
        y = np.array([e[key] for e in entries], dtype=float)
        ax.plot(x[good], y[good], "o-", color=c, label=f"{lab} per slope class")
        if (~good).any():
            ax.plot(x[~good], y[~good], "o", color="0.6", mfc="none")
        ymax = max(ymax, float(np.nanmax(y[good], initial=0.0)))
    if (~good).any():
        ax.plot(
            [],
            [],
            "o",
            color="0.6",
            mfc="none",
            label=f"class with < {min_cells} cells (not joined)",
        )
    top = ymax * 1.15
    ax.set_ylim(0, top)
    counts = ax.secondary_xaxis("top")  # cell count of each class, on top
    counts.set_xticks(x, [f"n={k:,}" for k in n], rotation=90, fontsize=7)
    counts.tick_params(length=3)
    for lab, g in zip(counts.get_xticklabels(), good):
        lab.set_color("k" if g else "0.55")
    counts.set_xlabel("valid cells per slope class", fontsize=8)
    for xi, e in zip(x, entries):
        for j, key in enumerate(("nmad", "std", "le90")):
            if e[key] > top:  # a sparse class off the scale: say so at the top
                ax.annotate(
                    f"{key} {e[key]:.1f} m ↑",
                    (xi, top),
                    textcoords="offset points",
                    xytext=(0, -10 - 9 * j),
                    ha="center",
                    fontsize=7,
                    color="0.4",
                )
    above_pct = 100 * float(np.mean(e_cells > top)) if ok.any() else 0.0
    ax.set_xlim(
        0,
        max(
            float(np.nanmax(s[ok], initial=1.0)) if ok.any() else 1.0,
            float(np.nanmax(x, initial=0.0)) + 2,
        )
        * 1.02,
    )
    ax.set_xlabel("slope of the reference (degrees)")
    ax.set_ylabel("error (m)")
    ax.set_title(
        f"Error against slope (y axis holds every class statistic; "
        f"{above_pct:.1f} % of the scattered cells above it)",
        fontsize=10,
    )
    leg = ax.legend(fontsize=8, loc="upper left", framealpha=0.9)
    if ok.any():  # the scatter's legend marker, visible
        h = leg.legend_handles[0]
        h.set_alpha(1.0)
        h.set_sizes([12])

    return _save(fig, path, overwrite)
