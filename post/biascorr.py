"""The steps of a co-registration chain (:mod:`stereodem.post.coreg`).

* :class:`NuthKaab` — horizontal + vertical shift, Nuth & Kääb (2011), iterated;
* :class:`VerticalShift` — the median of ``dh`` on stable terrain;
* :class:`Deramp` — a 2-D polynomial of order 1–3 in east/north (attitude tilts);
* :class:`AlongTrack` — a sum of sines along the ground track (ASTER jitter; MMASTER,
  Girod et al. 2017), frequencies found on the along-track profile and refined jointly;
* :class:`CrossTrack` — a low-order polynomial across the track (MMASTER);
* :class:`Curvature` — ``dh`` against maximum curvature, polynomial (Gardelle et al. 2012);
* :class:`ICP` — rigid point-to-plane ICP (translation + small rotation).

All heights/dh in metres, east/north/along/cross in metres of the local frame of
:func:`stereodem.post.coreg.local_metric_coords`.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import optimize

from stereodem.core import geodesy
from stereodem.core.blocks import default_threads, each_fixed_band
from stereodem.core.errors import ConvergenceError, InputError
from stereodem.core.grid import crs_unit
from stereodem.core.stats import nmad

from . import shift_units, terrain, warp
from .coreg import (
    Coreg,
    bilinear,
    local_metric_coords,
    param,
    robust_lstsq,
    track_coords,
)

log = logging.getLogger(__name__)

#: Sign of the shifts of ``nuth_kaab`` (dx, dy, dz) and ``vshift`` (dz), as the reports state it.
DISPLACEMENT = (
    "displacement of the DEM relative to the reference (x grid east, y grid north, z up); "
    "the correction applied is its opposite"
)
#: Sign of ``icp``'s translation (tx, ty, tz), as the reports state it: the opposite of
#: :data:`DISPLACEMENT` for the same offset.
MOTION = (
    "motion applied to the DEM to bring it onto the reference (x grid east, y grid north, "
    "z up): the opposite of nuth_kaab's dx, dy, dz for the same offset"
)


def _warp_shift(dem, east_m, north_m, resampling="bilinear"):
    """Heights of ``dem`` moved by ``east_m, north_m`` metres (grid metres on a projected grid:
    :func:`~stereodem.post.warp.metres_per_unit`), on its own grid (NaN where
    moved off the grid)."""
    t = warp.translated(dem.transform, dem.crs, dem.shape, east_m, north_m)
    return warp.to_grid(
        dem.heights,
        t,
        dem.crs,
        dem.transform,
        dem.crs,
        dem.shape,
        resampling=resampling,
        threads=default_threads(),  # the whole grid at once: on the process's thread budget
    ).astype(np.float64)


def _gradient_at_samples(sampler, z, dem):
    """East and north gradients of the heights ``z`` (m/m) at the sampler's positions: on a
    DEM grid's own cells only those cells are differenced (:func:`terrain.gradient_at`, the
    same values as the whole grid's gradient there); points between cells interpolate the
    whole grid's gradient."""
    if sampler.kind == "dem":
        return terrain.gradient_at(z, dem.transform, dem.crs, sampler.rows, sampler.cols)
    ge, gn = terrain.gradient(z, dem.transform, dem.crs)
    return sampler.values(ge), sampler.values(gn)


# ----------------------------------------------------------------------------- shifts


class VerticalShift(Coreg):
    """Remove the median of stable ``dh`` (σ: 1.2533·NMAD/√n, the median's formal σ)."""

    name = "vshift"

    @classmethod
    def from_arg(cls, n):
        raise InputError("vshift takes no ':N' argument")

    def _fit(self, sampler, dem, context):
        d = sampler.dh(dem.heights)
        d = d[np.isfinite(d)]
        if d.size < 3:
            raise InputError("vshift: fewer than 3 stable samples")
        self.dz = float(np.median(d))
        self.params = {
            "dz": param(self.dz, 1.2533 * nmad(d) / np.sqrt(d.size), "m"),
            "sign": DISPLACEMENT,
        }

    def _apply(self, dem):
        return dem.heights - self.dz


