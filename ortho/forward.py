"""The forward DRM of Bettemir (2006, §4.1 and §6.5): image -> ground, pixel by pixel.

Each image pixel's line of sight is intersected with the ellipsoid and moved along the ray by
the relief iteration until it meets the DEM
(:meth:`stereodem.sensor.models.base.SensorModel.localize_dem`); the irregular ground points are
then put on a map grid by nearest neighbour ("round to the nearest", thesis §4.1.9). This is the
thesis's method, kept for comparison and validation: holes appear where the ground is sampled more
finely than the image, and the backward projection of :mod:`stereodem.ortho.drm` is the production
path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pyproj import CRS

from stereodem.core import geodesy
from stereodem.core.errors import InputError
from stereodem.core.grid import MapGrid


@dataclass
class ForwardPoints:
    """Ground points of image pixels (forward DRM).

    ``col, row``: pixels; ``lon, lat`` degrees, ``h`` metres above the ellipsoid; ``x, y`` map
    coordinates in ``crs`` (metres); ``converged`` false where the relief iteration failed or
    left the DEM (NaN ground coordinates off the DEM); ``iterations`` per pixel.
    """

    col: np.ndarray
    row: np.ndarray
    lon: np.ndarray
    lat: np.ndarray
    h: np.ndarray
    x: np.ndarray
    y: np.ndarray
    crs: object
    converged: np.ndarray
    iterations: np.ndarray


def forward_localize(
    model,
    dem,
    *,
    cols=None,
    rows=None,
    step: int = 1,
    crs=None,
    threshold: float = 0.1,
    max_iterations: int = 30,
) -> ForwardPoints:
    """Localise image pixels on the DEM by the DRM relief iteration.

    Parameters
    ----------
    model : stereodem.sensor.models.base.SensorModel
    dem : stereodem.core.dem.DEM
    cols, rows : array_like, optional
        Pixels to localise (default every ``step``-th pixel of the image, both axes).
    crs : CRS-like, optional
        Map CRS of ``x, y`` (default the UTM zone of the image centre).
    threshold, max_iterations
        Relief-iteration stop (m) and cap (thesis: 0.1 m, 30).
    """
    if cols is None or rows is None:
        cols, rows = np.meshgrid(
            np.arange(0, model.width, step, dtype=float),
            np.arange(0, model.height, step, dtype=float),
        )
    cols, rows = np.broadcast_arrays(np.asarray(cols, float), np.asarray(rows, float))
    loc = model.localize_dem(cols, rows, dem, threshold=threshold, max_iterations=max_iterations)
    if crs is None:
        crs = geodesy.utm_crs(
            *model.center_lonlat(float(np.nanmedian(loc.h)) if np.isfinite(loc.h).any() else 0.0)
        )
    ok = np.isfinite(loc.lon) & np.isfinite(loc.lat)
    x = np.full(cols.shape, np.nan)
    y = np.full(cols.shape, np.nan)
    if ok.any():
        x[ok], y[ok] = geodesy.lonlat_to_crs(loc.lon[ok], loc.lat[ok], crs)
    return ForwardPoints(
        cols, rows, loc.lon, loc.lat, loc.h, x, y, crs, loc.converged, loc.iterations
    )


def forward_ortho(image, points: ForwardPoints, grid: MapGrid, *, nodata: float = np.nan):
    """Nearest-neighbour forward orthoimage: each pixel's value goes to the grid cell that
    contains its ground point; when several pixels land in one cell the one whose ground point
    is nearest the cell centre wins.

    Parameters
    ----------
    image : ndarray (rows, cols)
        Indexed at ``points.row, points.col`` (integers).
    points : ForwardPoints
        From :func:`forward_localize`, in ``grid.crs``.

    Returns
    -------
    data : ndarray float32 (grid rows, cols), ``nodata`` in cells no pixel reached.
    source : ndarray int64 (grid rows, cols)
        Flat index (into ``points``) of the pixel that filled each cell, -1 where empty.
    """
    if CRS.from_user_input(points.crs) != grid.crs:
        raise InputError("forward_ortho: the ground points and the grid use different CRSs")
    img = np.asarray(image)
    u, v = grid.colrow(points.x.ravel(), points.y.ravel())
    ok = np.isfinite(u) & np.isfinite(v) & points.converged.ravel()
    iu, iv = np.rint(np.where(ok, u, -1)), np.rint(np.where(ok, v, -1))
    ok &= (iu >= 0) & (iv >= 0) & (iu < grid.width) & (iv < grid.height)
    idx = np.nonzero(ok)[0]
    cell = (iv[idx] * grid.width + iu[idx]).astype(np.int64)
    dist = np.hypot(u[idx] - iu[idx], v[idx] - iv[idx])
    order = np.lexsort((dist, cell))  # by cell, nearest first
    first = np.unique(cell[order], return_index=True)[1]
    win = order[first]
    src = np.full(grid.width * grid.height, -1, dtype=np.int64)
    src[cell[win]] = idx[win]
    data = np.full(grid.width * grid.height, nodata, dtype=np.float32)
    pc = points.col.ravel()[idx[win]].astype(np.intp)
    pr = points.row.ravel()[idx[win]].astype(np.intp)
    data[cell[win]] = img[pr, pc]
    return data.reshape(grid.shape), src.reshape(grid.shape)
