"""Figure of an uncertainty run: the σ_horizontal map (metres, colour bar, scale) beside the bar
chart of the sources' shares of the horizontal variance."""

from __future__ import annotations

import numpy as np

from stereodem.core.png import save_png


def plot_uncertainty(maps, path, *, title: str | None = None, overwrite: bool = False):
    """Write a PNG of ``maps`` (:class:`stereodem.ortho.uncertainty.maps.UncertaintyMaps`);
    ``overwrite``: replace an existing ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sh = maps.sigma_horizontal
    w, s, e, n = maps.grid.bounds
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.8), gridspec_kw={"width_ratios": [1.3, 1]})
    x0, y0 = w, s
    im = ax.imshow(
        sh,
        extent=((w - x0) / 1e3, (e - x0) / 1e3, (s - y0) / 1e3, (n - y0) / 1e3),
        cmap="viridis",
        interpolation="nearest",
    )
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label("σ horizontal (m)")
    ax.set_xlabel(f"easting − {x0:.0f} (km)")
    ax.set_ylabel(f"northing − {y0:.0f} (km)")
    ax.set_title(f"σ_horizontal, {maps.method} (median {np.nanmedian(sh):.3g} m)")
    names = list(maps.shares)
    vals = np.array([maps.shares[k] for k in names])
    order = np.argsort(vals)
    bx.barh(np.arange(len(names)), vals[order], color="tab:blue")
    bx.set_yticks(np.arange(len(names)), [names[i] for i in order])
    bx.set_xlabel("share of the horizontal variance (whole image)")
    bx.set_xlim(0, max(1.0, float(np.nanmax(vals)) if vals.size else 1.0))
    for i, v in enumerate(vals[order]):
        bx.text(v, i, f" {v:.3f}", va="center", fontsize=8)
    bx.set_title("sources")
    if title:
        fig.suptitle(title)
    fig.tight_layout()

    return save_png(fig, path, dpi=110, overwrite=overwrite)