class NuthKaab(Coreg):
    """Iterated Nuth & Kääb (2011) shift: ``dh = −(∂z/∂E·dx + ∂z/∂N·dy) + dz`` on stable
    cells of slope ``min_slope``–``max_slope`` degrees, the DEM re-warped with the shift found
    so far until the increment is below ``tolerance_px`` pixel.

    ``dx, dy, dz``: displacement of the DEM relative to the reference (metres along x (grid
    east), y (grid north), up); ``apply`` removes it on the DEM's own grid (a DEM whose
    features sit 50 m east of the reference's has ``dx = +50``). ``dx, dy`` are metres of the
    DEM's grid (:func:`~stereodem.post.warp.metres_per_unit`): ground metres on a geographic
    grid, the CRS's units (grid metres, along its x/y axes) on a projected one, as xdem's; the
    parameters add the projection's ``scale_factor`` at the grid centre and, where it differs
    from 1 by over 0.1 %, ``dx_ground``/``dy_ground``
    (:func:`~stereodem.post.shift_units.ground_shift`).

    ``tilt=True`` (default) adds a plane in east/north to the least squares as a nuisance
    (fitted, not applied: ``deramp`` removes it): a ramp left in ``dh`` otherwise leaks into
    the shift where slope and position correlate (0.45 m of a 90 m shift on the benchmark).
    """

    name = "nuth_kaab"

    def __init__(
        self,
        *,
        max_iterations: int = 15,
        tolerance_px: float = 0.005,
        min_slope: float = 1.0,
        max_slope: float = 70.0,
        outlier_nmad: float = 3.0,
        resampling: str = "cubic",
        tilt: bool = True,
    ):
        super().__init__()
        self.tilt = bool(tilt)
        self.max_iterations = int(max_iterations)
        self.tolerance_px = float(tolerance_px)
        self.min_slope, self.max_slope = float(min_slope), float(max_slope)
        self.outlier_nmad = float(outlier_nmad)
        self.resampling = resampling
        self.dx = self.dy = self.dz = 0.0

    @classmethod
    def from_arg(cls, n):
        return cls(max_iterations=n)

    def _fit(self, sampler, dem, context):
        pe, pn = warp.metres_per_unit(dem.transform, dem.crs, dem.shape)
        pe, pn = abs(dem.transform.a) * pe, abs(dem.transform.e) * pn
        east = north = 0.0
        history, converged = [], False
        cov = np.full((3, 3), np.nan)
        for it in range(1, self.max_iterations + 1):
            z = dem.heights.astype(np.float64) if it == 1 else self._moved(dem, -east, -north)
            sge, sgn = _gradient_at_samples(sampler, z, dem)
            s = np.degrees(np.arctan(np.hypot(sge, sgn)))
            d = sampler.dh(z)
            ok = np.isfinite(d) & (s >= self.min_slope) & (s <= self.max_slope)
            if ok.sum() < 50:
                raise InputError(
                    f"{dem.path or 'DEM'}: only {int(ok.sum())} stable samples with "
                    "usable slope; cannot co-register"
                )
            cols = [-sge, -sgn, np.ones(d.size)]
            if self.tilt:
                cols += [sampler.east / 1e4, sampler.north / 1e4]
            a = np.column_stack(cols)
            p, cov, _ = robust_lstsq(a[ok], d[ok], n_sigma=self.outlier_nmad)
            if it == 1:  # the figure's data: dh / tan(slope) against aspect
                first = (
                    d[ok] - p[2] - (a[ok, 3:] @ p[3:] if self.tilt else 0.0),
                    -a[ok, 0],
                    -a[ok, 1],
                )
            east, north = east + p[0], north + p[1]
            step_px = float(np.hypot(p[0] / pe, p[1] / pn))
            history.append({"iteration": it, "dx": east, "dy": north, "step_px": step_px})
            if step_px < self.tolerance_px:
                converged = True
                break
        if not converged:
            log.warning(
                "Nuth-Kaab did not converge in %d iterations (last step %.4f px)",
                self.max_iterations,
                history[-1]["step_px"],
            )
        d = sampler.dh(self._moved(dem, -east, -north))
        d = d[np.isfinite(d)]
        if d.size == 0:
            raise ConvergenceError(
                f"{dem.path or 'DEM'}: the shift moved the DEM off the reference"
            )
        self.dx, self.dy, self.dz = float(east), float(north), float(np.median(d))
        sd = np.sqrt(np.diag(cov))[:3]
        self.params = {
            "dx": param(self.dx, sd[0], "m"),
            "dy": param(self.dy, sd[1], "m"),
            "dz": param(self.dz, 1.2533 * nmad(d) / np.sqrt(d.size), "m"),
            "iterations": len(history),
            "converged": converged,
            "sign": DISPLACEMENT,
        }
        self.params.update(
            shift_units.ground_shift(
                dem.transform,
                dem.crs,
                dem.shape,
                ("dx", "dy"),
                (self.dx, self.dy),
                sd[:2],
                what=f"{dem.path or 'DEM'}: nuth_kaab",
            )
        )
        d0, ge0, gn0 = first
        tan = np.hypot(ge0, gn0)
        aspect = np.degrees(np.arctan2(-ge0, -gn0)) % 360.0
        dx, dy = self.dx, self.dy
        self.curves = _binned_curve(
            aspect,
            d0 / np.maximum(tan, 1e-3),
            lambda x: dx * np.sin(np.radians(x)) + dy * np.cos(np.radians(x)),
            "aspect (deg, downhill, clockwise from north)",
            bins=36,
        )
        if self.curves:
            self.curves["y_label"] = "dh / tan(slope) (m)"
        self.curves["log"] = history

    def _moved(self, dem, east_m, north_m):
        """The DEM moved by ``east_m, north_m`` for an iteration's samples: with cubic
        resampling, GDAL's cubic kernel as one separable filter
        (:func:`stereodem.post.warp.shifted_cubic`, 5-10x faster than the warp on a 3000²
        grid; the same heights to float32 rounding, NaN instead of GDAL's re-weighting where
        the 4 x 4 support meets a void or the edge: those cells are left out of the fit);
        the applied DEM uses GDAL's warp itself (:func:`_warp_shift`)."""
        t = dem.transform
        if self.resampling != "cubic" or t.b or t.d:  # a rotated grid: GDAL's warp
            return _warp_shift(dem, east_m, north_m, self.resampling)
        cols, rows = warp.shift_in_pixels(t, dem.crs, dem.shape, east_m, north_m)
        return warp.shifted_cubic(dem.heights, cols, rows)

    def _apply(self, dem):
        return _warp_shift(dem, -self.dx, -self.dy, self.resampling) - self.dz


# ----------------------------------------------------------------------------- polynomials


def _poly_terms(u, v, order):
    """Columns u^i v^j for i + j <= order (constant first)."""
    return np.column_stack([u ** (k - j) * v**j for k in range(order + 1) for j in range(k + 1)])


def _poly_names(order, a="e", b="n"):
    return [f"c_{a}{k - j}{b}{j}" for k in range(order + 1) for j in range(k + 1)]


def _poly_degrees(order):
    """The total degree of each column of :func:`_poly_terms` (constant first)."""
    return [k for k in range(order + 1) for _ in range(k + 1)]


def per_power(degree: int, of: str = "m") -> str:
    """The unit of a polynomial coefficient of ``dh`` (metres) for a term of ``degree`` in a
    coordinate measured in ``of``: ``"m"``, ``"m/m"``, ``"m/m^2"``, ``"m/(1/100 m)"``."""
    if degree == 0:
        return "m"
    of = of if len(of.split()) == 1 else f"({of})"
    return f"m/{of}" + (f"^{degree}" if degree > 1 else "")


def _poly_params(names, degrees, coef, sd, scale: float, of: str = "m") -> dict:
    """Reported polynomial coefficients: those fitted on coordinates divided by ``scale``
    (10 km: a well-conditioned fit) given per ``of`` (metre) of the coordinate itself,
    value and σ divided by ``scale ** degree``, with :func:`per_power`'s unit (a plane's
    slope in m/m, as xdem's coefficients on a metre grid; it was labelled "m")."""
    return {
        k: param(v / scale**g, s / scale**g, per_power(g, of))
        for k, g, v, s in zip(names, degrees, coef, sd)
    }


def _coordinates_note(crs) -> str:
    """What the east/north metres of :func:`~stereodem.post.coreg.local_metric_coords` are
    on a grid in ``crs`` (the reports' ``coordinates``)."""
    if terrain._is_geographic(crs):
        return "east/north: ground metres from the grid centre"
    unit = crs_unit(crs)
    given = "" if unit == "metre" else f", its {unit or 'unit'} converted to metres"
    return (
        "east/north: grid metres along the grid's x/y from the grid centre (the CRS's "
        f"units{given}; ground metres = grid metres / the projection's scale factor)"
    )


class Deramp(Coreg):
    """A 2-D polynomial of ``dh`` in east/north (order 1–3, includes the constant; east/north
    metres from the grid centre, :func:`~stereodem.post.coreg.local_metric_coords`).

    Parameters ``c_e{i}n{j}``: the coefficient of ``east^i north^j`` in m/m^(i+j) (``c_e0n0``
    in m, the plane's slopes ``c_e1n0``, ``c_e0n1`` in m per m; on a projected grid per grid
    metre, as xdem's per CRS unit on a metre grid), with ``coordinates`` saying which metres.
    ``coef`` holds the fitted ones, on coordinates in units of 10 km (:attr:`SCALE`)."""

    name = "deramp"
    SCALE = 1.0e4

    def __init__(self, order: int = 1):
        super().__init__()
        if order not in (1, 2, 3):
            raise InputError(f"deramp order must be 1, 2 or 3, got {order}")
        self.order = int(order)
        self.name = f"deramp:{self.order}"

    @classmethod
    def from_arg(cls, n):
        return cls(n)

    def __repr__(self):
        return f"Deramp({self.order})"

    def _fit(self, sampler, dem, context):
        d = sampler.dh(dem.heights)
        a = _poly_terms(sampler.east / self.SCALE, sampler.north / self.SCALE, self.order)
        self.coef, cov, _ = robust_lstsq(a, d)
        sd = np.sqrt(np.diag(cov))
        self.params = _poly_params(
            _poly_names(self.order), _poly_degrees(self.order), self.coef, sd, self.SCALE
        )
        self.params["coordinates"] = _coordinates_note(dem.crs)

    def _apply(self, dem):
        e, n = local_metric_coords(dem.transform, dem.crs, dem.shape)
        out = np.empty(dem.shape, np.float64)
        for r0 in range(0, dem.shape[0], 256):  # row blocks: bounded memory
            eb, nb = e[r0 : r0 + 256], n[r0 : r0 + 256]
            a = _poly_terms(eb.ravel() / self.SCALE, nb.ravel() / self.SCALE, self.order)
            out[r0 : r0 + 256] = (a @ self.coef).reshape(eb.shape)
        return dem.heights - out


