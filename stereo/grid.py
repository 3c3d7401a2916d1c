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

from dataclasses import dataclass, field

import numpy as np
from affine import Affine
from pyproj import CRS

from sensor import geodesy
from sensor.errors import CRSError, InputError
from sensor.raster import write_geotiff

__all__ = ["DEMGrid", "grid_points", "grid_bounds"]

_VERTICAL_TAG = "STEREODEM_VERTICAL"


@dataclass
class DEMGrid:
    """A gridded DEM and its companion layers.

    Attributes
    ----------
    height : ndarray (rows, cols) float32
        Heights, metres (``vertical`` reference), NaN where no point fell.
    count : ndarray int32
        Number of points per cell (with ``"gaussian"``, points within the radius).
    score : ndarray float32
        Mean correlation score of the cell's points (NaN if none).
    ray_gap : ndarray float32
        Mean ray gap of the cell's points, metres.
    transform : affine.Affine
        Pixel-corner transform to ``crs``.
    crs : pyproj.CRS
    vertical : {"ellipsoid", "geoid"}
    """

    height: np.ndarray
    count: np.ndarray
    score: np.ndarray
    ray_gap: np.ndarray
    transform: Affine
    crs: CRS
    vertical: str = "ellipsoid"
    info: dict = field(default_factory=dict)

    @property
    def posting(self) -> float:
        return float(self.transform.a)

    def cell_centres(self):
        """Map coordinates ``(x, y)`` of all cell centres, arrays of the grid's shape."""
        rows, cols = self.height.shape
        jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
        return self.transform @ (jj, ii)

    def write(self, directory, *, overwrite=False, names=None):
        """Write ``dem.tif``, ``count.tif``, ``score.tif`` and ``raygap.tif`` in ``directory``.

        Float layers are float32 with NaN nodata; ``count`` is int32 with nodata 0. Each
        file is written atomically. Returns the dict of written paths.
        """
        from pathlib import Path
        d = Path(directory)
        names = names or dict(dem="dem.tif", count="count.tif", score="score.tif", raygap="raygap.tif")
        tags = {_VERTICAL_TAG: self.vertical}
        out = {}
        out["dem"] = write_geotiff(d / names["dem"], self.height.astype(np.float32), self.transform,
                                   self.crs, np.nan, overwrite=overwrite, tags=tags)
        out["count"] = write_geotiff(d / names["count"], self.count.astype(np.int32), self.transform,
                                     self.crs, 0, overwrite=overwrite)
        out["score"] = write_geotiff(d / names["score"], self.score.astype(np.float32), self.transform,
                                     self.crs, np.nan, overwrite=overwrite)
        out["raygap"] = write_geotiff(d / names["raygap"], self.ray_gap.astype(np.float32),
                                      self.transform, self.crs, np.nan, overwrite=overwrite)
        return out


def grid_bounds(x, y, posting):
    """Bounds ``(xmin, ymin, xmax, ymax)`` of the points snapped outward to multiples of ``posting``."""
    x, y = np.asarray(x), np.asarray(y)
    return (np.floor(np.nanmin(x) / posting) * posting, np.floor(np.nanmin(y) / posting) * posting,
            np.ceil(np.nanmax(x) / posting) * posting, np.ceil(np.nanmax(y) / posting) * posting)


def _density_sigma(fi, fj, rows, cols, posting):
    """Default gaussian width: ``max(posting / 2, mean point spacing)`` (CRS units)."""
    i, j = np.rint(fi).astype(np.int64), np.rint(fj).astype(np.int64)
    inside = (i >= 0) & (i < rows) & (j >= 0) & (j < cols)
    if not inside.any():
        return 0.5 * posting
    counts = np.bincount((i * cols + j)[inside])
    per_cell = inside.sum() / max(np.count_nonzero(counts), 1)
    return max(0.5 * posting, posting / np.sqrt(per_cell))


