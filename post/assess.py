"""Accuracy assessment of a DEM against a reference DEM and against check points.

The DEM is warped onto the **reference grid** (bilinear; this is stated in the report), its
heights first converted to the reference's vertical datum (EGM96 geoid ↔ WGS84 ellipsoid).
Differences are ``dh = DEM − reference``. Statistics (:mod:`stereodem.post.stats`) are given for the
whole overlap, per slope class (slope of the reference DEM, degrees, metric even on lon/lat
grids), per land-cover class, per elevation band (reference heights), with the linear fit of
error against slope; optionally before and after co-registration with a chain of
:mod:`stereodem.post.coreg` (default the chain's :class:`~stereodem.post.biascorr.NuthKaab`).

:func:`assess_dem` works through the reference grid in blocks of :data:`BLOCK_ROWS` rows
(warp, difference, slope, class statistics per block:
:class:`~stereodem.post.blockstats.StreamingStats`), so its memory does not grow with the
reference's size; the quantile statistics are then within
:data:`~stereodem.post.blockstats.QUANTILE_ERROR` of the exact ones (stated in the report) and
the figures are drawn from the decimated arrays they display anyway.
"""

from __future__ import annotations

import csv
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import rasterio
import rasterio.warp
from affine import Affine

from stereodem.core import geodesy, interrupt
from stereodem.core.dem import DEM, as_dem, file_vertical, to_vertical_of
from stereodem.core.errors import (
    CRSError,
    DEMError,
    InputError,
    NoOverlapError,
    VerticalReferenceError,
    not_found,
)
from stereodem.core.raster import check_map_raster, unreadable
from stereodem.sensor.io.gcps import parse_roles

from . import stats as st
from . import terrain, warp
from .blockstats import QUANTILE_ERROR, RESOLUTION, StreamingStats
from .coreg import CoregChain, parse_chain

log = logging.getLogger(__name__)

#: fewer compared cells than this make the assessment warn that its figures rest on them
#: alone (a 1 x 1 DEM reported NMAD 0 m and exited 0 without a word)
MIN_RELIABLE_CELLS = 30

#: rows of the reference grid per block of the assessment (a block's working arrays take
#: about 60 bytes per cell: 512 rows of a 7000-column reference ~ 0.2 GB)
BLOCK_ROWS = 512


# ----------------------------------------------------------------------------- vertical


def reconcile_vertical(dem: DEM, reference: DEM) -> tuple[DEM, str]:
    """Return ``dem`` in the vertical reference of ``reference`` and a note saying what was done
    (:func:`stereodem.core.dem.to_vertical_of`)."""
    return to_vertical_of(dem, reference, name="DEM")


# ----------------------------------------------------------------------------- results


@dataclass
class Comparison:
    """DEM and reference on the reference grid, and their difference."""

    dem: np.ndarray  #: DEM heights warped onto the reference grid (m)
    ref: np.ndarray  #: reference heights (m)
    dh: np.ndarray  #: DEM − reference (m), NaN where either is void
    slope: np.ndarray  #: slope of the reference (degrees)
    transform: object
    crs: object
    landcover: np.ndarray | None = None


@dataclass
class Assessment:
    """Result of :func:`assess_dem`: ``report`` (a JSON-ready dict) and what the figures draw:
    ``before``/``after`` hold the comparison decimated to figure size (every ``k``-th row and
    column of the reference grid, ``transform`` scaled by ``k``), ``histogram`` the
    accumulated differences of every cell (:class:`~stereodem.post.blockstats.StreamingStats`)."""

    report: dict
    before: Comparison
    after: Comparison | None = None
    extra: dict = field(default_factory=dict)
    histogram: StreamingStats | None = None


def _check_overlap(dem: DEM, reference: DEM) -> None:
    """:class:`NoOverlapError` (naming both files) unless the footprints of ``dem`` and
    ``reference`` overlap (lon/lat bounds, degrees)."""
    warp.check_overlap(
        dem.bounds_lonlat(),
        reference.bounds_lonlat(),
        dem.path or "DEM",
        reference.path or "reference",
    )


def _kernel_scale(dem: DEM, reference: DEM):
    """The kernel scale of ``dem``'s warp onto ``reference``'s grid between two CRSs, one for
    the whole grid (:func:`warp.grid_kernel_scale`), so that its blocks are warped as the
    whole grid is (GDAL's own is per chunk: the blocks of a turned grid were smoothed more than
    the whole grid, by up to metres), taken where the DEM lies on that grid (a reference far
    larger than the DEM: the scale at the reference's centre may be far off); None between
    grids of one CRS (GDAL's own: exact there)."""
    return warp.grid_kernel_scale(
        dem.transform,
        dem.crs,
        reference.transform,
        reference.crs,
        reference.shape,
        src_shape=dem.shape,
    )


def compare_on_reference_grid(
    dem: DEM, reference: DEM, *, resampling: str = "bilinear"
) -> Comparison:
    """Warp ``dem`` onto ``reference``'s grid (same vertical reference assumed) and difference.

    Raises :class:`NoOverlapError` if the footprints or the valid cells do not overlap.
    """
    _check_overlap(dem, reference)
    z = warp.to_grid(
        dem.heights,
        dem.transform,
        dem.crs,
        reference.transform,
        reference.crs,
        reference.shape,
        resampling=resampling,
        kernel_scale=_kernel_scale(dem, reference),
    )
    ref = reference.heights
    dh = z.astype(np.float64) - ref.astype(np.float64)
    if not np.isfinite(dh).any():
        raise NoOverlapError(
            f"{dem.path or 'DEM'}: no valid cell overlaps a valid cell of "
            f"{reference.path or 'the reference'}"
        )
    slope = terrain.slope_deg(ref, reference.transform, reference.crs)
    return Comparison(z, ref, dh, slope, reference.transform, reference.crs)