def _heading(step, context):
    h = step.heading if step.heading is not None else context.get("track_angle_deg")
    if h is None:
        raise InputError(
            f"{step.name}: the ground-track heading is unknown; give it "
            "(--track-angle DEG, track_angle_deg=...) or use a DEM made by stereodem"
        )
    try:
        h = float(h)
    except (TypeError, ValueError):
        h = float("nan")
    if not np.isfinite(h):  # NaN made the track profile's bin count negative: a traceback
        raise InputError(
            f"{step.name}: the ground-track heading must be a finite angle in degrees, got "
            f"{step.heading if step.heading is not None else context.get('track_angle_deg')}"
        )
    return h


def _set_track(step, context):
    """Choose the track of an along/cross-track step: its own heading if given, else the
    sensor model's frame of the context (:class:`~stereodem.post.track.TrackFrame`), else the
    context's heading; ``InputError`` when there is none."""
    frame = context.get("track_frame")
    if step.heading is None and frame is not None:
        step.frame, step.heading = frame, None
    else:
        step.frame, step.heading = None, _heading(step, context)


def _track_report(step) -> dict:
    if step.frame is not None:
        return {"track": step.frame.describe()}
    return {"heading_deg": step.heading, "track": "straight at heading_deg"}


def _sample_track(step, sampler, dem):
    """Along/cross-track metres at the samples."""
    if step.frame is not None:
        return step.frame.grid_coords(
            dem.transform,
            sampler.rows,
            sampler.cols,
            _ellipsoidal(dem, sampler.values(dem.heights)),
        )
    return track_coords(sampler.east, sampler.north, step.heading)


def _ellipsoidal(dem, z):
    """Heights ``z`` of ``dem`` as ellipsoidal heights to ~30 m (the track frame's height term
    is 0.15 m of ground per metre at most): a geoid DEM is raised by the mean EGM96
    undulation over its grid; a DEM of unknown reference is taken as it is."""
    z = np.asarray(z, np.float64)
    if dem.vertical != "geoid":
        return z

    lon, lat = geodesy.crs_to_lonlat(
        *(dem.transform @ (dem.shape[1] / 2.0, dem.shape[0] / 2.0)), dem.crs
    )
    return z + float(np.ravel(geodesy.geoid_undulation(lon, lat))[0])


def _grid_track(step, dem, rows: slice):
    """Along/cross-track metres of the cells of ``rows`` of the DEM grid."""
    if step.frame is not None:
        if not step.frame.matches(dem.crs):
            raise InputError(
                f"{step.name}: the DEM {dem.path or ''} is not in the CRS of the "
                f"track frame the step was fitted with ({step.frame.crs})"
            )
        r = np.arange(dem.shape[0])[rows]
        rr, cc = np.meshgrid(r, np.arange(dem.shape[1]), indexing="ij")
        return step.frame.grid_coords(dem.transform, rr, cc, _ellipsoidal(dem, dem.heights[rows]))
    e, n = local_metric_coords(dem.transform, dem.crs, dem.shape)
    return track_coords(e[rows], n[rows], step.heading)


class CrossTrack(Coreg):
    """A polynomial of ``dh`` in the cross-track coordinate (order 1–3, constant included),
    MMASTER's cross-track bias. Parameters ``c{k}`` in m/m^k of cross-track metres (``c0``
    in m); ``coef`` holds the fitted ones, on coordinates in units of 10 km (:attr:`SCALE`)."""

    name = "cross_track"
    SCALE = 1.0e4

    def __init__(self, order: int = 2, *, heading: float | None = None):
        super().__init__()
        if order not in (1, 2, 3):
            raise InputError(f"cross_track order must be 1, 2 or 3, got {order}")
        self.order, self.heading, self.frame = int(order), heading, None

    @classmethod
    def from_arg(cls, n):
        return cls(n)

    def _fit(self, sampler, dem, context):
        _set_track(self, context)
        _, c = _sample_track(self, sampler, dem)
        d = sampler.dh(dem.heights)
        a = np.vander(c / self.SCALE, self.order + 1, increasing=True)
        self.coef, cov, _ = robust_lstsq(a, d)
        sd = np.sqrt(np.diag(cov))
        k = range(self.order + 1)
        self.params = _poly_params([f"c{i}" for i in k], k, self.coef, sd, self.SCALE)
        self.params.update(_track_report(self))
        self.params["coordinates"] = "cross-track metres (right of the track)"
        self.curves = _binned_curve(
            c,
            d,
            lambda x: np.vander(x / self.SCALE, self.order + 1, increasing=True) @ self.coef,
            "cross-track distance (m)",
        )

    def _apply(self, dem):
        out = np.empty(dem.shape, np.float64)
        for r0 in range(0, dem.shape[0], 256):  # row blocks: bounded memory
            _, c = _grid_track(self, dem, slice(r0, r0 + 256))
            out[r0 : r0 + 256] = np.polynomial.polynomial.polyval(c / self.SCALE, self.coef)
        return dem.heights - out


