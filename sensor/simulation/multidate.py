"""Multi-date DEMs of the same terrain with a known elevation-change field (truth for stacks).

The truth: a reference surface ``h0`` (metres, on a :class:`~stereodem.core.grid.MapGrid`)
observed at ``t_ref`` and a rate field ``rate`` (m/yr, zero outside an outline), so that the
surface at date ``t`` is ``h0 + rate · (t − t_ref)`` (``t`` in decimal years).

Per-date DEM errors (shift, ramp, along-track oscillation, correlated noise) are injected by
:func:`stereodem.post.synthetic_series.dem_series` (with the co-registration tests' injector);
:func:`cloud_blunder` gives the heights a matcher finds over a cloud (the cloud top, hundreds of
metres above the terrain, sharp edges).

:func:`simulate_granule_series` renders the same truth as ASTER L1A granules, one per date
(through :func:`~stereodem.sensor.simulation.simulate.simulate_scene` and the granule writer),
so that granules -> DEMs -> stack -> rates can be checked end to end.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rasterio.features import rasterize
from scipy import ndimage

from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.core.grid import MapGrid
from stereodem.core.raster import write_geotiff
from stereodem.sensor.simulation.aster_granule import granule_from_scene, write_v004
from stereodem.sensor.simulation.simulate import simulate_scene, write_scene

DAYS_PER_YEAR = 365.25


def decimal_year(when) -> float:
    """Decimal year of a date or datetime (``numpy.datetime64`` accepted): 2010-07-02 -> ~2010.5."""
    d = np.datetime64(when, "s").astype("datetime64[s]").astype(object)
    if isinstance(d, _dt.date) and not isinstance(d, _dt.datetime):
        d = _dt.datetime(d.year, d.month, d.day)
    start = _dt.datetime(d.year, 1, 1)
    length = (_dt.datetime(d.year + 1, 1, 1) - start).total_seconds()
    return d.year + (d - start).total_seconds() / length


def cloud_blunder(terrain, centre, radius: float, top: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Heights a stereo matcher finds over a cloud: ``max(terrain, top)`` plus a few metres of
    texture inside an irregular blob around ``centre`` (col, row) of about ``radius`` cells,
    edges softened over one cell. Returns (added heights, cloud footprint)."""
    rows, cols = terrain.shape
    rr, cc = np.mgrid[0:rows, 0:cols].astype(np.float32)
    d = np.hypot(cc - centre[0], rr - centre[1]) / max(radius, 1.0)
    wobble = ndimage.gaussian_filter(
        rng.standard_normal(terrain.shape).astype(np.float32), radius / 3
    )
    wobble *= np.float32(0.25 / max(float(wobble.std()), 1e-9))
    inside = (d + wobble) < 1.0
    surface = np.maximum(terrain, np.float32(top)) + rng.normal(0, 3.0, terrain.shape).astype(
        np.float32
    )
    added = np.where(inside, surface - terrain, 0).astype(np.float32)
    added = ndimage.gaussian_filter(added, 1.0)
    return added, inside


@dataclass
class ChangeTruth:
    """The known elevation change: the surface ``h0`` at ``t_ref`` (decimal year) and the rate
    field (m/yr) on ``grid``; ``outline`` (shapely polygon in the grid's CRS) where it is not 0."""

    grid: MapGrid
    h0: np.ndarray
    rate: np.ndarray
    t_ref: float
    outline: object = None

    def surface(self, t: float) -> np.ndarray:
        """The true surface at decimal year ``t`` (metres)."""
        return (self.h0 + self.rate * np.float32(t - self.t_ref)).astype(np.float32)


