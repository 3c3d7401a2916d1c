"""Figure of an uncertainty run: the σ_horizontal map (map axes in km or degrees with a scale
bar, :func:`stereodem.core.mapaxes.map_axes`; colour bar in metres) beside the bar chart of
the sources' shares of the horizontal variance, each share written inside the axes (inside
its bar when the bar is long, after it otherwise)."""

from __future__ import annotations

import numpy as np

from stereodem.core.png import save_png

#: longest side (cells) of the map drawn: larger maps are decimated first (the figure is
#: ~600 px wide; drawing a 5000² raster costs seconds for nothing)
DISPLAY_CELLS = 1400

#: a share at least this long (of the axis) has its value written inside its bar
INSIDE = 0.6


def plot_uncertainty(maps, path, *, title: str | None = None, overwrite: bool = False):
    """Write a PNG of ``maps`` (:class:`stereodem.ortho.uncertainty.maps.UncertaintyMaps`);
    ``overwrite``: replace an existing ``path``."""
    return save_png(figure(maps, title=title), path, dpi=110, overwrite=overwrite)


def figure(maps, *, title: str | None = None):
    """The matplotlib Figure of :func:`plot_uncertainty` (not saved)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from affine import Affine

    from stereodem.core.mapaxes import map_axes

    sh = maps.sigma_horizontal
    transform = maps.grid.transform
    k = max(1, int(np.ceil(max(sh.shape) / DISPLAY_CELLS)))
    if k > 1:
        sh, transform = sh[::k, ::k], transform @ Affine.scale(k)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.8), gridspec_kw={"width_ratios": [1.3, 1]})
    extent = map_axes(ax, transform, maps.grid.crs, sh.shape)
    cmap = plt.get_cmap("viridis").with_extremes(bad=(0, 0, 0, 0))  # no data: transparent
    im = ax.imshow(sh, extent=extent, cmap=cmap, interpolation="nearest")
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label("σ horizontal (m)")
    med = float(np.nanmedian(sh)) if np.isfinite(sh).any() else float("nan")
    ax.set_title(f"σ horizontal, {maps.method} (median {med:.3g} m)", fontsize=10)

    names = list(maps.shares)
    vals = np.array([maps.shares[n] for n in names], float)
    order = np.argsort(np.nan_to_num(vals, nan=-1.0))
    y = np.arange(len(names))
    shown = np.nan_to_num(vals[order])
    bx.barh(y, shown, color="tab:blue", height=0.7)
    bx.set_yticks(y, [names[i] for i in order])
    bx.set_xlabel("share of the horizontal variance (whole image)")
    bx.set_xlim(0, 1.0)  # shares of one variance: 0..1
    bx.set_ylim(-0.6, len(names) - 0.4)
    for i, v in zip(y, vals[order]):
        text = "n/a" if not np.isfinite(v) else f"{v:.3f}"
        if np.isfinite(v) and v >= INSIDE:  # inside the bar, ending before its end
            bx.text(v - 0.01, i, text, va="center", ha="right", fontsize=8, color="white")
        else:  # after the bar, inside the axes
            bx.text(max(v, 0.0) + 0.01, i, text, va="center", ha="left", fontsize=8)
    bx.set_title("sources", fontsize=10)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig
