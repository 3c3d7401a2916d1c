"""Co-registration and bias-correction chains of a DEM against a reference (xdem's pattern).

Each step is a :class:`Coreg` with ``fit(ref, dem, stable=...)`` and ``apply(dem)``; steps
compose with ``+`` into a :class:`CoregChain` (or from text with :func:`parse_chain`), which
fits each step on the DEM corrected by the steps before it and records, for every step, its
parameters with standard deviations and the stable-terrain statistics of ``dh = DEM − reference``
before and after it (:meth:`CoregChain.report`).

The reference is either a DEM (any grid/CRS: warped once onto the DEM's grid) or altimetry
points (:class:`~stereodem.post.altimetry.AltimetryPoints`, lon/lat/h[/time]); both are seen by
the steps through a :class:`Sampler`: the stable sample positions on the DEM grid, their local
metric coordinates (east/north metres from the grid centre) and the reference heights there.
Both must share the DEM's vertical reference (see :func:`stereodem.post.assess.reconcile_vertical`).

Frames and units: heights and ``dh`` in metres; ``east``/``north`` in metres of a local
tangent frame at the DEM grid's centre (scale from :func:`stereodem.post.warp.metres_per_unit`);
the track heading in degrees clockwise from north; along-track coordinate
``a = east·sin θ + north·cos θ``, cross-track ``c = east·cos θ − north·sin θ`` (to the right of
the track), or, for a DEM made by stereodem, the curved track of its left sensor model
(:mod:`stereodem.post.track`).

The standard deviations reported are the formal ones of each least-squares fit (the residuals'
NMAD² times the inverse normal matrix) and treat the samples as independent; with spatially
correlated errors they are lower bounds (see :mod:`stereodem.post.spatialstats`).
"""

from __future__ import annotations

import abc
import logging
import time
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from stereodem.core import geodesy
from stereodem.core.blocks import default_threads
from stereodem.core.dem import DEM, as_dem, to_vertical_of
from stereodem.core.errors import DEMError, InputError, NoOverlapError
from stereodem.core.stats import nmad

from . import shift_units, terrain, warp
from .altimetry import AltimetryPoints

log = logging.getLogger(__name__)

#: default largest number of stable samples a step fits on (random, reproducible subset)
MAX_SAMPLES = 200_000
#: least share of the DEM's valid cells that must remain stable terrain
MIN_STABLE_FRACTION = 0.05


# ----------------------------------------------------------------------------- geometry


def local_metric_coords(transform, crs, shape, x=None, y=None):
    """East/north metres from the grid centre of CRS coordinates ``x, y`` (default: every
    cell centre of the grid, arrays of ``shape``): :func:`~stereodem.post.warp.metres_per_unit`'s
    metres, grid metres (the CRS's units) on a projected grid."""
    fx, fy = warp.metres_per_unit(transform, crs, shape)
    x0, y0 = transform @ (shape[1] / 2.0, shape[0] / 2.0)
    if x is None:
        cols = np.arange(shape[1]) + 0.5
        rows = np.arange(shape[0]) + 0.5
        xc = transform.c + transform.a * cols
        yc = transform.f + transform.e * rows
        east = np.broadcast_to(((xc - x0) * fx)[None, :], shape)
        north = np.broadcast_to(((yc - y0) * fy)[:, None], shape)
        return east, north
    return (np.asarray(x, float) - x0) * fx, (np.asarray(y, float) - y0) * fy


def track_coords(east, north, heading_deg: float):
    """Along-track and cross-track metres for a ground track of heading ``heading_deg``
    (degrees clockwise from north)."""
    t = np.radians(heading_deg)
    return east * np.sin(t) + north * np.cos(t), east * np.cos(t) - north * np.sin(t)


def bilinear(grid, rows, cols):
    """Bilinear values of ``grid`` at fractional (row, col) cell-centre indices; NaN outside
    or next to a void."""
    return ndimage.map_coordinates(
        np.asarray(grid, np.float64),
        [rows, cols],
        order=1,
        mode="constant",
        cval=np.nan,
        prefilter=False,
    )


# ----------------------------------------------------------------------------- samples


@dataclass
class Sampler:
    """Stable sample positions on a DEM grid and the reference heights there.

    ``rows, cols`` are cell-centre indices (integers for a DEM reference, fractional for
    points), ``east, north`` metres from the grid centre, ``ref`` the reference heights (m).
    """

    rows: np.ndarray
    cols: np.ndarray
    east: np.ndarray
    north: np.ndarray
    ref: np.ndarray
    shape: tuple
    kind: str = "dem"  #: "dem" or "points"
    n_stable: int = 0  #: stable reference cells/points before subsampling

    def values(self, grid) -> np.ndarray:
        """``grid`` (on the DEM grid) at the sample positions."""
        if self.kind == "dem":
            return np.asarray(grid, np.float64)[self.rows, self.cols]
        return bilinear(grid, self.rows, self.cols)

    def dh(self, heights) -> np.ndarray:
        """DEM − reference at the samples (NaN where the DEM is void)."""
        return self.values(heights) - self.ref

    def stats(self, heights) -> dict:
        """NMAD, median, mean, std and count of ``dh`` at the samples."""
        d = self.dh(heights)
        d = d[np.isfinite(d)]
        if d.size == 0:
            return {
                "n": 0,
                "nmad": float("nan"),
                "median": float("nan"),
                "mean": float("nan"),
                "std": float("nan"),
            }
        return {
            "n": int(d.size),
            "nmad": nmad(d),
            "median": float(np.median(d)),
            "mean": float(np.mean(d)),
            "std": float(np.std(d)),
        }


def reference_on_grid(ref: DEM, dem: DEM, *, resampling: str = "bilinear") -> np.ndarray:
    """The reference heights on ``dem``'s grid (metres, NaN outside); :class:`NoOverlapError`
    when the footprints or their valid cells do not overlap."""
    warp.check_overlap(
        dem.bounds_lonlat(), ref.bounds_lonlat(), dem.path or "DEM", ref.path or "reference"
    )
    same = (
        ref.shape == dem.shape and ref.transform.almost_equals(dem.transform) and ref.crs == dem.crs
    )
    if same:
        z = ref.heights.astype(np.float64)
    else:
        z = warp.to_grid(
            ref.heights,
            ref.transform,
            ref.crs,
            dem.transform,
            dem.crs,
            dem.shape,
            resampling=resampling,
            threads=default_threads(),  # the whole grid at once: on the process's thread budget
        ).astype(np.float64)
    if not (np.isfinite(z) & np.isfinite(dem.heights)).any():
        raise NoOverlapError(
            f"{ref.path or 'reference'}: no valid cell overlaps a valid cell of "
            f"{dem.path or 'the DEM'}"
        )
    return z


def make_sampler(
    ref,
    dem: DEM,
    stable=None,
    *,
    max_samples: int = MAX_SAMPLES,
    seed: int = 0,
    min_stable_fraction: float = MIN_STABLE_FRACTION,
) -> Sampler:
    """The :class:`Sampler` of a reference (DEM or altimetry points) on ``dem``'s grid.

    ``stable``: bool array on the DEM grid (True = stable terrain), or ``None`` (all).
    Raises :class:`InputError` when under ``min_stable_fraction`` of the DEM's valid cells
    (or of the points on the DEM) remain stable, saying how much was left.
    """
    terrain.check_not_rotated(dem.transform, dem.path)  # the fits take its slopes
    if stable is not None:
        stable = np.asarray(stable, bool)
        if stable.shape != dem.shape:
            raise InputError(f"stable mask shape {stable.shape} differs from the DEM's {dem.shape}")
    rng = np.random.default_rng(seed)
    east_g, north_g = None, None
    if isinstance(ref, AltimetryPoints):
        x, y = geodesy.lonlat_to_crs(ref.lon, ref.lat, dem.crs)
        c, r = ~dem.transform @ (np.asarray(x), np.asarray(y))
        cols, rows = np.asarray(c) - 0.5, np.asarray(r) - 0.5
        inside = (rows >= 0) & (cols >= 0) & (rows <= dem.shape[0] - 1) & (cols <= dem.shape[1] - 1)
        if not inside.any():
            raise NoOverlapError(
                f"{ref.path or 'points'}: no point falls on the DEM "
                f"{dem.path or ''} (lon/lat {tuple(round(v, 4) for v in dem.bounds_lonlat())})"
            )
        on_dem = inside & np.isfinite(bilinear(dem.heights, rows, cols))
        if not on_dem.any():
            raise NoOverlapError(f"{ref.path or 'points'}: every point on the DEM falls on a void")
        keep = on_dem.copy()
        if stable is not None:
            keep &= ndimage.map_coordinates(
                stable.astype(np.uint8), [rows, cols], order=0, mode="constant", cval=0
            ).astype(bool)
        _check_fraction(
            int(keep.sum()), int(on_dem.sum()), "points", ref.path, min_stable_fraction, dem.path
        )
        idx = np.flatnonzero(keep)
        if idx.size > max_samples:
            idx = np.sort(rng.choice(idx, max_samples, replace=False))
        e, n = local_metric_coords(dem.transform, dem.crs, dem.shape, x[idx], y[idx])
        return Sampler(
            rows[idx],
            cols[idx],
            e,
            n,
            ref.h[idx].astype(np.float64),
            dem.shape,
            "points",
            int(keep.sum()),
        )
    if not isinstance(ref, DEM):
        raise InputError(f"reference must be a DEM or AltimetryPoints, got {type(ref).__name__}")
    z = reference_on_grid(ref, dem)
    valid = np.isfinite(z) & np.isfinite(dem.heights)
    keep = valid if stable is None else valid & stable
    _check_fraction(
        int(keep.sum()), int(valid.sum()), "cells", ref.path, min_stable_fraction, dem.path
    )
    idx = np.flatnonzero(keep)
    if idx.size > max_samples:
        idx = np.sort(rng.choice(idx, max_samples, replace=False))
    rows, cols = np.unravel_index(idx, dem.shape)
    east_g, north_g = local_metric_coords(dem.transform, dem.crs, dem.shape)
    return Sampler(
        rows,
        cols,
        east_g[rows, cols],
        north_g[rows, cols],
        z[rows, cols],
        dem.shape,
        "dem",
        int(keep.sum()),
    )


#: fewest stable samples a co-registration is fitted on
MIN_STABLE_SAMPLES = 20


def _check_fraction(n_keep, n_valid, what, path, min_fraction, dem_path=None):
    share = n_keep / n_valid if n_valid else 0.0
    if share < min_fraction:
        raise InputError(
            f"{path or 'stable mask'}: only {100 * share:.1f} % of the overlapping {what} "
            f"({n_keep} of {n_valid}) are stable terrain; at least {100 * min_fraction:.0f} % "
            "needed"
        )
    if n_keep < MIN_STABLE_SAMPLES:  # a tiny overlap: the share says nothing
        raise InputError(
            f"{path or 'reference'}: only {n_keep} stable {what} overlap valid cells of "
            f"{dem_path or 'the DEM'} ({n_valid} overlapping in all); at least "
            f"{MIN_STABLE_SAMPLES} needed to co-register"
        )


# ----------------------------------------------------------------------------- robust fitting


def robust_lstsq(a, y, *, n_sigma: float = 3.0, iterations: int = 4):
    """Least squares ``a @ p ≈ y`` with outliers (|r − median| > ``n_sigma`` NMAD) rejected,
    iterated. Returns ``(p, cov, inliers)``; ``cov`` is NMAD² (AᵀA)⁻¹ of the inliers."""
    a = np.asarray(a, np.float64)
    y = np.asarray(y, np.float64)
    ok = np.isfinite(y) & np.all(np.isfinite(a), axis=1)
    if ok.sum() <= a.shape[1]:
        raise InputError(f"only {int(ok.sum())} usable samples for {a.shape[1]} parameters")
    p = np.zeros(a.shape[1])
    for _ in range(iterations):
        p, *_ = np.linalg.lstsq(a[ok], y[ok], rcond=None)
        r = y - a @ p
        s = nmad(r[ok])
        new = np.isfinite(r) & (np.abs(r - np.median(r[ok])) <= max(n_sigma * s, 1e-9))
        new &= np.all(np.isfinite(a), axis=1)
        if new.sum() <= a.shape[1] or np.array_equal(new, ok):
            break
        ok = new
    r = y[ok] - a[ok] @ p
    s = nmad(r)
    cov = s * s * np.linalg.pinv(a[ok].T @ a[ok])
    return p, cov, ok


def param(value, sigma, unit: str = "") -> dict:
    """A reported parameter: value, standard deviation and unit."""
    return {"value": float(value), "sigma": float(sigma), "unit": unit}


def _num(v, digits: int) -> str:
    return f"{v:.{digits}g}" if isinstance(v, (int, float)) and np.isfinite(v) else "–"


