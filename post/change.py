"""Elevation change between two DEMs (``stereodem change DEM_A DEM_B``): ``dh = B − A`` on A's
grid after co-registering B to A on stable terrain, and its σ map.

σ per cell is the heteroscedastic dispersion of ``dh`` on stable terrain against slope and
maximum curvature (Hugonnet et al. 2022; :func:`stereodem.post.spatialstats.heteroscedasticity`):
the NMAD of the stable ``dh`` in the cell's slope × curvature bin, interpolated. It is the σ of
the difference of the two DEMs, so it holds both DEMs' errors; a real change in unstable terrain
is not in it. With the two dates the rate ``dh / Δt`` and its σ follow.
"""

from __future__ import annotations

import numpy as np

from stereodem.core.blocks import default_threads
from stereodem.core.dem import DEM, as_dem
from stereodem.core.errors import InputError

from . import terrain, warp
from .assess import reconcile_vertical
from .biascorr import maximum_curvature
from .spatialstats import heteroscedasticity
from .stack_build import BuildSettings, exclude_mask, fit_chain
from .stats import error_stats


def dem_change(
    dem_a: DEM,
    dem_b: DEM,
    *,
    chain: str = "nuth_kaab,deramp:1",
    exclude=(),
    track_angle_deg: float | None = None,
    threads: int | None = None,
) -> dict:
    """``dh = B − A`` on A's grid and its σ map; returns a dict with ``dh``, ``sigma`` (arrays,
    m), ``stable`` (bool), ``coregistration`` (the chain's report), ``stats_stable`` (after) and
    ``heteroscedasticity`` (the binned table, without the per-cell array).

    ``threads``: threads of the warp onto A's grid, the curvature and the σ map (default: the
    process's budget, :func:`stereodem.core.blocks.default_threads`); the numbers do not
    depend on it. ``dem_a``/``dem_b`` may be DEM file paths."""
    dem_a, dem_b = as_dem(dem_a), as_dem(dem_b)
    threads = default_threads() if threads is None else int(threads)
    dem_b, vnote = reconcile_vertical(dem_b, dem_a)
    warp.check_overlap(
        dem_b.bounds_lonlat(),
        dem_a.bounds_lonlat(),
        f"{dem_b.path or 'DEM B'}",
        f"{dem_a.path or 'DEM A'}",
    )
    stable_b = exclude_mask(list(exclude), dem_b)
    settings = BuildSettings(chain=chain, exclude=list(exclude), track_angle_deg=track_angle_deg)
    corrected, report, _ = fit_chain(dem_a, dem_b, stable_b, settings, track_angle_deg)
    g = dem_a.grid
    hb = corrected.reproject(dem_a, threads=threads).heights  # B's heights on A's grid
    dh = (hb - dem_a.heights).astype(np.float32)
    if not np.isfinite(dh).any():
        raise InputError(f"{dem_b.path}: no overlap with {dem_a.path} after co-registration")
    stable = exclude_mask(list(exclude), dem_a)
    slope = terrain.slope_deg(dem_a.heights, g.transform, g.crs)
    curv = maximum_curvature(dem_a.heights, g.transform, g.crs, threads=threads)
    het = heteroscedasticity(np.where(stable, dh, np.nan), slope, curv, threads=threads)
    sigma = np.where(np.isfinite(dh), het.pop("sigma"), np.nan).astype(np.float32)
    return dict(
        dh=dh,
        sigma=sigma,
        stable=stable,
        coregistration=report,
        vertical=vnote,
        stats_stable=error_stats(dh[stable]),
        heteroscedasticity=het,
    )
