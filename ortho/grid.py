"""Output map grids for orthoimages: a north-up raster in a projected CRS.

The grid of an orthoimage is chosen from the sensor model and the DEM: the CRS is the UTM zone
of the image centre unless one is given, the posting is the image's ground sample distance
(:meth:`stereodem.sensor.models.base.SensorModel.gsd`) unless given, and the bounds enclose the
image footprint localised at the lowest and highest DEM heights under it, snapped outward to
multiples of the posting.
"""

from __future__ import annotations

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import CRSError, DEMCoverageError, InputError, SensorModelError
from stereodem.core.grid import MapGrid, grid_from_bounds, map_crs
from stereodem.core.memory import check_allocation


def _nice_posting(gsd: float) -> float:
    """The GSD rounded to three significant digits (a readable posting)."""
    return float(f"{gsd:.3g}")


def footprint_height_range(model, dem, *, samples: int = 41):
    """(min, max) ellipsoidal DEM height (m) under the image footprint.

    The footprint is localised at the DEM's mean height, its bounding box sampled on a
    ``samples x samples`` lattice; raises :class:`DEMCoverageError` if the DEM has no valid
    height there.
    """
    step = max(1, int(np.sqrt(dem.heights.size / 1e5)))
    h0 = float(np.nanmedian(dem.heights[::step, ::step]))  # first guess, any vertical datum
    lon, lat = model.footprint(h0)
    if not (np.isfinite(lon).any() and np.isfinite(lat).any()):
        # the model sees no ground at all (an absurd tilt, zero positions): not the DEM's fault
        name = getattr(model, "source", None) or getattr(model, "name", None) or "?"
        raise SensorModelError(
            f"the image's sensor model ({name}) localises no point of the image's border on "
            f"the Earth (at {h0:.0f} m): the model or its sidecar is wrong, not the DEM"
        )
    for _ in range(2):
        lo_, la_ = np.meshgrid(
            np.linspace(np.nanmin(lon), np.nanmax(lon), samples),
            np.linspace(np.nanmin(lat), np.nanmax(lat), samples),
        )
        z = dem.sample(lo_, la_)
        if not np.isfinite(z).any():
            raise DEMCoverageError(
                f"{dem.path or 'DEM'}: no valid height under the image footprint lon "
                f"{np.nanmin(lon):.5f}..{np.nanmax(lon):.5f}, lat "
                f"{np.nanmin(lat):.5f}..{np.nanmax(lat):.5f} (DEM extent lon/lat "
                f"{tuple(round(v, 5) for v in dem.bounds_lonlat())})"
            )
        h_lo, h_hi = float(np.nanmin(z)), float(np.nanmax(z))
        lon1, lat1 = model.footprint(h_lo)
        lon2, lat2 = model.footprint(h_hi)
        lon, lat = np.concatenate([lon1, lon2]), np.concatenate([lat1, lat2])
    return h_lo, h_hi


def grid_for_model(model, dem, *, res: float | None = None, crs=None, h_range=None) -> MapGrid:
    """The map grid of an orthoimage of ``model``'s image over ``dem``.

    Parameters
    ----------
    model : stereodem.sensor.models.base.SensorModel
    dem : stereodem.core.dem.DEM
        Used for the height range under the footprint (ellipsoidal).
    res : float, optional
        Posting in map units (m); default: the image GSD at the mean terrain height, to three
        significant digits.
    crs : CRS-like, optional
        Map CRS (projected); default the UTM zone of the image centre.
    h_range : (float, float), optional
        Ellipsoidal height range to localise the footprint at (default from the DEM).
    """
    h_lo, h_hi = h_range if h_range is not None else footprint_height_range(model, dem)
    if crs is None:
        crs = geodesy.utm_crs(*model.center_lonlat(0.5 * (h_lo + h_hi)))
    crs = map_crs(crs, "the orthoimage CRS")
    if not crs.is_projected:
        raise CRSError(f"the orthoimage CRS must be projected (metres), got {crs.to_string()}")
    if res is None:
        res = _nice_posting(model.gsd(0.5 * (h_lo + h_hi)))
    xs, ys = [], []
    for h in (h_lo, h_hi):
        lon, lat = model.footprint(h, n=21)
        x, y = geodesy.lonlat_to_crs(lon, lat, crs)
        xs.append(x)
        ys.append(y)
    x, y = np.concatenate(xs), np.concatenate(ys)
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise CRSError(f"the image footprint cannot be expressed in {crs.to_string()}")

    dx, dy = x.max() - x.min(), y.max() - y.min()
    # a posting beyond the whole footprint of an image (not of a pixel or a line of pixels,
    # whose footprint is a GSD or less across: one cell is their orthoimage)
    if 2.0 * model.gsd(0.5 * (h_lo + h_hi)) < max(dx, dy) < res:
        raise InputError(
            f"orthoimage posting {res:g} m exceeds the image footprint ({dx:.0f} x {dy:.0f} m): "
            "the orthoimage would be a single cell; choose a finer --res"
        )
    with np.errstate(over="ignore"):  # a posting of 1e-300: inf cells, refused below
        cells = dx / res * (dy / res)
    # the orthoimage (float32) and its per-cell image coordinates (2 x float64)
    check_allocation(
        20.0 * cells,
        f"an orthoimage grid of {cells:.3g} cells at posting {res:g} (choose a coarser --res)",
        fraction=0.5,
    )
    x0, x1, y0, y1 = x.min(), x.max(), y.min(), y.max()
    # an image of one row or column (or one pixel) has a footprint of no width through its
    # pixel centres: the pixel's own extent, half a posting each side, gives it one cell
    if x1 - x0 < res:
        x0, x1 = 0.5 * (x0 + x1) - 0.5 * res, 0.5 * (x0 + x1) + 0.5 * res
    if y1 - y0 < res:
        y0, y1 = 0.5 * (y0 + y1) - 0.5 * res, 0.5 * (y0 + y1) + 0.5 * res
    return grid_from_bounds((x0, y0, x1, y1), res, crs)
