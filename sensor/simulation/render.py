"""Rendering an image through a sensor model over a DEM (used by the scene simulator).

Every image pixel is localised on the DEM by the DRM relief iteration (as
:meth:`stereodem.sensor.models.base.SensorModel.localize_dem`), and the ground radiance is read
there. To keep ASTER-sized scenes fast, the exact model is evaluated on a coarse grid of pixels at
three heights and stored as the map-grid pixel coordinates of each ray, quadratic in height
(:class:`GridLocalizer`); the relief iteration then runs on float32 arrays in the DEM's pixel
coordinates with OpenCV bilinear sampling, block by block, each pixel starting from the height
of its coarse-grid neighbours. :func:`sampled_localization_error` measures the error of that
approximation against the exact model; it is reported by the simulator, not assumed.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from stereodem.core import geodesy
from stereodem.core.grid import MapGrid, OnGrid
from stereodem.sensor.models.base import SensorModel


@dataclass
class MapRaster(OnGrid):
    """A float32 raster (``data``, rows x cols) on a :class:`MapGrid`."""

    data: np.ndarray
    grid: MapGrid

    def sample(self, x, y, border=np.nan):
        """Bilinear values at map coordinates (float64 arrays; converted to float32 pixel maps)."""
        t = self.transform
        mc = ((np.asarray(x) - t.c) / t.a - 0.5).astype(np.float32)
        mr = ((np.asarray(y) - t.f) / t.e - 0.5).astype(np.float32)
        shape = mc.shape
        if mc.ndim == 1:
            return _remap_flat(self.data.astype(np.float32, copy=False), mc, mr, border=border)
        out = cv2.remap(
            self.data.astype(np.float32, copy=False),
            mc,
            mr,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float(border),
        )
        return out.reshape(shape)


def nanmean_blocks(a, block_rows: int = 512) -> float:
    """``np.nanmean(a)`` of a 2-D array by row blocks (``np.nanmean`` copies the whole array)."""
    total, count = 0.0, 0
    for r0 in range(0, a.shape[0], block_rows):
        b = a[r0 : r0 + block_rows]
        ok = np.isfinite(b)
        total += float(np.sum(b, where=ok, dtype=np.float64))
        count += int(ok.sum())
    return total / count if count else float("nan")


def _remap_flat(image, mc, mr, interpolation=cv2.INTER_LINEAR, border=np.nan):
    """``cv2.remap`` of ``image`` at flat float32 pixel coordinates (any length: laid out in
    rows of 1024, as remap maps must be < 32767 on each side)."""
    n = mc.size
    width = 1024 if n > 1024 else max(n, 1)
    pad = -n % width
    mc = np.pad(mc.ravel(), (0, pad)).reshape(-1, width)
    mr = np.pad(mr.ravel(), (0, pad)).reshape(-1, width)
    out = cv2.remap(
        image, mc, mr, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=float(border)
    )
    return out.ravel()[:n]


class GridLocalizer:
    """Approximate ``localize`` of a model: fractional pixel coordinates of a map grid as a
    quadratic in height, tabulated on a coarse grid of image pixels.

    The exact model is evaluated at the nodes of a coarse pixel grid (every ``step`` pixels)
    at three heights spanning ``heights``; per node and per map axis the quadratic through the
    three points is stored as float32 coefficients of ``u = (h - h_mid) / h_half``. Anywhere
    else the coefficients are interpolated bilinearly (``cv2.remap``, exact float arithmetic)
    between nodes. A ray is straight in ECEF; in map coordinates it bends by the Earth's
    curvature and the projection only (decimetres over kilometres of height), which the
    quadratic absorbs; the total error is measured by :func:`sampled_localization_error`
    (about 1e-3 pixel for ASTER at ``step=16``), not assumed.

    Parameters
    ----------
    model : SensorModel
    grid : MapGrid
        The map grid whose fractional (col, row) the localizer returns (cell centres at
        integers); normally the rendering DEM's.
    heights : sequence of float
        Ellipsoidal heights (m); their minimum and maximum bound the tabulated range
        (extrapolation beyond is quadratic).
    step : int
        Spacing (pixels) of the coarse pixel grid.
    """

    def __init__(self, model: SensorModel, grid: MapGrid, heights, step=16):
        self.model, self.grid, self.step = model, grid, int(step)
        self.crs = grid.crs
        lo, hi = float(np.min(heights)), float(np.max(heights))
        if not hi > lo:
            hi = lo + 1.0
        self.h_mid, self.h_half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        w, h = model.width, model.height
        self.gc = np.arange(0, w - 1 + step, step, dtype=float)
        self.gr = np.arange(0, h - 1 + step, step, dtype=float)
        cc, rr = np.meshgrid(self.gc, self.gr)
        pts = []
        for hk in (lo, self.h_mid, hi):  # u = -1, 0, 1
            lon, lat = model.localize(cc, rr, np.full(cc.shape, hk))
            x, y = geodesy.lonlat_to_crs(lon, lat, grid.crs)
            pts.append(grid.colrow(np.asarray(x), np.asarray(y)))
        coef = []
        for axis in (0, 1):
            pm, p0, pp = (p[axis] for p in pts)
            coef += [p0, 0.5 * (pp - pm), 0.5 * (pp + pm) - p0]
        self.coef = np.stack(coef).astype(np.float32)  # (6, len(gr), len(gc))

    def coefficients(self, col, row):
        """The six coefficient arrays (col c0, c1, c2, row c0, c1, c2) at image pixels."""
        col = np.asarray(col, np.float32)
        row = np.asarray(row, np.float32)
        mc, mr = col / np.float32(self.step), row / np.float32(self.step)
        if mc.ndim == 2 and max(mc.shape) < 32767:
            return np.stack(
                [
                    cv2.remap(g, mc, mr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                    for g in self.coef
                ]
            )
        out = np.stack([_remap_flat(g, mc, mr, border=np.nan) for g in self.coef])
        return out.reshape((6,) + mc.shape)

    def pixels_at(self, coef, h):
        """Map-grid fractional ``(col, row)`` (float32) of pixels with coefficients ``coef``
        (from :meth:`coefficients`) at ellipsoidal heights ``h``."""
        u = np.asarray(h, np.float32) - np.float32(self.h_mid)
        u *= np.float32(1.0 / self.h_half)
        out = []
        for k in (0, 3):  # c0 + u (c1 + u c2), in place
            p = np.multiply(u, coef[k + 2])
            p += coef[k + 1]
            p *= u
            p += coef[k]
            out.append(p)
        return out[0], out[1]


def _iterate_heights(loc: GridLocalizer, dem: MapRaster, coef, h_start, threshold, max_iterations):
    """Relief iteration: ``coef`` (6, ...) and ``h_start`` (...) float32; the results are flat.

    Solves ``DEM(ray(h)) = h`` per pixel. The first step is the DRM step ``h <- DEM(ray(h))``;
    after that a secant step on ``f(h) = DEM(ray(h)) - h`` (one step is exact inside a DEM cell,
    where the bilinear surface along the ray is nearly linear), kept only where the secant
    slope says the DRM step would contract (``-10 < f' < -0.1``), else the DRM step. A pixel
    stops when ``|f| < threshold`` (m); only the pixels still moving are carried into the next
    iteration. Returns ``(h, converged)``: ``h`` is the DEM height at the last ray point
    (within ``threshold`` of the ray's height), NaN where the ray leaves the DEM.
    """
    data = dem.data.astype(np.float32, copy=False)
    same_grid = dem.grid == loc.grid

    def dem_at(c, h_now):
        pc, pr = loc.pixels_at(c, h_now)
        if not same_grid:
            pc, pr = (a.astype(np.float32) for a in dem.grid.colrow(*loc.grid.xy(pc, pr)))
        if pc.ndim == 2 and max(pc.shape) < 32767:
            return cv2.remap(
                data, pc, pr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
            )
        return _remap_flat(data, pc, pr)  # NaN off the DEM or in its voids

    # first step on the arrays as given (2-D blocks need no re-layout), then flat
    h0 = np.asarray(h_start, np.float32)
    z = dem_at(coef, h0).ravel()
    coef = coef.reshape(6, -1)
    h = z.copy()
    f = z - h0.ravel()
    converged = np.abs(f) < threshold
    active = np.flatnonzero(np.abs(f) >= threshold)  # finite and still moving
    ca, hp, fp, ha = coef[:, active], h0.ravel()[active], f[active], z[active]
    for _ in range(max_iterations - 1):
        if active.size == 0:
            break
        z = dem_at(ca, ha)
        f = z - ha
        h[active] = z
        af = np.abs(f)
        converged[active[af < threshold]] = True
        keep = np.flatnonzero(af >= threshold)
        active, ca, z, f, hk = active[keep], ca[:, keep], z[keep], f[keep], ha[keep]
        with np.errstate(divide="ignore", invalid="ignore"):
            slope = (f - fp[keep]) / (hk - hp[keep])
            secant = hk - f / slope
        ha = np.where((slope < -0.1) & (slope > -10.0), secant, z)
        hp, fp = hk, f
    return h, converged


def localize_on_dem_grid(
    loc: GridLocalizer, dem: MapRaster, col, row, *, threshold=0.01, max_iterations=30, h0=None
):
    """DRM relief iteration for pixels using a :class:`GridLocalizer`.

    ``dem`` must be on ``loc.crs`` with ellipsoidal heights; ``h0`` is the starting height,
    a scalar or an array like ``col`` (default the DEM mean). Returns map ``x, y``
    (absolute, float64), height ``h`` and a ``converged`` mask; NaN where the ray leaves the
    DEM.
    """
    shape = np.shape(col)
    coef = loc.coefficients(col, row).reshape(6, -1)
    start = nanmean_blocks(dem.data) if h0 is None else h0
    h_start = np.broadcast_to(np.asarray(start, np.float32), shape).ravel()
    h, converged = _iterate_heights(loc, dem, coef, h_start, threshold, max_iterations)
    pc, pr = loc.pixels_at(coef, np.nan_to_num(h))
    x, y = loc.grid.xy(pc, pr)
    bad = ~np.isfinite(h)
    x[bad] = np.nan
    y[bad] = np.nan
    return x.reshape(shape), y.reshape(shape), h.reshape(shape), converged.reshape(shape)


def _coarse_start_heights(loc: GridLocalizer, dem: MapRaster, h0: float):
    """Heights of the coarse-grid nodes on the DEM (exact iteration), NaN filled with ``h0``:
    bilinearly interpolated, they start each pixel's iteration near its answer."""
    cc, rr = np.meshgrid(loc.gc.astype(np.float32), loc.gr.astype(np.float32))
    h, _ = _iterate_heights(loc, dem, loc.coef, np.full(cc.shape, h0, np.float32), 0.01, 30)
    return np.nan_to_num(h.reshape(cc.shape), nan=h0).astype(np.float32)


def render(
    model: SensorModel,
    dem: MapRaster,
    radiance: MapRaster,
    *,
    step=16,
    block_rows=256,
    heights=None,
    keep_ground: bool = True,
    h0=None,
):
    """Render the image seen by ``model``: radiance at each pixel's ground point on ``dem``.

    Every pixel is localised on the DEM by the DRM relief iteration through a
    :class:`GridLocalizer` (started from the heights of the nearby coarse-grid nodes), and
    the radiance is sampled bilinearly there; the work is done in blocks of ``block_rows``
    image rows with float32 arrays. Returns ``(image float32, ground_x, ground_y, ground_h,
    localizer)``; pixels whose ray leaves the DEM are NaN. With ``keep_ground=False`` the three
    ground arrays (20 bytes per pixel) are not kept and come back as None: memory is then the
    image plus one block. ``heights`` (min, max) bounds the tabulated height range (default
    the DEM's range +- 50 m); ``h0`` is the height used where no start height is known
    (default the DEM's mean).
    """
    h0 = nanmean_blocks(dem.data) if h0 is None else float(h0)
    if heights is None:
        lo, hi = float(np.nanmin(dem.data)), float(np.nanmax(dem.data))
        heights = (lo - 50.0, hi + 50.0)
    loc = GridLocalizer(model, dem.grid, heights, step=step)
    coarse_h = _coarse_start_heights(loc, dem, h0)
    w, hgt = model.width, model.height
    img = np.empty((hgt, w), np.float32)
    gx = gy = gh = None
    if keep_ground:
        gx = np.empty((hgt, w), np.float64)
        gy = np.empty((hgt, w), np.float64)
        gh = np.empty((hgt, w), np.float32)
    cols = np.arange(w, dtype=np.float32)
    rad = radiance.data.astype(np.float32, copy=False)
    same_grid = radiance.grid == loc.grid
    for r0 in range(0, hgt, block_rows):
        r1 = min(hgt, r0 + block_rows)
        cc, rr = np.meshgrid(cols, np.arange(r0, r1, dtype=np.float32))
        coef = loc.coefficients(cc, rr)
        start = cv2.remap(
            coarse_h,
            cc / np.float32(step),
            rr / np.float32(step),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        h, _ = _iterate_heights(loc, dem, coef, start, 0.01, 30)
        h = h.reshape(cc.shape)
        pc, pr = loc.pixels_at(coef, np.nan_to_num(h))
        if not same_grid:
            pc, pr = (a.astype(np.float32) for a in radiance.grid.colrow(*loc.grid.xy(pc, pr)))
        block = cv2.remap(
            rad, pc, pr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
        )
        block[~np.isfinite(h)] = np.nan
        img[r0:r1] = block
        if keep_ground:
            x, y = loc.grid.xy(pc, pr) if same_grid else radiance.grid.xy(pc, pr)
            x[~np.isfinite(h)] = np.nan
            y[~np.isfinite(h)] = np.nan
            gx[r0:r1], gy[r0:r1], gh[r0:r1] = x, y, h
    return img, gx, gy, gh, loc


def sampled_localization_error(
    model: SensorModel, loc: GridLocalizer, dem: MapRaster, n=2000, seed=0, h0=None
):
    """:func:`localization_error` on ``n`` random pixels localised again with ``loc`` (for
    renders made with ``keep_ground=False``)."""
    rng = np.random.default_rng(seed)
    r = rng.integers(0, model.height, n).astype(np.float32)
    c = rng.integers(0, model.width, n).astype(np.float32)
    x, y, h, _ = (a[0] for a in localize_on_dem_grid(loc, dem, c[None], r[None], h0=h0))
    ok = np.isfinite(h)
    if not ok.any():
        return float("nan")
    lon, lat = geodesy.crs_to_lonlat(x[ok], y[ok], loc.crs)
    pc, pr = model.project(lon, lat, h[ok].astype(float))
    return float(np.max(np.hypot(pc - c[ok], pr - r[ok])))


def localization_error(model: SensorModel, gx, gy, gh, crs, n=2000, seed=0):
    """Max distance (pixels) between rendered ground points and the exact model.

    Projects ``n`` random rendered ground points (map x, y, h) back into the image with the
    exact ``model.project`` and compares with the pixel they were rendered for.
    """
    rng = np.random.default_rng(seed)
    hgt, w = gh.shape
    r = rng.integers(0, hgt, n)
    c = rng.integers(0, w, n)
    ok = np.isfinite(gh[r, c])
    r, c = r[ok], c[ok]
    lon, lat = geodesy.crs_to_lonlat(gx[r, c], gy[r, c], crs)
    pc, pr = model.project(lon, lat, gh[r, c].astype(float))
    return float(np.max(np.hypot(pc - c, pr - r))) if r.size else float("nan")
