"""Putting one raster on another's grid (rasterio.warp.reproject), with shifts in metres."""

from __future__ import annotations

import numpy as np
from affine import Affine
from rasterio.crs import CRS as RioCRS
from rasterio.warp import Resampling, reproject

from stereodem.core import geodesy
from stereodem.core.errors import NoOverlapError

from . import terrain

_RESAMPLING = {
    "nearest": Resampling.nearest,
    "bilinear": Resampling.bilinear,
    "cubic": Resampling.cubic,
    "cubic_spline": Resampling.cubic_spline,
}


def to_grid(
    data,
    src_transform,
    src_crs,
    dst_transform,
    dst_crs,
    dst_shape,
    *,
    resampling: str = "bilinear",
    src_nodata=np.nan,
    dst_dtype=np.float32,
    threads: int | None = None,
):
    """Warp a 2-D array onto a destination grid; cells without data are NaN (or ``src_nodata``
    for integer rasters). GDAL's warper runs on ``threads`` threads (default 1: callers
    that warp blocks on a thread pool already use the cores; a caller that warps a whole grid
    passes the process's budget, :func:`stereodem.post.blocks.default_threads`); the result
    does not depend on it."""
    src = np.asarray(data)
    if np.issubdtype(np.dtype(dst_dtype), np.floating):
        src = src.astype(np.float32, copy=False)
        fill = np.nan
    else:
        fill = src_nodata if src_nodata is not None else 0
    dst = np.full(dst_shape, fill, dtype=dst_dtype)
    reproject(
        src,
        dst,
        src_transform=src_transform,
        src_crs=_rio_crs(src_crs),
        src_nodata=src_nodata,
        dst_transform=dst_transform,
        dst_crs=_rio_crs(dst_crs),
        dst_nodata=fill,
        resampling=_RESAMPLING[resampling],
        num_threads=max(1, int(threads or 1)),
    )
    return dst


def _rio_crs(crs):
    return RioCRS.from_wkt(geodesy._crs_key(crs))


def metres_per_unit(transform, crs, shape):
    """Metres per CRS unit east and north at the grid centre."""
    if terrain._is_geographic(crs):
        _, lat = terrain.grid_centre_lonlat(transform, crs, shape)
        mlon, mlat = terrain.metres_per_degree(lat)
        return float(mlon), float(mlat)
    f = terrain._linear_unit_factor(crs)
    return f, f


def translated(transform, crs, shape, east_m: float, north_m: float) -> Affine:
    """``transform`` moved by ``east_m``, ``north_m`` metres (converted at the grid centre)."""
    fx, fy = metres_per_unit(transform, crs, shape)
    return Affine.translation(east_m / fx, north_m / fy) @ transform


def check_overlap(a_bounds, b_bounds, a_name="DEM", b_name="reference"):
    """Raise :class:`NoOverlapError` if two (west, south, east, north) boxes do not overlap."""
    w = max(a_bounds[0], b_bounds[0])
    e = min(a_bounds[2], b_bounds[2])
    s = max(a_bounds[1], b_bounds[1])
    n = min(a_bounds[3], b_bounds[3])
    if w >= e or s >= n:
        raise NoOverlapError(
            f"{a_name} (lon/lat {tuple(round(v, 4) for v in a_bounds)}) does not "
            f"overlap {b_name} (lon/lat {tuple(round(v, 4) for v in b_bounds)})"
        )
