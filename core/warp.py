"""Putting one raster on another's grid: every warp of arrays (``rasterio.warp.reproject``,
GDAL's warper) goes through :func:`to_grid`, which keeps NaN as no data, wraps global lon/lat
grids across 180 E, and silences rasterio's in-memory "no geotransform" warning in a
thread-safe way. In ``core`` so that the DEM type itself can warp (:meth:`stereodem.core.dem.
DEM.reproject`); :mod:`stereodem.post.warp` re-exports it beside the shifts in metres."""

from __future__ import annotations

import logging
import warnings
from contextlib import contextmanager

import numpy as np
import rasterio
import rasterio.transform
from affine import Affine
from rasterio._err import CPLE_BaseError
from rasterio.crs import CRS as RioCRS
from rasterio.errors import NotGeoreferencedWarning
from rasterio.vrt import WarpedVRT
from rasterio.warp import Resampling, reproject, transform_bounds

from stereodem.core import geodesy
from stereodem.core.errors import NoOverlapError
from stereodem.core.grid import as_crs

log = logging.getLogger(__name__)

#: the resampling methods of :func:`to_grid`, by name
RESAMPLING_METHODS = ("nearest", "bilinear", "cubic", "cubic_spline")

#: largest error (source pixels) of GDAL's approximate transformer in a warp between two CRSs
#: (:func:`to_grid`, the mosaic's reads). ``rasterio.warp.reproject`` always interpolates the
#: coordinate transformation linearly along each destination row with GDAL's default of
#: 0.125 px, and that error has one sign along a row (a parabola between the exactly
#: transformed points): the warped grid is displaced by a few hundredths of a pixel on average,
#: which co-registration measures as a shift (2.4 m of 60 m cells between UTM 33N and EPSG:3413
#: at 78 N, 1.6 m from lon/lat to UTM). 0.001 px costs about the same time (a few more exact
#: points per row); ``tolerance=0`` is refused by rasterio's WarpedVRT.
TRANSFORM_TOLERANCE_PX = 1e-3


def _is_geographic(crs) -> bool:
    return bool(as_crs(crs).is_geographic)


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

_RESAMPLING = {name: getattr(Resampling, name) for name in RESAMPLING_METHODS}


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
    kernel_scale: tuple[float, float] | None = None,
):
    """Warp a 2-D array onto a destination grid; cells without data are NaN (or ``src_nodata``
    for integer rasters). GDAL's warper runs on ``threads`` threads (default 1: callers
    that warp blocks on a thread pool already use the cores; a caller that warps a whole grid
    passes the process's budget, :func:`stereodem.core.blocks.default_threads`); the result
    does not depend on it. ``kernel_scale``: GDAL's ``XSCALE``, ``YSCALE`` for a warp between
    two CRSs (:func:`kernel_scales`), which a caller warping a grid block by block computes
    once for the whole grid, so that every block is warped as the whole grid would be
    (None: GDAL's own, per chunk of the warp)."""
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
        src_crs=rio_crs(src_crs),
        src_nodata=src_nodata,
        dst_transform=dst_transform,
        dst_crs=rio_crs(dst_crs),
        dst_nodata=fill,
        resampling=_RESAMPLING[resampling],
        num_threads=max(1, int(threads or 1)),
        kernel_scale=kernel_scale,
    )
    _reproject(src, dst, src_transform, **kw)
    for turn in _overflow_turns(
        src_transform, src_crs, src.shape, dst_transform, dst_crs, dst_shape
    ):
        # the part of ``src`` beyond 180 (or -180) of a global grid: on its other edge
        more = np.full(dst_shape, fill, dtype=dst_dtype)
        _reproject(src, more, Affine.translation(turn, 0.0) @ src_transform, **kw)
        empty = np.isnan(dst) if np.isnan(fill) else dst == fill
        dst[empty] = more[empty]
    return dst


