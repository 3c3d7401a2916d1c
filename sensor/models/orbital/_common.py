"""What the orbital models share: the normalised line variable, quadratic polynomials in it,
virtual control points from a metadata model, the initial fit to them, and the Newton inverse
of a ground -> image mapping.

Time variable: every polynomial of the package is written in the centred and scaled line
``tau = (row - r_c) / s`` with ``r_c = s = (height - 1) / 2``, so ``tau`` runs over [-1, 1]
across the image (Topan 2009 notes §3.4: "centre and scale the polynomial variable"). A
coefficient ``P_1`` is therefore the change of ``P`` from the centre line to the last line,
in the unit of ``P``.
"""

from __future__ import annotations

import copy

import numpy as np
from scipy.optimize import least_squares

from stereodem.core import geodesy
from stereodem.core.errors import ConvergenceError, InputError, SensorModelError
from stereodem.sensor.models.parameters import checked_parameters


class CoefficientModel:
    """Mixin of the orbital models: coefficients in the dict ``self._c`` (every coefficient the
    model has, by name), validity heights in ``self._hr``.

    Gives ``with_parameters`` (a copy with some coefficients changed), ``_set`` (checked by
    :func:`~stereodem.sensor.models.parameters.checked_parameters`; the error lists
    :meth:`_parameter_listing`), ``height_bounds`` and the plain description ``to_dict`` /
    ``from_dict`` (for :mod:`stereodem.sensor.io.sidecar`): image size (pixels), the
    :attr:`DICT_FIELDS`, the model's own entries (:meth:`_dict_entries`), name and validity
    heights (metres above the ellipsoid).
    """

    #: Constructor arguments kept as attributes of the same name, written as they are.
    DICT_FIELDS: tuple = ()

    def _dict_entries(self) -> dict:
        """Hook: the description's entries after :attr:`DICT_FIELDS` (coefficients, tables)."""
        return {}

    @classmethod
    def _entries_from_dict(cls, d: dict) -> dict:
        """Hook: constructor arguments from the entries of :meth:`_dict_entries`."""
        return {}

    def to_dict(self) -> dict:
        """Plain description, for :mod:`stereodem.sensor.io.sidecar`."""
        return {
            "width": self.width,
            "height": self.height,
            **{k: getattr(self, k) for k in self.DICT_FIELDS},
            **self._dict_entries(),
            "name": self.name,
            "height_range": list(self._hr),
        }

    @classmethod
    def from_dict(cls, d: dict):
        """Inverse of :meth:`to_dict`."""
        return cls(
            width=d["width"],
            height=d["height"],
            **{k: d[k] for k in cls.DICT_FIELDS},
            **cls._entries_from_dict(d),
            name=d.get("name"),
            height_range=tuple(d.get("height_range", (-500.0, 9000.0))),
        )

    def with_parameters(self, **values):
        new = copy.copy(self)
        new._c = dict(self._c)
        new._set(values)
        return new

    def _set(self, values):
        self._c.update(
            checked_parameters(self._c, values, self.name, listing=self._parameter_listing())
        )

    def _parameter_listing(self) -> str | None:
        """How an unknown-parameter error lists the accepted names (None: all of ``_c``)."""
        return None

    def height_bounds(self):
        return self._hr


def line_variable(row, height: int):
    """Normalised line ``tau`` in [-1, 1] of (fractional) image rows."""
    half = 0.5 * (int(height) - 1) or 1.0
    return (np.asarray(row, float) - half) / half


def quadratic(c0, c1, c2, tau):
    """``c0 + c1 tau + c2 tau^2`` (broadcast)."""
    return c0 + tau * (c1 + tau * c2)


