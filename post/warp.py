"""Shifts in metres (ground metres on a geographic grid, grid metres, the CRS's units, on a
projected one) and the projection's scale; the warp of arrays itself, :func:`to_grid` and
its helpers, lives in :mod:`stereodem.core.warp` (re-exported here, where every ``post``
module has always found it)."""

from __future__ import annotations

import cv2
import numpy as np
from affine import Affine
from pyproj import CRS, Proj

from stereodem.core.warp import (  # noqa: F401 - re-exported: post's one place to warp
    RESAMPLING_METHODS,
    TRANSFORM_TOLERANCE_PX,
    WRAP_CELLS,
    _turn,
    beside,
    check_overlap,
    grid_kernel_scale,
    is_global,
    kernel_scale_options,
    kernel_scales,
    rio_crs,
    same_horizontal_crs,
    to_grid,
    wrapped,
)

from . import terrain


def metres_per_unit(transform, crs, shape):
    """Metres per CRS unit along the grid's x (east) and y (north) axes at the grid centre.

    Geographic CRS: ground metres per degree of longitude and of latitude at the centre's
    latitude (WGS84 radii). Projected CRS: the CRS's linear unit in metres (1.0 for metres,
    0.3048 for feet), the same everywhere: a length so converted is in *grid metres*, not
    ground metres; ground metres = grid metres / the projection's scale factor
    (:func:`scale_factors`; within 0.04 % of 1 in UTM, several % in a polar stereographic
    grid away from its true-scale latitude). Shifts in metres on a projected grid
    (:func:`translated`, the co-registration's ``dx``/``dy``) are grid metres."""
    if terrain._is_geographic(crs):
        _, lat = terrain.grid_centre_lonlat(transform, crs, shape)
        mlon, mlat = terrain.metres_per_degree(lat)
        return float(mlon), float(mlat)
    f = terrain._linear_unit_factor(crs)
    return f, f


def scale_factors(transform, crs, shape) -> tuple[float, float]:
    """The projection's point scale factors at the grid centre: ``(h, k)``, grid length over
    ground (WGS84 ellipsoid) length along the parallel (east) and along the meridian (north),
    pyproj's ``parallel_scale`` and ``meridional_scale`` (dimensionless; equal in a conformal
    projection: UTM, polar stereographic, Mercator). ``(1.0, 1.0)`` for a geographic CRS,
    whose degrees :func:`metres_per_unit` converts to ground metres itself.

    A length of ``d`` grid metres (CRS units times :func:`metres_per_unit`) along the grid's
    x axis is ``d / h`` ground metres, along y ``d / k`` (exact for a conformal projection,
    whose scale is the same in every direction, also where the grid's axes are turned from
    east/north; approximate for another away from its central meridian)."""
    if terrain._is_geographic(crs):
        return 1.0, 1.0
    lon, lat = terrain.grid_centre_lonlat(transform, crs, shape)
    f = Proj(CRS.from_user_input(crs)).get_factors(lon, lat)
    return float(f.parallel_scale), float(f.meridional_scale)


def translated(transform, crs, shape, east_m: float, north_m: float) -> Affine:
    """``transform`` moved by ``east_m``, ``north_m`` metres along its x/y axes (converted by
    :func:`metres_per_unit` at the grid centre: grid metres, the CRS's units, on a projected
    grid)."""
    fx, fy = metres_per_unit(transform, crs, shape)
    return Affine.translation(east_m / fx, north_m / fy) @ transform


def _keys_cubic(t: float) -> np.ndarray:
    """The four weights of GDAL's cubic kernel (Keys, a = -0.5) for a sample ``t`` in [0, 1)
    of the way from tap 1 to tap 2 (taps at -1, 0, 1, 2)."""
    a = -0.5
    d = np.abs(np.array([t + 1.0, t, 1.0 - t, 2.0 - t]))
    near = (a + 2) * d**3 - (a + 3) * d**2 + 1
    far = a * d**3 - 5 * a * d**2 + 8 * a * d - 4 * a
    return np.where(d <= 1, near, far)


def shifted_cubic(z, cols: float, rows: float) -> np.ndarray:
    """``z`` sampled at ``(row + rows, col + cols)`` for every cell, by the cubic convolution
    of GDAL's warper (Keys, a = -0.5): a pure translation of a grid is one separable 4 x 4
    filter with the same weights everywhere, so it runs as ``cv2.sepFilter2D`` (float64)
    instead of a warp. NaN where the 4 x 4 support leaves the grid or touches a NaN (GDAL
    instead re-weights the valid taps there: the two agree to rounding elsewhere).

    ``cols``/``rows``: the shift in pixels (any real numbers). Returns float64."""
    z = np.asarray(z, dtype=np.float64)
    h, w = z.shape
    ic, ir = int(np.floor(cols)), int(np.floor(rows))
    kx, ky = _keys_cubic(cols - ic), _keys_cubic(rows - ir)
    pad = cv2.copyMakeBorder(z, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=np.nan)
    # correlation with anchor 1: f[y, x] = sum_k k[k] * pad[y, x + k - 1], the sample at x + t
    f = cv2.sepFilter2D(pad, cv2.CV_64F, kx, ky, anchor=(1, 1), borderType=cv2.BORDER_REPLICATE)
    out = np.full((h, w), np.nan)
    # out[r, c] = f[r + ir + 2, c + ic + 2] where that lies inside f's valid part
    r0, r1 = max(0, -ir - 2), min(h, h - ir + 2)
    c0, c1 = max(0, -ic - 2), min(w, w - ic + 2)
    if r1 > r0 and c1 > c0:
        out[r0:r1, c0:c1] = f[r0 + ir + 2 : r1 + ir + 2, c0 + ic + 2 : c1 + ic + 2]
    return out


def shift_in_pixels(transform, crs, shape, east_m: float, north_m: float):
    """``(cols, rows)``: the pixel offsets at which :func:`translated`'s grid, warped back
    onto ``transform``, samples the original (a grid moved east samples to the west); for a
    north-up ``transform`` (no rotation terms)."""
    t = translated(transform, crs, shape, east_m, north_m)
    return -(t.c - transform.c) / transform.a, -(t.f - transform.f) / transform.e