def _landcover_source(landcover):
    """Land-cover raster (path or (array, transform, crs)) as (classes float64 with NaN for
    nodata, transform, crs) on its own grid."""
    if isinstance(landcover, (str, Path)):
        try:
            with rasterio.open(landcover) as ds:
                check_map_raster(landcover, ds, "the land-cover raster")
                arr = ds.read(1).astype(np.float64)
                nod = ds.nodata
                if nod is not None:
                    arr[arr == nod] = np.nan
                t, crs = ds.transform, ds.crs.to_wkt()
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(unreadable(landcover, "land-cover raster", exc)) from None
    else:
        arr, t, crs = np.asarray(landcover[0], dtype=np.float64), landcover[1], landcover[2]
    return arr, t, crs


def dem_footprint(z) -> np.ndarray:
    """Cells inside the footprint of a DEM: the convex hull of its valid cells (bool, the
    shape of ``z``). A stereo DEM covers the overlap of two image footprints, a convex
    quadrilateral, so the hull is that area with its interior voids counted in."""
    fin = np.isfinite(z)
    hull = _hull(_row_ends(fin, 0))
    out = np.zeros(fin.shape, dtype=np.uint8)
    if hull is not None:
        cv2.fillConvexPoly(out, hull, 1)
    return out.astype(bool) | fin


def _row_ends(fin, row0):
    """(col, row) of the first and last True cell of each row of ``fin`` (rows offset by
    ``row0``): the convex hull of these is that of every True cell."""
    has = fin.any(axis=1)
    rows = np.flatnonzero(has)
    first = np.argmax(fin[rows], axis=1)
    last = fin.shape[1] - 1 - np.argmax(fin[rows, ::-1], axis=1)
    r = rows + row0
    return np.concatenate([np.stack([first, r], 1), np.stack([last, r], 1)]).astype(np.int32)


def _hull(points):
    """Convex hull (OpenCV int32 vertices) of (col, row) points, or None without points."""
    pts = np.concatenate(points) if isinstance(points, list) else points
    return cv2.convexHull(pts) if len(pts) else None


def comparison_stats(
    cmp: Comparison,
    *,
    slope_bins=st.DEFAULT_SLOPE_BINS,
    elevation_bins=None,
    landcover_names: dict | None = None,
) -> dict:
    """The statistics block of a :class:`Comparison`: ``stats``, ``by_slope``,
    ``by_elevation``, ``by_landcover`` (if any), ``slope_fit`` and ``slope_class_trend``."""
    footprint = dem_footprint(cmp.dem) & np.isfinite(cmp.ref)
    out = {"stats": st.error_stats(cmp.dh, n_total=int(footprint.sum()))}
    out["by_slope"] = st.binned_stats(
        cmp.dh, cmp.slope, slope_bins, unit="deg", name="slope", footprint=footprint
    )
    ebins = elevation_bins if elevation_bins is not None else st.default_elevation_bins(cmp.ref)
    out["by_elevation"] = st.binned_stats(
        cmp.dh, cmp.ref, ebins, unit="m", name="elevation", footprint=footprint
    )
    out["by_landcover"] = (
        st.class_stats(cmp.dh, cmp.landcover, names=landcover_names, footprint=footprint)
        if cmp.landcover is not None
        else None
    )
    out["slope_fit"] = st.error_vs_slope(cmp.dh, cmp.slope)
    out["slope_class_trend"] = st.class_trend(out["by_slope"], x_key="slope_mean", y_key="nmad")
    return out


#: up to this many bin edges, :func:`class_codes` compares with each edge (one cheap pass
#: per edge) instead of a binary search per cell
_COMPARE_EDGES = 16