def parameter_text(params: dict) -> str:
    """A step's parameters (:meth:`Coreg.parameters`) on one line, for reports and result lines:
    ``name = value ± σ unit`` for every :func:`param`, ``name = value`` for a count, a flag or a
    number (``…_deg`` in degrees); the notes (``sign``, ``coordinates``, ``track``: text) and
    lists are left to :func:`parameter_notes`."""
    out = []
    for k, v in params.items():
        if isinstance(v, dict) and "value" in v:
            sigma = v.get("sigma")
            finite = isinstance(sigma, (int, float)) and np.isfinite(sigma)
            pm = f" ± {_num(sigma, 2)}" if finite else ""
            unit = f" {v['unit']}" if v.get("unit") else ""
            out.append(f"{k} = {_num(v['value'], 4)}{pm}{unit}")
        elif isinstance(v, bool):
            out.append(f"{k} = {'yes' if v else 'no'}")
        elif isinstance(v, (int, float)):
            out.append(f"{k} = {_num(v, 4)}" + (" deg" if k.endswith("_deg") else ""))
    return ", ".join(out)


def parameter_notes(params: dict) -> list[str]:
    """The text notes of a step's parameters (``coordinates``, ``track``; a track frame's
    ``source``), as ``name: text``; the sign conventions (``sign``) are left out: the reports
    say them with the shift."""
    out = []
    for k in ("coordinates", "track", "curvature_unit"):
        v = params.get(k)
        if isinstance(v, dict):
            v = v.get("source")
        if isinstance(v, str) and v:
            out.append(f"{k}: {v}")
    return out


#: a shift step's components (:func:`shift_text`): ``nuth_kaab``'s and ``vshift``'s
#: displacement of the DEM, ``icp``'s motion of the DEM (opposite signs for one offset; the
#: parameters' ``sign`` says the same)
SHIFTS = (
    (("dx", "dy", "dz"), "DEM displaced from the reference by"),
    (("tx", "ty", "tz"), "DEM moved onto the reference by"),
)


def shift_text(params: dict) -> tuple[str, tuple[str, ...]] | None:
    """A step's fitted shift with its sign spelled out, ``"DEM displaced from the reference
    by dx = +1.300 ± 0.012 m along x (grid east), dy = ..., dz = +2.000 ± 0.004 m (up)"`` (the
    horizontal axes in :func:`~stereodem.post.shift_units.shift_phrase`'s wording), and the
    names it states; None for a step without a shift (no ``dz``/``tz``)."""
    for names, what in SHIFTS:
        if not isinstance(params.get(names[2]), dict):
            continue
        said = [n for n in names if isinstance(params.get(n), dict)]
        value = {n: params[n]["value"] for n in said}
        sigma = {n: params[n].get("sigma") for n in said}
        parts = []
        if names[0] in said and names[1] in said:
            parts.append(
                shift_units.shift_phrase(
                    value[names[0]],
                    value[names[1]],
                    "+.3f",
                    sigmas=(sigma[names[0]], sigma[names[1]]),
                    names=names[:2],
                )
            )
        z, sz = value[names[2]], sigma[names[2]]
        pm = f" ± {sz:.3f}" if isinstance(sz, int | float) and np.isfinite(sz) else ""
        parts.append(f"{names[2]} = {z:+.3f}{pm} m (up)")
        return f"{what} {', '.join(parts)}", tuple(said)
    return None


def step_line(record: dict) -> str:
    """The result line of one fitted step, as every command prints it (``coregister``,
    ``assess --coregister/--chain``): a record of :meth:`CoregChain.report` (``step``,
    ``parameters``, the stable samples' ``before``/``after`` statistics) on one line, the
    stable NMAD before -> after the step (the median and the samples after it), then its
    parameters: a shift with its sign (:func:`shift_text`), the others by
    :func:`parameter_text`, and the grid-metres note of a horizontal shift on a projected
    grid (:func:`~stereodem.post.shift_units.shift_units`)."""
    params = record.get("parameters") or {}
    before, after = record.get("before") or {}, record.get("after") or {}
    parts = [
        f"{record['step']}: stable NMAD {_fixed(before.get('nmad'))} -> "
        f"{_fixed(after.get('nmad'))} m (median {_fixed(after.get('median'), '+.3f')} m, "
        f"n={after.get('n', 0)})"
    ]
    shift = shift_text(params)
    said = ()
    if shift is not None:
        text, said = shift
        parts.append(text)
    stated = {*said, *(f"{n}_ground" for n in said)}  # the ground metres: in the note
    rest = parameter_text({k: v for k, v in params.items() if k not in stated})
    if rest:
        parts.append(rest)
    note = shift_units.shift_units(params, said[:2]) if len(said) == 3 else ""
    return "; ".join(parts) + (f".{note}" if note else "")