def secant_rows(f, n: int, height: int, *, max_iterations: int = 30):
    """Image rows where ``f(row)[0] == 0``, by secant steps started at the first and last line.

    Parameters
    ----------
    f : callable
        ``f(rows) -> (residual, *extras)``: the misfit of each of ``n`` ground points at
        (fractional) ``rows``, shape (n,), and any by-products wanted at the solution.
    n : int
        Number of points.
    height : int
        Image height (rows); steps are clipped to ten image heights.
    max_iterations : int
        At most this many secant steps (stops earlier once every step is below 1e-9 rows).

    Returns
    -------
    row : ndarray (n,)
        The last iterate.
    out : tuple
        ``f(row)`` at that iterate.
    """
    r0 = np.zeros(n)
    r1 = np.full(n, height - 1.0)
    f0 = f(r0)[0]
    out = f(r1)
    for _ in range(max_iterations):
        f1 = out[0]
        den = f1 - f0
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(den != 0, -f1 * (r1 - r0) / den, 0.0)
        step = np.clip(np.nan_to_num(step), -10.0 * height, 10.0 * height)
        r0, f0 = r1, f1
        r1 = r1 + step
        out = f(r1)
        if np.all(np.abs(step) < 1e-9):
            break
    return r1, out


def virtual_points(reference, *, n: int = 9, heights=(-200.0, 1000.0, 3000.0)):
    """Ground points seen by ``reference`` on an ``n x n`` image grid at several heights.

    Returns ``(lon, lat, h, col, row)`` (degrees, metres above the ellipsoid, pixels): the
    metadata model's own image -> ground mapping, used to give a parametric model its initial
    values (the way an RPC is fitted to a physical model).
    """
    w, hgt = reference.width, reference.height
    c, r, z = np.meshgrid(
        np.linspace(0, w - 1, n),
        np.linspace(0, hgt - 1, n),
        np.asarray(heights, float),
        indexing="ij",
    )
    c, r, z = c.ravel(), r.ravel(), z.ravel()
    lon, lat = reference.localize(c, r, z)
    ok = np.isfinite(lon) & np.isfinite(lat)
    if ok.sum() < 12:
        raise SensorModelError(
            f"{type(reference).__name__}: too few pixels see the Earth to "
            "initialise an orbital model"
        )
    return lon[ok], lat[ok], z[ok], c[ok], r[ok]


#: Levenberg-Marquardt runs of :func:`fit_to_points` at most, each from the last's solution
LM_RESTARTS = 5


def fit_to_points(model, names, lon, lat, h, col, row, *, what: str):
    """Initial values: the named parameters of ``model`` fitted (Levenberg-Marquardt, scaled
    by the model's ``PARAMETER_STEPS``) to image coordinates of virtual points.

    Returns ``(model, rms_px)``; this is model construction from metadata (no weights, no
    statistics), not the GCP adjustment, which is the adjustment engine's job.
    """
    base = model.coefficients() if hasattr(model, "coefficients") else model.parameters()
    steps = np.array([model.PARAMETER_STEPS.get(n, 1e-6) for n in names], float)
    x0 = np.array([base[n] for n in names], float)

    def resid(u):
        m = model.with_parameters(**dict(zip(names, x0 + u * steps)))
        pc, pr = m.project(lon, lat, h)
        r = np.concatenate([pc - col, pr - row])
        return np.where(np.isfinite(r), r, 1e6)

    u = np.zeros(len(names))
    cost, best = np.inf, None
    # scaled by the Jacobian's columns and restarted from its own solution while that lowers
    # the cost: on these badly conditioned fits (15 values and a tilt) MINPACK's LM with unit
    # scales stopped short of the minimum, at a point that depended on SciPy's version (the Toutin
    # model's fit to the simulated ASTER scene: 0.045 px with SciPy 1.10, 0.035 px with 1.16;
    # 0.0349 px with both now)
    for _ in range(LM_RESTARTS):
        sol = least_squares(
            resid,
            u,
            method="lm",
            x_scale="jac",
            xtol=1e-12,
            ftol=1e-12,
            max_nfev=200 * (len(names) + 1),
        )
        better = sol.cost < cost * (1.0 - 1e-6)
        if best is None or sol.cost <= cost:
            u, cost, best = sol.x, sol.cost, sol
        if not better:
            break
    sol = best
    fitted = model.with_parameters(**dict(zip(names, x0 + sol.x * steps)))
    rms = float(np.sqrt(np.mean(sol.fun**2)))
    if not np.isfinite(rms) or rms > 50.0:
        raise ConvergenceError(
            f"{what}: the initial fit to the metadata model failed (rms {rms:.3g} px)"
        )
    return fitted, rms