def class_codes(v, edges, *, counts: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """The bin of each cell of ``v`` among ``edges`` (bins ``[e_i, e_i+1)``, the last one
    closed, as :func:`~stereodem.post.stats.binned_stats`) and the number of cells per bin.

    Returns ``codes`` (the shape of ``v``, :func:`_code_type` of the bins;
    -1 for cells outside the bins or not finite) and ``counts`` (int64, one per bin; None
    with ``counts=False``: the assessment counts its classes in the footprint instead)."""
    e = np.asarray(edges, dtype=np.float64)
    n_bins = e.size - 1
    inside = np.isfinite(v)
    inside &= v >= e[0]
    inside &= v <= e[-1]
    if e.size <= _COMPARE_EDGES:
        codes = np.zeros(v.shape, np.int8)
        for edge in e[1:-1]:
            codes += v >= edge  # edges passed: [e_i, e_i+1) -> i, e_last -> the last bin
    else:
        codes = np.searchsorted(e[1:-1], v, side="right").astype(_code_type(n_bins))
    np.copyto(codes, -1, where=~inside)
    if not counts:
        return codes, None
    if n_bins <= _COMPARE_EDGES:  # a count per bin is cheaper than bincount's int64 copy
        counts = np.array([np.count_nonzero(codes == i) for i in range(n_bins)], np.int64)
    else:
        counts = np.bincount(codes[inside], minlength=n_bins).astype(np.int64)
    return codes, counts


def _code_type(n_classes: int):
    """The smallest signed integer type holding -1 … ``n_classes`` (one more than the
    largest code: the bound of the last class); 8 or 16 bits for up to 32766 classes, which
    numpy's stable sort sorts by radix."""
    return np.min_scalar_type(-(n_classes + 1))


class _ClassAccumulator:
    """Per-class statistics of ``dh`` in classes of a variable (bins of edges, or the integer
    values of a land-cover raster), accumulated block by block; gives the entries of
    :func:`~stereodem.post.stats.binned_stats` / :func:`~stereodem.post.stats.class_stats`."""

    def __init__(self, edges=None, *, unit="", name="bin"):
        self.edges, self.unit, self.name = edges, unit, name
        self.stats, self.n_total, self.var_sum = {}, {}, {}

    def _entry(self, key):
        if key not in self.stats:
            self.stats[key], self.n_total[key], self.var_sum[key] = StreamingStats(), 0, 0.0
        return self.stats[key]

    def add(self, keys, x, codes, v):
        """Add a block already classed: ``keys`` the classes, and at the cells of finite
        difference, in the block's order: ``x`` the differences (float64, m), ``codes``
        their class (index into ``keys``, -1: none) and ``v`` the class variable. The cells
        are grouped by class with one stable sort of their codes, so each class sees its
        cells in the block's order. The classes' cell counts come from :meth:`set_totals`."""
        order = np.argsort(codes, kind="stable")  # a radix sort for 8-/16-bit codes
        sorted_codes = codes[order]
        x, v = x[order], v[order]
        # bounds of the classes (class indices in the codes' own type: no int64 copy)
        bounds = np.searchsorted(sorted_codes, np.arange(len(keys) + 1, dtype=codes.dtype))
        for i, key in enumerate(keys):
            k = int(key) if self.edges is not None else float(key)
            acc = self._entry(k)
            acc.add_finite(x[bounds[i] : bounds[i + 1]])
            self.var_sum[k] += float(v[bounds[i] : bounds[i + 1]].sum(dtype=np.float64))

    def set_totals(self, counts: dict) -> None:
        """Replace each class's cell count (``valid_pct``'s denominator) by ``counts[key]``
        (0 for a class not in it): the cells of the class inside the DEM's footprint, known
        once every block is in (:func:`blockwise_comparison`)."""
        for key in self.n_total:
            self.n_total[key] = int(counts.get(key, 0))

    def merge(self, other: _ClassAccumulator) -> _ClassAccumulator:
        """Add another block's class statistics (same classes) into these; returns self."""
        for key, acc in other.stats.items():
            self._entry(key).merge(acc)
            self.n_total[key] += other.n_total[key]
            self.var_sum[key] += other.var_sum[key]
        return self

    def binned(self) -> list[dict]:
        e, out = self.edges, []
        for i in range(e.size - 1):
            acc = self._entry(i)
            lo, hi, last = e[i], e[i + 1], i == e.size - 2
            r = acc.result(n_total=self.n_total[i])
            entry = {
                "class": st._bin_label(lo, hi, self.unit, last),
                "lower": float(lo),
                "upper": float(hi) if np.isfinite(hi) else None,
                f"{self.name}_mean": self.var_sum[i] / r["n"] if r["n"] else float("nan"),
            }
            entry.update(r)
            out.append(entry)
        return out

    def classes(self, names=None) -> list[dict]:
        """The entries of the classes with cells (in the footprint, after
        :meth:`set_totals`), by class value."""
        out = []
        for value in sorted(self.stats):
            if self.n_total[value] == 0:
                continue
            key = int(value) if float(value).is_integer() else float(value)
            entry = {"class": (names or {}).get(key, str(key)), "value": key}
            entry.update(self.stats[value].result(n_total=self.n_total[value]))
            out.append(entry)
        return out


def _value_codes(v):
    """Classes of a land-cover block ``v`` (float, NaN for none): the class values found and
    each cell's index into them (-1: none)."""
    fin = np.isfinite(v)
    keys, inverse = np.unique(v[fin], return_inverse=True)
    codes = np.full(v.shape, -1, _code_type(keys.size))
    codes[fin] = inverse.ravel()
    return keys, codes


def _row_blocks(n_rows: int, block_rows: int):
    for r0 in range(0, n_rows, block_rows):
        yield r0, min(r0 + block_rows, n_rows)


@dataclass
class _Block:
    """One block's share of :func:`blockwise_comparison`: accumulators and what the footprint
    and the figures need."""

    overall: StreamingStats
    fit: StreamingStats
    by_slope: _ClassAccumulator
    by_elev: _ClassAccumulator
    by_lc: _ClassAccumulator | None
    ends: np.ndarray
    fin_bits: np.ndarray
    display: dict
    #: each cell's class: ``"slope"``/``"elevation"`` codes (-1: none), ``"landcover"``
    #: ``(values, codes)``; counted inside the footprint once it is known
    classes: dict = field(default_factory=dict)

    def merge(self, other: _Block):
        self.overall.merge(other.overall)
        self.fit.merge(other.fit)
        self.by_slope.merge(other.by_slope)
        self.by_elev.merge(other.by_elev)
        if self.by_lc is not None:
            self.by_lc.merge(other.by_lc)


#: DEM cells beyond its edges within which a block is still warped (resampling kernels reach
#: two cells; the rest is margin)
MISS_MARGIN_CELLS = 8


def _misses(dem: DEM, transform, crs, shape) -> bool:
    """Whether the grid ``transform``, ``shape`` (in ``crs``) lies wholly beyond one edge of
    ``dem``'s grid, by more than :data:`MISS_MARGIN_CELLS` cells: no cell of it gets a
    height from the warp. Its outline (21 points a side) is taken to DEM pixels; a region
    whose outline lies beyond an edge lies there whole."""
    rows, cols = shape
    t = np.linspace(0.0, 1.0, 21)
    one, zero = np.ones_like(t), np.zeros_like(t)
    x, y = transform @ (
        np.concatenate([t, one, t, zero]) * cols,
        np.concatenate([zero, t, one, t]) * rows,
    )
    x, y = rasterio.warp.transform(warp.rio_crs(crs), warp.rio_crs(dem.crs), x, y)
    dem_t = warp.beside(dem.transform, dem.crs, dem.shape, transform, crs, shape)
    c, r = ~dem_t @ (np.asarray(x), np.asarray(y))
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r))):
        return False
    m, (n_r, n_c) = MISS_MARGIN_CELLS, dem.shape
    return bool(c.max() < -m or c.min() > n_c + m or r.max() < -m or r.min() > n_r + m)