def same_horizontal_crs(a, b) -> bool:
    """Whether two CRSs have the same horizontal part (a vertical part aside): a warp between
    grids of the two is an affine map of pixel coordinates."""
    a, b = as_crs(a), as_crs(b)
    a = a.sub_crs_list[0] if a.is_compound else a
    b = b.sub_crs_list[0] if b.is_compound else b
    return a == b


#: what PROJ's refusal of a point raises through :func:`rasterio.warp.transform`
_TRANSFORM_ERRORS = (rasterio.errors.RasterioError, CPLE_BaseError)


def kernel_scales(src_transform, src_crs, dst_transform, dst_crs, dst_shape) -> tuple[float, float]:
    """GDAL's ``XSCALE`` and ``YSCALE`` of a warp from a source grid onto a destination grid:
    destination cells per source cell along the source's x and y axes (1: the same cells,
    below 1: the destination is coarser, and the resampling kernel is widened by the inverse
    to average the source cells it covers), from the map of destination to source pixels at
    the destination grid's centre (its Jacobian: ``1 / |d(source x)/d(destination col, row)|``
    and the same for y), as terra's ``warp_scale``.

    GDAL computes them itself for every chunk it warps, as the chunk's size over the bounding
    box of its source window: on a grid turned against the source (a polar stereographic
    reference and a UTM DEM), a chunk of few rows has a tall source window, and its kernel
    is widened by far more than the cells' sizes ask for (a 512-row block of a 2000² grid
    between EPSG:3413 and UTM 33N: 0.89 m median error against an exact bilinear, 0.000 m for
    the whole grid). Given once for a whole grid, every block is warped alike."""
    rows, cols = dst_shape
    c, r = cols / 2.0, rows / 2.0
    x, y = dst_transform @ (np.array([c, c + 1.0, c]), np.array([r, r, r + 1.0]))
    if not same_horizontal_crs(src_crs, dst_crs):
        try:
            x, y = rasterio.warp.transform(rio_crs(dst_crs), rio_crs(src_crs), x, y)
        except _TRANSFORM_ERRORS as exc:  # e.g. "Point outside of projection domain"
            raise ValueError(
                f"the destination grid's centre has no position in the source CRS ({exc})"
            ) from None
    sc, sr = ~src_transform @ (np.asarray(x, float), np.asarray(y, float))
    along_x = float(np.hypot(sc[1] - sc[0], sc[2] - sc[0]))
    along_y = float(np.hypot(sr[1] - sr[0], sr[2] - sr[0]))
    if not (np.isfinite(along_x) and np.isfinite(along_y) and along_x > 0 and along_y > 0):
        raise ValueError("the destination grid's centre has no position in the source grid")
    return 1.0 / along_x, 1.0 / along_y


def kernel_scale_options(kernel_scale) -> dict:
    """GDAL warp options (a ``WarpedVRT``'s keyword arguments) that set the kernel scale
    ``(XSCALE, YSCALE)`` (:func:`kernel_scales`) of every chunk of a warp; none for None
    (GDAL's own, per chunk)."""
    if kernel_scale is None:
        return {}
    return {"XSCALE": repr(float(kernel_scale[0])), "YSCALE": repr(float(kernel_scale[1]))}