def fit_to_reference(model, reference, *name_sets):
    """``model``'s initial values fitted (:func:`fit_to_points`) to the virtual points of the
    metadata model ``reference`` (:func:`virtual_points`), one fit per list of parameter names in
    ``name_sets``, each started from the last; the last fit's RMS (pixels) is kept in the
    returned model's ``init_rms_px``."""
    pts = virtual_points(reference)
    for names in name_sets:
        model, rms = fit_to_points(model, names, *pts, what=model.name)
    model.init_rms_px = rms
    return model


def invert_projection(
    model,
    col,
    row,
    h,
    *,
    lon0: float,
    lat0: float,
    iterations: int = 20,
    tolerance_px: float = 1e-7,
):
    """``(lon, lat)`` such that ``model.project(lon, lat, h) == (col, row)``, by Newton steps
    in a local east/north frame (metres) with a finite-difference Jacobian; vectorised.

    NaN where the iteration does not converge.
    """
    col, row, h = np.broadcast_arrays(
        np.asarray(col, float), np.asarray(row, float), np.asarray(h, float)
    )
    shape = col.shape
    c, r, hh = col.ravel(), row.ravel(), h.ravel()
    e = np.zeros(c.size)
    n = np.zeros(c.size)

    def proj(e_, n_):
        x, y, z = geodesy.enu_to_ecef(e_, n_, hh * 0.0, lon0, lat0, 0.0)
        lo, la, _ = geodesy.ecef_to_geodetic(x, y, z)
        pc, pr = model.project(np.asarray(lo, float), np.asarray(la, float), hh)
        return np.asarray(pc, float), np.asarray(pr, float), lo, la

    step = 10.0
    done = np.zeros(c.size, bool)
    for _ in range(iterations):
        pc, pr, lo, la = proj(e, n)
        fc, fr = pc - c, pr - r
        done = np.abs(fc) + np.abs(fr) < tolerance_px
        if done.all():
            break
        ce, re_, _, _ = proj(e + step, n)
        cn, rn, _, _ = proj(e, n + step)
        a, b = (ce - pc) / step, (cn - pc) / step
        cc, d = (re_ - pr) / step, (rn - pr) / step
        det = a * d - b * cc
        with np.errstate(divide="ignore", invalid="ignore"):
            de = (d * fc - b * fr) / det
            dn = (-cc * fc + a * fr) / det
        e = e - np.nan_to_num(de)
        n = n - np.nan_to_num(dn)
    pc, pr, lo, la = proj(e, n)
    ok = np.isfinite(pc) & (np.abs(pc - c) + np.abs(pr - r) < 1e-3)
    lo = np.where(ok, lo, np.nan)
    la = np.where(ok, la, np.nan)
    return np.asarray(lo, float).reshape(shape), np.asarray(la, float).reshape(shape)


def require_gcps(n_gcp: int, names, what: str, *, n_prior: int = 0) -> None:
    """Raise :class:`~stereodem.core.errors.InputError` when ``n_gcp`` GCPs (two
    observations each) cannot determine the parameters ``names`` with one redundant
    observation (so that sigma0 exists; the adjustment engine's rule, in which each of
    ``n_prior`` weighted parameters counts as one observation)."""
    from stereodem.sensor.estimation.adjust.single import required_gcps

    u = len(list(names))
    need = required_gcps(u, n_prior)
    if n_gcp < need:
        weighted = f" ({n_prior} of them weighted)" if n_prior else ""
        raise InputError(
            f"{what}: {n_gcp} GCP(s) cannot determine its {u} "
            f"parameters{weighted}; at least {need} are needed"
        )


def require_inside(
    model, col, row, *, what: str = "check points", source: str = "", image: str = ""
) -> None:
    """Raise :class:`~stereodem.core.errors.InputError` when image points fall outside the
    image (pixel centres from -0.5 to width - 0.5); ``source`` names the points' file and
    ``image`` the image, for the message."""
    col, row = np.asarray(col, float), np.asarray(row, float)
    out = ~(
        (col >= -0.5) & (col <= model.width - 0.5) & (row >= -0.5) & (row <= model.height - 0.5)
    )
    if np.any(out):
        where = f"{source}: " if source else ""
        raise InputError(
            f"{where}{int(out.sum())} of {col.size} {what} lie outside the "
            f"{model.width} x {model.height} image{f' {image}' if image else ''}"
        )