def _compare_block(
    r0, r1, dem: DEM, reference: DEM, resampling, slope_edges, elev_edges, lc, k, scale=None
):
    """Warp, difference, slope and class statistics of reference rows ``r0:r1`` (``scale``:
    the whole grid's kernel scale of a warp between two CRSs, :func:`warp.kernel_scales`).

    The statistics take the cells where both heights are finite (``dh`` finite), as
    compressed 1-D arrays in the block's order: ``dh`` (float64, m), the slope (degrees)
    and the reference height there, each computed once for every accumulator."""
    ref = reference.heights
    rows, cols = ref.shape
    T = reference.transform
    tb = T @ Affine.translation(0, r0)
    if _misses(dem, tb, reference.crs, (r1 - r0, cols)):
        z = np.full((r1 - r0, cols), np.nan, np.float32)  # what the warp gives there
    else:
        z = warp.to_grid(
            dem.heights,
            dem.transform,
            dem.crs,
            tb,
            reference.crs,
            (r1 - r0, cols),
            resampling=resampling,
            kernel_scale=scale,
        )
    h0, h1 = max(r0 - 1, 0), min(r1 + 1, rows)
    slope = terrain.slope_deg(
        ref[h0:h1], T @ Affine.translation(0, h0), reference.crs, rows=slice(r0 - h0, r1 - h0)
    )
    rb = ref[r0:r1]
    fin_z = np.isfinite(z)
    both = fin_z & np.isfinite(rb)  # where dh = z - rb is finite
    ref_b = rb[both]
    dh = np.subtract(z[both], ref_b, dtype=np.float64)
    slope_b = slope[both]
    b = _Block(
        StreamingStats(),
        StreamingStats(covariate=True),
        _ClassAccumulator(slope_edges, unit="deg", name="slope"),
        _ClassAccumulator(elev_edges, unit="m", name="elevation"),
        _ClassAccumulator() if lc is not None else None,
        _row_ends(fin_z, r0),
        np.packbits(fin_z, axis=1),
        {},
    )
    fit_ok = np.isfinite(slope_b)  # slope is void next to reference voids
    if fit_ok.all():  # the fit takes every difference: its moments and bins are overall's
        b.fit.add_finite(dh, slope_b)
        b.overall = b.fit.without_covariate()
    else:
        b.overall.add_finite(dh)
        b.fit.add_finite(dh[fit_ok], slope_b[fit_ok])
    codes, _ = class_codes(slope, slope_edges, counts=False)
    keys = np.arange(slope_edges.size - 1)
    b.by_slope.add(keys, dh, codes[both], slope_b)
    b.classes["slope"] = codes
    codes, _ = class_codes(rb, elev_edges, counts=False)
    keys = np.arange(elev_edges.size - 1)
    b.by_elev.add(keys, dh, codes[both], ref_b)
    b.classes["elevation"] = codes
    if lc is not None:
        cls = warp.to_grid(
            lc[0],
            lc[1],
            lc[2],
            tb,
            reference.crs,
            (r1 - r0, cols),
            resampling="nearest",
            dst_dtype=np.float64,
        )
        keys, codes = _value_codes(cls)
        b.by_lc.add(keys, dh, codes[both], cls[both])
        b.classes["landcover"] = (keys, codes)
    s0 = (-r0) % k
    zd, rd = z[s0::k, ::k], rb[s0::k, ::k]
    b.display = {
        "dem": np.array(zd),
        "ref": np.array(rd),
        "dh": np.subtract(zd, rd, dtype=np.float64),
        "slope": np.array(slope[s0::k, ::k]),
    }
    return b


