"""A series of erroneous DEMs of a changing surface, for the stack tests and benchmark: the
truth of :class:`stereodem.sensor.simulation.multidate.ChangeTruth` at each date, with that
date's errors injected by :func:`stereodem.post.synthetic.inject_errors` (shift, offset, ramp,
along-track sines, correlated noise) and optionally a cloud
(:func:`stereodem.sensor.simulation.multidate.cloud_blunder`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyogrio
import shapely
from affine import Affine
from pyproj import CRS

from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.sensor.simulation.multidate import ChangeTruth, cloud_blunder, decimal_year

from . import warp
from .synthetic import InjectedErrors, inject_errors


@dataclass
class SeriesDEM:
    """One DEM of a series: the DEM, its date, what was injected, the noise-only heights
    (truth + noise, same grid) and the cloud footprint (bool)."""

    dem: DEM
    date: np.datetime64
    spec: InjectedErrors
    noise_only: np.ndarray
    cloud: np.ndarray


def dem_series(truth: ChangeTruth, dates, specs, *, clouds=None, vertical=None) -> list[SeriesDEM]:
    """One :class:`SeriesDEM` per date. ``specs``: one :class:`InjectedErrors` per date;
    ``clouds``: per date None or ``{"centre": (col, row), "radius": cells, "top": m}``."""
    if len(dates) != len(specs):
        raise InputError(f"{len(dates)} dates for {len(specs)} error specifications")
    clouds = clouds or [None] * len(dates)
    out = []
    for d, spec, cloud in zip(dates, specs, clouds):
        z = truth.surface(decimal_year(d))
        clean = DEM(z, truth.grid.transform, truth.grid.crs, vertical, None)
        dem, info = inject_errors(clean, spec)
        h = dem.heights
        footprint = np.zeros(h.shape, bool)
        if cloud:
            rng = np.random.default_rng(spec.seed + 7)
            added, footprint = cloud_blunder(h, cloud["centre"], cloud["radius"], cloud["top"], rng)
            h = (h + added).astype(np.float32)
        out.append(
            SeriesDEM(
                DEM(h, dem.transform, dem.crs, vertical, None),
                np.datetime64(d, "D"),
                spec,
                (z + info["noise"]).astype(np.float32),
                footprint,
            )
        )
    return out


def write_polygons(path, geoms, crs, *, driver: str | None = None):
    """Write shapely polygons with their CRS as a vector file (pyogrio; the driver from the
    suffix: .gpkg, .geojson, .shp), one ``id`` field (1, 2, ...)."""
    geoms = list(geoms)
    wkb = np.array([shapely.to_wkb(g) for g in geoms], dtype=object)
    pyogrio.raw.write(
        str(path),
        wkb,
        [np.arange(1, len(geoms) + 1, dtype=np.int32)],
        ["id"],
        driver=driver,
        geometry_type="Polygon",
        crs=CRS.from_user_input(crs).to_wkt(),
    )
    return path


def utm_reference(dem: DEM, size: int, res: float, *, centre_lonlat=None) -> DEM:
    """A ``size`` × ``size`` crop of ``dem`` resampled (cubic) on a UTM grid of ``res`` metres
    around ``centre_lonlat`` (default the DEM's centre); keeps the vertical reference."""
    if centre_lonlat is None:
        w, s, e, n = dem.bounds_lonlat()
        centre_lonlat = ((w + e) / 2, (s + n) / 2)
    crs = geodesy.utm_crs(*centre_lonlat)
    x0, y0 = geodesy.lonlat_to_crs(*centre_lonlat, crs)
    x0 = np.floor(float(x0) / res) * res - size / 2 * res
    y0 = np.floor(float(y0) / res) * res + size / 2 * res
    t = Affine(res, 0.0, x0, 0.0, -res, y0)
    h = warp.to_grid(dem.heights, dem.transform, dem.crs, t, crs, (size, size), resampling="cubic")
    if np.isnan(h).any():
        raise InputError(f"{dem.path or 'DEM'}: does not cover the {size} x {size} crop")
    return DEM(h, t, crs, dem.vertical, None)


def glacier_outline(grid, *, centre=(0.6, 0.45), radius=0.15):
    """A disc-like outline at ``centre`` (col, row fractions) of ``radius`` × the grid width,
    in the grid's CRS (a shapely polygon), slightly irregular."""
    cx, cy = grid.transform @ (grid.width * centre[0], grid.height * centre[1])
    r = grid.width * abs(grid.transform.a) * radius
    ang = np.linspace(0, 2 * np.pi, 73)[:-1]
    rr = r * (1 + 0.15 * np.sin(3 * ang) + 0.08 * np.cos(5 * ang))
    return shapely.Polygon(np.column_stack([cx + rr * np.cos(ang), cy + rr * np.sin(ang)]))
