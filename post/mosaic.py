"""DEM mosaics computed block by block (ASP ``dem_mosaic``): one CRS, one vertical reference,
seams blended with distance-to-edge weights, statistics of the stack, in bounded memory.

Flow: :func:`plan_mosaic` opens the DEMs' headers (:mod:`.mosaic_sources`), optionally
co-registers each to a reference (:mod:`.mosaic_coreg`), reconciles the vertical references and
lays one output grid over the footprints (the first DEM's CRS, posting and lattice unless
told otherwise); :func:`mosaic_block` computes one block of the output from the DEMs whose
footprint meets it, read through windows (directly where a DEM lies on the output lattice,
through GDAL's warper — bilinear — where it does not: other CRS, posting or a co-registration
shift); :func:`run_mosaic` writes the blocks into a COG
(:class:`~stereodem.core.blockwrite.BlockWriter`), here or on a ``dask.distributed`` cluster.

Methods, per output cell, over the DEMs with a height there (``count`` of them):

* ``blend`` (default): weighted mean with weight ``min(d, L)^p / σ²``, ``d`` the distance
  (cells, Euclidean) from the cell to the nearest void or edge of that DEM inside the mosaic
  (the mosaic's outer border is not an edge), ``L`` the blending
  length, ``p`` the weights exponent (2, as ``dem_mosaic``) and ``σ`` the DEM's 1σ layer
  where every DEM carries one (else 1). A DEM's weight falls to zero at its edges, so a seam
  between DEMs with different biases becomes a ramp ``L`` cells wide instead of a step. The
  distance is computed on the block plus a halo of ``L`` cells, which is exact for the capped
  weight: the mosaic does not depend on the block size (tested).
* ``first`` / ``last``: the first / last DEM on the command line with a height;
  ``min``, ``max``, ``mean``, ``median``;
* ``count``, ``stddev`` (population, NaN where fewer than two DEMs), ``nmad`` (1.4826 × median
  absolute deviation, NaN where fewer than two DEMs): the statistic is the only band.

Other methods write three bands: the heights, ``count`` and the spread — the propagated 1σ
(``sigma``: √Σw²σ² / Σw) where ``blend`` uses σ layers, else ``stddev`` of the contributing
heights.

Memory (:func:`memory_bound`): one block's working set — the block plus halo for each DEM
read in turn (the running sums of ``blend``/``mean``/... do not grow with the number of DEMs),
plus for ``median``/``nmad`` the stack of the block's DEMs (K × block² values) — and GDAL's
block cache. It depends on the block size and the number of DEMs overlapping one block, not on
the mosaic's size or the number of DEMs.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import time
from dataclasses import asdict, dataclass, field, replace
from typing import NamedTuple

import cv2
import numpy as np
import rasterio
from pyproj import CRS
from rasterio.enums import Resampling
from rasterio.vrt import WarpedVRT
from rasterio.windows import Window

from stereodem.core import geodesy
from stereodem.core.blockwrite import CACHE_MB, OVERVIEW_CHUNK_MB, BlockWriter
from stereodem.core.dem import (
    DEM,
    ELLIPSOID,
    GEOID,
    UNDECLARED_NODATA,
    Voided,
    height_scaling,
    void_nodata,
)
from stereodem.core.errors import DEMError, InputError, NoOverlapError, StereodemError, portable
from stereodem.core.grid import MapGrid
from stereodem.core.raster import unreadable
from stereodem.core.stats import nanmedian, nmad

from .choices import MOSAIC_METHODS
from .mosaic_coreg import check_reference, crop_reference, fitter
from .mosaic_sources import (
    Source,
    mosaic_geoid,
    open_sources,
    output_grid,
    reconcile_vertical,
    select_sources,
)
from .shift_units import shift_phrase, shift_units
from .warp import (
    TRANSFORM_TOLERANCE_PX,
    grid_kernel_scale,
    kernel_scale_options,
    translated,
)

log = logging.getLogger(__name__)

__all__ = [
    "METHODS",
    "MosaicBlock",
    "MosaicPlan",
    "blocks",
    "coregister_sources",
    "memory_bound",
    "mosaic_block",
    "plan_mosaic",
    "run_mosaic",
]

METHODS = MOSAIC_METHODS  # the choices live in a light module (the parser imports them)
#: methods that need the stack of one block (K layers) rather than running sums
STACK_METHODS = ("median", "nmad")
#: methods whose statistic is the only band
SINGLE_BAND = ("count", "stddev", "nmad")
#: GDAL block cache while reading (MB): part of the memory bound
READ_CACHE_MB = 32
_SIGMA_FLOOR = 0.01  # m: σ below this is taken as this (a zero σ would take all weight)


@dataclass(frozen=True)
class MosaicPlan:
    """Everything a block needs (picklable: Dask workers get it once).

    Attributes
    ----------
    grid : MapGrid
        Output grid (horizontal CRS, GDAL pixel-corner transform).
    sources : tuple of Source
        DEMs used, in command-line order, footprints in the output CRS.
    method : str
        One of :data:`METHODS`.
    vertical : {"geoid", "ellipsoid"} or None
        Vertical reference of the output; DEMs of the other are converted with EGM96.
    block : int
        Output block size, cells.
    blend_length : int
        ``L``: distance (cells) over which a DEM's weight rises from its edge (``blend``).
    weights_exponent : float
        ``p`` of the blending weight.
    use_sigma : bool
        Every DEM carries a σ layer: ``blend`` weights by 1/σ² and propagates σ.
    geoid_wkt : str or None
        With ``vertical == "geoid"``: the output's geoid (vertical CRS, WKT) when it is not
        EGM96 (:func:`~stereodem.post.mosaic_sources.mosaic_geoid`).
    """

    grid: MapGrid
    sources: tuple
    method: str = "blend"
    vertical: str | None = None
    block: int = 512
    blend_length: int = 50
    weights_exponent: float = 2.0
    use_sigma: bool = False
    report: dict = field(default_factory=dict, compare=False)
    geoid_wkt: str | None = None

    @property
    def halo(self) -> int:
        return self.blend_length if self.method == "blend" else 0

    def bands(self) -> list[str]:
        """Band descriptions of the output."""
        geoid = CRS.from_wkt(self.geoid_wkt).name if self.geoid_wkt else "EGM96 height"
        what = {
            GEOID: f"height above the {geoid.removesuffix(' height')} geoid",
            ELLIPSOID: "height above the WGS84 ellipsoid",
        }
        if self.method in SINGLE_BAND:
            return [
                {
                    "count": "count (DEMs with a height)",
                    "stddev": "stddev (of the DEMs' heights)",
                    "nmad": "nmad (of the DEMs' heights)",
                }[self.method]
            ]
        spread = (
            "sigma (1-sigma, propagated)"
            if (self.method == "blend" and self.use_sigma)
            else "stddev (of the DEMs' heights)"
        )
        return [what.get(self.vertical, "height"), "count (DEMs with a height)", spread]

    def units(self) -> list[str]:
        return ["" if b.startswith("count") else "metre" for b in self.bands()]

    def footprints(self) -> np.ndarray:
        return np.array([s.bounds for s in self.sources], dtype=np.float64).reshape(-1, 4)


# --------------------------------------------------------------------------- planning


def plan_mosaic(
    paths,
    *,
    method: str = "blend",
    crs=None,
    res=None,
    bounds=None,
    vertical: str | None = None,
    dem_vertical: str | None = None,
    block: int = 512,
    blend_length: int = 50,
    weights_exponent: float = 2.0,
    use_sigma: bool = True,
    reference=None,
    coreg_chain: str | None = None,
) -> MosaicPlan:
    """Open, check and lay out a mosaic of the DEM files ``paths``.

    Parameters
    ----------
    method : str
        One of :data:`METHODS`.
    crs, res, bounds
        Output CRS (default: the first DEM's), posting in its units (default: the first DEM's)
        and (west, south, east, north) extent (default: the union of the footprints).
    vertical : {"geoid", "ellipsoid"}, optional
        Output vertical reference (default: the first DEM's).
    dem_vertical : {"geoid", "ellipsoid"}, optional
        Vertical reference of DEMs whose file does not say.
    block, blend_length, weights_exponent
        See :class:`MosaicPlan`.
    use_sigma : bool
        Weight ``blend`` by the DEMs' σ layers when every DEM has one.
    reference : path, optional
        Co-register every DEM to this DEM first (``coreg_chain``: see :mod:`.mosaic_coreg`).

    Raises
    ------
    InputError (and subclasses)
        One line naming the file: unreadable, no CRS, not north-up, vertical reference
        unknown among known ones, or no DEM overlapping the extent.
    """
    paths = [paths] if isinstance(paths, str | os.PathLike) else list(paths)  # one file
    if method not in METHODS:
        raise InputError(f"--method {method!r}: expected one of {', '.join(METHODS)}")
    if int(block) < 16:
        raise InputError(f"--block must be at least 16 cells, got {block}")
    if int(blend_length) < 1:
        raise InputError(f"--blend-length must be at least 1 cell, got {blend_length}")
    if not weights_exponent > 0:
        raise InputError(f"--weights-exponent must be positive, got {weights_exponent}")
    sources = open_sources(paths, vertical=dem_vertical)
    target = reconcile_vertical(sources, vertical)
    skipped = []
    coreg = {}
    if reference is not None:
        check_reference(reference)
        sources, skipped, coreg = coregister_sources(
            sources, reference, chain=coreg_chain, dem_vertical=dem_vertical
        )
    grid, placed = output_grid(sources, crs=crs, res=res, bounds=bounds)
    used, outside, islands = select_sources(placed, grid)
    skipped += outside
    geoid = mosaic_geoid(used, target)
    sigma = bool(use_sigma) and all(s.sigma is not None for s in used)
    if use_sigma and not sigma and any(s.sigma is not None for s in used):
        log.warning(
            "only %d of %d DEMs carry a σ layer: blending by distance only",
            sum(s.sigma is not None for s in used),
            len(used),
        )
    conversions = [
        dict(path=s.path, vertical=s.vertical, to=target)
        for s in used
        if s.vertical is not None and target is not None and s.vertical != target
    ]
    report = dict(
        method=method,
        n_inputs=len(paths),
        n_used=len(used),
        skipped=skipped,
        islands=islands,
        vertical=target,
        geoid=(CRS.from_wkt(geoid).name if geoid else "EGM96 height") if target == GEOID else None,
        vertical_conversions=conversions,
        sigma_weighting=sigma,
        coregistration=coreg,
        reprojected=[s.path for s in used if not _on_lattice(s, grid)],
        grid=dict(
            crs=grid.crs.to_string(),
            transform=list(grid.transform)[:6],
            width=grid.width,
            height=grid.height,
            posting=grid.posting,
        ),
    )
    plan = MosaicPlan(
        grid,
        tuple(used),
        method,
        target,
        int(block),
        int(blend_length),
        float(weights_exponent),
        sigma,
        report,
        geoid,
    )
    k = max_overlap(plan)
    report.update(
        max_dems_per_block=k,
        memory_bound_mb=memory_bound(plan, k) / 2**20,
        block=int(block),
        blend_length=int(blend_length),
        weights_exponent=float(weights_exponent),
    )
    return plan


def coregister_sources(sources, reference, *, chain: str | None = None, dem_vertical=None):
    """Co-register each DEM to ``reference`` (one DEM in memory at a time, the reference read
    over that DEM's footprint only). Returns (sources with their grids moved and ``dz`` set,
    skipped ``[{path, reason}]``, ``{path: correction report}``). A DEM that misses the
    reference or cannot be fitted is named and skipped."""
    fit = fitter(chain or "nuth_kaab")
    out, skipped, reports = [], [], {}
    voided = {}  # the reference's cells the DEM reading rules voided: one warning
    for s in sources:
        try:
            ref = crop_reference(
                reference, s.native_bounds, s.crs, vertical=dem_vertical, voided=voided
            )
            if ref.vertical != s.vertical:
                if ref.vertical is None or s.vertical is None:
                    raise InputError(
                        f"{reference}: vertical reference of the reference or of "
                        f"{s.path} unknown (say it with --dem-vertical)"
                    )
                ref = ref.to_reference(s.vertical)
            dem = DEM.from_file(s.path, vertical=s.vertical)
            corr = fit(ref, dem)
        except (NoOverlapError, DEMError) as exc:
            reason = " ".join(str(exc).split())
            log.warning("%s: not co-registered, skipped (%s)", s.path, reason)
            skipped.append(dict(path=s.path, reason=f"co-registration: {reason}"))
            continue

        t = translated(s.transform, s.crs, (s.height, s.width), -corr.dx, -corr.dy)
        out.append(replace(s, transform=t, shift_m=(-corr.dx, -corr.dy), dz=float(corr.dz)))
        reports[s.path] = dict(corr.report, dx=corr.dx, dy=corr.dy, dz=corr.dz)
        log.info(
            "%s: co-registered, %s, dz = %+.2f m.%s",
            s.path,
            shift_phrase(corr.dx, corr.dy, "+.2f"),
            corr.dz,
            shift_units(reports[s.path]),
        )
    for path, v in voided.items():
        v.warn(path)
    if not out:
        raise NoOverlapError(f"{reference}: no DEM could be co-registered to the reference")
    return out, skipped, reports


def blocks(plan: MosaicPlan):
    """Output blocks ``(row0, col0, rows, cols)`` in row-major order."""
    g, b = plan.grid, plan.block
    return [
        (r, c, min(b, g.height - r), min(b, g.width - c))
        for r in range(0, g.height, b)
        for c in range(0, g.width, b)
    ]


def _block_bounds(plan, r0, c0, rows, cols):
    t = plan.grid.transform
    return (t.c + c0 * t.a, t.f + (r0 + rows) * t.e, t.c + (c0 + cols) * t.a, t.f + r0 * t.e)


def _meeting(plan, r0, c0, rows, cols) -> np.ndarray:
    """Indices of the DEMs whose footprint meets the block (in command-line order)."""
    w, s, e, n = _block_bounds(plan, r0, c0, rows, cols)
    f = plan.footprints()
    return np.flatnonzero((f[:, 0] < e) & (f[:, 2] > w) & (f[:, 1] < n) & (f[:, 3] > s))


def max_overlap(plan: MosaicPlan) -> int:
    """Largest number of DEMs meeting one block (``K`` of :func:`memory_bound`)."""
    return max((len(_meeting(plan, *b)) for b in blocks(plan)), default=0)


def memory_bound(plan: MosaicPlan, k: int | None = None) -> int:
    """Bytes one block's computation may hold, beyond the interpreter and libraries:

    ``48 B × (b + 2L)²`` for the DEM being read (heights, mask, σ, distance, weight, geoid
    undulation; one DEM at a time), ``64 B × b²`` for the running sums, ``40 B × K × b²`` for
    the stack of ``median``/``nmad`` (float32 stack, float64 copies of the median), plus GDAL's
    read and write caches (:data:`READ_CACHE_MB` + the writer's) and the overview chunk of the
    final COG copy. ``b`` block, ``L`` halo,
    ``K`` DEMs meeting one block (:func:`max_overlap`).
    """
    k = max_overlap(plan) if k is None else int(k)
    b, h = plan.block, plan.halo
    n = 48 * (b + 2 * h) ** 2 + 64 * b * b + len(plan.bands()) * 4 * b * b
    if plan.method in STACK_METHODS:
        n += 40 * k * b * b
    return int(n + (READ_CACHE_MB + CACHE_MB + OVERVIEW_CHUNK_MB) * 2**20)


# --------------------------------------------------------------------------- reading


def _on_lattice(s: Source, grid: MapGrid) -> bool:
    """The DEM's cells are output cells (same CRS and posting, whole-cell offset)."""
    t, g = s.transform, grid.transform
    if not (np.isclose(t.a, g.a, rtol=1e-9) and np.isclose(t.e, g.e, rtol=1e-9)):
        return False
    dc, dr = (g.c - t.c) / t.a, (g.f - t.f) / t.e
    return abs(dc - round(dc)) < 1e-6 and abs(dr - round(dr)) < 1e-6 and s.crs.equals(grid.crs)


@functools.lru_cache(maxsize=256)  # one per DEM and grid: 2.5-4.5 ms, for each block's read
def _kernel_scale(s: Source, grid: MapGrid):
    """The kernel scale of the DEM's bilinear warp onto the output grid (GDAL's ``XSCALE``,
    ``YSCALE``: output cells per DEM cell along the DEM's axes,
    :func:`~stereodem.core.warp.grid_kernel_scale`), one for the whole grid, so that every
    window read warps the DEM as a read of the whole grid would. GDAL's own is per chunk of the
    warp (a small window is warped in the VRT's blocks of 128 rows, GDAL's default; a large
    one, with GDAL 3.10, in one piece): between two CRSs a chunk of a grid turned against the
    DEM (UTM onto polar stereographic) has a tall source window and its kernel was widened
    more, so the mosaic depended on its blocks (a 10 m UTM 33N DEM on a 30 m EPSG:3413 grid of
    269 x 269 cells: 8.5 m at most, median 0.23 m between 16-cell windows and the whole grid).

    Taken at the centre of the part of the grid that the DEM's footprint (``s.bounds``, output
    CRS) covers, not at the grid's centre: the mosaic's grid may be far larger than the DEM
    (1000 km more of an EPSG:3413 grid: a scale 1.4 % off, 0.2 m). None between grids of one
    CRS, and where that centre has no place in the DEM's CRS (GDAL's own, per chunk)."""
    return grid_kernel_scale(
        s.transform,
        s.crs_wkt,
        grid.transform,
        grid.crs,
        (grid.height, grid.width),
        footprint=s.bounds if len(s.bounds) == 4 else None,
    )


def read_on_grid(
    s: Source,
    grid: MapGrid,
    r0: int,
    c0: int,
    rows: int,
    cols: int,
    layer=None,
    *,
    voided: dict | None = None,
    count=None,
) -> np.ndarray:
    """The DEM's values (or its σ layer: ``layer=(path, band)``) on the output cells
    ``[r0:r0+rows, c0:c0+cols]``: float32 metres (GDAL's scale and offset applied, feet
    converted: :func:`~stereodem.core.dem.height_scaling`), NaN where it has none. Cells on
    the output lattice are copied; otherwise GDAL's warper resamples (bilinear) through a
    window, with one kernel scale for the whole grid (:func:`_kernel_scale`): any window
    gives the values of the whole grid's read.

    Heights follow :meth:`DEM.from_file`'s reading rules (:func:`~stereodem.core.dem.void_nodata`:
    -9999 in a file without a nodata value and heights no place on Earth has are no-data):
    what they voided (the cells ``count`` indexes, default all) is added to
    ``voided[s.path]`` (a :class:`~stereodem.core.dem.Voided`), for one warning per file
    once every block is read, or warned at once without ``voided``."""
    path, band = layer or (s.path, 1)
    out = np.full((rows, cols), np.nan, np.float32)
    sentinel = None
    try:
        with rasterio.open(path) as ds:
            nodata = ds.nodata
            if _on_lattice(s, grid):
                g, t = grid.transform, s.transform
                dc, dr = int(round((g.c - t.c) / t.a)), int(round((g.f - t.f) / t.e))
                sc0, sr0 = max(c0 + dc, 0), max(r0 + dr, 0)
                sc1, sr1 = min(c0 + dc + cols, s.width), min(r0 + dr + rows, s.height)
                if sc1 <= sc0 or sr1 <= sr0:
                    return out
                a = ds.read(band, window=Window(sc0, sr0, sc1 - sc0, sr1 - sr0), masked=True)
                out[sr0 - dr - r0 : sr1 - dr - r0, sc0 - dc - c0 : sc1 - dc - c0] = a.astype(
                    np.float32
                ).filled(np.nan)
            else:
                src_nodata = ds.nodata
                dtype = np.dtype(ds.dtypes[band - 1])
                if src_nodata is None and np.issubdtype(dtype, np.floating):
                    src_nodata = np.nan
                undeclared = (
                    layer is None and ds.nodata is None and _holds(dtype, UNDECLARED_NODATA)
                )
                if undeclared:  # GDAL's no-data (NaN too), not blended into its neighbours
                    src_nodata = UNDECLARED_NODATA

                scale = kernel_scale_options(_kernel_scale(s, grid))

                def warped(src, resampling):
                    with WarpedVRT(
                        ds,
                        src_crs=s.crs_wkt,
                        src_transform=s.transform,
                        src_nodata=src,
                        crs=grid.crs.to_wkt(),
                        transform=grid.transform,
                        width=grid.width,
                        height=grid.height,
                        nodata=np.nan,
                        dtype="float32",
                        resampling=resampling,
                        tolerance=TRANSFORM_TOLERANCE_PX,  # GDAL's 0.125 px: a shift
                        **scale,  # warp options: one kernel scale, whatever the window
                    ) as vrt:
                        return vrt.read(band, window=Window(c0, r0, cols, rows), masked=True)

                out[:] = warped(src_nodata, Resampling.bilinear).filled(np.nan)
                if undeclared:  # the cells whose nearest stored value is the sentinel
                    near = warped(None, Resampling.nearest).filled(np.nan)
                    sentinel = near == np.float32(UNDECLARED_NODATA)
            scaling = height_scaling(ds, band)  # decimetres, feet: metres
    except rasterio.errors.RasterioIOError as exc:
        raise DEMError(unreadable(path, "DEM", exc)) from None
    if layer is not None:  # a σ layer: no height rules
        if scaling != (1.0, 0.0):
            out *= np.float32(scaling[0])
            out += np.float32(scaling[1])
        out[~np.isfinite(out)] = np.nan
        return out
    found = void_nodata(out, nodata, *scaling, sentinel=sentinel, count=count)
    if voided is None:
        found.warn(s.path)
    elif found:
        voided.setdefault(s.path, Voided()).add(found)
    return out


def _holds(dtype: np.dtype, value: float) -> bool:
    """Whether rasters of ``dtype`` can store ``value``."""
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        return info.min <= value <= info.max
    return True


def edge_weight(
    valid: np.ndarray, length: int, exponent: float, border=(False, False, False, False)
) -> np.ndarray:
    """Blending weight ``min(d, L)^p`` (float32), ``d`` the Euclidean distance in cells from
    each valid cell to the nearest invalid one, 0 on invalid cells.

    ``border`` (top, bottom, left, right): sides of the array beyond which cells count as
    invalid; on the other sides (by default all) nothing beyond the array counts, so a window
    with a halo of ``L`` gives the capped weight exactly. The mosaic does not count its outer
    border as an edge: where two DEMs both reach it, tapering both there would leave a step
    along the border where one of them ends."""
    top, bottom, left, right = (int(bool(b)) for b in border)
    padded = np.pad(valid.astype(np.uint8), ((top, bottom), (left, right)))
    d = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d = d[top : d.shape[0] - bottom, left : d.shape[1] - right]
    return np.power(np.minimum(d, np.float32(length)), np.float32(exponent)).astype(np.float32)


# --------------------------------------------------------------------------- one block


def _read_env():
    """GDAL settings of the block reads (here and in Dask workers): the bounded block cache,
    and no listing of each DEM's folder on open (the georeferencing comes from the plan;
    with hundreds of DEMs in one folder every open cost ~20 ms)."""
    return rasterio.Env(GDAL_CACHEMAX=READ_CACHE_MB, GDAL_DISABLE_READDIR_ON_OPEN="EMPTY_DIR")


class MosaicBlock(NamedTuple):
    """One computed block of a mosaic (:func:`mosaic_block`)."""

    r0: int  #: first output row
    c0: int  #: first output column
    arrays: np.ndarray  #: (bands, rows, cols) float32
    contributors: list  #: indices into ``plan.sources`` of the DEMs with a valid height here
    #: what the DEM reading rules made no-data here, by path
    #: (:class:`~stereodem.core.dem.Voided`; :func:`run_mosaic` warns once per file)
    voided: dict


def mosaic_block(plan: MosaicPlan, r0: int, c0: int, rows: int, cols: int) -> MosaicBlock:
    """One output block (:class:`MosaicBlock`). Pure function of the plan and the files
    (runs in Dask workers)."""
    with _read_env():
        return _mosaic_block(plan, r0, c0, rows, cols)


def _mosaic_block_task(plan: MosaicPlan, r0: int, c0: int, rows: int, cols: int):
    """:func:`mosaic_block` as a Dask task: a stereodem error (a DEM that does not read) is
    returned, not raised, and :func:`_dask_blocks` raises it in the client, so that the
    command ends with its one-line error (raised, it reached the client as a bare
    ``Exception`` when GDAL's error was in its chain: :func:`~stereodem.core.errors.portable`,
    and each worker logged it with its traceback)."""
    try:
        return mosaic_block(plan, r0, c0, rows, cols)
    except StereodemError as exc:
        return portable(exc)


def _mosaic_block(plan, r0, c0, rows, cols):
    g, m, h = plan.grid, plan.method, plan.halo
    wr0, wc0 = max(r0 - h, 0), max(c0 - h, 0)
    wr1, wc1 = min(r0 + rows + h, g.height), min(c0 + cols + h, g.width)
    core = (slice(r0 - wr0, r0 - wr0 + rows), slice(c0 - wc0, c0 - wc0 + cols))
    undulation = None
    n = np.zeros((rows, cols), np.int32)
    s1 = np.zeros((rows, cols))
    s2 = np.zeros((rows, cols))
    value = np.full((rows, cols), np.nan, np.float32)
    sw = np.zeros((rows, cols))
    swz = np.zeros((rows, cols))
    sw2s2 = np.zeros((rows, cols))
    stack = []
    contributors = []
    voided = {}
    for i in _meeting(plan, r0, c0, rows, cols):
        s = plan.sources[i]
        if m == "blend":  # the halo's cells are counted in their own blocks
            z = read_on_grid(s, g, wr0, wc0, wr1 - wr0, wc1 - wc0, voided=voided, count=core)
        else:
            z = read_on_grid(s, g, r0, c0, rows, cols, voided=voided)
        if s.vertical is not None and plan.vertical is not None and s.vertical != plan.vertical:
            if undulation is None:
                jj, ii = np.meshgrid(np.arange(wc0, wc1), np.arange(wr0, wr1))
                undulation = geodesy.geoid_undulation(*g.lonlat(jj, ii)).astype(np.float32)
            und = undulation if m == "blend" else undulation[core]
            z = z + und if plan.vertical == ELLIPSOID else z - und
        if s.dz:
            z = z - np.float32(s.dz)
        valid_w = np.isfinite(z)
        zc = z[core] if m == "blend" else z
        valid = np.isfinite(zc)
        if not valid.any():
            continue
        contributors.append(i)
        n += valid
        zz = np.where(valid, zc, np.float32(0)).astype(np.float64)
        s1 += zz
        s2 += zz * zz
        if m == "blend":
            w = edge_weight(valid_w, plan.blend_length, plan.weights_exponent)[core].astype(
                np.float64
            )
            if plan.use_sigma:
                sig = read_on_grid(s, g, r0, c0, rows, cols, layer=s.sigma).astype(np.float64)
                bad = ~(sig > 0)
                if bad.all():
                    sig[:] = 1.0
                elif bad.any():
                    sig[bad] = np.nanmax(sig[~bad])  # no σ at a cell: the DEM's worst here
                sig = np.maximum(sig, _SIGMA_FLOOR)
                w = w / (sig * sig)
                sw2s2 += np.where(valid, w * w * sig * sig, 0.0)
            sw += np.where(valid, w, 0.0)
            swz += np.where(valid, w * zz, 0.0)
        elif m == "first":
            take = valid & np.isnan(value)
            value[take] = zc[take]
        elif m == "last":
            value[valid] = zc[valid]
        elif m == "min":
            value = np.fmin(value, zc)
        elif m == "max":
            value = np.fmax(value, zc)
        elif m in STACK_METHODS:
            stack.append(zc)
    have = n > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(have, s1 / np.maximum(n, 1), np.nan)
        var = np.maximum(s2 / np.maximum(n, 1) - mean * mean, 0.0)
        std = np.where(n >= 2, np.sqrt(var), np.nan)
    if m == "blend":
        # every valid cell has d >= 1, hence w > 0: sw > 0 wherever n > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            value = np.where(have, swz / sw, np.nan)
            spread = np.where(have, np.sqrt(sw2s2) / sw, np.nan) if plan.use_sigma else std
    else:
        spread = std
    if m == "mean":
        value = mean
    elif m in STACK_METHODS:
        if stack:
            st = np.stack(stack)
            del stack
            value = nanmedian(st, axis=0) if m == "median" else nmad(st, axis=0)
            del st
    if m == "count":
        bands = [n.astype(np.float32)]
    elif m == "stddev":
        bands = [std]
    elif m == "nmad":
        bands = [np.where(n >= 2, value, np.nan)]
    else:
        bands = [value, np.where(have, n, np.nan), spread]
    arrays = np.stack([np.asarray(b, np.float32) for b in bands])
    return MosaicBlock(r0, c0, arrays, contributors, voided)


# --------------------------------------------------------------------------- the job


def _dask_blocks(plan, todo, address, workers):
    """Blocks computed on a ``dask.distributed`` cluster (``address``, or a local cluster of
    ``workers`` processes for ``"local"``, default all cores, each pinned to its share of the
    cores: :func:`stereodem.core.threads.worker_threads`), yielded as they finish, with at
    most two per worker in flight (so finished blocks never pile up in the client)."""
    try:
        from dask.distributed import Client, as_completed, wait
    except ImportError:  # pragma: no cover - optional extra
        raise InputError("--dask needs dask.distributed (pip install 'stereodem[dask]')") from None
    from stereodem.core.dask_threads import local_cluster, quiet_distributed_logging
    from stereodem.core.threads import pool_size, register_dask_plugin, worker_threads

    quiet_distributed_logging()
    cluster = None
    if address in (None, "local"):
        cluster = local_cluster(pool_size(workers))
        client = Client(cluster)
        # N workers: the cores shared; they log as this process does
        register_dask_plugin(client, worker_threads(workers), own_workers=True)
    elif address == "threads":  # in-process cluster (tests)
        cluster = local_cluster(1, max(int(workers or 1), 1), processes=False)
        client = Client(cluster)
    else:
        from stereodem.core.dask_threads import connect

        client = connect(address)
        register_dask_plugin(client)  # each node's cores shared out over its workers' slots
    inflight = set()  # submitted, not yet handed on

    def submit(p, block):
        fut = client.submit(_mosaic_block_task, p, *block, pure=False)
        inflight.add(fut)
        return fut

    try:
        nthreads = max(sum(client.nthreads().values()), 1)
        [p] = client.scatter([plan], broadcast=True)
        queue = list(todo)
        pending = as_completed()
        for _ in range(min(2 * nthreads, len(queue))):
            pending.add(submit(p, queue.pop(0)))
        for fut in pending:
            inflight.discard(fut)
            block = fut.result()
            if isinstance(block, BaseException):  # a DEM that does not read (_mosaic_block_task)
                raise block
            yield block
            fut.release()
            if queue:
                pending.add(submit(p, queue.pop(0)))
    finally:
        if inflight:  # stopped early: the blocks under way end first (at most two a worker),
            # else every worker closed under one logged that it "ended with CancelledError"
            # above the command's own one-line error
            with contextlib.suppress(Exception):
                wait(list(inflight), timeout=60)
        client.close()
        if cluster is not None:
            cluster.close()


def run_mosaic(
    plan: MosaicPlan,
    out,
    *,
    overwrite: bool = False,
    creation_options=None,
    dask: str | None = None,
    workers: int | None = None,
    progress=None,
) -> dict:
    """Compute every block and write the mosaic ``out`` (a COG, atomically). Returns the
    report (plan, bands, seconds, valid share); a DEM whose footprint meets the mosaic but
    that has no valid height in it is not counted in ``n_used`` and is listed in
    ``skipped``, with a warning. ``dask``: scheduler address, ``"local"`` for
    a local cluster of ``workers`` processes (default all cores); None computes here, block
    after block, on the calling process's thread budget (``stereodem mosaic --workers``).
    ``progress(done, total)`` after each block."""
    t0 = time.perf_counter()
    todo = blocks(plan)
    tags = dict(STEREODEM_MOSAIC_METHOD=plan.method, STEREODEM_MOSAIC_DEMS=len(plan.sources))
    n_valid = n_data = 0
    contributed = set()
    voided = {}  # by path: what the DEM reading rules made no-data, over every block
    with BlockWriter(
        out,
        plan.grid,
        plan.bands(),
        units=plan.units(),
        vertical=plan.vertical,
        geoid_crs=CRS.from_wkt(plan.geoid_wkt) if plan.geoid_wkt else None,
        overwrite=overwrite,
        creation_options=creation_options,
        tags=tags,
    ) as w:
        results = (
            (mosaic_block(plan, *b) for b in todo)
            if dask is None
            else _dask_blocks(plan, todo, dask, workers)
        )
        for k, b in enumerate(results, start=1):
            w.write(b.r0, b.c0, b.arrays)
            contributed.update(b.contributors)
            for path, v in b.voided.items():
                voided.setdefault(path, Voided()).add(v)
            n_valid += int(np.isfinite(b.arrays[0]).sum())
            if plan.method == "count":
                n_data += int(np.count_nonzero(b.arrays[0] > 0))
            if progress is not None:
                progress(k, len(todo))
        for path, v in voided.items():  # once per file, not per block
            v.warn(path)
        if (n_data if plan.method == "count" else n_valid) == 0:
            # all-void DEMs, or --bounds over their voids: refused, not written as a mosaic
            raise DEMError(_empty_mosaic_message(plan))
    void = [s.path for i, s in enumerate(plan.sources) if i not in contributed]
    for path in void:
        log.warning("%s: no valid height over the mosaic's extent; it contributed nothing", path)
    report = dict(
        plan.report,
        n_used=len(plan.sources) - len(void),
        skipped=plan.report["skipped"]
        + [dict(path=p, reason="no valid height over the mosaic's extent") for p in void],
        output=str(out),
        bands=plan.bands(),
        n_blocks=len(todo),
        valid_share=n_valid / float(plan.grid.width * plan.grid.height),
        seconds=time.perf_counter() - t0,
        seconds_cog=w.cog_seconds,
        dask=dask,
    )
    return report


def _empty_mosaic_message(plan: MosaicPlan) -> str:
    """Why a mosaic has no valid cell: its DEMs have no valid height over its extent (or,
    for stddev / nmad, no cell is covered by two of them)."""
    paths = [s.path for s in plan.sources]
    names = ", ".join(paths[:3]) + (f" and {len(paths) - 3} more" if len(paths) > 3 else "")
    if plan.method in ("stddev", "nmad"):
        return (
            f"{names}: no cell of the mosaic has valid heights from two DEMs "
            f"(--method {plan.method} needs two); nothing to write"
        )
    b = tuple(round(v, 3) for v in plan.grid.bounds)
    return f"{names}: no valid height over the mosaic's extent {b}; nothing to write"


def plan_summary(plan: MosaicPlan) -> dict:
    """The plan as JSON-able values (for reports)."""
    d = asdict(plan)
    d.pop("grid"), d.pop("sources"), d.pop("report")
    return d