def blockwise_comparison(
    dem: DEM,
    reference: DEM,
    *,
    resampling: str = "bilinear",
    slope_bins=st.DEFAULT_SLOPE_BINS,
    elevation_bins=None,
    landcover=None,
    landcover_names: dict | None = None,
    block_rows: int = BLOCK_ROWS,
    display_cells: int | None = None,
    threads: int = 1,
):
    """Compare ``dem`` with ``reference`` on the reference grid block by block (same vertical
    reference assumed); returns ``(statistics, display, histogram)``.

    ``statistics`` is the block of :func:`comparison_stats` (``stats``, ``by_slope``,
    ``by_elevation``, ``by_landcover``, ``slope_fit``, ``slope_class_trend``) with the
    quantiles within :data:`~stereodem.post.blockstats.QUANTILE_ERROR`; ``display`` the
    :class:`Comparison` decimated to at most ``display_cells`` per side (default
    :data:`stereodem.post.figures.DISPLAY_CELLS`: what the figures draw); ``histogram`` the
    :class:`~stereodem.post.blockstats.StreamingStats` of all differences. Each block of
    ``block_rows`` reference rows is warped, differenced and its slope taken (with one halo
    row each side, so slopes equal those of the whole grid); memory is ``threads`` blocks'
    arrays plus the accumulators, and a byte per reference cell for the footprint (the
    convex hull of the warped DEM's cells, known after the last block) and for each
    classification, whose cells inside it are then counted (``valid_pct`` per class: the
    class's share of valid cells in the footprint, as the overall one). Blocks run on
    ``threads`` threads and their accumulators are merged in block order, so the result
    does not depend on ``threads``.

    Raises :class:`NoOverlapError` if the footprints or the valid cells do not overlap.
    """
    from . import figures

    _check_overlap(dem, reference)
    ref = reference.heights
    rows, cols = ref.shape
    T = reference.transform
    slope_edges = st.bin_edges(slope_bins, "slope")
    if elevation_bins is None:
        elevation_bins = st.default_elevation_bins(np.array([np.nanmin(ref), np.nanmax(ref)]))
    elev_edges = st.bin_edges(elevation_bins, "elevation")
    lc = _landcover_source(landcover) if landcover is not None else None
    k = (
        figures._decimation((rows, cols))
        if display_cells is None
        else max(1, int(np.ceil(max(rows, cols) / display_cells)))
    )
    blocks = list(_row_blocks(rows, block_rows))
    # between two CRSs, one kernel scale for every block (_kernel_scale)
    args = (
        dem,
        reference,
        resampling,
        slope_edges,
        elev_edges,
        lc,
        k,
        _kernel_scale(dem, reference),
    )
    ends, fin_bits, disp = [], [], {"dem": [], "ref": [], "dh": [], "slope": []}
    classes = []
    total = None

    def take(b: _Block):
        nonlocal total
        ends.append(b.ends)
        fin_bits.append(b.fin_bits)
        classes.append(b.classes)
        for name, a in b.display.items():
            disp[name].append(a)
        b.ends = b.fin_bits = b.display = b.classes = None
        if total is None:
            total = b
        else:
            total.merge(b)

    if threads > 1 and len(blocks) > 1:
        with ThreadPoolExecutor(max_workers=threads) as ex:
            # at most 2 blocks per thread in flight (memory), merged in block order
            pending = []
            for r0, r1 in blocks:
                interrupt.check()  # a stop request ends the comparison between blocks
                pending.append(ex.submit(_compare_block, r0, r1, *args))
                if len(pending) >= 2 * threads:
                    take(pending.pop(0).result())
            for f in pending:
                take(f.result())
    else:
        for r0, r1 in blocks:
            interrupt.check()
            take(_compare_block(r0, r1, *args))
    overall = total.overall
    if overall.n == 0:
        raise NoOverlapError(
            f"{dem.path or 'DEM'}: no valid cell overlaps a valid cell of "
            f"{reference.path or 'the reference'}"
        )
    if overall.n < MIN_RELIABLE_CELLS:  # NMAD 0 from one cell is no accuracy figure
        log.warning(
            "%s: only %d cell(s) overlap valid cells of %s: the statistics rest on them alone",
            dem.path or "DEM",
            overall.n,
            reference.path or "the reference",
        )
    # footprint: the convex hull of the warped DEM's cells, with the reference valid
    # (one uint8 mask of the grid: OpenCV's fill of a polygon shifted per block differs from
    # the whole fill along the clipped edges)
    hull = _hull(ends)
    mask = np.zeros((rows, cols), np.uint8)
    if hull is not None:
        cv2.fillConvexPoly(mask, hull, 1)

    # the cells of each class inside the footprint: valid_pct per class is the share of valid
    # cells where the DEM could have data, as the overall one (not diluted by the class's
    # cells of the reference beyond the DEM)
    n_classes = {"slope": slope_edges.size - 1, "elevation": elev_edges.size - 1}

    def counts(i):  # the footprint's cells in block i, and per class
        (r0, r1), cls = blocks[i], classes[i]
        inside = mask[r0:r1].view(bool) | np.unpackbits(fin_bits[i], axis=1, count=cols).view(bool)
        inside &= np.isfinite(ref[r0:r1])
        outside = ~inside
        got = {"all": int(cols * (r1 - r0) - np.count_nonzero(outside))}
        for name, codes in cls.items():
            values, codes = codes if name == "landcover" else (None, codes)
            np.copyto(codes, -1, where=outside)  # the block's own codes: nobody else reads them
            n = n_classes[name] if values is None else len(values)
            if n <= _COMPARE_EDGES:  # a pass per class (byte compares) beats bincount's copy
                got[name] = (values, [np.count_nonzero(codes == k) for k in range(n)])
            else:
                got[name] = (values, np.bincount(codes[codes >= 0], minlength=n)[:n].tolist())
        return got

    n_total = 0
    n_slope = np.zeros(n_classes["slope"], np.int64)
    n_elev = np.zeros(n_classes["elevation"], np.int64)
    n_lc: dict = {}
    with ThreadPoolExecutor(max(1, threads)) as ex:  # element-wise passes: the GIL released
        for got in ex.map(counts, range(len(blocks))):
            n_total += got["all"]
            n_slope += np.asarray(got["slope"][1], np.int64)
            n_elev += np.asarray(got["elevation"][1], np.int64)
            if "landcover" in got:
                for key, n in zip(*got["landcover"]):
                    n_lc[float(key)] = n_lc.get(float(key), 0) + int(n)
    mask = None  # the footprint: a byte per reference cell
    classes.clear()  # the codes: a byte per reference cell and classification
    total.by_slope.set_totals(dict(enumerate(n_slope.tolist())))
    total.by_elev.set_totals(dict(enumerate(n_elev.tolist())))
    if total.by_lc is not None:
        total.by_lc.set_totals(n_lc)
    out = {"stats": overall.result(n_total=n_total)}
    out["by_slope"] = total.by_slope.binned()
    out["by_elevation"] = total.by_elev.binned()
    out["by_landcover"] = total.by_lc.classes(landcover_names) if total.by_lc is not None else None
    fit = total.fit
    f = fit.abs_deviation_fit(float(fit.quantile(0.5))) if fit.n else {"n": 0}
    out["slope_fit"] = {
        "slope_m_per_deg": f.get("slope", float("nan")),
        "intercept_m": f.get("intercept", float("nan")),
        "r": f.get("r", float("nan")),
        "n": int(f["n"]),
        "error": "abs(dh - median(dh))",
    }
    out["slope_class_trend"] = st.class_trend(out["by_slope"], x_key="slope_mean", y_key="nmad")
    out["statistics"] = {
        "method": f"blocks of {block_rows} reference rows; quantiles from a "
        f"histogram of {RESOLUTION:g} m bins",
        "max_quantile_error_m": dict(QUANTILE_ERROR),
    }
    display = Comparison(
        *(np.concatenate(disp[n]) for n in ("dem", "ref", "dh", "slope")),
        T @ Affine.scale(k),
        reference.crs,
    )
    return out, display, overall


