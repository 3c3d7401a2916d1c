"""Figures of a co-registration chain: dh before/after on the DEM grid, and each bias step's
binned dh against its variable with the fitted curve (PNG, written atomically)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

from .altimetry import AltimetryPoints
from .coreg import parameter_text, reference_on_grid

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from affine import Affine
from matplotlib.ticker import MaxNLocator

from stereodem.core.mapaxes import map_axes
from stereodem.core.stats import nmad

from .figures import _save, diverging_cmap


def _dh_on_grid(ref, dem):
    if isinstance(ref, AltimetryPoints):
        return None

    return reference_on_grid(ref, dem)


def dh_before_after_png(z_ref, dem, out, mask, path, *, overwrite=False, ref_name="reference"):
    """Two maps of DEM − reference (before, after) in map coordinates (km axes, a scale bar),
    stable NMAD in the titles; one diverging colour scale centred on 0, clipped at ± twice the
    98th percentile of |dh| after on stable terrain, the share of cells beyond it said in each
    map's title; the DEM's and the reference's names in the figure's title."""
    b = dem.heights - z_ref
    a = out.heights - z_ref
    k = max(1, int(np.ceil(max(b.shape) / 900)))
    lim = float(np.nanpercentile(np.abs(a[mask]), 98)) * 2 if np.isfinite(a[mask]).any() else 5.0
    lim = lim if lim > 0 else 1.0
    fig, ax = plt.subplots(1, 2, figsize=(11, 5.0))
    transform = dem.transform @ Affine.scale(k)
    for axis, d, title in zip(ax, (b, a), ("before", "after")):
        fin = d[np.isfinite(d)]
        beyond = 100 * float(np.mean(np.abs(fin) > lim)) if fin.size else 0.0
        stable_nmad, d = nmad(d[mask]), d[::k, ::k]
        extent = map_axes(axis, transform, dem.crs, d.shape)  # km axes and a scale bar
        axis.yaxis.set_major_locator(MaxNLocator(5))  # rotated labels: fewer, apart
        im = axis.imshow(
            np.ma.masked_invalid(d),
            cmap=diverging_cmap(),
            vmin=-lim,
            vmax=lim,
            interpolation="nearest",
            extent=extent,
        )
        axis.set_title(
            f"{title}: stable NMAD {stable_nmad:.2f} m\n"
            f"{beyond:.1f} % of cells beyond ±{lim:.2f} m",
            fontsize=9,
        )
    name = Path(dem.path).name if getattr(dem, "path", None) else "DEM"
    fig.suptitle(
        f"{name} − {ref_name} before and after co-registration; hatched: no data\n"
        f"colour scale clipped at ±{lim:.2f} m (twice the 98th percentile of |dh| after, "
        "stable terrain)",
        fontsize=10,
    )
    fig.colorbar(im, ax=ax, shrink=0.8, extend="both", label="DEM − reference (m)")
    return _save(fig, path, overwrite)


def _lines(items, width: int) -> str:
    """``items`` joined by ", " on lines of about ``width`` characters, never split."""
    lines = [""]
    for it in items:
        if lines[-1] and len(lines[-1]) + 2 + len(it) > width:
            lines[-1] += ","
            lines.append(it)
        else:
            lines[-1] = f"{lines[-1]}, {it}" if lines[-1] else it
    return "\n".join(lines)


def curve_png(
    step,
    path,
    *,
    overwrite=False,
    dem_name: str = "DEM",
    ref_name: str = "reference",
    index: int | None = None,
    n_steps: int | None = None,
):
    """Binned median dh against the step's variable and the fitted curve; the title names the
    DEM, the reference and the step's place in the chain, the legend gives the fitted values
    with σ and units (:func:`~stereodem.post.coreg.parameter_text`)."""
    c = step.curves
    fig, ax = plt.subplots(figsize=(6.5, 3.9))
    ax.plot(c["bin_centre"], c["bin_median"], ".", ms=4, label="binned median dh (stable)")
    fitted = parameter_text(step.parameters())
    label = "fit" + (": " + _lines(fitted.split(", "), 60) if fitted else "")
    ax.plot(c["model_x"], c["model_y"], "-", lw=1.5, label=label)
    ax.set_xlabel(c["x_label"])
    ax.set_ylabel(c.get("y_label", "dh (m)"))
    place = f"step {index + 1} of {n_steps}: " if index is not None and n_steps else ""
    ax.set_title(
        f"{dem_name} − {ref_name}, co-registration {place}{step.name}\n"
        "binned dh on stable terrain (before this step) and the fitted correction",
        fontsize=9,
    )
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.16))  # off the data
    return _save(fig, path, overwrite)


def chain_figures(chain, ref, dem, out, mask, out_dir, *, overwrite=False) -> dict:
    """Write the chain's figures into ``out_dir``; returns name -> path."""
    out_dir = Path(out_dir)
    files = {}
    z = _dh_on_grid(ref, dem)
    if z is not None:
        files["dh_png"] = str(
            dh_before_after_png(
                z,
                dem,
                out,
                mask & np.isfinite(z),
                out_dir / "coreg_dh.png",
                overwrite=overwrite,
                ref_name=Path(ref.path).name if getattr(ref, "path", None) else "reference",
            )
        )
    dem_name = Path(dem.path).name if getattr(dem, "path", None) else "DEM"
    ref_name = Path(ref.path).name if getattr(ref, "path", None) else "reference"
    for i, step in enumerate(chain.steps):
        if step.curves and "bin_centre" in step.curves:
            name = f"coreg_{i}_{step.name.replace(':', '')}.png"
            files[f"{step.name}_png"] = str(
                curve_png(
                    step,
                    out_dir / name,
                    overwrite=overwrite,
                    dem_name=dem_name,
                    ref_name=ref_name,
                    index=i,
                    n_steps=len(chain.steps),
                )
            )
    return files