def grid_points(lon, lat, h, *, posting: float, crs=None, bounds=None, score=None, ray_gap=None,
                method: str = "mean", sigma: float | None = None, radius: int | None = None,
                geoid: bool = False) -> DEMGrid:
    """Grid ground points into a DEM.

    Parameters
    ----------
    lon, lat, h : array_like (N,)
        Points: degrees and metres above the WGS84 ellipsoid. Non-finite points are ignored.
    posting : float
        Cell size in CRS units (metres for UTM).
    crs : CRS-like, optional
        Output CRS; default the UTM zone of the points (:func:`sensor.geodesy.utm_crs`).
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
    DEMGrid
    """
    lon, lat, h = (np.asarray(a, np.float64).ravel() for a in (lon, lat, h))
    n = h.size
    score = np.full(n, np.nan) if score is None else np.asarray(score, np.float64).ravel()
    ray_gap = np.full(n, np.nan) if ray_gap is None else np.asarray(ray_gap, np.float64).ravel()
    ok = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h)
    lon, lat, h, score, ray_gap = lon[ok], lat[ok], h[ok], score[ok], ray_gap[ok]
    if not posting or posting <= 0 or not np.isfinite(posting):
        raise InputError(f"grid posting must be positive, got {posting!r}")
    if crs is None:
        if lon.size == 0:
            raise InputError("no valid point to grid (and no CRS given to build an empty grid)")
        crs = geodesy.utm_crs(lon, lat)
    try:
        crs = CRS.from_user_input(crs)
    except Exception as exc:
        raise CRSError(f"unusable output CRS {crs!r}: {exc}") from None
    x, y = geodesy.lonlat_to_crs(lon, lat, crs)
    x, y = np.asarray(x, float), np.asarray(y, float)
    if geoid and h.size:
        h = geodesy.ellipsoid_to_geoid(lon, lat, h)
    if bounds is None:
        if x.size == 0:
            raise InputError("no valid point to grid and no bounds given")
        bounds = grid_bounds(x, y, posting)
    xmin, ymin, xmax, ymax = (float(b) for b in bounds)
    cols = max(1, int(round((xmax - xmin) / posting)))
    rows = max(1, int(round((ymax - ymin) / posting)))
    transform = Affine(posting, 0.0, xmin, 0.0, -posting, ymax)
    # continuous cell coordinates, cell centres at integers
    fj = (x - xmin) / posting - 0.5
    fi = (ymax - y) / posting - 0.5
    ncell = rows * cols
    if method == "mean":
        offsets = [(0, 0)]
        sig = None
    elif method == "gaussian":
        sig = float(sigma) if sigma else _density_sigma(fi, fj, rows, cols, posting)
        if radius is None:
            radius = max(1, int(np.ceil(2.0 * sig / posting - 1e-9)))
        offsets = [(di, dj) for di in range(-radius, radius + 1) for dj in range(-radius, radius + 1)]
    else:
        raise InputError(f"unknown gridding method {method!r} (mean or gaussian)")
    wsum = np.zeros(ncell)
    hsum = np.zeros(ncell)
    cnt = np.zeros(ncell)
    ssum, swt = np.zeros(ncell), np.zeros(ncell)
    gsum, gwt = np.zeros(ncell), np.zeros(ncell)
    i0, j0 = np.rint(fi).astype(np.int64), np.rint(fj).astype(np.int64)
    sok, gok = np.isfinite(score), np.isfinite(ray_gap)
    for di, dj in offsets:                      # a handful of neighbour offsets
        i, j = i0 + di, j0 + dj
        inside = (i >= 0) & (i < rows) & (j >= 0) & (j < cols)
        if sig is None:
            w = np.ones(inside.sum())
        else:
            r2 = ((i - fi) ** 2 + (j - fj) ** 2)[inside] * posting ** 2
            w = np.exp(-0.5 * r2 / sig ** 2)
        idx = (i * cols + j)[inside]
        wsum += np.bincount(idx, w, ncell)
        hsum += np.bincount(idx, w * h[inside], ncell)
        cnt += np.bincount(idx, minlength=ncell)
        s_in, g_in = sok[inside], gok[inside]
        ssum += np.bincount(idx[s_in], (w * score[inside])[s_in], ncell)
        swt += np.bincount(idx[s_in], w[s_in], ncell)
        gsum += np.bincount(idx[g_in], (w * ray_gap[inside])[g_in], ncell)
        gwt += np.bincount(idx[g_in], w[g_in], ncell)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = np.where(wsum > 0, hsum / wsum, np.nan)
        sc = np.where(swt > 0, ssum / swt, np.nan)
        gp = np.where(gwt > 0, gsum / gwt, np.nan)
    shape = (rows, cols)
    return DEMGrid(height.reshape(shape).astype(np.float32), cnt.reshape(shape).astype(np.int32),
                   sc.reshape(shape).astype(np.float32), gp.reshape(shape).astype(np.float32),
                   transform, crs, "geoid" if geoid else "ellipsoid",
                   info=dict(n_points=int(h.size), method=method))