def _binned_curve(x, d, model, label, bins: int = 60):
    """Binned medians of ``d`` against ``x`` and the fitted model, for the figures."""
    ok = np.isfinite(x) & np.isfinite(d)
    if ok.sum() < 10:
        return {}
    edges = np.quantile(x[ok], np.linspace(0, 1, bins + 1))
    edges = np.unique(edges)
    k = np.clip(np.searchsorted(edges, x[ok], side="right") - 1, 0, edges.size - 2)
    med = np.array(
        [np.median(d[ok][k == i]) if np.any(k == i) else np.nan for i in range(edges.size - 1)]
    )
    cen = 0.5 * (edges[:-1] + edges[1:])
    xs = np.linspace(edges[0], edges[-1], 400)
    return {
        "x_label": label,
        "bin_centre": cen.tolist(),
        "bin_median": med.tolist(),
        "model_x": xs.tolist(),
        "model_y": np.asarray(model(xs), float).tolist(),
    }


# ----------------------------------------------------------------------------- along track


def _sines(t, f, a, b):
    """Σ a_k sin(2π f_k t) + b_k cos(2π f_k t) (t in m, f in cycles/m)."""
    ph = 2.0 * np.pi * np.outer(t, f)
    return np.sin(ph) @ a + np.cos(ph) @ b


def _resolved(fs, a, b, length, profile) -> bool:
    """Whether refined sines are a resolvable set: frequencies at least ``1/length`` apart
    (the profile's Rayleigh resolution; two sines closer than that trade amplitude against
    each other and grow into a large pair that cancels) and no amplitude above the
    profile's full range."""
    f = np.sort(np.abs(fs))
    if f.size > 1 and np.min(np.diff(f)) < 1.0 / length:
        return False
    span = float(np.nanmax(profile) - np.nanmin(profile))
    return bool(np.all(np.hypot(a, b) <= span))