def _with_vertical(d, vertical: str | None) -> DEM:
    """``d`` (a :class:`DEM` or a path) as a DEM, ``vertical`` its vertical reference where
    it says none, by the rule of the files (:func:`~stereodem.core.dem.file_vertical`): a
    ``vertical`` that contradicts a DEM's own is not applied, with a warning naming it (a
    DEM object was relabelled: an ellipsoidal DEM given ``dem_vertical="geoid"`` came out
    tens of metres off, where its file was read as ellipsoidal). Anything else is a
    :class:`DEMError` naming its type (:func:`as_dem`)."""
    if not isinstance(d, DEM):
        return as_dem(d, vertical=vertical)
    vert = file_vertical(d.path or "DEM", None, d.vertical, vertical)
    return d if vert == d.vertical else replace(d, vertical=vert)


def assess_dem(
    dem,
    reference,
    *,
    coregister: bool = False,
    landcover=None,
    landcover_names: dict | None = None,
    slope_bins=st.DEFAULT_SLOPE_BINS,
    elevation_bins=None,
    checkpoints=None,
    checkpoint_crs=None,
    checkpoint_vertical: str | None = None,
    dem_vertical: str | None = None,
    ref_vertical: str | None = None,
    resampling: str = "bilinear",
    coregistration=None,
    threads: int = 1,
    reconciled: tuple[DEM, str] | None = None,
) -> Assessment:
    """Assess ``dem`` against ``reference`` (DEM objects or paths).

    Parameters
    ----------
    coregister : bool
        Also co-register (``coregistration``: a :class:`~stereodem.post.coreg.CoregChain`, a
        step or a chain string; default ``"nuth_kaab"``; a :class:`CoregChain` already fitted,
        on this DEM in the reference's vertical reference, is applied as it is: e.g. fitted on
        a stable mask and a track, as ``stereodem assess --chain`` does) and assess again after
        the whole chain; the report then has
        ``coregistration`` (:func:`coregistration_summary`: ``dx``, ``dy``, ``dz`` metres
        along x (grid east), y (grid north), up, the DEM's displacement relative to the
        reference, with σ, and every step; ``dx``/``dy`` in the DEM grid's metres, the CRS's
        units on a projected grid, with the projection's ``scale_factor`` and, where it
        matters, ``dx_ground``/``dy_ground``) and ``after_coregistration``.
    landcover : path or (array, transform, crs)
        Integer classes; warped onto the reference grid by nearest neighbour.
    slope_bins, elevation_bins : sequence of edges
        Degrees and metres; elevation bands default to 5 bands over the reference range.
    checkpoints : path or (x, y, z) arrays, optional
        See :func:`assess_checkpoints`.
    dem_vertical, ref_vertical : {"geoid", "ellipsoid"}, optional
        The vertical references of a DEM that says none (a file without one in its CRS or
        tags, a :class:`DEM` whose ``vertical`` is None); one that contradicts what the DEM
        says is not applied, with a warning (:func:`~stereodem.core.dem.file_vertical`).
    threads : int
        Threads for the blocks of :func:`blockwise_comparison` (the result does not depend
        on it).
    reconciled : (DEM, str), optional
        What :func:`reconcile_vertical` gives for ``dem`` and ``reference`` (DEM objects, no
        ``dem_vertical``/``ref_vertical``), when the caller already has it: the DEM is not
        converted a second time (a full-grid geoid lookup), e.g. ``assess_stage``'s, which
        fits its chain on it first. Its vertical reference must be the reference's.
    """
    dem = _with_vertical(dem, dem_vertical)
    reference = _with_vertical(reference, ref_vertical)
    # slopes on the reference's grid, the hillshade on the DEM's: neither may be rotated
    terrain.check_not_rotated(reference.transform, reference.path or "reference")
    terrain.check_not_rotated(dem.transform, dem.path)
    if reconciled is None:
        dem_v, vnote = reconcile_vertical(dem, reference)
    else:
        dem_v, vnote = reconciled
        if dem_v.vertical != reference.vertical or dem_v.shape != dem.shape:
            raise InputError(
                f"{dem.path or 'DEM'}: reconciled= is not this DEM in the reference's vertical "
                f"reference ({dem_v.vertical}, {dem_v.shape} cells; the reference's "
                f"{reference.vertical}, the DEM's {dem.shape})"
            )
    kw = dict(
        resampling=resampling,
        slope_bins=slope_bins,
        elevation_bins=elevation_bins,
        landcover=landcover,
        landcover_names=landcover_names,
        threads=threads,
    )
    block, cmp, hist = blockwise_comparison(dem_v, reference, **kw)
    report = {
        "dem": str(dem.path) if dem.path else None,
        "reference": str(reference.path) if reference.path else None,
        "grid": {
            "on": "reference",
            "resampling": resampling,
            "crs": reference.crs.to_string(),
            "shape": list(reference.shape),
            "transform": list(reference.transform)[:6],
            "pixel_size_m": _pixel_size_report(reference),
        },
        "vertical": {"dem": dem.vertical, "reference": reference.vertical, "note": vnote},
        "difference": "dem - reference (m)",
        "slope_bins_deg": [float(b) for b in slope_bins],
    }
    report.update(block)
    result = Assessment(report, cmp, histogram=hist)
    if isinstance(checkpoints, (str, Path)):  # read once: its log line once, not per stage
        checkpoints = read_checkpoints(checkpoints, crs=checkpoint_crs)
        checkpoint_crs = None  # read_checkpoints gives longitude/latitude
    if checkpoints is not None:
        report["checkpoints"] = assess_checkpoints(
            dem, checkpoints, crs=checkpoint_crs, vertical=checkpoint_vertical
        )
    else:
        report["checkpoints"] = None
    report["coregistration"] = None
    if coregister:
        chain = coregistration if coregistration is not None else "nuth_kaab"
        chain = (
            parse_chain(chain)
            if isinstance(chain, str)
            else chain
            if isinstance(chain, CoregChain)
            else CoregChain([chain])
        )
        if not (isinstance(chain, CoregChain) and chain.fitted and chain.records):
            chain.fit(reference, dem_v)  # on the DEM's grid (reference warped to it)
        report["coregistration"] = coregistration_summary(chain, reference)
        shifted = chain.apply(dem_v)
        report["after_coregistration"], cmp2, _ = blockwise_comparison(shifted, reference, **kw)
        if checkpoints is not None:
            sh = chain.apply(dem)  # corrected in the DEM's own vertical reference
            report["after_coregistration"]["checkpoints"] = assess_checkpoints(
                sh, checkpoints, crs=checkpoint_crs, vertical=checkpoint_vertical
            )
        result.after = cmp2
    log.info(
        "assessment: n=%d rmse=%.3f nmad=%.3f",
        report["stats"]["n"],
        report["stats"]["rmse"],
        report["stats"]["nmad"],
    )
    return result


