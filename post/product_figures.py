"""Quick-look PNGs of the ``change``, ``stack`` and ``mosaic`` products, drawn with the
assessment's helpers (:mod:`stereodem.post.figures`: map axes with a scale bar, decimation to
:data:`~stereodem.post.figures.DISPLAY_CELLS`, the diverging scale centred on 0 with its
clipping said, no data transparent over a hatch) and written by
:func:`stereodem.core.png.save_png` (overwrite policy, atomic).

* ``change``: ``dh_map.png`` (B − A, m, diverging) and ``dh_sigma_map.png`` (its σ, m);
* ``stack``: ``rate_map.png`` (m/yr, diverging), ``rate_sigma_map.png`` (m/yr) and
  ``n_obs_map.png`` (dates used per cell);
* ``mosaic``: ``<OUT>_hillshade.png`` (the mosaic's shaded relief) and ``<OUT>_count.png``
  (DEMs contributing per cell), or the single statistic of ``count``/``stddev``/``nmad``.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rasterio  # noqa: E402
from affine import Affine  # noqa: E402
from matplotlib.colors import BoundaryNorm, ListedColormap  # noqa: E402

from stereodem.core.mapaxes import map_axes  # noqa: E402

from . import figures  # noqa: E402
from .choices import CHANGE_FIGURES, STACK_FIGURES  # noqa: E402, F401 (the figures' names)
from .figures import _prepare, _save  # noqa: E402


def magnitude_map_png(a, path, *, transform, crs, title, label, unit="m", overwrite=False):
    """Map of a non-negative quantity (a σ) on a sequential scale from 0 to the 98th
    percentile of its finite cells, the share beyond said; no data transparent (hatched)."""
    z, t = _prepare(a, transform)
    fin = z[np.isfinite(z)]
    hi = float(np.percentile(fin, 98)) if fin.size else 1.0
    hi = hi if hi > 0 else 1.0
    beyond = 100 * float(np.mean(fin > hi)) if fin.size else 0.0
    fig, ax = plt.subplots(figsize=(6.5, 6))
    extent = map_axes(ax, t, crs, z.shape)
    cmap = plt.get_cmap("viridis").with_extremes(bad=(0, 0, 0, 0))
    im = ax.imshow(
        np.ma.masked_invalid(z),
        cmap=cmap,
        vmin=0.0,
        vmax=hi,
        interpolation="nearest",
        extent=extent,
    )
    fig.colorbar(im, ax=ax, shrink=0.8, extend="max", label=label)
    ax.set_title(
        f"{title}; hatched: no data\ncolour scale 0 to {hi:.3g} {unit} (98th percentile): "
        f"{beyond:.1f} % of cells beyond",
        fontsize=10,
    )
    return _save(fig, path, overwrite)


def count_map_png(count, path, *, transform, crs, title, label, none="none", overwrite=False):
    """Map of a per-cell count (dates, DEMs): one colour per value, 0 as no data (hatched,
    ``none`` says what it means), the share of cells at each count in the colour bar's
    ticks."""
    z, t = _prepare(np.where(np.asarray(count) > 0, count, np.nan), transform)
    fin = z[np.isfinite(z)].astype(int)
    top = int(fin.max()) if fin.size else 1
    values = np.arange(1, top + 1)
    cmap = ListedColormap(plt.get_cmap("viridis")(np.linspace(0.0, 1.0, max(top, 2)))[:top])
    cmap = cmap.with_extremes(bad=(0, 0, 0, 0))
    norm = BoundaryNorm(np.arange(0.5, top + 1.5), cmap.N)
    fig, ax = plt.subplots(figsize=(6.5, 6))
    extent = map_axes(ax, t, crs, z.shape)
    im = ax.imshow(
        np.ma.masked_invalid(z), cmap=cmap, norm=norm, interpolation="nearest", extent=extent
    )
    shown = values if top <= 12 else np.unique(np.linspace(1, top, 8).round().astype(int))
    cb = fig.colorbar(im, ax=ax, shrink=0.8, ticks=shown, label=label)
    cb.ax.set_yticklabels(
        [f"{v} ({100 * np.mean(fin == v):.0f} %)" if fin.size else str(v) for v in shown]
    )
    ax.set_title(
        f"{title}; hatched: {none}\ncolour bar: count (share of the counted cells)",
        fontsize=10,
    )
    return _save(fig, path, overwrite)


def change_figures(dh, sigma, transform, crs, out_dir, *, names, overwrite=False) -> dict:
    """``dh_map.png`` and ``dh_sigma_map.png`` of ``stereodem change`` in ``out_dir``;
    ``names``: (A's file name, B's); returns name -> path."""
    a, b = names
    out_dir = Path(out_dir)
    return {
        "dh_map": figures.difference_map_png(
            dh,
            out_dir / CHANGE_FIGURES["dh_map"],
            overwrite=overwrite,
            transform=transform,
            crs=crs,
            title=f"dh = {b} − {a} (B co-registered to A)",
            label="dh = B − A (m)",
        ),
        "dh_sigma_map": magnitude_map_png(
            sigma,
            out_dir / CHANGE_FIGURES["dh_sigma_map"],
            transform=transform,
            crs=crs,
            title=f"σ of dh ({b} − {a}, 1σ)",
            label="σ of dh (m)",
            overwrite=overwrite,
        ),
    }


def stack_figures(rates: dict, transform, crs, out_dir, *, what: str, overwrite=False) -> dict:
    """``rate_map.png``, ``rate_sigma_map.png`` and ``n_obs_map.png`` of ``stereodem stack``
    (``rates``: :func:`~stereodem.post.stack.stack_rates`'s arrays) in ``out_dir``; ``what``
    names the stack in the titles (its DEM count and dates); returns name -> path."""
    out_dir = Path(out_dir)
    return {
        "rate_map": figures.difference_map_png(
            rates["rate"],
            out_dir / STACK_FIGURES["rate_map"],
            overwrite=overwrite,
            transform=transform,
            crs=crs,
            title=f"Elevation change rate, {what}",
            label="rate (m/yr)",
            unit="m/yr",
            what="rate",
        ),
        "rate_sigma_map": magnitude_map_png(
            rates["rate_sigma"],
            out_dir / STACK_FIGURES["rate_sigma_map"],
            transform=transform,
            crs=crs,
            title=f"σ of the rate (1σ), {what}",
            label="σ of the rate (m/yr)",
            unit="m/yr",
            overwrite=overwrite,
        ),
        "n_obs_map": count_map_png(
            rates["n_obs"],
            out_dir / STACK_FIGURES["n_obs_map"],
            transform=transform,
            crs=crs,
            title=f"Dates used per cell, {what}",
            label="dates used (after rejection)",
            none="no date",
            overwrite=overwrite,
        ),
    }


def mosaic_figure_paths(out, method: str) -> dict:
    """The quick-look PNGs of the mosaic ``out`` (``OUT.tif`` -> ``OUT_<what>.png``)."""
    out = Path(out)
    names = {"count": ("count",), "stddev": ("stddev",), "nmad": ("nmad",)}.get(
        method, ("hillshade", "count")
    )
    return {n: out.with_name(f"{out.stem}_{n}.png") for n in names}


#: longest side (cells) of the mosaic's quick looks: about the figure's own pixels, so that
#: drawing them (a float64 RGBA copy of the image inside matplotlib, the shaded relief's
#: gradients) stays within the mosaic's memory bound (at DISPLAY_CELLS, 1400, the quick looks
#: of bench_mosaic's 17 M-cell mosaic peaked at 208 MB above the libraries, its blend at 71)
QUICKLOOK_CELLS = 700


def _read_decimated(ds, band: int):
    """Band ``band`` of an open raster at about :data:`QUICKLOOK_CELLS` on its longer side
    (the COG's overviews: the mosaic is never read whole), NaN for no data, and the transform
    of what was read."""
    k = max(1, int(np.ceil(max(ds.height, ds.width) / QUICKLOOK_CELLS)))
    shape = (max(1, ds.height // k), max(1, ds.width // k))
    a = ds.read(band, out_shape=shape, masked=True).astype(np.float64).filled(np.nan)
    t = ds.transform @ Affine.scale(ds.width / shape[1], ds.height / shape[0])
    return a, t


def mosaic_figures(out, method: str, *, n_dems: int, overwrite=False) -> dict:
    """The quick-look PNGs of the mosaic GeoTIFF ``out`` (:func:`mosaic_figure_paths`), read
    from its overviews; returns name -> path."""
    paths = mosaic_figure_paths(out, method)
    name = Path(out).name
    files = {}
    with rasterio.open(out) as ds:
        crs = ds.crs
        for key, path in paths.items():
            if key == "hillshade":
                z, t = _read_decimated(ds, 1)
                files[key] = figures.hillshade_png(
                    z,
                    t,
                    crs,
                    path,
                    overwrite=overwrite,
                    height_label=f"{ds.descriptions[0] or 'height'} (m)",
                    title=f"Shaded relief of {name} ({n_dems} DEMs, {method})",
                )
            elif key == "count":
                c, t = _read_decimated(ds, 1 if method == "count" else 2)
                files[key] = count_map_png(
                    np.nan_to_num(c, nan=0.0),
                    path,
                    transform=t,
                    crs=crs,
                    title=f"DEMs contributing per cell of {name}",
                    label="DEMs with a height",
                    none="no DEM",
                    overwrite=overwrite,
                )
            else:  # stddev / nmad of the DEMs' heights
                z, t = _read_decimated(ds, 1)
                files[key] = magnitude_map_png(
                    z,
                    path,
                    transform=t,
                    crs=crs,
                    title=f"{method} of the DEMs' heights, {name}",
                    label=f"{method} (m)",
                    overwrite=overwrite,
                )
    return {k: str(v) for k, v in files.items()}