class AlongTrack(Coreg):
    """A sum of sines of ``dh`` along the ground track (satellite jitter; MMASTER).

    Frequencies are found one at a time on the binned along-track profile of the residual
    (periodogram peak between ``min_wavelength`` and ``max_wavelength`` metres), kept while
    the amplitude exceeds ``min_amplitude`` m and 4 formal σ and the profile's variance drops
    by 5 %; then all sines (frequency, sine and cosine amplitudes) and an offset are refined
    jointly by robust non-linear least squares on the samples.
    """

    name = "along_track"

    def __init__(
        self,
        n_sines: int = 3,
        *,
        heading: float | None = None,
        min_wavelength: float = 1000.0,
        max_wavelength: float | None = None,
        min_amplitude: float = 0.2,
        bin_m: float | None = None,
    ):
        super().__init__()
        self.n_sines = int(n_sines)
        if not 1 <= self.n_sines <= 10:
            raise InputError(f"along_track: number of sines must be 1-10, got {n_sines}")
        self.heading, self.frame = heading, None
        self.min_wavelength, self.max_wavelength = float(min_wavelength), max_wavelength
        self.min_amplitude = float(min_amplitude)
        self.bin_m = bin_m
        self.freq = np.zeros(0)
        self.amp_sin = np.zeros(0)
        self.amp_cos = np.zeros(0)
        self.offset = 0.0

    @classmethod
    def from_arg(cls, n):
        return cls(n)

    def _profile(self, t, d, bin_m):
        ok = np.isfinite(d)
        t0 = t[ok].min()
        k = ((t[ok] - t0) / bin_m).astype(np.int64)
        n = int(k.max()) + 1
        # binned median by sorting once (vectorised)
        order = np.lexsort((d[ok], k))
        ks, ds = k[order], d[ok][order]
        starts = np.searchsorted(ks, np.arange(n))
        ends = np.searchsorted(ks, np.arange(n), side="right")
        cnt = ends - starts
        med = np.full(n, np.nan)
        has = cnt > 0
        mid_lo = starts[has] + (cnt[has] - 1) // 2
        mid_hi = starts[has] + cnt[has] // 2
        med[has] = 0.5 * (ds[mid_lo] + ds[mid_hi])
        centres = t0 + (np.arange(n) + 0.5) * bin_m
        return centres, med, cnt

    def _fit(self, sampler, dem, context):
        _set_track(self, context)
        t, _ = _sample_track(self, sampler, dem)
        d = sampler.dh(dem.heights)
        ok = np.isfinite(d)
        if ok.sum() < 100:
            raise InputError("along_track: fewer than 100 stable samples")
        px = abs(dem.transform.a) * warp.metres_per_unit(dem.transform, dem.crs, dem.shape)[0]
        span = float(np.nanmax(t[ok]) - np.nanmin(t[ok]))
        # profile bins: a pixel, but at most 4000 bins along the track (bounded periodogram)
        bin_m = float(
            self.bin_m
            or max(
                px,
                0.5
                * abs(dem.transform.e)
                * warp.metres_per_unit(dem.transform, dem.crs, dem.shape)[1],
                span / 4000.0,
            )
        )
        centres, prof, cnt = self._profile(t, d - np.median(d[ok]), bin_m)
        length = centres[-1] - centres[0] + bin_m
        max_wl = float(self.max_wavelength or length / 2.0)
        good = cnt >= 5
        if good.sum() < 20:
            raise InputError("along_track: the stable samples cover too short a track")
        x, y = centres[good], prof[good]
        w = np.sqrt(cnt[good])
        fmin, fmax = 1.0 / max_wl, 1.0 / max(self.min_wavelength, 2.5 * bin_m)
        freqs = np.linspace(fmin, fmax, 4 * int(np.ceil(length * (fmax - fmin))) + 1)
        found: list[float] = []
        resid = y - np.median(y)
        for _ in range(self.n_sines):
            # weighted periodogram of the residual profile (least-squares spectral analysis)
            ph = 2 * np.pi * np.outer(x, freqs)
            s, c = np.sin(ph), np.cos(ph)
            ww = w / w.sum()
            power = ((ww * resid) @ s) ** 2 / (ww @ (s * s)) + ((ww * resid) @ c) ** 2 / (
                ww @ (c * c)
            )
            f = float(freqs[int(np.argmax(power))])
            fs = np.array(found + [f])
            p = self._refine_profile(x, y, w, fs)
            if p is None:
                break
            fs, a, b, off = p
            if not _resolved(fs, a, b, length, y):
                break
            new = y - off - _sines(x, fs, a, b)
            amp = float(np.hypot(a[-1], b[-1]))
            var_drop = 1.0 - np.average(new**2, weights=w**2) / np.average(resid**2, weights=w**2)
            if amp < self.min_amplitude or var_drop < 0.05:
                break
            found = list(fs)
            resid = new
        if not found:
            self.freq = self.amp_sin = self.amp_cos = np.zeros(0)
            self.offset = 0.0
            self.params = {"n_sines": 0, **_track_report(self)}
            self.curves = _binned_curve(
                t, d, lambda z: np.zeros_like(z), "along-track distance (m)"
            )
            return
        self._refine_samples(t, d, np.array(found))
        self.curves = _binned_curve(
            t,
            d,
            self._model,
            "along-track distance (m)",
            bins=min(400, max(60, int(length / bin_m / 2))),
        )

    @staticmethod
    def _refine_profile(x, y, w, fs):
        k = fs.size

        def resid(p):
            return w * (y - p[0] - _sines(x, p[1 : k + 1], p[k + 1 : 2 * k + 1], p[2 * k + 1 :]))

        # linear start for the amplitudes at fixed frequencies
        ph = 2 * np.pi * np.outer(x, fs)
        a = np.column_stack([np.ones_like(x), np.sin(ph), np.cos(ph)]) * w[:, None]
        lin, *_ = np.linalg.lstsq(a, w * y, rcond=None)
        p0 = np.concatenate([[lin[0]], fs, lin[1 : k + 1], lin[k + 1 :]])
        try:
            sol = optimize.least_squares(
                resid, p0, loss="soft_l1", f_scale=max(nmad(y), 1e-3), x_scale="jac"
            )
        except (ValueError, np.linalg.LinAlgError):
            return None
        p = sol.x
        return p[1 : k + 1], p[k + 1 : 2 * k + 1], p[2 * k + 1 :], p[0]

    def _refine_samples(self, t, d, fs):
        ok = np.isfinite(d)
        tt, dd = t[ok], d[ok]
        k = fs.size
        ph = 2 * np.pi * np.outer(tt, fs)
        a = np.column_stack([np.ones_like(tt), np.sin(ph), np.cos(ph)])
        lin, *_ = np.linalg.lstsq(a, dd, rcond=None)
        p0 = np.concatenate([[lin[0]], fs, lin[1 : k + 1], lin[k + 1 :]])
        scale = max(nmad(dd - a @ lin), 1e-3)

        def resid(p):
            return dd - p[0] - _sines(tt, p[1 : k + 1], p[k + 1 : 2 * k + 1], p[2 * k + 1 :])

        sol = optimize.least_squares(resid, p0, loss="soft_l1", f_scale=scale, x_scale="jac")
        p = sol.x
        r = resid(p)
        s = nmad(r)
        inl = np.abs(r - np.median(r)) <= 3 * s
        jac = sol.jac[inl]
        cov = s * s * np.linalg.pinv(jac.T @ jac)
        self.offset, self.freq = float(p[0]), p[1 : k + 1]
        self.amp_sin, self.amp_cos = p[k + 1 : 2 * k + 1], p[2 * k + 1 :]
        sd = np.sqrt(np.diag(cov))
        self.params = {
            "offset": param(self.offset, sd[0], "m"),
            "n_sines": k,
            **_track_report(self),
        }
        for i in range(k):
            f, a_, b_ = self.freq[i], self.amp_sin[i], self.amp_cos[i]
            sf, sa, sb = sd[1 + i], sd[1 + k + i], sd[1 + 2 * k + i]
            amp = float(np.hypot(a_, b_))
            # propagated σ of amplitude (from sine/cosine parts) and wavelength (from frequency)
            s_amp = float(np.hypot(a_ * sa, b_ * sb) / amp) if amp > 0 else float("nan")
            self.params[f"sine{i + 1}_wavelength"] = param(1.0 / f, sf / f**2, "m")
            self.params[f"sine{i + 1}_amplitude"] = param(amp, s_amp, "m")
            self.params[f"sine{i + 1}_phase"] = param(
                float(np.arctan2(b_, a_)), float("nan"), "rad"
            )

    def _model(self, t):
        if self.freq.size == 0:
            return np.zeros_like(np.asarray(t, float))
        shp = np.shape(t)
        return (self.offset + _sines(np.ravel(t), self.freq, self.amp_sin, self.amp_cos)).reshape(
            shp
        )

    def _apply(self, dem):
        if self.freq.size == 0:
            return dem.heights.astype(np.float64)
        # evaluated cell by cell (any heading or track frame), in row blocks of bounded memory
        out = np.empty(dem.shape, np.float64)
        for r0 in range(0, dem.shape[0], 256):
            t, _ = _grid_track(self, dem, slice(r0, r0 + 256))
            out[r0 : r0 + 256] = self._model(t)
        return dem.heights - out


