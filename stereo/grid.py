"""Gridding of 3-D points into a DEM raster, with count, score and ray-gap layers.

Points (lon, lat, h) are projected into a map CRS (the UTM zone of the points by default) and
accumulated into cells of a regular grid with ``np.bincount``:

* ``"mean"``: the mean height of the points falling in each cell (s2p ``dsm_radius = 0``);
* ``"gaussian"``: each point spreads into the cells within ``radius`` cells of it, weighted by
  ``exp(-r^2 / 2 sigma^2)`` with ``r`` the distance from the point to the cell centre (s2p
  ``plyflatten`` with ``dsm_sigma``), which also fills one-cell gaps. The default width
  follows the point density: ``sigma = max(posting / 2, spacing)`` with ``spacing`` the mean
  point spacing (``posting / sqrt(points per occupied cell)``), so that every cell averages
  a similar number of points (about six) whether the posting is twice the image GSD (ASTER:
  four points per cell, ``sigma = posting / 2``) or equal to it (Pleiades on s2p's 0.5 m grid:
  about one point per cell, ``sigma ~ posting``).

Heights are ellipsoidal unless EGM96 geoid heights are requested. The grid uses the GDAL
pixel-corner affine transform; cell ``[i, j]`` has its centre at ``transform * (j + 0.5, i + 0.5)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from affine import Affine

from stereodem.core import geodesy
from stereodem.core.blocks import each_band
from stereodem.core.dem import DEM, ELLIPSOID, GEOID
from stereodem.core.errors import InputError
from stereodem.core.grid import MapGrid, OnGrid, as_crs
from stereodem.stereo.settings import GRIDDING_METHODS

__all__ = [
    "GridSpec",
    "CellSums",
    "SUM_LAYERS",
    "accumulate",
    "finish",
    "grid_points",
    "grid_bounds",
]


def grid_bounds(x, y, posting):
    """Bounds ``(xmin, ymin, xmax, ymax)`` of the points snapped outward to multiples of
    ``posting``."""
    x, y = np.asarray(x), np.asarray(y)
    return (
        np.floor(np.nanmin(x) / posting) * posting,
        np.floor(np.nanmin(y) / posting) * posting,
        np.ceil(np.nanmax(x) / posting) * posting,
        np.ceil(np.nanmax(y) / posting) * posting,
    )


def _density_sigma(fi, fj, rows, cols, posting):
    """Default gaussian width: ``max(posting / 2, mean point spacing)`` (CRS units)."""
    i, j = np.rint(fi).astype(np.int64), np.rint(fj).astype(np.int64)
    inside = (i >= 0) & (i < rows) & (j >= 0) & (j < cols)
    if not inside.any():
        return 0.5 * posting
    counts = np.bincount((i * cols + j)[inside])
    per_cell = inside.sum() / max(np.count_nonzero(counts), 1)
    return max(0.5 * posting, posting / np.sqrt(per_cell))


@dataclass(frozen=True)
class GridSpec(OnGrid):
    """The output lattice and the cell estimator, fixed before any point is gridded.

    Attributes
    ----------
    grid : MapGrid
        The lattice (north-up, square cells of ``posting`` CRS units).
    method : {"mean", "gaussian"}
    sigma : float, optional
        Gaussian width (CRS units); ``None``: the density rule of the module docstring,
        applied to each batch of points (each stereo tile).
    radius : int, optional
        Gaussian support half-width in cells; ``None``: ``ceil(2 sigma / posting)``, >= 1.
    geoid : bool
        Grid EGM96 geoid heights instead of ellipsoidal heights.
    """

    grid: MapGrid
    method: str = "gaussian"
    sigma: float | None = None
    radius: int | None = None
    geoid: bool = False

    @classmethod
    def from_bounds(cls, bounds, posting, crs, **options):
        """Lattice covering ``bounds`` (xmin, ymin, xmax, ymax; cell edges) at ``posting``."""
        if not posting or posting <= 0 or not np.isfinite(posting):
            raise InputError(f"grid posting must be positive, got {posting!r}")
        crs = as_crs(crs)
        method = options.get("method", "gaussian")
        if method not in GRIDDING_METHODS:
            raise InputError(
                f"unknown gridding method {method!r} ({' or '.join(GRIDDING_METHODS)})"
            )
        xmin, ymin, xmax, ymax = (float(b) for b in bounds)
        cols = max(1, int(round((xmax - xmin) / posting)))
        rows = max(1, int(round((ymax - ymin) / posting)))
        grid = MapGrid(Affine(posting, 0.0, xmin, 0.0, -posting, ymax), cols, rows, crs)
        return cls(grid, **options)


#: layers of :class:`CellSums` (weighted sums per cell)
SUM_LAYERS = ("weight", "height", "count", "score_weight", "score", "gap_weight", "gap")


@dataclass
class CellSums:
    """Weighted sums of a batch of points over a window of a :class:`GridSpec` lattice.

    ``sums[k]`` is layer ``SUM_LAYERS[k]`` on the window whose top-left cell is
    ``(row0, col0)`` of the lattice. Sums of several batches add (:meth:`add_to`), so a scene
    is gridded tile by tile with the same result as all points at once (up to the order of
    floating-point additions, which is fixed: tile order).
    """

    row0: int
    col0: int
    sums: np.ndarray
    n_points: int = 0

    def add_to(self, total: np.ndarray):
        """Add these sums into ``total`` (``(len(SUM_LAYERS), rows, cols)``, the whole lattice)."""
        _, h, w = self.sums.shape
        if h and w:
            total[:, self.row0 : self.row0 + h, self.col0 : self.col0 + w] += self.sums


def accumulate(spec: GridSpec, lon, lat, h, *, score=None, ray_gap=None, xy=None) -> CellSums:
    """Weighted sums of the points ``(lon, lat, h)`` (degrees, metres above the ellipsoid)
    on the smallest window of ``spec`` holding their support. Non-finite points are ignored.
    ``xy``: the points' coordinates in ``spec.crs`` if the caller already has them.
    """
    lon, lat, h = (np.asarray(a, np.float64).ravel() for a in (lon, lat, h))
    n = h.size
    score = np.full(n, np.nan) if score is None else np.asarray(score, np.float64).ravel()
    ray_gap = np.full(n, np.nan) if ray_gap is None else np.asarray(ray_gap, np.float64).ravel()
    ok = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h)
    lon, lat, h, score, ray_gap = lon[ok], lat[ok], h[ok], score[ok], ray_gap[ok]
    empty = CellSums(0, 0, np.zeros((len(SUM_LAYERS), 0, 0)))
    if h.size == 0:
        return empty
    if xy is None:
        x, y = geodesy.lonlat_to_crs(lon, lat, spec.crs)
    else:
        x, y = (np.asarray(v, np.float64).ravel()[ok] for v in xy)
    if spec.geoid:
        h = geodesy.ellipsoid_to_geoid(lon, lat, h)
    rows, cols = spec.shape
    posting = spec.posting
    # continuous cell coordinates, cell centres at integers
    fj = (np.asarray(x, float) - spec.transform.c) / posting - 0.5
    fi = (spec.transform.f - np.asarray(y, float)) / posting - 0.5
    if spec.method == "mean":
        offsets, sig, radius = [(0, 0)], None, 0
    else:
        sig = float(spec.sigma) if spec.sigma else _density_sigma(fi, fj, rows, cols, posting)
        radius = (
            spec.radius
            if spec.radius is not None
            else max(1, int(np.ceil(2.0 * sig / posting - 1e-9)))
        )
        offsets = [
            (di, dj) for di in range(-radius, radius + 1) for dj in range(-radius, radius + 1)
        ]
    i0, j0 = np.rint(fi).astype(np.int64), np.rint(fj).astype(np.int64)
    # the window: the points' cells plus the support, clipped to the lattice
    r0, r1 = max(int(i0.min()) - radius, 0), min(int(i0.max()) + radius + 1, rows)
    c0, c1 = max(int(j0.min()) - radius, 0), min(int(j0.max()) + radius + 1, cols)
    if r1 <= r0 or c1 <= c0:
        return empty
    wr, wc = r1 - r0, c1 - c0
    ncell = wr * wc
    sums = np.zeros((len(SUM_LAYERS), ncell))
    sok, gok = np.isfinite(score), np.isfinite(ray_gap)
    all_sok, all_gok = bool(sok.all()), bool(gok.all())
    score, ray_gap = np.where(sok, score, 0.0), np.where(gok, ray_gap, 0.0)
    base = (i0 - r0) * wc + (j0 - c0)  # cell index of each point in the window
    lo_i, hi_i, lo_j, hi_j = int(i0.min()), int(i0.max()), int(j0.min()), int(j0.max())
    if sig is not None:  # squared offsets along each axis, shared
        dsq_i = {di: ((i0 + di) - fi) ** 2 for di in range(-radius, radius + 1)}
        dsq_j = {dj: ((j0 + dj) - fj) ** 2 for dj in range(-radius, radius + 1)}
    for di, dj in offsets:  # a handful of neighbour offsets
        if r0 <= lo_i + di and hi_i + di < r1 and c0 <= lo_j + dj and hi_j + dj < c1:
            sel = slice(None)  # every point's cell is in the window
        else:
            i, j = i0 + di, j0 + dj
            sel = (i >= r0) & (i < r1) & (j >= c0) & (j < c1)
        if sig is None:
            w = np.ones(h.size if isinstance(sel, slice) else int(sel.sum()))
        else:
            # exp(-0.5 r2 / sig^2), r2 = (dsq_i + dsq_j) posting^2: the same operations in
            # the same order, in place
            w = dsq_i[di] + dsq_j[dj] if isinstance(sel, slice) else (dsq_i[di] + dsq_j[dj])[sel]
            w *= posting**2
            w *= -0.5
            w /= sig**2
            np.exp(w, out=w)
        idx = (base + (di * wc + dj))[sel]
        bw = np.bincount(idx, w, ncell)
        sums[0] += bw
        sums[1] += np.bincount(idx, w * h[sel], ncell)
        # a layer whose values are all finite has the weights of the height layer (w · 1)
        ws = w if all_sok else w * sok[sel]
        wg = w if all_gok else w * gok[sel]
        sums[3] += bw if all_sok else np.bincount(idx, ws, ncell)
        sums[4] += np.bincount(idx, ws * score[sel], ncell)
        sums[5] += bw if all_gok else np.bincount(idx, wg, ncell)
        sums[6] += np.bincount(idx, wg * ray_gap[sel], ncell)
    sums[2] = _support_counts(i0 - r0, j0 - c0, wr, wc, radius).ravel()
    n_points = int(((i0 >= 0) & (i0 < rows) & (j0 >= 0) & (j0 < cols)).sum())
    return CellSums(r0, c0, sums.reshape(len(SUM_LAYERS), wr, wc), n_points)


def _support_counts(i, j, rows, cols, radius):
    """Number of points whose ``(2 radius + 1)^2`` support covers each cell of a
    ``rows x cols`` window, from the points' cells ``(i, j)`` in the window (they may lie up
    to ``radius`` outside it): one count of the points per cell, then a box sum (cumulative
    sums; exact, the counts are integers)."""
    pad = radius
    keep = (i >= -pad) & (i < rows + pad) & (j >= -pad) & (j < cols + pad)
    hp, wp = rows + 2 * pad, cols + 2 * pad
    n = np.bincount((i[keep] + pad) * wp + (j[keep] + pad), minlength=hp * wp).reshape(hp, wp)
    c = np.zeros((hp + 1, wp + 1))
    c[1:, 1:] = n.cumsum(0).cumsum(1)
    k = 2 * radius + 1
    return c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]


def finish(spec: GridSpec, total: np.ndarray, *, crop: bool = False) -> DEM:
    """The DEM and its ``count``, ``score`` and ``ray_gap`` layers from the summed
    :class:`CellSums` of a whole lattice.

    ``crop`` trims the grid to the cells that received points (keeping the lattice). The
    layers are computed in row bands on the process's threads
    (:func:`stereodem.core.blocks.each_band`; cell by cell, so the same values).
    """
    t = total
    transform = spec.transform
    if crop:
        rows_ok = np.flatnonzero(t[0].any(axis=1))
        cols_ok = np.flatnonzero(t[0].any(axis=0))
        if rows_ok.size:
            t = t[:, rows_ok[0] : rows_ok[-1] + 1, cols_ok[0] : cols_ok[-1] + 1]
            transform = transform @ Affine.translation(int(cols_ok[0]), int(rows_ok[0]))
    shape = t.shape[1:]
    height, sc, gp = (np.empty(shape, np.float32) for _ in range(3))
    count = np.empty(shape, np.int32)

    def band(rows):  # layer = weighted sum / weight, for (out, sum layer, weight layer)
        r = slice(*rows)
        for out, num, den in ((height, 1, 0), (sc, 4, 3), (gp, 6, 5)):
            _mean(t[num, r], t[den, r], out[r])
        count[r] = t[2, r]

    each_band(band, shape[0])
    return DEM(
        height,
        transform,
        spec.crs,
        GEOID if spec.geoid else ELLIPSOID,
        count=count,
        score=sc,
        ray_gap=gp,
    )


def _mean(num, den, out):
    """``num / den`` (float64) as float32 into ``out`` where ``den > 0``, else NaN."""
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.divide(num, den)
    q[~(den > 0)] = np.nan
    out[...] = q


def grid_points(
    lon,
    lat,
    h,
    *,
    posting: float,
    crs=None,
    bounds=None,
    score=None,
    ray_gap=None,
    method: str = "mean",
    sigma: float | None = None,
    radius: int | None = None,
    geoid: bool = False,
) -> DEM:
    """Grid ground points into a DEM.

    Parameters
    ----------
    lon, lat, h : array_like (N,)
        Points: degrees and metres above the WGS84 ellipsoid. Non-finite points are ignored.
    posting : float
        Cell size in CRS units (metres for UTM).
    crs : CRS-like, optional
        Output CRS; default the UTM zone of the points (:func:`stereodem.core.geodesy.utm_crs`).
    bounds : (xmin, ymin, xmax, ymax), optional
        Grid extent in the CRS (cell edges); default the points' extent snapped to the posting.
    score, ray_gap : array_like (N,), optional
        Per-point correlation score and ray gap (m), averaged into their layers.
    method : {"mean", "gaussian"}
        Cell estimator (see the module docstring).
    sigma : float, optional
        Gaussian width in CRS units (default ``max(posting / 2, mean point spacing)``, see the
        module docstring).
    radius : int, optional
        Half-width of the gaussian support in cells (default ``ceil(2 sigma / posting)``, at
        least 1).
    geoid : bool
        Output EGM96 geoid heights instead of ellipsoidal heights.

    Returns
    -------
    DEM
        with ``count``, ``score`` and ``ray_gap`` layers.
    """
    lon, lat, h = (np.asarray(a, np.float64).ravel() for a in (lon, lat, h))
    ok = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h)
    if not posting or posting <= 0 or not np.isfinite(posting):
        raise InputError(f"grid posting must be positive, got {posting!r}")
    if crs is None:
        if not ok.any():
            raise InputError("no valid point to grid (and no CRS given to build an empty grid)")
        crs = geodesy.utm_crs(lon[ok], lat[ok])
    crs = as_crs(crs)
    x, y = np.full(lon.shape, np.nan), np.full(lon.shape, np.nan)
    if ok.any():
        x[ok], y[ok] = geodesy.lonlat_to_crs(lon[ok], lat[ok], crs)
    if bounds is None:
        if not ok.any():
            raise InputError("no valid point to grid and no bounds given")
        bounds = grid_bounds(x[ok], y[ok], posting)
    spec = GridSpec.from_bounds(
        bounds, posting, crs, method=method, sigma=sigma, radius=radius, geoid=geoid
    )
    cells = accumulate(spec, lon, lat, h, score=score, ray_gap=ray_gap, xy=(x, y))
    total = np.zeros((len(SUM_LAYERS),) + tuple(spec.shape))
    cells.add_to(total)
    return finish(spec, total)