def _fixed(v, spec: str = ".3f") -> str:
    """``v`` formatted, or "n/a" for a statistic without a value (no sample)."""
    return f"{v:{spec}}" if isinstance(v, int | float) and np.isfinite(v) else "n/a"


# ----------------------------------------------------------------------------- base classes


class Coreg(abc.ABC):
    """One correction step: :meth:`fit` estimates, :meth:`apply` removes (same grid).

    Subclasses implement ``_fit(sampler, dem, context)`` (set ``self.params``: name ->
    :func:`param` dict, and ``self.curves`` for figures) and ``_apply(dem)`` (heights on the
    DEM's grid).
    """

    name = "coreg"

    def __init__(self):
        self.params: dict = {}
        self.curves: dict = {}
        self.fitted = False

    def __add__(self, other) -> CoregChain:
        return CoregChain([self]) + other

    def __repr__(self):
        return f"{type(self).__name__}()"

    def fit(
        self,
        ref,
        dem: DEM,
        stable=None,
        *,
        track_angle_deg: float | None = None,
        track_frame=None,
        max_samples: int = MAX_SAMPLES,
        seed: int = 0,
    ):
        """Fit on ``dem`` against ``ref`` (a :class:`DEM` on any grid, or
        :class:`~stereodem.post.altimetry.AltimetryPoints`), on the ``stable`` cells (bool
        array on the DEM grid): this step alone (a chain of one), or every step of a
        :class:`CoregChain` in turn. ``track_angle_deg``: ground-track heading (degrees clockwise
        from north) for ``along_track``/``cross_track``; ``track_frame``
        (:class:`~stereodem.post.track.TrackFrame`, in the DEM's CRS): the sensor model's
        along/cross-track coordinates, used by those steps instead of the heading's straight
        track. ``ref`` and ``dem`` may also be DEM file paths. A reference in another
        vertical reference than the DEM's is converted to the DEM's
        (:func:`~stereodem.core.dem.to_vertical_of`: a geoid reference for an ellipsoidal
        DEM was compared as it was, the geoid undulation fitted as a shift); one known and
        the other not is a :class:`VerticalReferenceError`. Returns ``self``."""
        dem = as_dem(dem)
        if not isinstance(ref, AltimetryPoints):
            ref = as_dem(ref)
        if ref.vertical != dem.vertical:
            ref, note = to_vertical_of(ref, dem, name="reference")
            log.info("co-registration: %s", note)
        chain = self._as_chain()
        sampler = make_sampler(ref, dem, stable, max_samples=max_samples, seed=seed)
        context = {
            "track_angle_deg": track_angle_deg,
            "track_frame": track_frame,
            "reference": ref,
            "stable": stable,
        }
        chain.fit_samples(sampler, dem, context)
        return self

    def _as_chain(self) -> CoregChain:
        """The chain :meth:`fit` runs: this step alone."""
        return CoregChain([self])

    def fit_samples(self, sampler: Sampler, dem: DEM, context: dict):
        self._fit(sampler, dem, context)
        self.fitted = True
        return self

    def apply(self, dem: DEM) -> DEM:
        """``dem`` (a :class:`DEM` or a DEM file path) with this step's fitted error removed,
        on the same grid, in the same vertical reference (its geoid too: ``geoid_crs``); the
        companion layers are not carried over."""
        if not self.fitted:
            raise DEMError(f"{type(self).__name__}.apply called before fit")
        dem = as_dem(dem)
        return DEM(
            np.asarray(self._apply(dem), np.float32),
            dem.transform,
            dem.crs,
            dem.vertical,
            dem.path,
            geoid_crs=dem.geoid_crs,
        )

    @abc.abstractmethod
    def _fit(self, sampler, dem, context):
        """Estimate this step's parameters on the stable samples (``sampler``) of ``dem``."""

    @abc.abstractmethod
    def _apply(self, dem):
        """The heights of ``dem`` (array on its grid) with the fitted error removed."""

    def parameters(self) -> dict:
        return self.params


