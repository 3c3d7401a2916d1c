"""Gridding of 3-D points into a DEM raster, with count, score and ray-gap layers.

Points (lon, lat, h) are projected into a map CRS (the UTM zone of the points by default) and
accumulated into cells of a regular grid (weighted sums of every layer at once, as the
product of a sparse cells x points weight matrix with the points' values):

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
from scipy import sparse

from stereodem.core import geodesy, localfit
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


def _density_sigma(i, j, rows, cols, posting):
    """Default gaussian width: ``max(posting / 2, mean point spacing)`` (CRS units), from the
    points' cells ``(i, j)`` (integers; those outside the ``rows x cols`` lattice ignored)."""
    inside = (i >= 0) & (i < rows) & (j >= 0) & (j < cols)
    if not inside.any():
        return 0.5 * posting
    i, j = i[inside], j[inside]
    i0, j0 = int(i.min()), int(j.min())
    counts = np.bincount((i - i0) * (int(j.max()) - j0 + 1) + (j - j0))
    per_cell = i.size / max(np.count_nonzero(counts), 1)
    return max(0.5 * posting, posting / np.sqrt(per_cell))


#: the narrowest and the widest Gaussian of the cell estimator, in postings
MIN_SIGMA_POSTINGS, MAX_SIGMA_POSTINGS = 0.1, 10


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
        sigma = options.get("sigma")
        lo, hi = MIN_SIGMA_POSTINGS * posting, MAX_SIGMA_POSTINGS * posting
        if sigma is not None and not lo <= sigma <= hi:
            # the support is 2 sigma each side: 1e6 m at a 30 m posting was a window of
            # 133333^2 cells per tile, every tile failed; 1e-300 m a ZeroDivisionError in each
            # tile (and below a tenth of a cell the weights underflow to 0)
            raise InputError(
                f"the gridding's gaussian_sigma must be {MIN_SIGMA_POSTINGS:g} to "
                f"{MAX_SIGMA_POSTINGS:g} postings ({lo:g} to {hi:g} CRS units at a posting of "
                f"{posting:g}), got {sigma}"
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
        tol = geodesy.metres_in_crs(localfit.TILE_TOLERANCE_M, spec.crs)
        x, y = geodesy.lonlat_to_crs(lon, lat, spec.crs, tolerance=tol)
    else:
        x, y = (np.asarray(v, np.float64).ravel()[ok] for v in xy)
    if spec.geoid:
        h = geodesy.ellipsoid_to_geoid(lon, lat, h)
    rows, cols = spec.shape
    posting = spec.posting
    # continuous cell coordinates, cell centres at integers
    fj = (np.asarray(x, float) - spec.transform.c) / posting - 0.5
    fi = (spec.transform.f - np.asarray(y, float)) / posting - 0.5
    i0, j0 = np.rint(fi).astype(np.int64), np.rint(fj).astype(np.int64)
    if spec.method == "mean":
        sig, radius = None, 0
    else:
        sig = float(spec.sigma) if spec.sigma else _density_sigma(i0, j0, rows, cols, posting)
        radius = (
            spec.radius
            if spec.radius is not None
            else max(1, int(np.ceil(2.0 * sig / posting - 1e-9)))
        )
    n_points = int(((i0 >= 0) & (i0 < rows) & (j0 >= 0) & (j0 < cols)).sum())
    # the points whose support reaches the lattice
    near = (i0 >= -radius) & (i0 < rows + radius) & (j0 >= -radius) & (j0 < cols + radius)
    if not near.all():
        i0, j0, fi, fj = i0[near], j0[near], fi[near], fj[near]
        h, score, ray_gap = h[near], score[near], ray_gap[near]
    if h.size == 0:
        return empty
    # the padded window: the points' cells plus the support, which may reach up to
    # ``radius`` cells beyond the lattice; cropped to the lattice at the end
    pr0, pc0 = int(i0.min()) - radius, int(j0.min()) - radius
    shape = (int(i0.max()) + radius + 1 - pr0, int(j0.max()) + radius + 1 - pc0)
    # the value layers: a layer whose values are all finite has the weights of the height
    # layer (w · 1), so its weight column is the first one
    sok, gok = np.isfinite(score), np.isfinite(ray_gap)
    columns, layer_of = [np.ones(h.size), h], {0: 0, 1: 1}
    for layer, (fin, v) in zip((3, 5), ((sok, score), (gok, ray_gap))):
        if fin.all():
            layer_of[layer] = 0
        else:
            layer_of[layer] = len(columns)
            columns.append(fin.astype(np.float64))
        layer_of[layer + 1] = len(columns)
        columns.append(v if layer_of[layer] == 0 else np.where(fin, v, 0.0))
    k = 0.0 if sig is None else 0.5 * posting**2 / sig**2  # per cell^2
    spread = _gaussian_spread(
        i0 - pr0, j0 - pc0, fi - i0, fj - j0, np.stack(columns, 1), k, radius, shape
    )
    r0, r1 = max(pr0, 0), min(pr0 + shape[0], rows)
    c0, c1 = max(pc0, 0), min(pc0 + shape[1], cols)
    spread = spread.reshape(shape + (len(columns),))[r0 - pr0 : r1 - pr0, c0 - pc0 : c1 - pc0]
    wr, wc = r1 - r0, c1 - c0
    sums = np.empty((len(SUM_LAYERS), wr, wc))
    for layer, col in layer_of.items():
        sums[layer] = spread[:, :, col]
    sums[2] = _support_counts(i0 - r0, j0 - c0, wr, wc, radius)
    return CellSums(r0, c0, sums, n_points)


#: points per block of :func:`_gaussian_spread` (its sparse matrix stays a few MB)
SPREAD_BLOCK = 32768


def _gaussian_spread(i, j, u, v, values, k, radius, shape):
    """Sums over the points of ``exp(-k ((di - u)^2 + (dj - v)^2)) · values`` into the cells
    ``(i + di, j + dj)``, ``|di|, |dj| <= radius``, of a window of ``shape`` cells.

    ``(i, j)``: each point's cell in the window (its support lies inside the window);
    ``(u, v)``: the point's offset from that cell's centre (cells, in [-0.5, 0.5]); ``values``
    (n, L): the layers to sum; ``k``: the Gaussian's ``1 / (2 sigma^2)`` in cells^-2 (0: a
    plain sum, weight 1). Returns (rows · cols, L).

    The weight is separable (one factor per row offset, one per column offset). The points'
    weights form a sparse matrix (cells x points, ``(2 radius + 1)^2`` entries per point)
    whose product with ``values`` gives every layer in one pass; it is built for blocks of
    :data:`SPREAD_BLOCK` points over the rows of cells each block reaches. The sums are in a
    fixed order (blocks, then points), so they do not depend on the machine.
    """
    n, nv = values.shape
    rows, cols = shape
    m = 2 * radius + 1
    off = np.arange(-radius, radius + 1, dtype=np.float64)
    dtype = np.int32 if rows * cols < 2**31 else np.int64
    cell_off = (
        (np.arange(-radius, radius + 1)[:, None] * cols + np.arange(-radius, radius + 1))
        .astype(dtype)
        .ravel()
    )
    out = np.zeros((rows * cols, nv))
    block = min(n, SPREAD_BLOCK)
    weights, idx = np.empty((block, m, m)), np.empty((block, m * m), dtype)
    outer = np.empty((m, m, block))
    ptr = np.arange(0, block * m * m + 1, m * m, dtype=dtype)
    for s in range(0, n, SPREAD_BLOCK):
        b = slice(s, min(s + SPREAD_BLOCK, n))
        ib, jb = i[b], j[b]
        nb = ib.size
        lo, hi = int(ib.min()) - radius, int(ib.max()) + radius + 1  # the block's rows of cells
        w = weights[:nb]
        if k:
            # offset-major (m, nb) factors and their outer product along the points (numpy's
            # loops run over the points, not over m), then point-major for the matrix: the
            # same products wi[a] * wj[c] of each point, 4x faster than broadcasting (nb, m)
            wi = np.subtract(off[:, None], u[None, b])
            wj = np.subtract(off[:, None], v[None, b])
            for f in (wi, wj):
                np.square(f, out=f)
                f *= -k
                np.exp(f, out=f)
            prod = np.multiply(wi[:, None, :], wj[None, :, :], out=outer[:, :, :nb])
            w.reshape(nb, m * m)[...] = prod.reshape(m * m, nb).T
        else:
            w.fill(1.0)
        cell = ((ib - lo) * cols + jb).astype(dtype)
        if cell.min() + cell_off[0] < 0 or cell.max() + cell_off[-1] >= (hi - lo) * cols:
            # scipy does not check the indices of a matrix built from its arrays
            raise RuntimeError("gridding: a point's support leaves its window")
        ix = idx[:nb]
        for t in range(m * m):  # per offset: long contiguous loops, not (nb, m^2) broadcasting
            np.add(cell, cell_off[t], out=ix[:, t])
        mat = sparse.csc_matrix(
            (w.ravel(), ix.ravel(), ptr[: ib.size + 1]), shape=((hi - lo) * cols, ib.size)
        )
        out[lo * cols : hi * cols] += mat @ values[b]
    return out


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
