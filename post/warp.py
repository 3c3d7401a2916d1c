"""Putting one raster on another's grid (rasterio.warp.reproject), with shifts in metres
(ground metres on a geographic grid, grid metres, the CRS's units, on a projected one)."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import rasterio.transform
from affine import Affine
from pyproj import CRS, Proj
from rasterio.crs import CRS as RioCRS
from rasterio.errors import NotGeoreferencedWarning
from rasterio.warp import Resampling, reproject, transform_bounds

from stereodem.core import geodesy
from stereodem.core.errors import NoOverlapError

from . import terrain

_IN_MEMORY_WARP = r"rasterio\.warp$"


def _ignore_in_memory_warp_warning() -> None:
    """rasterio's ``reproject`` of arrays warns "Dataset has no geotransform, gcps, or rpcs"
    from its in-memory datasets although it is given their transforms; it suppresses that
    with ``warnings.catch_warnings``, which is not thread-safe before Python 3.14 (one thread
    leaving the block restores the filters another thread had set), so blocks warped on
    threads printed the warning at random (about 1 in 2000 calls on 4 threads; the same in
    geoutils #851, odc-geo #131). One process-wide filter, for that warning from
    ``rasterio.warp`` only (every call here passes both transforms; reading a file without
    georeferencing still warns, and a DEM without one is an error: :mod:`stereodem.core.dem`),
    set when this module is imported and again by a warp that finds it gone (a
    ``catch_warnings`` block around the import, as pytest's, restores the filters of before)."""
    for action, _, category, module, _ in warnings.filters:
        if category is NotGeoreferencedWarning and module is not None:
            if action == "ignore" and module.pattern == _IN_MEMORY_WARP:
                return
    warnings.filterwarnings("ignore", category=NotGeoreferencedWarning, module=_IN_MEMORY_WARP)


_ignore_in_memory_warp_warning()

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
    passes the process's budget, :func:`stereodem.core.blocks.default_threads`); the result
    does not depend on it."""
    _ignore_in_memory_warp_warning()
    src = np.asarray(data)
    src_transform = beside(src_transform, src_crs, src.shape, dst_transform, dst_crs, dst_shape)
    if is_global(src_transform, src_crs, src.shape) and _near_seam(
        src_transform, src_crs, src.shape, dst_transform, dst_crs, dst_shape
    ):  # interpolated across its seam at 180
        src, src_transform = wrapped(src, src_transform, WRAP_CELLS)
    if np.issubdtype(np.dtype(dst_dtype), np.floating):
        src = src.astype(np.float32, copy=False)
        fill = np.nan
    else:
        fill = src_nodata if src_nodata is not None else 0
    dst = np.full(dst_shape, fill, dtype=dst_dtype)
    kw = dict(
        src_crs=_rio_crs(src_crs),
        src_nodata=src_nodata,
        dst_transform=dst_transform,
        dst_crs=_rio_crs(dst_crs),
        dst_nodata=fill,
        resampling=_RESAMPLING[resampling],
        num_threads=max(1, int(threads or 1)),
    )
    reproject(src, dst, src_transform=src_transform, **kw)
    for turn in _overflow_turns(
        src_transform, src_crs, src.shape, dst_transform, dst_crs, dst_shape
    ):
        # the part of ``src`` beyond 180 (or -180) of a global grid: on its other edge
        more = np.full(dst_shape, fill, dtype=dst_dtype)
        reproject(src, more, src_transform=Affine.translation(turn, 0.0) @ src_transform, **kw)
        empty = np.isnan(dst) if np.isnan(fill) else dst == fill
        dst[empty] = more[empty]
    return dst


#: columns a global lon/lat grid is extended by on either side, from its other edge, before
#: a warp: the support of the cubic kernels (2), so cells within a cell of 180 E interpolate
#: across it instead of taking the edge column's value
WRAP_CELLS = 3


def is_global(transform, crs, shape) -> bool:
    """Whether a north-up grid in a geographic CRS spans the whole turn of longitude (within
    half a cell): its east edge is its west edge again."""
    if transform.b or transform.d or not terrain._is_geographic(crs):
        return False
    return abs(abs(transform.a) * shape[-1] - 360.0) <= abs(transform.a) / 2


def wrapped(data, transform, cells: int):
    """A global lon/lat grid (:func:`is_global`) extended by ``cells`` columns on either side,
    from its other edge (west of -180 the columns at 180 and so on); returns
    ``(data, transform)``."""
    data = np.asarray(data)
    cells = min(int(cells), data.shape[-1])
    data = np.concatenate([data[..., -cells:], data, data[..., :cells]], axis=-1)
    return data, transform @ Affine.translation(-cells, 0)


def _near_seam(src_transform, src_crs, src_shape, dst_transform, dst_crs, dst_shape) -> bool:
    """Whether the grid ``dst`` comes within :data:`WRAP_CELLS` cells of the edges of the
    global lon/lat grid ``src`` (or crosses the antimeridian): only then is ``src`` extended
    (a copy of it)."""
    bounds = rasterio.transform.array_bounds(*dst_shape[-2:], dst_transform)
    try:
        w, _, e, _ = transform_bounds(_rio_crs(dst_crs), _rio_crs(src_crs), *bounds, densify_pts=21)
    except Exception:  # noqa: BLE001 - bounds PROJ cannot take: extend, to be safe
        return True
    margin = WRAP_CELLS * abs(src_transform.a)
    sw, se = sorted((src_transform.c, src_transform.c + src_transform.a * src_shape[-1]))
    return w > e or w < sw + margin or e > se - margin


def _overflow_turns(src_transform, src_crs, src_shape, dst_transform, dst_crs, dst_shape):
    """The turns (±360) that put the part of a lon/lat grid ``src`` lying beyond the edge of a
    global lon/lat grid ``dst`` (:func:`is_global`: a DEM at 179.9..180.1 E against a
    -180..180 reference) onto ``dst``'s other edge; GDAL does not wrap between grids of one
    geographic CRS."""
    if not (terrain._is_geographic(src_crs) and is_global(dst_transform, dst_crs, dst_shape)):
        return []
    sw, se = sorted((src_transform.c, src_transform.c + src_transform.a * src_shape[-1]))
    dw, de = sorted((dst_transform.c, dst_transform.c + dst_transform.a * dst_shape[-1]))
    return [t for t, beyond in ((-360.0, se > de), (360.0, sw < dw)) if beyond]


def _turn(a_west, a_east, b_west, b_east) -> float:
    """Whole turns (degrees, a multiple of 360) that put longitudes ``b_west..b_east`` nearest
    ``a_west..a_east``: 0 unless they lie on either side of the antimeridian."""
    return 360.0 * round(((a_west + a_east) - (b_west + b_east)) / 720.0)


def beside(src_transform, src_crs, src_shape, dst_transform, dst_crs, dst_shape) -> Affine:
    """``src_transform`` moved by whole turns of longitude beside the grid ``dst_transform``
    when both CRSs are geographic (a DEM at 179.97..180.03 E and a reference tile at
    -180..-179.9 E overlap; GDAL does not wrap between grids in one geographic CRS, so
    warping one onto the other gave no cell); unchanged otherwise."""
    if not (terrain._is_geographic(src_crs) and terrain._is_geographic(dst_crs)):
        return src_transform
    turn = _turn(
        dst_transform.c,
        dst_transform.c + dst_transform.a * dst_shape[-1],
        src_transform.c,
        src_transform.c + src_transform.a * src_shape[-1],
    )
    return Affine.translation(turn, 0.0) @ src_transform if turn else src_transform


def _rio_crs(crs):
    return RioCRS.from_wkt(geodesy._crs_key(crs))


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


def check_overlap(a_bounds, b_bounds, a_name="DEM", b_name="reference"):
    """Raise :class:`NoOverlapError` if two (west, south, east, north) boxes do not overlap
    (longitudes compared modulo 360 degrees: 179.97..180.03 overlaps -180..-179.9; a box whose
    west exceeds its east, as GDAL gives a footprint across the antimeridian, ends east of
    180)."""
    aw, ae = a_bounds[0], a_bounds[2] + (360.0 if a_bounds[0] > a_bounds[2] else 0.0)
    bw, be = b_bounds[0], b_bounds[2] + (360.0 if b_bounds[0] > b_bounds[2] else 0.0)
    turn = _turn(aw, ae, bw, be)
    w = max(aw, bw + turn)
    e = min(ae, be + turn)
    s = max(a_bounds[1], b_bounds[1])
    n = min(a_bounds[3], b_bounds[3])
    if w >= e or s >= n:
        raise NoOverlapError(
            f"{a_name} (lon/lat {tuple(round(v, 4) for v in a_bounds)}) does not "
            f"overlap {b_name} (lon/lat {tuple(round(v, 4) for v in b_bounds)})"
        )