def thinning_truth(
    grid: MapGrid, h0, outline, *, t_ref: float, rate_low: float = -2.0, rate_high: float = -0.5
) -> ChangeTruth:
    """A glacier-like change: inside ``outline`` (shapely polygon, grid CRS) the rate varies
    linearly with elevation from ``rate_low`` (m/yr) at the outline's lowest cell to
    ``rate_high`` at its highest (thinning strongest at the tongue); 0 outside."""
    inside = rasterize(
        [(outline, 1)], out_shape=grid.shape, transform=grid.transform, fill=0, dtype="uint8"
    ).astype(bool)
    if not inside.any():
        raise InputError("the outline covers no cell of the grid")
    h0 = np.asarray(h0, np.float32)
    lo, hi = np.nanmin(h0[inside]), np.nanmax(h0[inside])
    frac = (h0 - lo) / max(hi - lo, 1e-6)
    rate = np.where(inside, rate_low + (rate_high - rate_low) * frac, 0).astype(np.float32)
    return ChangeTruth(grid, h0, rate, float(t_ref), outline)


def write_dem_series(dems, dates, out_dir, *, overwrite: bool = False, stem: str = "dem") -> list:
    """Write each :class:`DEM` as ``<stem>_<YYYY-MM-DD>.tif`` with its date in the GeoTIFF tag
    ``ACQUISITION_DATE`` (how :mod:`stereodem.post.dates` finds it); returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for dem, date in zip(dems, dates):
        day = str(np.datetime64(date, "D"))
        p = out / f"{stem}_{day}.tif"
        write_geotiff(
            p,
            dem.heights,
            dem.transform,
            dem.crs,
            np.nan,
            overwrite=overwrite,
            vertical=dem.vertical,
            tags={"ACQUISITION_DATE": day},
            descriptions="height",
            units="metre",
        )
        paths.append(p)
    return paths


# ----------------------------------------------------------------------------- granules


def simulate_granule_series(
    dem: DEM,
    dates,
    *,
    outline_lonlat,
    t_ref: float,
    rate_low: float = -2.0,
    rate_high: float = -0.5,
    out_dir,
    size=(300, 300),
    seed: int = 0,
    cloud: dict | None = None,
    overwrite: bool = False,
) -> list:
    """ASTER L1A V004 granules of ``dem``'s terrain, one per date, with the terrain changed by
    a thinning field inside ``outline_lonlat`` (shapely polygon, lon/lat degrees): each date's
    DEM is ``dem + rate · (t − t_ref)`` on ``dem``'s own grid, rendered through the ASTER preset
    and written by the granule writer with that date as acquisition start.

    ``cloud`` (``{"date_index": k, "centre_lonlat": (lon, lat), "radius_deg": r, "top": m}``)
    raises the rendered surface of one date to a cloud top (the matcher sees the cloud).

    Returns a list of dicts: ``date``, ``granule`` (path), ``folder`` (with the scene truth)."""
    g = dem.grid
    truth = thinning_truth(
        g, dem.heights, outline_lonlat, t_ref=t_ref, rate_low=rate_low, rate_high=rate_high
    )
    out = Path(out_dir)
    records = []
    for k, d in enumerate(dates):
        day = np.datetime64(d, "D")
        z = truth.surface(decimal_year(day))
        if cloud and cloud.get("date_index") == k:
            lon, lat = g.cell_centres()
            r = np.hypot(lon - cloud["centre_lonlat"][0], lat - cloud["centre_lonlat"][1])
            z = np.where(r < cloud["radius_deg"], np.maximum(z, np.float32(cloud["top"])), z)
        dated = DEM(z.astype(np.float32), dem.transform, dem.crs, dem.vertical, dem.path)
        scene = simulate_scene(
            "aster",
            size=size,
            right_size=(round(size[0] * 5000 / 4100 / 10.0) * 10, round(size[1] * 5400 / 4200)),
            dem=dated,
            seed=seed + k,
        )
        start = _dt.datetime.fromisoformat(str(day)).replace(hour=8, minute=30)
        gr = granule_from_scene(scene, seed=seed + k, start=start)
        folder = write_scene(scene, out / str(day), overwrite=overwrite, write_images=False)
        path = write_v004(gr, folder / f"{gr.granule_id}.hdf", overwrite=overwrite)
        records.append(dict(date=str(day), granule=path, folder=folder))
    return records