class CoregChain(Coreg):
    """Steps applied in order; each is fitted on the DEM corrected by the ones before it."""

    name = "chain"

    def __init__(self, steps=()):
        super().__init__()
        self.steps = list(steps)
        self.records: list[dict] = []
        self.sampler: Sampler | None = None

    def __add__(self, other) -> CoregChain:
        more = other.steps if isinstance(other, CoregChain) else [other]
        return CoregChain(self.steps + list(more))

    def __repr__(self):
        return " + ".join(repr(s) for s in self.steps)

    def _as_chain(self) -> CoregChain:
        if not self.steps:
            raise InputError("empty co-registration chain")
        return self

    def _fit(self, sampler, dem, context):
        """Every step in turn, each fitted on ``dem`` corrected by the ones before it; the
        stable-cell statistics before and after each step go to :meth:`report`."""
        self.sampler = sampler
        self.records = []
        current = dem
        for step in self.steps:
            before = sampler.stats(current.heights)
            t0 = time.perf_counter()
            step.fit_samples(sampler, current, context)
            current = step.apply(current)
            after = sampler.stats(current.heights)
            self.records.append(
                {
                    "step": step.name,
                    "parameters": step.parameters(),
                    "before": before,
                    "after": after,
                    "seconds": time.perf_counter() - t0,
                }
            )
            # the step's result line as the commands print it (one format: step_line); at
            # debug level, since coregister and assess print it themselves (-v said it twice)
            log.debug("%s", step_line(self.records[-1]))
        self.corrected = current

    def apply(self, dem: DEM) -> DEM:
        if not self.fitted:
            raise DEMError("CoregChain.apply called before fit")
        dem = as_dem(dem)
        for step in self.steps:
            dem = step.apply(dem)
        return dem

    def _apply(self, dem):
        return self.apply(dem).heights

    def parameters(self) -> dict:
        return {f"{i}:{s.name}": s.parameters() for i, s in enumerate(self.steps)}

    def report(self) -> list[dict]:
        """One dict per step: ``step``, ``parameters`` (name -> value, sigma, unit), stable
        ``before``/``after`` statistics (nmad, median, mean, std, n) and ``seconds``."""
        return list(self.records)


# ----------------------------------------------------------------------------- parsing


def _registry():
    from . import biascorr

    return {
        "nuth_kaab": biascorr.NuthKaab,
        "vshift": biascorr.VerticalShift,
        "deramp": biascorr.Deramp,
        "along_track": biascorr.AlongTrack,
        "cross_track": biascorr.CrossTrack,
        "curvature": biascorr.Curvature,
        "icp": biascorr.ICP,
    }


STEP_NAMES = ("nuth_kaab", "vshift", "deramp", "along_track", "cross_track", "curvature", "icp")


def parse_chain(text: str) -> CoregChain:
    """A chain from ``"nuth_kaab,deramp:2,along_track"``: step names separated by commas, an
    optional ``:N`` giving the polynomial order (``deramp``, ``cross_track``, ``curvature``) or
    the number of sines (``along_track``)."""
    reg = _registry()
    steps = []
    for item in str(text).split(","):
        item = item.strip()
        if not item:
            continue
        name, _, arg = item.partition(":")
        name = name.strip().lower()
        if name not in reg:
            raise InputError(
                f"unknown co-registration step {name!r} in {text!r}; "
                f"choose from {', '.join(STEP_NAMES)}"
            )
        if arg:
            try:
                n = int(arg)
            except ValueError:
                raise InputError(f"step {item!r}: expected an integer after ':'") from None
            steps.append(reg[name].from_arg(n))
        else:
            steps.append(reg[name]())
    if not steps:
        raise InputError(f"empty co-registration chain {text!r}")
    return CoregChain(steps)


def __getattr__(name):  # the steps live in biascorr (one job per module)
    if name in (
        "NuthKaab",
        "VerticalShift",
        "Deramp",
        "AlongTrack",
        "CrossTrack",
        "Curvature",
        "ICP",
    ):
        from . import biascorr

        return getattr(biascorr, name)
    if name == "StableMask":
        from .masks import StableMask

        return StableMask
    if name == "AltimetryPoints":
        from .altimetry import AltimetryPoints

        return AltimetryPoints
    raise AttributeError(name)