def grid_kernel_scale(
    src_transform, src_crs, dst_transform, dst_crs, dst_shape, *, src_shape=None, footprint=None
):
    """The kernel scale to give GDAL for every piece (block, window) of a warp of a source
    grid onto a destination grid, so that the pieces are warped as the whole grid is:
    :func:`kernel_scales` between two CRSs; None between grids of one horizontal CRS (an
    affine map of pixel coordinates: GDAL's own per-chunk scale is then the cells' size ratio
    in every chunk, exact, and stays).

    Taken at the centre of the part of the destination grid (``dst_transform``, ``dst_shape``
    in cells) that the source covers: its ``footprint`` (west, south, east, north in
    ``dst_crs``), else that of the source grid of ``src_shape`` (cells), else the whole
    destination grid. Where the source is small on a large grid the scale differs across it:
    a 30 m UTM 33N DEM at 60 N on a 0.01 degree lon/lat grid of lon 0..40 E, lat 0..75 N has
    an x scale of 0.054 at the DEM and 0.034 at the grid's centre (its kernel 1.6 times too
    wide). None as well where that centre has no position in the source CRS (logged; GDAL's
    own scale, per chunk, then)."""
    if same_horizontal_crs(src_crs, dst_crs):
        return None
    rows, cols = (int(n) for n in dst_shape[-2:])
    if footprint is None and src_shape is not None:
        bounds = rasterio.transform.array_bounds(*src_shape[-2:], src_transform)
        try:
            footprint = transform_bounds(
                rio_crs(src_crs), rio_crs(dst_crs), *bounds, densify_pts=21
            )
        except Exception:  # noqa: BLE001 - bounds PROJ cannot take: the whole grid's centre
            footprint = None
    r0, r1, c0, c1 = _covered_window(dst_transform, rows, cols, footprint)
    try:
        return kernel_scales(
            src_transform,
            src_crs,
            dst_transform @ Affine.translation(c0, r0),
            dst_crs,
            (r1 - r0, c1 - c0),
        )
    except ValueError as exc:
        log.debug("kernel scale: %s; GDAL's own, per chunk", exc)
        return None


def _covered_window(transform, rows: int, cols: int, footprint) -> tuple[int, int, int, int]:
    """Rows ``r0:r1`` and columns ``c0:c1`` of a north-up grid that the box ``footprint``
    (west, south, east, north in the grid's CRS; None: all of it) covers; the whole grid where
    the box misses it (or is not finite)."""
    if footprint is not None and len(footprint) == 4 and np.all(np.isfinite(footprint)):
        w, south, e, n = (float(v) for v in footprint)
        cw, ce = sorted(((w - transform.c) / transform.a, (e - transform.c) / transform.a))
        rn, rs = sorted(((n - transform.f) / transform.e, (south - transform.f) / transform.e))
        c0, c1 = int(np.clip(np.floor(cw), 0, cols)), int(np.clip(np.ceil(ce), 0, cols))
        r0, r1 = int(np.clip(np.floor(rn), 0, rows)), int(np.clip(np.ceil(rs), 0, rows))
        if c1 > c0 and r1 > r0:
            return r0, r1, c0, c1
    return 0, rows, 0, cols


def _reproject(
    src, dst, src_transform, *, src_crs, dst_crs, src_nodata, dst_nodata, kernel_scale=None, **kw
):
    """``rasterio.warp.reproject`` of the array ``src`` into ``dst`` (filled in place), with
    the coordinate transformation within :data:`TRANSFORM_TOLERANCE_PX` of exact.

    Between grids of one CRS the map from destination to source pixels is affine, which GDAL's
    approximate transformer (linear along rows, 0.125 px allowed; ``reproject`` has no way to
    ask for less) reproduces exactly: ``reproject`` itself. Between two CRSs ``src`` is read
    through a ``WarpedVRT`` of that tolerance (the same warper, kernels, no-data handling and
    threads) over a GDAL dataset on the array's own memory (:func:`_array_dataset`): the
    warper reads the source window of each of its chunks, so a block of a large grid costs
    the block, not the whole source (it was written whole into an in-memory GeoTIFF per
    call: every block of an assessment copied the DEM; the same values, bit for bit)."""
    if same_horizontal_crs(src_crs, dst_crs):
        reproject(
            src,
            dst,
            src_transform=src_transform,
            src_crs=src_crs,
            dst_crs=dst_crs,
            src_nodata=src_nodata,
            dst_nodata=dst_nodata,
            **kw,
        )
        return
    bands = src[None] if src.ndim == 2 else src
    scale = kernel_scale_options(kernel_scale)  # GDAL's per-chunk scale replaced by the caller's
    with (
        _array_dataset(bands, src_transform) as ds,
        WarpedVRT(
            ds,
            src_crs=src_crs,
            src_transform=src_transform,
            src_nodata=src_nodata,
            crs=dst_crs,
            transform=kw["dst_transform"],
            width=dst.shape[-1],
            height=dst.shape[-2],
            nodata=dst_nodata,
            dtype=dst.dtype.name,
            resampling=kw["resampling"],
            tolerance=TRANSFORM_TOLERANCE_PX,
            NUM_THREADS=kw["num_threads"],  # a keyword: WarpedVRT's **kwargs are warp options
            **scale,
        ) as vrt,
    ):
        out = vrt.read()
    dst[...] = out[0] if dst.ndim == 2 else out