# ----------------------------------------------------------------------------- curvature


#: rows of one band of :func:`maximum_curvature`'s work (its float64 temporaries, a dozen
#: arrays of the band's size, stay a few tens of MB whatever the grid)
CURVATURE_BAND_ROWS = 256


def maximum_curvature(heights, transform, crs, *, threads: int | None = None):
    """Signed principal curvature of largest magnitude of the height field, in 1/(100 m)
    (xdem's unit); positive where the surface is convex up (ridges negative... see below).

    The Hessian of z(east, north) in m⁻¹ from central differences; its eigenvalue of largest
    absolute value, times 100. Negative on ridges and peaks, positive in valleys and pits.

    Worked out in bands of :data:`CURVATURE_BAND_ROWS` rows on ``threads`` threads (default:
    the process's budget, :func:`stereodem.core.blocks.default_threads`), each band with the
    one row of first gradients either side that its second differences read: the numbers of
    :func:`terrain.gradient` applied twice to the whole grid, bit for bit, on any number of
    threads.
    """
    z = np.asarray(heights, np.float64)
    n_r = z.shape[0]
    if z.ndim != 2 or n_r < 2 or z.shape[1] < 2:
        return _maximum_curvature_whole(z, transform, crs)
    dx, dy = terrain.pixel_size_m(transform, crs, z.shape)
    out = np.empty(z.shape, np.float64)

    def band(rows):
        r0, r1 = rows
        a0, a1 = max(0, r0 - 1), min(n_r, r1 + 1)
        ge, gn = terrain._gradient_rows(z, dx, dy, a0, a1)  # first gradients, rows a0:a1
        sx, sy = dx[a0:a1], dy[a0:a1]
        gee, gen = terrain._gradient_rows(ge, sx, sy, r0 - a0, r1 - a0)
        gne, gnn = terrain._gradient_rows(gn, sx, sy, r0 - a0, r1 - a0)
        out[r0:r1] = _largest_eigenvalue(gee, gen, gne, gnn)

    each_fixed_band(band, n_r, CURVATURE_BAND_ROWS, threads=threads)
    return out


def _maximum_curvature_whole(z, transform, crs):
    ge, gn = terrain.gradient(z, transform, crs)
    gee, gen = terrain.gradient(ge, transform, crs)
    gne, gnn = terrain.gradient(gn, transform, crs)
    return _largest_eigenvalue(gee, gen, gne, gnn)


def _largest_eigenvalue(gee, gen, gne, gnn):
    """The Hessian's eigenvalue of largest magnitude, times 100 (1/(100 m))."""
    gx = 0.5 * (gen + gne)
    m = 0.5 * (gee + gnn)
    r = np.sqrt(0.25 * (gee - gnn) ** 2 + gx**2)
    l1, l2 = m + r, m - r
    return 100.0 * np.where(np.abs(l1) >= np.abs(l2), l1, l2)


class Curvature(Coreg):
    """``dh`` against the DEM's own maximum curvature (1/100 m), a polynomial of order 1–3
    fitted robustly on the samples (Gardelle et al. 2012); the correction is held constant
    beyond the 0.5–99.5 % curvature range of the fit (no extrapolation)."""

    name = "curvature"

    def __init__(self, order: int = 2):
        super().__init__()
        if order not in (1, 2, 3):
            raise InputError(f"curvature order must be 1, 2 or 3, got {order}")
        self.order = int(order)

    @classmethod
    def from_arg(cls, n):
        return cls(n)

    def _fit(self, sampler, dem, context):
        curv = maximum_curvature(dem.heights, dem.transform, dem.crs)
        c = sampler.values(curv)
        d = sampler.dh(dem.heights)
        ok = np.isfinite(c) & np.isfinite(d)
        self.range = tuple(np.quantile(c[ok], [0.005, 0.995]).tolist())
        cc = np.clip(c, *self.range)
        a = np.vander(cc, self.order + 1, increasing=True)
        self.coef, cov, _ = robust_lstsq(a, d)
        sd = np.sqrt(np.diag(cov))
        k = range(self.order + 1)
        self.params = _poly_params([f"c{i}" for i in k], k, self.coef, sd, 1.0, "1/100 m")
        self.params["curvature_unit"] = "1/(100 m)"
        self.params["curvature_range"] = list(self.range)
        self.curves = _binned_curve(
            cc,
            d,
            lambda x: np.polynomial.polynomial.polyval(x, self.coef),
            "maximum curvature (1/100 m)",
        )

    def _apply(self, dem):
        curv = maximum_curvature(dem.heights, dem.transform, dem.crs)
        corr = np.polynomial.polynomial.polyval(np.clip(curv, *self.range), self.coef)
        corr = np.where(np.isfinite(corr), corr, np.polynomial.polynomial.polyval(0.0, self.coef))
        return dem.heights - corr