def coregistration_summary(chain, reference: DEM) -> dict:
    """The assessment's ``coregistration`` entry from a fitted chain: the total shift ``dx``,
    ``dy`` (m along the grid's x/y axes, grid east/north, summed over the ``nuth_kaab``
    steps; ``dx_px``/``dy_px`` in reference pixels) and ``dz`` (m up, summed over
    ``nuth_kaab``/``vshift``) with their σ (root sum of squares), ``iterations``/``converged``
    of the shift steps, the stable-terrain NMAD before the first and after the last step, and
    every step's record (:meth:`CoregChain.report`).

    ``dx``/``dy`` are metres of the DEM's grid (:func:`~stereodem.post.warp.metres_per_unit`:
    the CRS's units, grid metres, on a projected grid); ``scale_factor`` is the projection's
    ``[h, k]`` at that grid's centre (None without ``nuth_kaab``), ``horizontal_unit`` says
    which metres, and ``dx_ground``/``dy_ground`` (with ``_sigma``) are the shift in ground
    metres where the scale differs from 1 by over 0.1 %
    (:func:`~stereodem.post.shift_units.ground_shift`)."""
    dx = dy = dz = 0.0
    vx = vy = vz = 0.0
    iterations, converged = 0, True
    scale, ground, unit = None, False, None
    for step in chain.steps:
        p = step.parameters()
        if step.name == "nuth_kaab":
            scale = p.get("scale_factor", scale)  # every step on the DEM's grid: the same
            ground = ground or "dx_ground" in p
            unit = p.get("horizontal_unit", unit)
            dx, dy = dx + p["dx"]["value"], dy + p["dy"]["value"]
            vx, vy = vx + p["dx"]["sigma"] ** 2, vy + p["dy"]["sigma"] ** 2
            iterations += int(p["iterations"])
            converged &= bool(p["converged"])
        if step.name in ("nuth_kaab", "vshift"):
            dz, vz = dz + p["dz"]["value"], vz + p["dz"]["sigma"] ** 2
    pe, pn = _pixel_size_report(reference)
    rec = chain.report()
    out = {
        "method": " + ".join(s.name for s in chain.steps),
        "dx": dx,
        "dy": dy,
        "dz": dz,
        "dx_sigma": float(np.sqrt(vx)),
        "dy_sigma": float(np.sqrt(vy)),
        "dz_sigma": float(np.sqrt(vz)),
        "dx_px": dx / pe,
        "dy_px": dy / pn,
        "pixel_size_m": [pe, pn],
        "iterations": iterations,
        "converged": converged,
        "nmad_before": rec[0]["before"]["nmad"],
        "nmad_after": rec[-1]["after"]["nmad"],
        "frame": "metres along x (grid east), y (grid north), up (dx, dy: see "
        "horizontal_unit); displacement of the DEM relative to the reference",
        "scale_factor": scale,
        "horizontal_unit": unit,
        "steps": rec,
    }
    if ground:  # the projection's scale differs from 1 by over 0.1 % (shift_units.ground_shift)
        for name, v, var, k in (("dx", dx, vx, scale[0]), ("dy", dy, vy, scale[1])):
            out[f"{name}_ground"] = v / k
            out[f"{name}_ground_sigma"] = float(np.sqrt(var)) / k
    return out


def _pixel_size_report(d: DEM):
    pe, pn = terrain.pixel_size_m(d.transform, d.crs, d.shape)
    mid = pe.shape[0] // 2
    return [float(abs(pe[mid, 0])), float(abs(pn[mid, 0]))]


# ----------------------------------------------------------------------------- check points

_LON = ("lon", "longitude", "long")
_LAT = ("lat", "latitude")
_X = ("x", "easting", "e")
_Y = ("y", "northing", "n")
_Z = ("height", "h", "z", "elevation", "alt", "altitude")


