"""The sensor-model contract and what is written once on top of it.

Every sensor model (frame camera, pushbroom, ASTER, RPC, fitted generic models) implements

* ``project(lon, lat, h) -> (col, row)``: ground to image;
* ``localize(col, row, h) -> (lon, lat)``: image to ground at ellipsoidal height ``h``;

on numpy arrays (broadcast), with longitude/latitude in degrees (WGS84), heights in metres
above the WGS84 ellipsoid, and image coordinates with the centre of the top-left pixel at
(0, 0), ``col`` to the right and ``row`` down.

On top of that contract this module provides lines of sight, localisation on a DEM by the
differential rectification method's relief iteration (Bettemir 2006, §4.1.8), footprints and
ground sampling distance. Physical models may override :meth:`SensorModel.rays` with their
exact ECEF rays; the generic version builds rays from two localisations.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from stereodem.core import geodesy
from stereodem.core.dem import as_dem
from stereodem.core.errors import DEMError, SensorModelError

log = logging.getLogger(__name__)


@dataclass
class DEMLocalization:
    """Result of :meth:`SensorModel.localize_dem`.

    ``lon``, ``lat`` in degrees, ``h`` in metres above the ellipsoid; ``iterations`` per
    point; ``converged`` false where the relief iteration did not meet the threshold within
    the cap or left the DEM (those points keep their last estimate, or NaN off the DEM).
    """

    lon: np.ndarray
    lat: np.ndarray
    h: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray

    @property
    def mean_iterations(self) -> float:
        return float(np.mean(self.iterations)) if self.iterations.size else 0.0


def pair_height_bounds(left, right) -> tuple[float, float]:
    """Heights (m, ellipsoidal) within both models' validity ranges (:meth:`SensorModel.
    height_bounds`): the pair's common range, ``lo > hi`` when the ranges do not overlap."""
    (llo, lhi), (rlo, rhi) = left.height_bounds(), right.height_bounds()
    return max(llo, rlo), min(lhi, rhi)


class SensorModel:
    """Base class of all sensor models; subclasses implement ``project`` and ``localize``.

    Attributes
    ----------
    width, height : int
        Image size in pixels (columns, rows).
    """

    width: int
    height: int

    # ------------------------------------------------------------------ contract
    def project(self, lon, lat, h):  # pragma: no cover - abstract
        """Ground (deg, deg, m above ellipsoid) to image ``(col, row)``."""
        raise NotImplementedError(f"{type(self).__name__} must implement project()")

    def localize(self, col, row, h):  # pragma: no cover - abstract
        """Image ``(col, row)`` at ellipsoidal height ``h`` (m) to ``(lon, lat)`` in degrees."""
        raise NotImplementedError(f"{type(self).__name__} must implement localize()")

    # ------------------------------------------------------------------ shared geometry
    def height_bounds(self):
        """Heights (m) between which rays are built; models override with their validity range."""
        return (-500.0, 9000.0)

    def rays(self, col, row):
        """Lines of sight of pixels in ECEF.

        Returns ``(origin, direction)`` arrays of shape (..., 3): ``origin`` is a point of the
        ray high above the terrain and ``direction`` a unit vector pointing down the ray. The
        generic version localises each pixel at the two :meth:`height_bounds`.
        """
        col, row = broadcast_coordinates(self, col, row, what="image coordinates")
        hlo, hhi = self.height_bounds()
        lo = np.stack(
            geodesy.geodetic_to_ecef(*self.localize(col, row, hlo), np.full(col.shape, hlo)), -1
        )
        hi = np.stack(
            geodesy.geodetic_to_ecef(*self.localize(col, row, hhi), np.full(col.shape, hhi)), -1
        )
        d = lo - hi
        return hi, d / np.linalg.norm(d, axis=-1, keepdims=True)

    def localize_dem(
        self, col, row, dem, *, threshold: float = 0.1, max_iterations: int = 30, h0: float = 0.0
    ) -> DEMLocalization:
        """Localise pixels on a DEM by the DRM relief iteration.

        The ray is first intersected with the ellipsoid at height ``h0`` (the thesis uses the
        ellipsoid itself, ``h0 = 0``); then, repeatedly, the DEM is read at the current ground
        point and the point is moved along the ray to that height, until two successive DEM
        readings differ by less than ``threshold`` metres (Bettemir 2006, Eq. 4.47: the step
        uses the difference of successive DEM readings). The thesis moves the point by the
        linearised horizontal displacement ``dh tan(z)`` with the ellipsoid radii of curvature;
        here the move is exact, by re-localising the pixel at the new height, which is the
        limit of that formula.

        Parameters
        ----------
        dem : stereodem.core.dem.DEM, path, or any object with ``sample(lon, lat)``
            DEM giving ellipsoidal heights (geoid DEMs are converted by the DEM); a path is
            read with :meth:`~stereodem.core.dem.DEM.from_file`.
        threshold : float
            Convergence threshold on the height change, metres (thesis: 0.1 m).
        max_iterations : int
            Iteration cap (thesis: 30).
        """
        if isinstance(dem, (str, os.PathLike)):
            dem = as_dem(dem)
        elif not callable(getattr(dem, "sample", None)):
            raise DEMError(
                f"{type(self).__name__}.localize_dem: dem must be a DEM, a DEM file path or "
                f"anything with sample(lon, lat) -> ellipsoidal heights, got "
                f"{type(dem).__name__}"
            )
        col, row = broadcast_coordinates(self, col, row, what="image coordinates")
        shape = col.shape
        c, r = col.ravel(), row.ravel()
        h = np.full(c.shape, float(h0))
        lon, lat = self.localize(c, r, h)
        lon, lat = np.asarray(lon, float), np.asarray(lat, float)
        iters = np.zeros(c.shape, dtype=np.int16)
        done = np.zeros(c.shape, dtype=bool)
        active = np.arange(c.size)
        for _ in range(max_iterations):
            if active.size == 0:
                break
            h_dem = dem.sample(lon[active], lat[active])
            off = ~np.isfinite(h_dem)
            dh = h_dem - h[active]
            iters[active] += 1
            conv = np.abs(dh) < threshold
            move = ~off & ~conv
            idx = active[move]
            if idx.size:
                h[idx] = h_dem[move]
                lon[idx], lat[idx] = self.localize(c[idx], r[idx], h[idx])
            # converged: the point is at the DEM surface to the threshold
            cidx = active[conv & ~off]
            h[cidx] = h_dem[conv & ~off]
            done[cidx] = True
            gone = active[off]
            lon[gone] = lat[gone] = h[gone] = np.nan
            active = active[move]
        n_bad = int((~done).sum())
        if n_bad:
            log.info("DRM relief iteration: %d of %d point(s) did not converge", n_bad, c.size)
        return DEMLocalization(
            lon.reshape(shape),
            lat.reshape(shape),
            h.reshape(shape),
            iters.reshape(shape),
            done.reshape(shape),
        )

    def footprint(self, h: float = 0.0, n: int = 11):
        """Image border localised at height ``h``: ``(lon, lat)`` arrays of the closed outline."""
        w, hgt = self.width, self.height
        t = np.linspace(0.0, 1.0, n)
        cols = np.concatenate([t * (w - 1), np.full(n, w - 1.0), (1 - t) * (w - 1), np.zeros(n)])
        rows = np.concatenate(
            [np.zeros(n), t * (hgt - 1), np.full(n, hgt - 1.0), (1 - t) * (hgt - 1)]
        )
        return self.localize(cols, rows, np.full(cols.shape, float(h)))

    def center_lonlat(self, h: float = 0.0):
        lon, lat = self.localize(
            np.array([(self.width - 1) / 2]), np.array([(self.height - 1) / 2]), h
        )
        return float(lon[0]), float(lat[0])

    def gsd(self, h: float = 0.0):
        """Ground sample distance (m) at the image centre: mean of the column and row steps."""
        c0, r0 = (self.width - 1) / 2, (self.height - 1) / 2
        cols = np.array([c0, c0 + 1, c0])
        rows = np.array([r0, r0, r0 + 1])
        lon, lat = self.localize(cols, rows, np.full(3, float(h)))
        x, y, z = geodesy.geodetic_to_ecef(lon, lat, np.full(3, float(h)))
        p = np.stack([x, y, z], -1)
        return float(0.5 * (np.linalg.norm(p[1] - p[0]) + np.linalg.norm(p[2] - p[0])))

    def check_inputs(self, *arrays, what="coordinates"):
        """Raise :class:`SensorModelError` when inputs are not numbers of shapes that
        broadcast together (:func:`broadcast_coordinates`) or contain NaN/inf (clear error,
        no NaN soup)."""
        for a in broadcast_coordinates(self, *arrays, what=what):
            if not np.all(np.isfinite(a)):
                raise SensorModelError(
                    f"{type(self).__name__}: non-finite {what} given "
                    f"({int((~np.isfinite(a)).sum())} value(s))"
                )


def broadcast_coordinates(model, *arrays, what="coordinates"):
    """``arrays`` as float64 arrays broadcast to one shape (``np.broadcast_arrays``); a
    :class:`SensorModelError` naming the model and ``what`` when they are not numbers, or
    the shapes when they do not broadcast (numpy's ValueError, which named neither)."""
    try:
        values = [np.asarray(a, dtype=np.float64) for a in arrays]
    except (TypeError, ValueError) as exc:
        raise SensorModelError(
            f"{type(model).__name__}: {what} must be numbers ({' '.join(str(exc).split())})"
        ) from None
    try:
        return np.broadcast_arrays(*values)
    except ValueError:
        shapes = ", ".join(str(v.shape) for v in values)
        raise SensorModelError(
            f"{type(model).__name__}: {what} must be of shapes that broadcast together, "
            f"got {shapes}"
        ) from None


def localize_on_rays(model, col, row, h):
    """``model.localize`` for a model with exact :meth:`SensorModel.rays`: each pixel's line of
    sight intersected with ellipsoidal height ``h`` (m); ``(lon, lat)`` in degrees, NaN where
    the ray misses, in the broadcast shape of the inputs."""
    model.check_inputs(col, row, h, what="image coordinates or heights")
    col, row, h = broadcast_coordinates(model, col, row, h)
    o, d = model.rays(col, row)
    lon, lat = ray_to_lonlat(o, d, h)
    return np.asarray(lon, float).reshape(col.shape), np.asarray(lat, float).reshape(col.shape)


def ray_to_lonlat(origin, direction, h):
    """Intersect ECEF rays with ellipsoidal height ``h``; returns ``(lon, lat)`` in degrees."""
    p = geodesy.intersect_height(origin, direction, h)
    lon, lat, _ = geodesy.ecef_to_geodetic(p[..., 0], p[..., 1], p[..., 2])
    return np.asarray(lon), np.asarray(lat)
