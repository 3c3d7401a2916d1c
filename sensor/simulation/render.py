"""Rendering an image through a sensor model over a DEM (used by the scene simulator).

Every image pixel is localised on the DEM by the DRM relief iteration (as
:meth:`stereodem.sensor.models.base.SensorModel.localize_dem`), and the ground radiance is read there. To keep
ASTER-sized scenes fast, the exact model is evaluated on a coarse grid of pixels at a few
heights, mapped into the map grid, and interpolated (bilinear in col/row, piecewise linear in
height); the relief iteration then runs on whole arrays in map coordinates with OpenCV
bilinear sampling of the DEM. :func:`localization_error` measures the error of that
approximation against the exact model; it is reported by the simulator, not assumed.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from stereodem.sensor.geo import geodesy
from stereodem.sensor.geo.grid import MapGrid, OnGrid
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
            # cv2.remap maps must be < 32767 on each side: lay long vectors out in rows
            n, width = mc.size, 1024 if mc.size > 32000 else 1
            pad = -n % width
            mc = np.pad(mc, (0, pad)).reshape(-1, width)
            mr = np.pad(mr, (0, pad)).reshape(-1, width)
            out = cv2.remap(self.data.astype(np.float32, copy=False), mc, mr, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=float(border))
            return out.ravel()[:n]
        out = cv2.remap(self.data.astype(np.float32, copy=False), mc, mr, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=float(border))
        return out.reshape(shape)


def nanmean_blocks(a, block_rows: int = 512) -> float:
    """``np.nanmean(a)`` of a 2-D array by row blocks (``np.nanmean`` copies the whole array)."""
    total, count = 0.0, 0
    for r0 in range(0, a.shape[0], block_rows):
        b = a[r0:r0 + block_rows]
        ok = np.isfinite(b)
        total += float(np.sum(b, where=ok, dtype=np.float64))
        count += int(ok.sum())
    return total / count if count else float("nan")


class GridLocalizer:
    """Approximate ``localize`` of a model on a coarse grid, in map coordinates.

    Parameters
    ----------
    model : SensorModel
    crs : map CRS of the output coordinates
    heights : sequence of float
        Ellipsoidal heights (m) at which the exact model is evaluated; the approximation is
        piecewise linear between them (rays are straight, so it is nearly exact).
    step : int
        Spacing of the coarse pixel grid.
    origin : (x0, y0)
        Map coordinates subtracted before storing as float32 (keeps mm precision).
    """

    def __init__(self, model: SensorModel, crs, heights, step=32, origin=(0.0, 0.0)):
        self.model, self.crs, self.step = model, crs, int(step)
        self.heights = np.asarray(sorted(heights), float)
        self.origin = origin
        w, h = model.width, model.height
        self.gc = np.arange(0, w - 1 + step, step, dtype=float)
        self.gr = np.arange(0, h - 1 + step, step, dtype=float)
        cc, rr = np.meshgrid(self.gc, self.gr)
        xs, ys = [], []
        for hk in self.heights:
            lon, lat = model.localize(cc, rr, np.full(cc.shape, hk))
            x, y = geodesy.lonlat_to_crs(lon, lat, crs)
            xs.append((np.asarray(x) - origin[0]).astype(np.float32))
            ys.append((np.asarray(y) - origin[1]).astype(np.float32))
        self.X, self.Y = np.stack(xs), np.stack(ys)

    def _bilinear(self, grids, col, row):
        mc = (col / self.step).astype(np.float32)
        mr = (row / self.step).astype(np.float32)
        return [cv2.remap(g, mc, mr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for g in grids]

    def layers(self, col, row):
        """Map x, y (relative to ``origin``) of pixels at every grid height: 2 arrays (K, ...)."""
        xs = np.stack(self._bilinear(list(self.X), col, row))
        ys = np.stack(self._bilinear(list(self.Y), col, row))
        return xs, ys

    def at_height(self, xs, ys, h):
        """Interpolate the per-height layers linearly to heights ``h`` (array like a layer)."""
        H = self.heights
        k = np.clip(np.searchsorted(H, h) - 1, 0, len(H) - 2)
        h0 = H[k]
        t = ((h - h0) / (H[k + 1] - h0)).astype(np.float32)
        x0 = np.take_along_axis(xs, k[None], 0)[0]
        x1 = np.take_along_axis(xs, (k + 1)[None], 0)[0]
        y0 = np.take_along_axis(ys, k[None], 0)[0]
        y1 = np.take_along_axis(ys, (k + 1)[None], 0)[0]
        return x0 + t * (x1 - x0), y0 + t * (y1 - y0)


def localize_on_dem_grid(loc: GridLocalizer, dem: MapRaster, col, row, *, threshold=0.01,
                         max_iterations=30, h0=None):
    """DRM relief iteration for pixels using a :class:`GridLocalizer`.

    ``dem`` must be on ``loc.crs`` with ellipsoidal heights; ``h0`` is the starting height
    (default the DEM mean). Each pixel iterates until its height changes by less than
    ``threshold`` (m); only the pixels still moving are carried into the next iteration.
    Returns map ``x, y`` (absolute), height ``h`` and a ``converged`` mask; NaN where the ray
    leaves the DEM.
    """
    xs, ys = loc.layers(col, row)
    shape = np.shape(col)
    k = xs.shape[0]
    xs, ys = xs.reshape(k, -1), ys.reshape(k, -1)
    ox, oy = loc.origin
    start = nanmean_blocks(dem.data) if h0 is None else float(h0)
    h = np.full(xs.shape[1], start, np.float32)
    converged = np.zeros(xs.shape[1], bool)
    active = np.arange(xs.shape[1])
    xa, ya, ha = xs, ys, h
    for _ in range(max_iterations):
        x, y = loc.at_height(xa, ya, ha)
        z = dem.sample(x.astype(np.float64) + ox, y.astype(np.float64) + oy)
        ok = np.isfinite(z)
        conv = ok & (np.abs(z - ha) < threshold)
        h[active] = np.where(ok, z, np.nan)
        converged[active[conv]] = True
        keep = ok & ~conv
        if not keep.any():
            break
        active, xa, ya, ha = active[keep], xa[:, keep], ya[:, keep], z[keep].astype(np.float32)
    x, y = loc.at_height(xs, ys, np.nan_to_num(h))
    # back to absolute float64 map coordinates (float32 would round UTM northings to 0.25 m)
    x = np.where(np.isfinite(h), x.astype(np.float64) + ox, np.nan)
    y = np.where(np.isfinite(h), y.astype(np.float64) + oy, np.nan)
    return x.reshape(shape), y.reshape(shape), h.reshape(shape), converged.reshape(shape)


def render(model: SensorModel, dem: MapRaster, radiance: MapRaster, *, step=32, block_rows=256,
           heights=None, keep_ground: bool = True):
    """Render the image seen by ``model``: radiance at each pixel's ground point on ``dem``.

    Returns ``(image float32, ground_x, ground_y, ground_h, localizer)``; pixels whose ray
    leaves the DEM are NaN. With ``keep_ground=False`` the three ground arrays (20 bytes per
    pixel) are not kept and come back as None: memory is then the image plus one block.
    """
    if heights is None:
        lo, hi = float(np.nanmin(dem.data)), float(np.nanmax(dem.data))
        heights = np.linspace(lo - 50.0, hi + 50.0, 4)
    t = dem.transform
    loc = GridLocalizer(model, dem.crs, heights, step=step, origin=(t.c, t.f))
    w, hgt = model.width, model.height
    img = np.empty((hgt, w), np.float32)
    gx = gy = gh = None
    if keep_ground:
        gx = np.empty((hgt, w), np.float64)
        gy = np.empty((hgt, w), np.float64)
        gh = np.empty((hgt, w), np.float32)
    cols = np.arange(w, dtype=np.float32)
    h0 = nanmean_blocks(dem.data)
    for r0 in range(0, hgt, block_rows):
        r1 = min(hgt, r0 + block_rows)
        cc, rr = np.meshgrid(cols, np.arange(r0, r1, dtype=np.float32))
        x, y, h, _ = localize_on_dem_grid(loc, dem, cc, rr, h0=h0)
        img[r0:r1] = radiance.sample(x, y)
        if keep_ground:
            gx[r0:r1], gy[r0:r1], gh[r0:r1] = x, y, h
    return img, gx, gy, gh, loc


def sampled_localization_error(model: SensorModel, loc: GridLocalizer, dem: MapRaster, n=2000,
                               seed=0, h0=None):
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