#: GDAL's names of the array types :func:`_array_dataset` hands over as they are
_GDAL_TYPES = {
    "uint8": "Byte",
    "uint16": "UInt16",
    "int16": "Int16",
    "uint32": "UInt32",
    "int32": "Int32",
    "uint64": "UInt64",
    "int64": "Int64",
    "float32": "Float32",
    "float64": "Float64",
}


@contextmanager
def _array_dataset(bands, transform):
    """A read-only GDAL dataset (MEM driver) on the memory of ``bands`` (bands, rows,
    cols), no copy, open for the ``with`` block (which holds the array meanwhile). Its
    geotransform is ``transform`` (rasterio warns of a dataset without one); it has no CRS
    and no no-data value: the ``WarpedVRT`` over it is given them. A new dataset per call:
    blocks warped on threads share no GDAL dataset, only the array they read. Types the MEM
    driver may lack (int8 before GDAL 3.7, bool, float16) are widened exactly, a copy, as is
    a strided view (the dataset's rows are the array's, contiguous).

    GDAL >= 3.10 opens a ``MEM:::`` name only with ``GDAL_MEM_ENABLE_OPEN`` (against such
    names in untrusted files); it is set for this open alone, as rasterio's own
    ``MemoryDataset`` does (which opens in update mode, of which ``WarpedVRT`` warns)."""
    if bands.dtype.name not in _GDAL_TYPES:
        if bands.dtype.kind not in "biuf":
            raise TypeError(f"cannot warp an array of {bands.dtype}")
        bands = bands.astype(np.float64 if bands.dtype.kind == "f" else np.int16)
    bands = np.require(bands, requirements=("C", "A"))  # a copy only of a strided view
    count, rows, cols = bands.shape
    options = {
        "DATAPOINTER": bands.__array_interface__["data"][0],
        "PIXELS": cols,
        "LINES": rows,
        "BANDS": count,
        "DATATYPE": _GDAL_TYPES[bands.dtype.name],
        "GEOTRANSFORM": "/".join(repr(float(v)) for v in transform.to_gdal()),
    }
    name = "MEM:::" + ",".join(f"{k}={v}" for k, v in options.items())
    with rasterio.Env(GDAL_MEM_ENABLE_OPEN="YES"):
        ds = rasterio.open(name)
    with ds:
        yield ds


#: columns a global lon/lat grid is extended by on either side, from its other edge, before
#: a warp: the support of the cubic kernels (2), so cells within a cell of 180 E interpolate
#: across it instead of taking the edge column's value
WRAP_CELLS = 3


def is_global(transform, crs, shape) -> bool:
    """Whether a north-up grid in a geographic CRS spans the whole turn of longitude (within
    half a cell): its east edge is its west edge again."""
    if transform.b or transform.d or not _is_geographic(crs):
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
        w, _, e, _ = transform_bounds(rio_crs(dst_crs), rio_crs(src_crs), *bounds, densify_pts=21)
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
    if not (_is_geographic(src_crs) and is_global(dst_transform, dst_crs, dst_shape)):
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
    if not (_is_geographic(src_crs) and _is_geographic(dst_crs)):
        return src_transform
    turn = _turn(
        dst_transform.c,
        dst_transform.c + dst_transform.a * dst_shape[-1],
        src_transform.c,
        src_transform.c + src_transform.a * src_shape[-1],
    )
    return Affine.translation(turn, 0.0) @ src_transform if turn else src_transform


def rio_crs(crs):
    """``crs`` (anything pyproj takes) as a rasterio CRS, through its WKT; :class:`CRSError`
    for an unusable one."""
    return RioCRS.from_wkt(geodesy._crs_key(crs))


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
