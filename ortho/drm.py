"""Differential rectification (DRM) orthoimages by backward projection on a map grid.

For every cell of a north-up map grid the ground point (map x, y and the DEM's ellipsoidal
height there) is projected into the image by the exact sensor model, and the image is
resampled there (Ok 2005 §6: "build the orthoimage by backward projection"; Bettemir 2006
§4.1 gives the per-pixel forward variant, :mod:`stereodem.ortho.forward`).

Speed comes from evaluating ``model.project`` only on a coarse lattice of ground points
(every ``step`` cells) at a few heights spanning the DEM range, and interpolating: bilinearly
in map x, y and by a polynomial in height (Chebyshev nodes). The interpolation error is
*measured* against the exact model on a check set (lattice mid-cells at random heights) and
the step and number of height nodes are refined until it is below ``tolerance`` pixels
(default 0.01 px); the measured figure is returned with the orthoimage.

The per-cell maps are evaluated in float32 (separable lattice interpolation, float32 DEM
bilinear sampling, Horner in height; ~2e-4 px rounding for images of a few thousand pixels) and
row blocks can run on several threads (``threads``): numpy and OpenCV release the GIL.

Resampling is :func:`cv2.remap` (bilinear, bicubic, Lanczos-4 or nearest) on row blocks; an output
cell is nodata when the kernel touches an image nodata pixel or leaves the image, when the DEM has
no height there, or when it falls outside the image footprint.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
from affine import Affine

from stereodem.core import geodesy
from stereodem.core.dem import DEM, ELLIPSOID, as_dem
from stereodem.core.errors import DEMCoverageError, InputError, SensorModelError
from stereodem.core.grid import MapGrid, OnGrid
from stereodem.core.raster import write_geotiff
from stereodem.sensor.models.base import SensorModel
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.models.rpc_direct import check_validity

from .grid import grid_for_model

log = logging.getLogger(__name__)

RESAMPLING = {
    "nearest": cv2.INTER_NEAREST,
    "bilinear": cv2.INTER_LINEAR,
    "cubic": cv2.INTER_CUBIC,
    "lanczos": cv2.INTER_LANCZOS4,
}
# kernel support (size, anchor) of each interpolation, for the nodata test
_SUPPORT = {"nearest": (1, 0), "bilinear": (2, 0), "cubic": (4, 1), "lanczos": (8, 3)}


# --------------------------------------------------------------------------- DEM on the grid


def crop_dem(dem: DEM, grid: MapGrid, *, margin: int = 3, fill: DEM | None = None) -> DEM:
    """The part of ``dem`` under ``grid`` (plus ``margin`` DEM cells), heights ellipsoidal.

    With ``fill`` (a second DEM), the window covers the whole grid even where ``dem`` does
    not, and cells without a height in ``dem`` (holes, or outside it) take ``fill``'s
    ellipsoidal height there (bilinear). Raises :class:`DEMCoverageError` naming the DEM and
    the grid extent when they do not overlap (and no ``fill`` is given).
    """
    gc = np.linspace(-0.5, grid.width - 0.5, 33)
    gr = np.linspace(-0.5, grid.height - 0.5, 33)
    cc, rr = np.meshgrid(gc, gr)
    lon, lat = grid.lonlat(cc, rr)
    x, y = geodesy.lonlat_to_crs(lon, lat, dem.crs)
    c, r = ~dem.transform @ (np.asarray(x), np.asarray(y))
    rows, cols = dem.shape
    c0, c1 = int(np.floor(np.nanmin(c))) - margin, int(np.ceil(np.nanmax(c))) + margin
    r0, r1 = int(np.floor(np.nanmin(r))) - margin, int(np.ceil(np.nanmax(r))) + margin
    if fill is not None:
        return _crop_filled(dem, fill, c0, r0, c1, r1)
    c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, cols), min(r1, rows)
    if c1 - c0 < 2 or r1 - r0 < 2 or not np.isfinite(dem.heights[r0:r1, c0:c1]).any():
        raise DEMCoverageError(
            f"{dem.path or 'DEM'}: the DEM does not cover the orthoimage area lon "
            f"{np.nanmin(lon):.5f}..{np.nanmax(lon):.5f}, lat "
            f"{np.nanmin(lat):.5f}..{np.nanmax(lat):.5f} (DEM extent lon/lat "
            f"{tuple(round(v, 5) for v in dem.bounds_lonlat())})"
        )
    sub = DEM(
        dem.heights[r0:r1, c0:c1].copy(),
        dem.transform @ Affine.translation(c0, r0),
        dem.crs,
        dem.vertical,
        dem.path,
    )
    return sub.to_reference(ELLIPSOID)


def _crop_filled(dem: DEM, fill: DEM, c0, r0, c1, r1) -> DEM:
    """Window [r0:r1, c0:c1] of ``dem``'s grid (may exceed it), ellipsoidal heights, its
    missing cells filled from ``fill``; ``info["filled_cells"]`` counts them."""
    rows, cols = dem.shape
    h = np.full((r1 - r0, c1 - c0), np.nan, np.float32)
    a0, b0, a1, b1 = max(c0, 0), max(r0, 0), min(c1, cols), min(r1, rows)
    if a1 > a0 and b1 > b0:
        h[b0 - r0 : b1 - r0, a0 - c0 : a1 - c0] = dem.heights[b0:b1, a0:a1]
    transform = dem.transform @ Affine.translation(c0, r0)
    rr, cc = np.nonzero(~np.isfinite(h))
    if np.isfinite(h).any():
        h = (
            DEM(h, transform, dem.crs, dem.vertical, dem.path)
            .to_reference(ELLIPSOID)
            .heights.copy()
        )
    if rr.size:
        x, y = transform @ (cc + 0.5, rr + 0.5)
        lon, lat = geodesy.crs_to_lonlat(np.asarray(x), np.asarray(y), dem.crs)
        h[rr, cc] = fill.sample(lon, lat, reference=ELLIPSOID)
    if not np.isfinite(h).any():
        raise DEMCoverageError(
            f"{dem.path or 'DEM'} and {fill.path or 'fill DEM'}: neither covers the orthoimage area"
        )
    out = DEM(h, transform, dem.crs, ELLIPSOID, dem.path)
    out.filled_cells = int(rr.size - np.count_nonzero(~np.isfinite(h[rr, cc])))
    return out


def _check_rpc_heights(model, dem: DEM):
    """An RPC (possibly image-corrected) evaluated on DEM heights outside its validity range
    extrapolates its polynomials: raise a one-line :class:`RPCError` instead (a DEM in feet,
    or the wrong DEM)."""
    inner = model
    while not isinstance(inner, RPCModel) and hasattr(inner, "model"):
        inner = inner.model
    if not isinstance(inner, RPCModel):
        return
    # the DEM under the image's footprint (localised at the middle of the validity range)
    lon, lat = inner.footprint(float(np.mean(inner.height_bounds())))
    c_lon, c_lat = inner.center_lonlat(float(np.mean(inner.height_bounds())))
    lon, lat = np.append(np.asarray(lon, float), c_lon), np.append(np.asarray(lat, float), c_lat)
    h = np.asarray(dem.sample(lon, lat), float)
    ok = np.isfinite(h)
    if ok.any():
        check_validity(inner, lon[ok], lat[ok], h[ok])


#: positions within this fraction of a post of a post line are taken on it (a float32 map's
#: round-off is ~1e-5 post for grids of a few thousand posts): :func:`bilinear_nan`
POST_SNAP = 1e-3


def _snapped(f, n):
    """Fractional offsets within :data:`POST_SNAP` of 0 or 1 set to 0 or 1 (clipped to them
    at the array's edges, which the inside test extends by the same amount)."""
    f = np.where(np.abs(f) < POST_SNAP, 0, f)
    f = np.where(np.abs(f - 1) < POST_SNAP, 1, f)
    return np.clip(f, 0, 1).astype(f.dtype, copy=False) if n > 1 else np.zeros_like(f)


def bilinear_nan(array, c, r, *, dtype=np.float64):
    """Bilinear interpolation of ``array`` at fractional (col, row), centres at integers.

    Result in ``dtype`` (float64 by default; float32 for the ortho's per-cell maps); NaN
    outside ``[0, n-1]`` or when a neighbour with a weight is NaN (voids are never filled).
    The one rule of where a DEM has a height: a position within :data:`POST_SNAP` of a post
    line is on it, and a neighbour of no weight does not count, so a map cell on a valid
    post beside a void has its height (the float32 lattice put it 1e-5 post off, and the
    void's weight of 1e-5 made it NaN: a ring of nodata around every hole).
    """
    rows, cols = array.shape
    c, r = np.asarray(c), np.asarray(r)
    inside = (c >= -POST_SNAP) & (r >= -POST_SNAP)
    inside &= (c <= cols - 1 + POST_SNAP) & (r <= rows - 1 + POST_SNAP)
    itype = np.int32 if rows * cols < 2**31 - cols - 2 else np.intp  # int32: faster gathers
    c0 = np.clip(np.where(inside, c, 0).astype(itype), 0, max(cols - 2, 0))
    r0 = np.clip(np.where(inside, r, 0).astype(itype), 0, max(rows - 2, 0))
    fc = _snapped(np.subtract(c, c0, dtype=dtype), cols)
    fr = _snapped(np.subtract(r, r0, dtype=dtype), rows)
    idx = r0 * itype(cols) + c0
    flat = np.asarray(array).ravel()
    z00, z01, z10, z11 = (
        flat.take(i, mode="clip").astype(dtype, copy=False)
        for i in (idx, idx + 1, idx + cols, idx + cols + 1)
    )
    # a neighbour of no weight takes its partner's value (a NaN there must not count)
    for a, b, w in ((z01, z00, fc), (z11, z10, fc)):
        np.copyto(a, b, where=w == 0)
    for a, b, w in ((z00, z01, fc), (z10, z11, fc)):
        np.copyto(a, b, where=w == 1)
    z01 -= z00
    z01 *= fc
    z01 += z00  # top edge
    z11 -= z10
    z11 *= fc
    z11 += z10  # bottom edge
    np.copyto(z11, z01, where=fr == 0)
    np.copyto(z01, z11, where=fr == 1)
    z11 -= z01
    z11 *= fr
    z11 += z01
    z11[~inside] = np.nan
    return z11


# --------------------------------------------------------------------------- backward map


def _cheb_nodes(lo, hi, k):
    j = np.arange(k)
    return 0.5 * (lo + hi) - 0.5 * (hi - lo) * np.cos((2 * j + 1) * np.pi / (2 * k))


@dataclass
class BackwardMap:
    """Ground -> image map of a grid, interpolated from a coarse lattice of exact projections.

    Lattice node ``(j, i)`` sits at grid cell ``(row, col) = (j * step, i * step)``. At each
    node the image coordinates are a polynomial of degree ``n_heights - 1`` in the normalised
    height ``t = (h - h_mid) / h_half``; coefficients are interpolated bilinearly between nodes.

    Attributes
    ----------
    grid : MapGrid
    step : int
        Lattice spacing, grid cells.
    h_nodes : ndarray
        Ellipsoidal heights (m) where the model was evaluated.
    coef_col, coef_row : ndarray (n_heights, ny, nx)
        Monomial coefficients in ``t`` at the nodes (pixels).
    dem_col, dem_row : ndarray (ny, nx)
        Fractional DEM pixel coordinates (centres at integers) of the nodes (for height lookup).
    error_px : float
        Largest measured |interpolated - exact| image displacement on the check set, pixels.
    error_dem_px : float
        Largest measured DEM-position interpolation error on the check set, DEM pixels.
    n_model_points : int
        Number of exact ``model.project`` evaluations used (lattice and checks).
    """

    grid: MapGrid
    step: int
    h_nodes: np.ndarray
    h_mid: float
    h_half: float
    coef_col: np.ndarray
    coef_row: np.ndarray
    dem: DEM | None = None
    dem_col: np.ndarray | None = None
    dem_row: np.ndarray | None = None
    error_px: float = float("nan")
    error_dem_px: float = float("nan")
    n_model_points: int = 0
    history: list = field(default_factory=list)
    _planes: tuple | None = field(default=None, repr=False)

    @property
    def n_heights(self):
        return len(self.h_nodes)

    # -- bilinear lattice interpolation at fractional grid coordinates (u = col, v = row)
    def _weights(self, u, v):
        ny, nx = self.coef_col.shape[1:]
        fu, fv = np.asarray(u, float) / self.step, np.asarray(v, float) / self.step
        i = np.clip(np.floor(fu), 0, nx - 2).astype(np.intp)
        j = np.clip(np.floor(fv), 0, ny - 2).astype(np.intp)
        return i, j, fu - i, fv - j

    @staticmethod
    def _lerp2(a, i, j, t, s):
        return (1 - s) * ((1 - t) * a[..., j, i] + t * a[..., j, i + 1]) + s * (
            (1 - t) * a[..., j + 1, i] + t * a[..., j + 1, i + 1]
        )

    def _horner(self, coefs, h):
        tn = (np.asarray(h, float) - self.h_mid) / self.h_half
        out = coefs[-1]
        for k in range(coefs.shape[0] - 2, -1, -1):
            out = out * tn + coefs[k]
        return out

    def image_coords_grid(self, u, v, h):
        """Image ``(col, row)`` of ground points at fractional grid coordinates ``u, v``
        (cell centres at integers) and ellipsoidal heights ``h`` (m)."""
        u, v, h = np.broadcast_arrays(
            np.asarray(u, float), np.asarray(v, float), np.asarray(h, float)
        )
        i, j, t, s = self._weights(u, v)
        cc = self._lerp2(self.coef_col, i, j, t, s)
        rc = self._lerp2(self.coef_row, i, j, t, s)
        return self._horner(cc, h), self._horner(rc, h)

    def image_coords(self, x, y, h):
        """Image ``(col, row)`` of ground points at map ``x, y`` (grid CRS) and height ``h``."""
        u, v = self.grid.colrow(x, y)
        return self.image_coords_grid(u, v, h)

    def dem_coords_grid(self, u, v):
        """Fractional DEM pixel (col, row) at grid coordinates (interpolated from the lattice)."""
        i, j, t, s = self._weights(u, v)
        return self._lerp2(self.dem_col, i, j, t, s), self._lerp2(self.dem_row, i, j, t, s)

    def heights_grid(self, u, v):
        """Ellipsoidal DEM height (m) at grid coordinates, NaN off the DEM or on voids."""
        dc, dr = self.dem_coords_grid(u, v)
        return bilinear_nan(self.dem.heights, dc, dr)

    def _x_weights(self, nx):
        """Lattice column index and weight of every grid column (bilinear in x)."""
        f = np.arange(self.grid.width, dtype=float) / self.step
        i = np.clip(np.floor(f), 0, nx - 2).astype(np.intp)
        return i, f - i

    def _y_weights(self, row0, row1, ny):
        f = np.arange(row0, row1, dtype=float) / self.step
        j = np.clip(np.floor(f), 0, ny - 2).astype(np.intp)
        return j, f - j

    def interpolate_planes(self, planes, row0: int, row1: int):
        """Bilinear interpolation of lattice planes ``(P, ny, nx)`` to grid rows ``row0:row1``
        (all columns), separable: lattice rows first interpolated along x, then along y.
        Float64; returns ``(P, row1 - row0, width)``."""
        planes = np.asarray(planes, float)
        ny, nx = planes.shape[1:]
        j, s = self._y_weights(row0, row1, ny)
        lo, hi = int(j.min()), int(j.max()) + 2
        i, t = self._x_weights(nx)
        sub = planes[:, lo:hi]
        ax = sub[:, :, i] * (1 - t) + sub[:, :, i + 1] * t  # (P, nsub, W)
        a0 = ax[:, j - lo]
        return a0 + s[None, :, None] * (ax[:, j + 1 - lo] - a0)

    def _rows_x(self):
        """Every lattice row interpolated along x to all grid columns (float32, cached):
        ``(A, D)`` with ``A[:, j]`` the values on lattice row ``j`` and ``D[:, j]`` the
        difference to row ``j + 1``; planes are DEM col, DEM row, col and row coefficients."""
        if self._planes is None:
            planes = np.concatenate(
                [self.dem_col[None], self.dem_row[None], self.coef_col, self.coef_row]
            )
            nx = planes.shape[2]
            i, t = self._x_weights(nx)
            ax = planes[:, :, i] * (1 - t) + planes[:, :, i + 1] * t  # float64 (P, ny, W)
            d = np.diff(ax, axis=1)
            self._planes = (ax[:, :-1].astype(np.float32), d.astype(np.float32))
        return self._planes

    def lattice_lonlat(self):
        """Longitude/latitude (deg) of the lattice nodes, arrays (ny, nx)."""
        uu, vv = _lattice(self.grid, self.step)
        U, V = np.meshgrid(uu.astype(float), vv.astype(float))
        return self.grid.lonlat(U, V)

    def block(self, row0: int, row1: int, *, dem_coords: bool = False):
        """``(col, row, h)`` float32 arrays (rows ``row0:row1`` x all grid columns) of the grid
        block: DEM height by bilinear interpolation (NaN off the DEM), image position by the
        interpolated map at that height (at ``h_mid`` where there is no height). With
        ``dem_coords`` also the fractional DEM pixel ``(dem_col, dem_row)`` of every cell.

        Float32 throughout (values rounded to ~2e-4 px for images up to 4096 px; the test
        suite measures the stored maps against the exact model).
        """
        A, D = self._rows_x()
        j, s = self._y_weights(row0, row1, A.shape[1] + 1)
        s = s.astype(np.float32)[:, None]
        k = self.n_heights

        bands = np.flatnonzero(np.diff(j)) + 1
        bands = list(zip(np.r_[0, bands], np.r_[bands, j.size]))

        def plane(p):
            # one (B, W) float32 plane; rows of one lattice band share their two lattice rows
            out = np.empty((j.size, A.shape[2]), np.float32)
            for b0, b1 in bands:
                np.multiply(s[b0:b1], D[p, j[b0]], out=out[b0:b1])
                out[b0:b1] += A[p, j[b0]]
            return out

        dc, dr = plane(0), plane(1)
        h = bilinear_nan(self.dem.heights, dc, dr, dtype=np.float32)
        tn = np.where(np.isfinite(h), h, np.float32(self.h_mid))
        tn -= np.float32(self.h_mid)
        tn *= np.float32(1.0 / self.h_half)

        def horner(first):
            out = plane(first + k - 1)
            for m in range(k - 2, -1, -1):
                out *= tn
                out += plane(first + m)
            return out

        if dem_coords:
            return horner(2), horner(2 + k), h, dc, dr
        return horner(2), horner(2 + k), h


def _lattice(grid: MapGrid, step: int):
    nx = int(np.ceil((grid.width - 1) / step)) + 1
    ny = int(np.ceil((grid.height - 1) / step)) + 1
    return np.arange(max(nx, 2)) * step, np.arange(max(ny, 2)) * step


def _project_lattice(model, grid, step, h_nodes, dem):
    uu, vv = _lattice(grid, step)
    U, V = np.meshgrid(uu.astype(float), vv.astype(float))
    lon, lat = grid.lonlat(U, V)
    cols, rows = model.project(lon[None], lat[None], np.asarray(h_nodes, float)[:, None, None])
    dx, dy = geodesy.lonlat_to_crs(lon, lat, dem.crs)
    dc, dr = ~dem.transform @ (np.asarray(dx), np.asarray(dy))
    return (
        np.asarray(cols, float),
        np.asarray(rows, float),
        np.asarray(dc) - 0.5,
        np.asarray(dr) - 0.5,
    )


def build_backward_map(
    model,
    grid: MapGrid,
    dem: DEM,
    *,
    tolerance: float = 0.01,
    h_range=None,
    step: int | None = None,
    n_heights: int = 2,
    n_check: int = 4000,
    seed: int = 0,
) -> BackwardMap:
    """Build the interpolated ground -> image map of ``grid`` for ``model`` over ``dem``.

    Parameters
    ----------
    dem : DEM
        Ellipsoidal DEM (e.g. from :func:`crop_dem`).
    tolerance : float
        Bound on the measured interpolation error, image pixels.
    h_range : (float, float), optional
        Ellipsoidal heights to cover; default the DEM's valid range (plus 2 %).
    step : int, optional
        Initial lattice spacing in grid cells (default 64, halved until the bound holds).
    n_heights : int
        Initial number of height nodes (raised until the bound holds, at most 8).

    Returns
    -------
    BackwardMap with ``error_px`` the measured maximum error (pixels).
    """
    if dem.vertical != ELLIPSOID:
        dem = dem.to_reference(ELLIPSOID)
    if h_range is None:
        h_range = (float(np.nanmin(dem.heights)), float(np.nanmax(dem.heights)))
    lo, hi = float(h_range[0]), float(h_range[1])
    pad = max(1.0, 0.02 * (hi - lo))
    lo, hi = lo - pad, hi + pad
    h_mid, h_half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    rng = np.random.default_rng(seed)
    step = int(
        step or min(64, max(1, 2 ** int(np.ceil(np.log2(max(grid.width, grid.height) / 2)))))
    )
    k = int(n_heights)
    n_eval = 0
    history = []
    while True:
        h_nodes = _cheb_nodes(lo, hi, k)
        C, R, DC, DR = _project_lattice(model, grid, step, h_nodes, dem)
        n_eval += C.size
        tn = (h_nodes - h_mid) / h_half
        vinv = np.linalg.inv(np.vander(tn, k, increasing=True))  # node values -> monomials
        coef_c = np.einsum("mk,kyx->myx", vinv, C)
        coef_r = np.einsum("mk,kyx->myx", vinv, R)
        bm = BackwardMap(grid, step, h_nodes, h_mid, h_half, coef_c, coef_r, dem, DC, DR)
        # ---- check set: lattice mid-cells (worst case of bilinear) at random heights,
        # plus random positions
        ny, nx = DC.shape
        m = min(n_check, (ny - 1) * (nx - 1))
        cell = rng.choice((ny - 1) * (nx - 1), size=m, replace=False)
        u = (cell % (nx - 1) + 0.5) * step
        v = (cell // (nx - 1) + 0.5) * step
        u = np.concatenate([u, rng.uniform(0, grid.width - 1, m)])
        v = np.concatenate([v, rng.uniform(0, grid.height - 1, m)])
        hc = rng.uniform(lo, hi, u.size)
        lon, lat = grid.lonlat(u, v)
        ce, re = model.project(lon, lat, hc)
        n_eval += u.size
        ci, ri = bm.image_coords_grid(u, v, hc)
        err = np.hypot(ci - ce, ri - re)
        ok = np.isfinite(ce) & np.isfinite(re)
        if not ok.any():
            raise SensorModelError(
                f"{type(model).__name__}: the model gives no image position on the grid"
            )
        e_tot = float(np.nanmax(err[ok])) if np.isfinite(err[ok]).all() else float("inf")
        # split the error: at node heights only the x,y interpolation acts
        kk = rng.integers(0, k, u.size)
        ci2, ri2 = bm.image_coords_grid(u, v, h_nodes[kk])
        ce2, re2 = model.project(lon, lat, h_nodes[kk])
        n_eval += u.size
        e_xy = float(np.nanmax(np.hypot(ci2 - ce2, ri2 - re2)[ok]))
        dx, dy = geodesy.lonlat_to_crs(lon, lat, dem.crs)
        dce, dre = ~dem.transform @ (np.asarray(dx), np.asarray(dy))
        dci, dri = bm.dem_coords_grid(u, v)
        e_dem = float(np.max(np.hypot(dci - (dce - 0.5), dri - (dre - 0.5))))
        history.append(
            dict(step=step, n_heights=k, error_px=e_tot, error_xy_px=e_xy, error_dem_px=e_dem)
        )
        log.debug(
            "backward map: step %d, %d heights: error %.2e px (xy %.2e)", step, k, e_tot, e_xy
        )
        if e_tot <= tolerance and e_dem <= 1e-3:
            break
        refined = False
        if (e_xy > 0.5 * tolerance or e_dem > 1e-3) and step > 1:
            step, refined = step // 2, True
        if e_tot - e_xy > 0.5 * tolerance and k < 8:
            k, refined = k + 1, True
        if not refined:
            if k < 8:
                k += 1
            elif step > 1:
                step //= 2
            else:
                break
    if e_tot > tolerance:
        log.warning(
            "backward map: interpolation error %.3g px exceeds the %.3g px tolerance",
            e_tot,
            tolerance,
        )
    bm.error_px, bm.error_dem_px, bm.n_model_points, bm.history = e_tot, e_dem, n_eval, history
    return bm


# --------------------------------------------------------------------------- resampling


def _as_image(image, image_nodata):
    if isinstance(image, (str, os.PathLike)):
        raise InputError(
            f"orthorectify: image must be an array; {image} is a path: read it first "
            "(stereodem.read_image)"
        )
    a = np.asarray(image)
    if a.ndim != 2:
        raise InputError(f"orthorectify: expected a 2-D image, got shape {a.shape}")
    valid = np.ones(a.shape, dtype=bool)
    if isinstance(image, np.ma.MaskedArray):
        valid &= ~np.ma.getmaskarray(image)
        a = image.filled(0)
    img = a.astype(np.float32)
    if image_nodata is not None and not (
        isinstance(image_nodata, float) and np.isnan(image_nodata)
    ):
        valid &= a != image_nodata
    valid &= np.isfinite(img)
    img[~valid] = 0.0
    return img, valid


def _support_ok(valid, resampling):
    """Cells whose whole resampling kernel lies on valid pixels, indexed at floor/round."""
    size, anchor = _SUPPORT[resampling]
    v = valid.astype(np.uint8)
    if size == 1:
        return v
    return cv2.erode(
        v,
        np.ones((size, size), np.uint8),
        anchor=(anchor, anchor),
        borderType=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def remap_nan(img, ok, col, row, resampling, nodata=np.nan):
    """Resample ``img`` at (col, row) maps with :func:`cv2.remap`.

    Nodata where the kernel touches an invalid pixel (``ok``: validity eroded by the kernel
    support, indexed at the kernel's anchor pixel) or leaves the image. Images wider or taller
    than OpenCV's 32767 px limit are cropped to the block's window.
    """
    H, W = img.shape
    inside = (col >= 0) & (row >= 0) & (col <= W - 1) & (row <= H - 1)  # False on NaN
    shift = 0.5 if resampling == "nearest" else 0.0
    ic = np.where(inside, col + shift, 0).astype(np.intp)
    ir = np.where(inside, row + shift, 0).astype(np.intp)
    np.minimum(ic, W - 1, out=ic)
    np.minimum(ir, H - 1, out=ir)
    good = inside & (ok.ravel().take(ir * W + ic, mode="clip") > 0)
    out = np.full(col.shape, nodata, dtype=np.float32)
    if not good.any():
        return out
    c0 = r0 = 0
    src = img
    if W > 32000 or H > 32000:
        m = 3
        c0, c1 = max(int(ic[good].min()) - m, 0), min(int(ic[good].max()) + m + 1, W)
        r0, r1 = max(int(ir[good].min()) - m, 0), min(int(ir[good].max()) + m + 1, H)
        if c1 - c0 > 32000 or r1 - r0 > 32000:
            raise InputError(
                "orthorectify: a block spans more than 32000 image pixels; use smaller blocks"
            )
        src = np.ascontiguousarray(img[r0:r1, c0:c1])
    mx = (col - c0).astype(np.float32)
    my = (row - r0).astype(np.float32)
    res = cv2.remap(
        src, mx, my, RESAMPLING[resampling], borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    np.copyto(out, res, where=good)
    return out


# --------------------------------------------------------------------------- orthoimage


@dataclass
class Ortho(OnGrid):
    """An orthoimage on a map grid.

    Attributes
    ----------
    data : ndarray (rows, cols) float32
        Resampled image values, ``nodata`` where invalid.
    grid : MapGrid
        Output grid (``transform``, ``crs`` are shortcuts).
    valid : ndarray bool
        Cells with a value.
    nodata : float
    heights : ndarray float32
        Ellipsoidal DEM heights used per cell (m), NaN off the DEM or on voids.
    interpolation_error_px : float
        Measured maximum error (pixels) of the interpolated ground -> image map against the
        exact model on the check set (see :func:`build_backward_map`).
    backward_map : BackwardMap
    dem_missing : dict
        ``n_cells`` inside the image footprint but outside the DEM, and their lon/lat bounds;
        ``n_footprint`` cells under the image footprint, ``n_no_height`` of them without a
        height (holes or outside), their ``footprint_share`` (:func:`dem_gaps`' rule), and
        ``filled_cells`` taken from ``fill_dem``.
    col, row : ndarray float32, optional
        Image coordinates per cell (``keep_maps=True``).
    """

    data: np.ndarray
    grid: MapGrid
    valid: np.ndarray
    nodata: float
    heights: np.ndarray
    interpolation_error_px: float
    backward_map: BackwardMap
    resampling: str
    dem_missing: dict
    col: np.ndarray | None = None
    row: np.ndarray | None = None

    def report(self) -> dict:
        """Figures for logs and reports (plain types)."""
        bm = self.backward_map
        return dict(
            width=self.grid.width,
            height=self.grid.height,
            **self.grid.res_report(),  # res, res_unit (res_m only on a metre grid)
            crs=self.grid.crs.to_string(),
            resampling=self.resampling,
            valid_fraction=float(self.valid.mean()),
            interpolation_error_px=self.interpolation_error_px,
            dem_interpolation_error_px=bm.error_dem_px,
            lattice_step=bm.step,
            n_heights=bm.n_heights,
            n_model_points=bm.n_model_points,
            dem_missing_cells=self.dem_missing["n_cells"],
            dem_no_height_share=self.dem_missing.get("footprint_share", 0.0),
        )

    def write(self, path, *, overwrite=False, tags=None, dtype=None, creation_options=None):
        """Write as a Cloud-Optimised GeoTIFF (rasterio), nodata set, the report as tags.

        Parameters
        ----------
        dtype : numpy dtype, optional
            Data type of the file; pass the input image's (``image.dtype``) to keep it. Integer
            types get the resampled values rounded and clipped to the type's range, and as
            nodata the first of 0, the type's maximum, its minimum that no valid cell takes
            (an internal mask when every one is taken). Default float32 (``nodata`` as is).
        creation_options : dict or list of "KEY=VALUE", optional
            GDAL COG creation options (:func:`stereodem.core.raster.write_geotiff`).
        """
        t = {f"STEREODEM_{k.upper()}": v for k, v in self.report().items()}
        t.update(tags or {})
        data, nodata, mask = self.data, self.nodata, None
        dt = np.dtype(dtype) if dtype is not None else np.dtype(np.float32)
        if np.issubdtype(dt, np.integer):
            info = np.iinfo(dt)
            vals = np.clip(np.rint(np.where(self.valid, self.data, 0)), info.min, info.max).astype(
                dt
            )
            taken = vals[self.valid]
            nodata = next((v for v in (0, info.max, info.min) if not (taken == v).any()), None)
            if nodata is None:
                mask = self.valid
            else:
                vals[~self.valid] = nodata
            data = vals
        elif dt != self.data.dtype:
            data = self.data.astype(dt)
        return write_geotiff(
            path,
            data,
            self.grid.transform,
            self.grid.crs,
            nodata,
            overwrite=overwrite,
            tags=t,
            mask=mask,
            descriptions=f"orthoimage ({self.resampling} resampling)",
            overview_resampling="average",
            creation_options=creation_options,
        )


def _progressing(results, progress, total):
    for r1, miss in results:
        if progress is not None:
            progress(r1, total)
        yield r1, miss


# ----------------------------------------------------------------- DEM gaps under the footprint
# One rule for "no DEM height under X % of the image footprint", which ortho and uncertainty
# (and the pipeline) report: of the map-grid cells whose image position (at their DEM height,
# at the middle height where there is none) lies in the image, the share without a DEM height
# (DEM voids, or outside the DEM). Counted exactly, cell by cell, on the product's grid.


def _in_footprint(col, row, model) -> np.ndarray:
    """Whether each cell's image position (:meth:`BackwardMap.block`'s ``col, row``: at the
    middle height where there is no DEM height) lies in the image."""
    return (col >= -0.5) & (row >= -0.5) & (col <= model.width - 0.5) & (row <= model.height - 0.5)


def _footprint_counts(foot, no_height) -> tuple[int, int]:
    """(footprint cells, footprint cells without a DEM height) of one block, from its
    footprint mask (:func:`_in_footprint`) and its cells without a height."""
    return int(np.count_nonzero(foot)), int(np.count_nonzero(foot & no_height))


def _no_height_share(n_no_height: int, n_footprint: int) -> float:
    return float(n_no_height) / max(int(n_footprint), 1)


def dem_gaps(model, dem, grid: MapGrid, *, fill_dem=None, tolerance: float = 0.01) -> dict:
    """Cells of ``grid`` under the image footprint without a height in ``dem`` (voids, or
    outside it; ``fill_dem`` fills them as :func:`orthorectify` does): ``n_footprint``,
    ``n_no_height`` and their ``footprint_share``, the figures :func:`orthorectify` reports
    (``Ortho.dem_missing``) for the same model, DEM and grid, without resampling an image
    (the uncertainty maps' warning uses it)."""
    dem = as_dem(dem)
    fill = as_dem(fill_dem) if fill_dem is not None else None
    bm = build_backward_map(model, grid, crop_dem(dem, grid, fill=fill), tolerance=tolerance)
    H, W = grid.shape
    rows = max(16, min(H, 262_144 // max(W, 1)))
    n_foot = n_no = 0
    for r0 in range(0, H, rows):
        col, row, h = bm.block(r0, min(H, r0 + rows))
        a, b = _footprint_counts(_in_footprint(col, row, model), ~np.isfinite(h))
        n_foot, n_no = n_foot + a, n_no + b
    return dict(
        n_footprint=n_foot, n_no_height=n_no, footprint_share=_no_height_share(n_no, n_foot)
    )


def no_height_message(dem_name, missing: dict, consequence: str, image: str | None = None) -> str:
    """The warning for ``missing`` (:func:`dem_gaps` or ``Ortho.dem_missing``) that every
    command gives: ``"<dem>: no DEM height under 5.1% of the image footprint (N map cell(s):
    holes or outside the DEM): <consequence>"``; ``image``: which image, where a job has
    several (``"of the left image's footprint"``)."""
    whose = f"the {image} image's" if image else "the image"
    return (
        f"{dem_name or 'DEM'}: no DEM height under {100 * missing['footprint_share']:.1f}% of "
        f"{whose} footprint ({missing['n_no_height']} map cell(s): holes or outside the DEM): "
        f"{consequence}"
    )


def orthorectify(
    image,
    model,
    dem,
    *,
    grid: MapGrid | None = None,
    res: float | None = None,
    crs=None,
    resampling: str = "bilinear",
    nodata: float = np.nan,
    image_nodata=None,
    tolerance: float = 0.01,
    block_rows: int | None = None,
    keep_maps: bool = False,
    strict_dem: bool = False,
    progress=None,
    threads: int = 1,
    fill_dem=None,
    image_name: str | None = None,
) -> Ortho:
    """Orthorectify an image by backward DRM projection onto a north-up map grid.

    Parameters
    ----------
    image : ndarray (rows, cols) or masked array
        The image of ``model`` (``model.height`` x ``model.width``).
    model : stereodem.sensor.models.base.SensorModel
    dem : stereodem.core.dem.DEM or path
        Terrain heights (geoid DEMs are converted to ellipsoidal heights).
    grid : MapGrid, optional
        Output grid (for example, shared by both images of a stereo pair). Default:
        :func:`stereodem.ortho.grid.grid_for_model` with ``res`` and ``crs``.
    res : float, optional
        Posting, metres (default the image GSD).
    crs : CRS-like, optional
        Map CRS (default the UTM zone of the image centre).
    resampling : {"bilinear", "cubic", "nearest"}
    nodata : float
        Output value of cells without data (default NaN).
    image_nodata : number, optional
        Input value marking invalid image pixels (NaN is always invalid).
    tolerance : float
        Bound on the ground -> image interpolation error, pixels (measured, reported).
    block_rows : int, optional
        Output rows per block (memory is bounded by the block); default about 4 M cells.
    keep_maps : bool
        Keep the per-cell image coordinates (``Ortho.col``, ``Ortho.row``).
    strict_dem : bool
        Raise :class:`DEMCoverageError` when part of the image footprint is outside the DEM.
    image_name : str, optional
        What the warnings call the image where a job orthorectifies several (``"left"``).
    progress : callable, optional
        Called as ``progress(rows_done, rows_total)`` after each block (from the calling
        thread, in row order).
    threads : int or concurrent.futures.Executor
        Row blocks processed concurrently by this many threads (numpy and OpenCV release the
        GIL), or submitted to this thread pool (one pool shared by several orthoimages keeps
        every thread busy until the last block of any of them); the result does not depend
        on it.
    fill_dem : DEM or path, optional
        Fallback heights where ``dem`` has none (holes, or outside it).

    Cells of the image footprint without a DEM height are nodata; their number and share of
    the footprint's cells are logged as a warning and returned in ``Ortho.dem_missing``
    (``n_no_height``, ``n_footprint``, ``footprint_share``; :func:`dem_gaps` gives the same
    figures without an image).

    Returns
    -------
    Ortho
    """
    if resampling not in RESAMPLING:
        raise InputError(f"resampling must be one of {sorted(RESAMPLING)}, got {resampling!r}")
    if not isinstance(model, SensorModel):
        raise InputError(
            f"orthorectify: model must be a sensor model (stereodem.load_model), got "
            f"{type(model).__name__}"
        )
    dem = as_dem(dem)
    _check_rpc_heights(model, dem)
    img, valid = _as_image(image, image_nodata)
    if img.shape != (model.height, model.width):
        raise InputError(
            f"orthorectify: image shape {img.shape} differs from its model's "
            f"{(model.height, model.width)} (rows, cols)"
        )
    if grid is None:
        grid = grid_for_model(model, dem, res=res, crs=crs)
    fill = as_dem(fill_dem) if fill_dem is not None else None
    dem_e = crop_dem(dem, grid, fill=fill)
    bm = build_backward_map(model, grid, dem_e, tolerance=tolerance)
    ok = _support_ok(valid, resampling)
    H, W = grid.shape
    block_rows = int(block_rows or max(16, min(H, 262_144 // max(W, 1))))
    data = np.full((H, W), nodata, dtype=np.float32)
    heights = np.empty((H, W), dtype=np.float32)
    cols_map = np.empty((H, W), np.float32) if keep_maps else None
    rows_map = np.empty((H, W), np.float32) if keep_maps else None
    dr_rows, dr_cols = dem_e.shape

    def run_block(r0):
        r1 = min(H, r0 + block_rows)
        col, row, h, dcol, drow = bm.block(r0, r1, dem_coords=True)
        heights[r0:r1] = h
        nohgt = ~np.isfinite(h)
        miss = None
        # footprint cells, and those without a DEM height (the one rule: _footprint_counts)
        foot = _in_footprint(col, row, model)
        counts = _footprint_counts(foot, nohgt)
        if nohgt.any():
            infoot = foot[nohgt]
            dcc, drr = dcol[nohgt][infoot], drow[nohgt][infoot]
            outside = (dcc < 0) | (drr < 0) | (dcc > dr_cols - 1) | (drr > dr_rows - 1)
            if outside.any():
                uu, vv = np.nonzero(nohgt)
                uu, vv = uu[infoot][outside], vv[infoot][outside]
                lon, lat = grid.lonlat(vv, uu + r0)
                miss = (int(outside.sum()), [np.min(lon), np.min(lat)], [np.max(lon), np.max(lat)])
            col[nohgt] = np.nan
            row[nohgt] = np.nan
        del dcol, drow
        data[r0:r1] = remap_nan(img, ok, col, row, resampling, nodata)
        if keep_maps:
            cols_map[r0:r1], rows_map[r0:r1] = col, row
        return r1, (miss, counts)

    starts = range(0, H, block_rows)
    if isinstance(threads, Executor):
        done = list(_progressing(threads.map(run_block, starts), progress, H))
    elif int(threads) > 1:
        with ThreadPoolExecutor(max_workers=int(threads)) as pool:
            done = list(_progressing(pool.map(run_block, starts), progress, H))
    else:
        done = list(_progressing(map(run_block, starts), progress, H))
    n_footprint = sum(m[1][0] for _, m in done)
    n_no_height = sum(m[1][1] for _, m in done)
    misses = [m[0] for _, m in done if m[0] is not None]
    n_missing = sum(m[0] for m in misses)
    miss_lo = np.min([m[1] for m in misses], axis=0) if misses else None
    miss_hi = np.max([m[2] for m in misses], axis=0) if misses else None
    valid_out = np.isfinite(data) if np.isnan(nodata) else data != nodata
    missing = dict(
        n_cells=n_missing,
        lonlat_bounds=(tuple(float(v) for v in (*miss_lo, *miss_hi)) if n_missing else None),
        n_no_height=int(n_no_height),
        n_footprint=int(n_footprint),
        footprint_share=_no_height_share(n_no_height, n_footprint),
        filled_cells=int(getattr(dem_e, "filled_cells", 0)),
    )
    if n_no_height and not (strict_dem and n_missing):
        hint = "" if fill is not None else "; a second DEM can fill them (fill_dem / --fill-dem)"
        log.warning(
            "%s", no_height_message(dem.path, missing, "nodata there" + hint, image=image_name)
        )
    if n_missing:
        msg = (
            f"{dem.path or 'DEM'}: the DEM does not cover the image footprint: {n_missing} cell(s) "
            f"missing in lon {miss_lo[0]:.5f}..{miss_hi[0]:.5f}, lat "
            f"{miss_lo[1]:.5f}..{miss_hi[1]:.5f}"
        )
        if strict_dem:
            raise DEMCoverageError(msg)
    return Ortho(
        data,
        grid,
        valid_out,
        nodata,
        heights,
        bm.error_px,
        bm,
        resampling,
        missing,
        cols_map,
        rows_map,
    )