# ----------------------------------------------------------------------------- ICP


class ICP(Coreg):
    """Rigid point-to-plane ICP of the DEM surface onto the reference: a translation
    (tx, ty, tz metres; tx, ty in the grid's metres as NuthKaab's dx, dy, with ``scale_factor``
    and ``tx_ground``/``ty_ground`` likewise) and small rotations (ωe, ωn, ωu radians about
    the grid centre at the mean height), linearised and iterated. Normals from the DEM's
    gradient; each DEM cell's counterpart is the reference directly below it (vertical
    correspondences on gridded surfaces). ``apply`` moves the surface rigidly and resamples it
    on the DEM grid."""

    name = "icp"

    def __init__(self, max_iterations: int = 20, tolerance_m: float = 0.01):
        super().__init__()
        self.max_iterations, self.tolerance_m = int(max_iterations), float(tolerance_m)
        self.t = np.zeros(3)
        self.w = np.zeros(3)
        self.z0 = 0.0

    @classmethod
    def from_arg(cls, n):
        return cls(max_iterations=n)

    def _fit(self, sampler, dem, context):
        self.z0 = float(np.nanmean(dem.heights))
        self.t, self.w = np.zeros(3), np.zeros(3)
        cov = np.full((6, 6), np.nan)
        for _ in range(self.max_iterations):
            z = self._moved(dem)
            ge, gn = terrain.gradient(z, dem.transform, dem.crs)
            gi, ni = sampler.values(ge), sampler.values(gn)
            zi = sampler.values(z)
            d = zi - sampler.ref
            norm = np.sqrt(1 + gi**2 + ni**2)
            nx, ny, nz = -gi / norm, -ni / norm, 1 / norm
            px, py, pz = sampler.east, sampler.north, zi - self.z0
            # n·(ω × p + t) = −n·(p − q) ; q − p = (0, 0, −d)
            a = np.column_stack(
                [nx, ny, nz, nz * py - ny * pz, nx * pz - nz * px, ny * px - nx * py]
            )
            y = -nz * d
            p, cov, _ = robust_lstsq(a, y)
            self.t = self.t + p[:3]
            self.w = self.w + p[3:]
            if np.linalg.norm(p[:3]) + np.linalg.norm(p[3:]) * 1e4 < self.tolerance_m:
                break
        sd = np.sqrt(np.diag(cov))
        names = ["tx", "ty", "tz", "omega_e", "omega_n", "omega_u"]
        units = ["m", "m", "m", "rad", "rad", "rad"]
        vals = np.concatenate([self.t, self.w])
        self.params = {k: param(v, s, u) for k, v, s, u in zip(names, vals, sd, units)}
        self.params["sign"] = MOTION
        self.params.update(
            shift_units.ground_shift(
                dem.transform,
                dem.crs,
                dem.shape,
                ("tx", "ty"),
                self.t[:2],
                sd[:2],
                what=f"{dem.path or 'DEM'}: icp",
            )
        )

    def _moved(self, dem):
        """The DEM moved by the current rigid transform, resampled on its grid: a cell at
        (e, n) takes the source point p with R·p + t = (e, n, ·), found with the source
        height taken at the cell itself (one fixed-point step)."""
        e, n = local_metric_coords(dem.transform, dem.crs, dem.shape)
        z = dem.heights.astype(np.float64) - self.z0
        wx, wy, wz = self.w
        # inverse small rotation: p ≈ q − t − ω × (q − t)
        qe, qn, qz = e - self.t[0], n - self.t[1], z - self.t[2]
        se = qe - (wy * qz - wz * qn)
        sn = qn - (wz * qe - wx * qz)
        fx, fy = warp.metres_per_unit(dem.transform, dem.crs, dem.shape)
        x0, y0 = dem.transform @ (dem.shape[1] / 2.0, dem.shape[0] / 2.0)
        c, r = ~dem.transform @ (x0 + se / fx, y0 + sn / fy)
        cols, rows = np.asarray(c) - 0.5, np.asarray(r) - 0.5
        zs = bilinear(dem.heights, rows, cols) - self.z0
        # height of the moved source point: (R p + t)_z = pz + ωx·pn − ωy·pe + tz
        return zs + wx * sn - wy * se + self.t[2] + self.z0

    def _apply(self, dem):
        return self._moved(dem)