def _check_roles(path, roles, *, quiet: bool = False) -> np.ndarray:
    """Which rows of a check-point CSV with a ``role`` column are check points: ``check``
    (an empty role is ``gcp``, as :func:`stereodem.sensor.io.gcps.read_gcps` reads it);
    an unknown role, or no check point at all, is an :class:`InputError` naming the file.
    The GCPs left out are logged unless ``quiet``."""
    role = parse_roles(roles, f"{path}: ")
    keep = role == "check"
    if not keep.any():
        raise InputError(
            f"{path}: no check point: its {role.size} point(s) all have the role gcp (used in "
            "the estimation, no independent check); mark the check points role=check"
        )
    if not keep.all() and not quiet:
        log.info(
            "%s: %d check point(s); %d GCP(s) (role gcp) left out", path, keep.sum(), (~keep).sum()
        )
    return keep


def check_checkpoints(path, *, crs=None) -> None:
    """The refusals of :func:`read_checkpoints` before any work, without its log line (which
    the read that uses the points gives: the file is read twice, logged once)."""
    read_checkpoints(path, crs=crs, quiet=True)


def read_checkpoints(path, *, crs=None, quiet: bool = False):
    """Read check points from a CSV with a header.

    Columns ``lon``/``lat`` (degrees WGS84) or ``x``/``y`` (then ``crs`` is required), and
    ``height``/``h``/``z``; an ``id`` column is kept if present. A ``role`` column (the GCP
    CSV of ``stereodem adjust``, :mod:`stereodem.sensor.io.gcps`: ``gcp``, the default, or
    ``check``) keeps the ``check`` points only: a GCP used in the estimation is no
    independent check of the result; how many are left out is logged (not when ``quiet``).

    Returns
    -------
    lon, lat, z : ndarray float64 ; ids : list of str
    """
    path = str(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except FileNotFoundError:
        raise InputError(not_found(path, "check points")) from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the check points ({exc.strerror})") from None
    except (UnicodeDecodeError, csv.Error):
        raise InputError(f"{path}: not a text CSV of check points (binary or garbled)") from None
    if not rows:
        raise InputError(f"{path}: no check point")
    cols = {c.strip().lower(): c for c in rows[0].keys() if c is not None}

    def pick(names):
        for n in names:
            if n in cols:
                return cols[n]
        return None

    cx, cy = pick(_LON), pick(_LAT)
    geographic = cx is not None and cy is not None
    if not geographic:
        cx, cy = pick(_X), pick(_Y)
    cz = pick(_Z)
    if cx is None or cy is None or cz is None:
        raise InputError(f"{path}: need columns lon,lat,height or x,y,z; got {list(cols)}")
    try:
        x = np.array([float(r[cx]) for r in rows])
        y = np.array([float(r[cy]) for r in rows])
        z = np.array([float(r[cz]) for r in rows])
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: non-numeric check point coordinate ({exc})") from None
    cid = pick(("id", "name", "point"))
    ids = [r[cid] for r in rows] if cid else [str(i) for i in range(len(rows))]
    crole = pick(("role",))
    if crole is not None:
        keep = _check_roles(path, [r[crole] for r in rows], quiet=quiet)
        x, y, z, ids = x[keep], y[keep], z[keep], [i for i, k in zip(ids, keep) if k]
    if geographic and crs is None:
        lon, lat = x, y
    else:
        if crs is None:
            raise CRSError(f"{path}: x/y check points need a CRS (--checkpoints-crs)")
        lon, lat = geodesy.crs_to_lonlat(x, y, crs)
    return np.asarray(lon, float), np.asarray(lat, float), z, ids


def assess_checkpoints(dem, checkpoints, *, crs=None, vertical: str | None = None) -> dict:
    """DEM − check point heights, the DEM sampled bilinearly at each point.

    Parameters
    ----------
    checkpoints : path or (lon, lat, z) arrays (degrees, metres), or (lon, lat, z, ids) as
        :func:`read_checkpoints` returns them
    vertical : {"geoid", "ellipsoid"}, optional
        Vertical reference of the check-point heights; the DEM is converted to it. ``None``
        assumes the DEM's own reference (stated in the result).
    """
    dem = as_dem(dem)
    if isinstance(checkpoints, (str, Path)):
        lon, lat, z, ids = read_checkpoints(checkpoints, crs=crs)
    else:
        lon, lat, z = (np.asarray(a, dtype=np.float64) for a in checkpoints[:3])
        if crs is not None:
            lon, lat = geodesy.crs_to_lonlat(lon, lat, crs)
        ids = [str(i) for i in (checkpoints[3] if len(checkpoints) > 3 else range(lon.size))]
    if vertical is not None and dem.vertical is None:
        raise VerticalReferenceError(
            f"{dem.path or 'DEM'}: vertical reference unknown; check "
            f"points are {vertical} (give --dem-vertical)"
        )
    hz, status = dem.sample(lon, lat, reference=vertical, return_status=True)
    dh = hz - z
    res = st.error_stats(dh)
    if res["n"] == 0:
        raise DEMError(
            f"{dem.path or 'DEM'}: none of the {lon.size} check points falls on a valid DEM cell"
        )
    note = (
        f"check points {vertical}"
        if vertical
        else f"check points assumed {dem.vertical or 'same as DEM'}"
    )
    return {
        "stats": res,
        "vertical": note,
        "sampling": "bilinear",
        "outside": int((status == 1).sum()),
        "on_void": int((status == 2).sum()),
        "points": [
            {
                "id": i,
                "lon": float(a),
                "lat": float(b),
                "z": float(c),
                "dem": float(d) if np.isfinite(d) else None,
                "dh": float(e) if np.isfinite(e) else None,
            }
            for i, a, b, c, d, e in zip(ids, lon, lat, z, hz, dh)
        ],
    }
