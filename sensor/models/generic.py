"""Generic (non-rigorous) sensor models fitted to ground control points.

The twelve-model orthorectification comparison of Ok (2005, Ch. 3.1.3 and Ch. 6) without its
two rigorous models: 2-D and 3-D polynomials, polynomials with relief (Pala & Pons 1995 and
Ok's 2nd-order extension), the 8-parameter projective transformation and its pushbroom variant
(Novak 1992), the DLT and the extended DLT (Okamoto et al. 1999), and terrain-dependent rational
functions of order 1–3 with separate denominators (Tao & Hu 2001).

Frames and normalisation
------------------------
Ok fitted in projected map coordinates (UTM E, N and height H). Here every model maps the
ground point ``(X, Y, Z) = (E, N, h)`` — easting and northing in a projected CRS (by default the
UTM zone of the GCPs, :func:`stereodem.core.geodesy.utm_crs`) and the ellipsoidal height — to the
image ``(col, row)``, but always through normalised coordinates: each ground axis is centred
and scaled into [-1, 1] over the GCPs (RPC-style offset/scale), and so is each image axis
(the extended DLT scales the image coordinates without centring them, see below). Centring and
scaling removes the ill-conditioning that made Ok drop the ``Y^2`` term of the 3rd-order 2-D
polynomial (its Table 6.5 correlations are those of raw UTM coordinates); all ten terms are
kept. The public interface stays ``project(lon, lat, h) -> (col, row)`` and
``localize(col, row, h) -> (lon, lat)`` (:class:`stereodem.sensor.models.base.SensorModel`).

Term sets (``X, Y, Z`` normalised; one equation each for ``x = col`` and ``y = row``)
------------------------------------------------------------------------------------
========================  ==================================================================
``poly2d-1/2/3``          all monomials ``X^i Y^j`` with ``i + j <= k`` (3 / 6 / 10 terms)
``poly3d-1/2/3``          all monomials ``X^i Y^j Z^l``, ``i + j + l <= k`` (4 / 10 / 20)
``relief-1``              ``1, X, Y, Z, XZ, YZ`` (Pala & Pons 1995)
``relief-2``              ``(1, X, Y, X^2, Y^2, XY) x (1, Z)`` (Ok 2005, 12 terms)
``projective``            ``x = (a1 X + a2 Y + a3) / (c1 X + c2 Y + 1)``, ``y`` likewise (8)
``projective-pushbroom``  ``x`` as above, ``y = b1 X + b2 Y + b3`` (Novak 1992; y along track)
``dlt``                   ``x = (L1 X + L2 Y + L3 Z + L4) / (L9 X + L10 Y + L11 Z + 1)`` (11)
``edlt``                  DLT ``+ a12 x y`` in ``x`` and ``+ a13 y^2`` in ``y`` (13)
``rational-1/2/3``        ``x = P1 / P2``, ``y = P3 / P4``, ``P`` cubic-ordered 3-D
                          polynomials of order k, denominator constants fixed to 1 (14/38/78)
========================  ==================================================================

Estimation
----------
Polynomials: linear least squares. Projective, DLT, extended DLT: the linear (algebraic)
solution obtained by multiplying through by the denominator, refined by Gauss–Newton
(Levenberg–Marquardt) on the image residuals, i.e. the iterated least squares of Ok's App. B
(the algebraic solution alone shifts error between x and y; Ok's DLT y residuals suggest that
is what happened there). Rational functions: linearised by the denominator and solved with
Tikhonov regularisation, the weight chosen from the GCPs alone by generalised cross-validation
or the L-curve (:mod:`stereodem.sensor.estimation.regularize`) — not by minimising the check-point
error as Ok did — and re-solved with rows reweighted by the previous denominator (Tao & Hu 2001) so
that the minimised quantity approaches the image residual.

GCP files
---------
Read and written by :mod:`stereodem.sensor.io.gcps` (``ControlPoints``, ``read_gcps``,
``write_gcps``); ``ControlPoints.arrays()`` gives the arrays :func:`fit_model` takes.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from pyproj import CRS
from scipy.optimize import least_squares

from stereodem.core import geodesy
from stereodem.core.errors import CRSError, InputError
from stereodem.sensor.choices import GENERIC_MODEL_NAMES
from stereodem.sensor.estimation import regularize
from stereodem.sensor.models.base import SensorModel, broadcast_coordinates

log = logging.getLogger(__name__)

__all__ = ["MODEL_NAMES", "GenericModel", "FitReport", "fit_model", "minimum_gcps", "n_parameters"]


# ---------------------------------------------------------------------------- term sets
def _poly_exponents(order: int, dims: int):
    """Exponents (n_terms, 3) of all monomials of total degree <= order, in the cubic RPC order.

    For 3-D and order 3 the order is Ok's (and Tao & Hu's): 1, X, Y, Z, X^2, Y^2, Z^2, XY, XZ,
    YZ, X^3, Y^3, Z^3, X^2Y, X^2Z, Y^2X, Y^2Z, Z^2X, Z^2Y, XYZ; lower orders and 2-D sets are
    prefixes / subsets of it.
    """
    full = [
        (0, 0, 0),
        (1, 0, 0),
        (0, 1, 0),
        (0, 0, 1),
        (2, 0, 0),
        (0, 2, 0),
        (0, 0, 2),
        (1, 1, 0),
        (1, 0, 1),
        (0, 1, 1),
        (3, 0, 0),
        (0, 3, 0),
        (0, 0, 3),
        (2, 1, 0),
        (2, 0, 1),
        (1, 2, 0),
        (0, 2, 1),
        (1, 0, 2),
        (0, 1, 2),
        (1, 1, 1),
    ]
    out = [e for e in full if sum(e) <= order and (dims == 3 or e[2] == 0)]
    return np.array(out, dtype=np.int64).reshape(-1, 3)


_RELIEF = {
    1: [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (0, 1, 1)],
    2: [
        (0, 0, 0),
        (1, 0, 0),
        (0, 1, 0),
        (2, 0, 0),
        (0, 2, 0),
        (1, 1, 0),
        (0, 0, 1),
        (1, 0, 1),
        (0, 1, 1),
        (2, 0, 1),
        (0, 2, 1),
        (1, 1, 1),
    ],
}


def _terms(exps: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Monomials of normalised ground points ``G`` (n, 3) -> (n, n_terms)."""
    if exps.shape[0] == 0:
        return np.zeros(G.shape[:-1] + (0,))
    out = np.ones(G.shape[:-1] + (exps.shape[0],))
    for axis in range(3):
        p = exps[:, axis]
        if np.any(p):
            out = out * G[..., axis : axis + 1] ** p
    return out


# ---------------------------------------------------------------------------- model forms
@dataclass(frozen=True)
class _Solution:
    params: np.ndarray
    condition_number: float
    condition_number_regularized: float
    method: str | None = None
    weight: float | None = None


class _PolyForm:
    """Separate linear polynomials for x and y sharing one term set."""

    centre_image = True
    regularizable = False

    def __init__(self, exps):
        self.exps = np.asarray(exps, dtype=np.int64)
        self.n_params = 2 * self.exps.shape[0]
        self.min_gcps = self.exps.shape[0]

    def evaluate(self, p, G):
        T = _terms(self.exps, G)
        k = self.exps.shape[0]
        return T @ p[:k], T @ p[k:]

    def fit(self, G, x, y, regularization, reweight_iterations=0):
        T = _terms(self.exps, G)
        sol, *_ = np.linalg.lstsq(T, np.stack([x, y], -1), rcond=None)
        c = regularize.condition_number(T)
        return _Solution(np.concatenate([sol[:, 0], sol[:, 1]]), c, c)


class _RationalForm:
    """``x = Nx / (1 + Dx)``, ``y = Ny / (1 + Dy)`` with linear term sets.

    ``shared`` ties the two denominators (projective, DLT); ``extended`` adds Okamoto's
    ``a12 x y`` and ``a13 y^2``; ``regularizable`` selects the Tikhonov-regularised linearised
    solution (rational functions) instead of the algebraic + Gauss–Newton one.
    """

    def __init__(self, nx, dx, ny, dy, *, shared=False, extended=False, regularizable=False):
        self.nx, self.dx = (
            np.asarray(nx, np.int64).reshape(-1, 3),
            np.asarray(dx, np.int64).reshape(-1, 3),
        )
        self.ny, self.dy = (
            np.asarray(ny, np.int64).reshape(-1, 3),
            np.asarray(dy, np.int64).reshape(-1, 3),
        )
        self.shared = shared
        self.extended = extended
        self.regularizable = regularizable
        self.centre_image = not extended
        kx, ky = len(self.nx), len(self.ny)
        if shared:
            self.n_params = kx + ky + len(self.dx) + 2 * extended
            self.min_gcps = math.ceil(self.n_params / 2)
        else:
            self.n_params = kx + len(self.dx) + ky + len(self.dy)
            self.min_gcps = max(kx + len(self.dx), ky + len(self.dy))

    # parameter layout: [ax, (cx), ay, (cy)] or, shared, [ax, ay, c, (a12, a13)]
    def _split(self, p):
        kx, ky, jx = len(self.nx), len(self.ny), len(self.dx)
        if self.shared:
            ax, ay, c = p[:kx], p[kx : kx + ky], p[kx + ky : kx + ky + jx]
            ext = p[kx + ky + jx :]
            return ax, c, ay, c, ext
        return p[:kx], p[kx : kx + jx], p[kx + jx : kx + jx + ky], p[kx + jx + ky :], p[:0]

    def evaluate(self, p, G):
        ax, cx, ay, cy, ext = self._split(p)
        Dx = 1.0 + _terms(self.dx, G) @ cx
        Dy = Dx if self.shared else 1.0 + _terms(self.dy, G) @ cy
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (_terms(self.nx, G) @ ax) / Dx
            v = (_terms(self.ny, G) @ ay) / Dy
            if not self.extended:
                return u, v
            a12, a13 = ext
            # y = v + a13 y^2 -> the root that tends to v as a13 -> 0; x = u + a12 x y
            y = 2.0 * v / (1.0 + np.sqrt(1.0 - 4.0 * a13 * v))
            return u / (1.0 - a12 * y), y

    def _linear_system(self, G, x, y):
        """Equations obtained by multiplying through by the denominator(s), and their RHS."""
        Tnx, Tdx, Tny, Tdy = (_terms(e, G) for e in (self.nx, self.dx, self.ny, self.dy))
        n = G.shape[0]
        zx, zy = np.zeros((n, Tny.shape[1])), np.zeros((n, Tnx.shape[1]))
        if self.shared:
            rows_x = [Tnx, zx, -x[:, None] * Tdx]
            rows_y = [zy, Tny, -y[:, None] * Tdx]
            return np.block([rows_x, rows_y]), np.concatenate([x, y]), (Tdx, Tdx)
        Ax = np.hstack([Tnx, -x[:, None] * Tdx])
        Ay = np.hstack([Tny, -y[:, None] * Tdy])
        return (Ax, Ay), (x, y), (Tdx, Tdy)

    def fit(self, G, x, y, regularization, reweight_iterations=0):
        if self.regularizable:
            return self._fit_regularized(G, x, y, regularization, reweight_iterations)
        A, b, _ = self._linear_system(G, x, y)
        if isinstance(A, tuple):
            A = np.block(
                [
                    [A[0], np.zeros((A[0].shape[0], A[1].shape[1]))],
                    [np.zeros((A[1].shape[0], A[0].shape[1])), A[1]],
                ]
            )
            b = np.concatenate(b)
        p0, *_ = np.linalg.lstsq(A, b, rcond=None)
        if self.extended:  # start from the refined DLT with a12 = a13 = 0
            p0 = np.concatenate([_FORMS["dlt"].fit(G, x, y, None).params, [0.0, 0.0]])
        obs = np.concatenate([x, y])

        def resid(p):
            u, v = self.evaluate(p, G)
            r = np.concatenate([u, v]) - obs
            return np.where(np.isfinite(r), r, 1e6)

        res = least_squares(
            resid,
            p0,
            method="lm",
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
            max_nfev=200 * (self.n_params + 1),
        )
        p = res.x if res.cost <= 0.5 * float(np.sum(resid(p0) ** 2)) else p0
        J = res.jac if p is res.x else _numeric_jacobian(resid, p)
        c = regularize.condition_number(J)
        return _Solution(p, c, c)

    def _fit_regularized(self, G, x, y, regularization, reweight_iterations=0):
        (Ax, Ay), (bx, by), (Tdx, Tdy) = self._linear_system(G, x, y)
        wx = np.ones_like(bx)
        wy = np.ones_like(by)
        for it in range(reweight_iterations + 1):
            A = np.block(
                [
                    [wx[:, None] * Ax, np.zeros((Ax.shape[0], Ay.shape[1]))],
                    [np.zeros((Ay.shape[0], Ax.shape[1])), wy[:, None] * Ay],
                ]
            )
            b = np.concatenate([wx * bx, wy * by])
            sv = regularize.SVDSystem.of(A, b)
            method, lam = _choose_weight(regularization, A, b, sv)
            p = sv.solve(lam)
            _, cx, _, cy, _ = self._split(p)
            Dx, Dy = 1.0 + Tdx @ cx, 1.0 + Tdy @ cy
            if it == reweight_iterations or not (
                np.all(np.abs(Dx) > 1e-3) and np.all(np.abs(Dy) > 1e-3)
            ):
                break
            wx, wy = 1.0 / np.abs(Dx), 1.0 / np.abs(Dy)
        return _Solution(
            p,
            regularize.condition_number(A),
            regularize.condition_number(A, lam),
            method,
            lam if method is not None else None,
        )


def _numeric_jacobian(fun, p, step=1e-7):
    f0 = fun(p)
    J = np.empty((f0.size, p.size))
    for i in range(p.size):  # loop over a handful of parameters
        q = p.copy()
        q[i] += step
        J[:, i] = (fun(q) - f0) / step
    return J


def _choose_weight(regularization, A, b, sv):
    if regularization is None:
        return None, 0.0
    if isinstance(regularization, str):
        key = regularization.lower()
        if key == "gcv":
            return "gcv", regularize.gcv_weight(A, b, svd=sv)
        if key in ("lcurve", "l-curve"):
            return "lcurve", regularize.lcurve_weight(A, b, svd=sv)
        raise InputError(
            f"unknown regularization {regularization!r} "
            "(expected 'gcv', 'lcurve', None or a weight)"
        )
    lam = float(regularization)
    if not np.isfinite(lam) or lam < 0:
        raise InputError(f"regularization weight must be finite and >= 0, got {regularization!r}")
    return "fixed", lam


def _make_forms():
    forms = {}
    for k in (1, 2, 3):
        forms[f"poly2d-{k}"] = _PolyForm(_poly_exponents(k, 2))
    for k in (1, 2, 3):
        forms[f"poly3d-{k}"] = _PolyForm(_poly_exponents(k, 3))
    for k in (1, 2):
        forms[f"relief-{k}"] = _PolyForm(_RELIEF[k])
    lin2 = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
    den2 = [(1, 0, 0), (0, 1, 0)]
    lin3 = _poly_exponents(1, 3)
    den3 = lin3[1:]
    forms["projective"] = _RationalForm(lin2, den2, lin2, den2, shared=True)
    forms["projective-pushbroom"] = _RationalForm(lin2, den2, lin2, [])
    forms["dlt"] = _RationalForm(lin3, den3, lin3, den3, shared=True)
    forms["edlt"] = _RationalForm(lin3, den3, lin3, den3, shared=True, extended=True)
    for k in (1, 2, 3):
        e = _poly_exponents(k, 3)
        forms[f"rational-{k}"] = _RationalForm(e, e[1:], e, e[1:], regularizable=True)
    return forms


_FORMS = _make_forms()
#: Names of the fitted models, as exposed on the command line: the light module's tuple (the
#: parser imports it), checked equal to the forms' names by tests/app/test_choices.py.
MODEL_NAMES = GENERIC_MODEL_NAMES


def _form(name):
    try:
        return _FORMS[name]
    except KeyError:
        raise InputError(
            f"unknown generic model {name!r}; choose one of {', '.join(MODEL_NAMES)}"
        ) from None


def minimum_gcps(name: str) -> int:
    """Minimum number of GCPs for model ``name`` (unknowns of the larger equation system).

    Corrects Ok's Table 3.2, which double-counts the shared projective/DLT unknowns and
    ignores the fixed denominator constants: projective 4, DLT 6, extended DLT 7, rational
    functions 7 / 19 / 39.
    """
    return _form(name).min_gcps


def n_parameters(name: str) -> int:
    """Number of estimated coefficients of model ``name`` (both image coordinates)."""
    return _form(name).n_params


# ---------------------------------------------------------------------------- the model
@dataclass(frozen=True)
class _Normalization:
    ground_offset: np.ndarray  # (3,) E, N (m), h (m)
    ground_scale: np.ndarray  # (3,)
    image_offset: np.ndarray  # (2,) col, row (px)
    image_scale: np.ndarray  # (2,)


class GenericModel(SensorModel):
    """A generic model fitted to GCPs; see the module docstring for the forms.

    Built by :func:`fit_model`. Implements the :class:`stereodem.sensor.models.base.SensorModel`
    contract: ``project(lon, lat, h) -> (col, row)`` (degrees, ellipsoidal metres -> pixels) and
    ``localize(col, row, h) -> (lon, lat)`` by Newton iteration on ``project`` in the map plane.

    Attributes
    ----------
    name : str
        Model name (one of :data:`MODEL_NAMES`).
    params : ndarray
        Coefficients, in normalised coordinates.
    crs : pyproj.CRS
        Projected CRS of the ground frame (easting, northing in metres).
    width, height : int
        Image size in pixels.
    """

    def __init__(
        self,
        name,
        params,
        *,
        crs,
        normalization: _Normalization,
        width,
        height,
        h_range,
        inverse_affine,
    ):
        self.name = name
        self._form = _form(name)
        self.params = np.asarray(params, dtype=np.float64)
        self.crs = crs
        self.norm = normalization
        self.width, self.height = int(width), int(height)
        self.h_range = (float(h_range[0]), float(h_range[1]))
        self._inverse = np.asarray(inverse_affine, dtype=np.float64)  # (4, 2): [1, x, y, Z] -> X, Y

    # ------------------------------------------------------------ normalised evaluation
    def _ground(self, lon, lat, h):
        E, N = geodesy.lonlat_to_crs(lon, lat, self.crs)
        G = np.stack([np.asarray(E, float), np.asarray(N, float), np.asarray(h, float)], -1)
        return (G - self.norm.ground_offset) / self.norm.ground_scale

    def _eval_norm(self, G):
        return self._form.evaluate(self.params, G)

    def _to_pixels(self, xn, yn):
        return (
            xn * self.norm.image_scale[0] + self.norm.image_offset[0],
            yn * self.norm.image_scale[1] + self.norm.image_offset[1],
        )

    # ------------------------------------------------------------ contract
    def project(self, lon, lat, h):
        """Ground ``(lon, lat)`` in degrees and ellipsoidal height ``h`` (m) to ``(col, row)`` px.

        Non-finite inputs give NaN.
        """
        lon, lat, h = broadcast_coordinates(self, lon, lat, h, what="ground coordinates")
        ok = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h)
        col = np.full(lon.shape, np.nan)
        row = np.full(lon.shape, np.nan)
        if np.any(ok):
            G = self._ground(lon[ok], lat[ok], h[ok])
            c, r = self._to_pixels(*self._eval_norm(G))
            col[ok], row[ok] = c, r
        return col, row

    def localize(self, col, row, h, *, tolerance: float = 1e-6, max_iterations: int = 30):
        """Image ``(col, row)`` at ellipsoidal height ``h`` (m) to ``(lon, lat)`` in degrees.

        Newton iteration on the model function in the normalised map plane (``h`` fixed),
        started from an affine inverse fitted to the GCPs, with a finite-difference 2x2
        Jacobian, until the image residual is below ``tolerance`` pixels. Points that do not
        converge (outside the model's domain) are NaN.
        """
        col, row, h = broadcast_coordinates(self, col, row, h, what="image coordinates or heights")
        shape = col.shape
        c, r, hh = col.ravel(), row.ravel(), h.ravel()
        xn = (c - self.norm.image_offset[0]) / self.norm.image_scale[0]
        yn = (r - self.norm.image_offset[1]) / self.norm.image_scale[1]
        Z = (hh - self.norm.ground_offset[2]) / self.norm.ground_scale[2]
        XY = np.stack([np.ones_like(xn), xn, yn, Z], -1) @ self._inverse
        ok = np.isfinite(XY).all(-1)
        done = np.zeros(c.shape, dtype=bool)
        isx, isy = self.norm.image_scale
        step = 1e-6
        active = np.flatnonzero(ok)
        for _ in range(max_iterations):
            if active.size == 0:
                break
            G = np.stack([XY[active, 0], XY[active, 1], Z[active]], -1)
            fx, fy = self._eval_norm(G)
            ex, ey = (fx - xn[active]) * isx, (fy - yn[active]) * isy  # pixels
            conv = np.hypot(ex, ey) < tolerance * 1e-2
            Gx, Gy = G.copy(), G.copy()
            Gx[:, 0] += step
            Gy[:, 1] += step
            fxx, fyx = self._eval_norm(Gx)
            fxy, fyy = self._eval_norm(Gy)
            a, b = (fxx - fx) / step * isx, (fxy - fx) / step * isx
            cc, d = (fyx - fy) / step * isy, (fyy - fy) / step * isy
            det = a * d - b * cc
            with np.errstate(divide="ignore", invalid="ignore"):
                dX = (d * ex - b * ey) / det
                dY = (a * ey - cc * ex) / det
            bad = ~(np.isfinite(dX) & np.isfinite(dY)) | ~np.isfinite(ex)
            done[active[conv]] = True
            move = ~conv & ~bad
            XY[active[move], 0] -= dX[move]
            XY[active[move], 1] -= dY[move]
            active = active[move]
        # final check of every point against the tolerance
        G = np.stack([XY[:, 0], XY[:, 1], Z], -1)
        fx, fy = self._eval_norm(G)
        err = np.hypot((fx - xn) * isx, (fy - yn) * isy)
        good = ok & np.isfinite(err) & (err < tolerance)
        if not np.all(good):
            log.info(
                "%s: localize did not converge for %d of %d point(s)",
                self.name,
                int((~good).sum()),
                good.size,
            )
        E = XY[:, 0] * self.norm.ground_scale[0] + self.norm.ground_offset[0]
        N = XY[:, 1] * self.norm.ground_scale[1] + self.norm.ground_offset[1]
        E[~good] = np.nan
        N[~good] = np.nan
        lon = np.full(E.shape, np.nan)
        lat = np.full(E.shape, np.nan)
        if np.any(good):
            lo, la = geodesy.crs_to_lonlat(E[good], N[good], self.crs)
            lon[good], lat[good] = lo, la
        return lon.reshape(shape), lat.reshape(shape)

    def height_bounds(self):
        """Heights (m) between which rays are built: the GCP height range widened by half its
        span."""
        lo, hi = self.h_range
        pad = 0.5 * (hi - lo) + 100.0
        return (lo - pad, hi + pad)

    MODEL_TYPE = "generic"

    # ------------------------------------------------------------ adjustable parameters
    def parameters(self) -> dict:
        """The coefficients as ``{"c00": ..., "c01": ...}`` (normalised coordinates, unit 1),
        the protocol of :mod:`stereodem.sensor.models.parameters`."""
        return {f"c{k:02d}": float(v) for k, v in enumerate(self.params)}

    def with_parameters(self, **values) -> GenericModel:
        """A copy with some coefficients changed."""
        p = self.params.copy()
        for k, v in values.items():
            try:
                i = int(k[1:]) if k.startswith("c") else -1
            except ValueError:
                i = -1
            if not 0 <= i < p.size:
                raise InputError(f"{self.name}: unknown parameter {k!r} (c00..c{p.size - 1:02d})")
            p[i] = float(v)
        return GenericModel(
            self.name,
            p,
            crs=self.crs,
            normalization=self.norm,
            width=self.width,
            height=self.height,
            h_range=self.h_range,
            inverse_affine=self._inverse,
        )

    def to_dict(self) -> dict:
        """Plain description of the fitted model (for reports and for re-creating it)."""
        return {
            "model": self.name,
            "crs": self.crs.to_string(),
            "params": self.params.tolist(),
            "ground_offset": self.norm.ground_offset.tolist(),
            "ground_scale": self.norm.ground_scale.tolist(),
            "image_offset": self.norm.image_offset.tolist(),
            "image_scale": self.norm.image_scale.tolist(),
            "width": self.width,
            "height": self.height,
            "h_range": list(self.h_range),
            "inverse_affine": self._inverse.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> GenericModel:
        """Inverse of :meth:`to_dict` (model sidecars)."""
        a = lambda k: np.asarray(d[k], dtype=np.float64)  # noqa: E731
        norm = _Normalization(
            a("ground_offset"), a("ground_scale"), a("image_offset"), a("image_scale")
        )
        return cls(
            d["model"],
            a("params"),
            crs=CRS.from_user_input(d["crs"]),
            normalization=norm,
            width=d["width"],
            height=d["height"],
            h_range=d["h_range"],
            inverse_affine=a("inverse_affine"),
        )


# ---------------------------------------------------------------------------- fitting
@dataclass
class FitReport:
    """Quality of a generic-model fit. RMSEs in pixels; ``nan`` for check points when none.

    ``rmse_x``/``rmse_y`` are along columns/rows, ``rmse = sqrt(rmse_x^2 + rmse_y^2)``; RMSEs
    divide by ``N - ddof`` (Ok 2005 used ``ddof = 1``). ``condition_number`` is that of the
    normal matrix of the (normalised, linearised) estimation at the solution;
    ``condition_number_regularized`` adds the Tikhonov term.
    """

    model: str
    n_gcp: int
    n_check: int
    n_params: int
    gcp_rmse_x: float
    gcp_rmse_y: float
    gcp_rmse: float
    check_rmse_x: float
    check_rmse_y: float
    check_rmse: float
    condition_number: float
    condition_number_regularized: float
    regularization: str | None
    regularization_weight: float | None
    crs: str
    gcp_residuals: np.ndarray = field(repr=False, default=None)  # (n_gcp, 2) col, row px
    check_residuals: np.ndarray = field(repr=False, default=None)  # (n_check, 2)

    def to_dict(self) -> dict:
        """Scalars of the report (no residual arrays), JSON-ready (NaN -> None)."""
        out = {}
        for k, v in self.__dict__.items():
            if k.endswith("_residuals"):
                continue
            if isinstance(v, float) and not np.isfinite(v) and not np.isinf(v):
                v = None
            out[k] = v
        return out


def _as_points(name, arrays, what):
    labels = ("lon", "lat", "h", "col", "row")
    try:
        arrs = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64).ravel() for a in arrays))
    except ValueError:
        raise InputError(
            f"{name}: {what} arrays have different lengths "
            f"({', '.join(str(np.size(a)) for a in arrays)})"
        ) from None
    for lab, a in zip(labels, arrs):
        bad = ~np.isfinite(a)
        if np.any(bad):
            raise InputError(f"{name}: {int(bad.sum())} non-finite {what} value(s) in '{lab}'")
    return arrs


def _rmse(res, ddof):
    n = res.shape[0]
    if n - ddof <= 0:
        return (float("nan"),) * 3
    rx = float(np.sqrt(np.sum(res[:, 0] ** 2) / (n - ddof)))
    ry = float(np.sqrt(np.sum(res[:, 1] ** 2) / (n - ddof)))
    return rx, ry, float(np.hypot(rx, ry))


#: smallest ratio of the GCPs' ground spread across their principal line to that along it
#: (1e-3: 10 m across a 10 km line; well-spread sets are above 0.1)
MIN_SPREAD_RATIO = 1e-3


def _check_spread(name, EN):
    """Refuse GCPs that lie on one line on the ground (or on one point): every generic model
    maps the ground plane, which such a set leaves undetermined across the line; the fit then
    "succeeds" with a near-zero RMSE and localises far from the truth off the line."""
    d = EN - EN.mean(0)
    s = np.linalg.svd(d, compute_uv=False)
    if s[0] == 0 or s[1] < MIN_SPREAD_RATIO * s[0]:
        n = EN.shape[0]
        along, across = (2 * s / np.sqrt(n)) if s[0] > 0 else (0.0, 0.0)
        raise InputError(
            f"model '{name}': the {n} GCPs lie on one line on the ground (spread "
            f"{across:.3g} m across it for {along:.3g} m along it): the model is undetermined "
            "across it; use GCPs spread over the image"
        )


def _scale(lo, hi):
    s = 0.5 * (hi - lo)
    return np.where(s > 0, s, 1.0)


def fit_model(
    name: str,
    gcp_lon,
    gcp_lat,
    gcp_h,
    gcp_col,
    gcp_row,
    *,
    check=None,
    regularization="lcurve",
    reweight_iterations: int = 0,
    crs=None,
    image_size=None,
    rmse_ddof: int = 0,
):
    """Fit generic model ``name`` to GCPs and assess it at check points.

    Parameters
    ----------
    name : str
        One of :data:`MODEL_NAMES`.
    gcp_lon, gcp_lat : array_like
        GCP longitude, latitude (degrees, WGS84).
    gcp_h : array_like
        GCP ellipsoidal heights (m).
    gcp_col, gcp_row : array_like
        GCP image coordinates (px; centre of the top-left pixel at (0, 0)).
    check : tuple of 5 arrays, optional
        ``(lon, lat, h, col, row)`` of independent check points; never used by the fit.
    regularization : {"lcurve", "gcv"} or float or None
        Tikhonov regularisation of the rational functions: the weight chosen by the L-curve
        corner or generalised cross-validation on the GCP equations, a fixed weight (Ok's
        ``h``), or none (plain least squares). Ignored by the other models, which are not
        regularised. The default is the L-curve: on simulated pushbroom scenes GCV, applied to
        the linearised equations (whose design matrix holds the noisy image coordinates),
        chose weights 10-30 times too small for the 2nd/3rd-order functions, leaving
        denominator poles between the GCPs, while the L-curve corner fell near the weight
        that minimises the check-point error.
    reweight_iterations : int
        Rational functions: number of re-solutions with the linearised equations weighted by
        the inverse of the previous denominator (Tao & Hu 2001), the weight re-chosen each
        time. Default 0: on simulated pushbroom data reweighting with a GCV weight sometimes
        placed a denominator pole near a GCP.
    crs : pyproj CRS-like, optional
        Projected CRS of the fitting frame; by default the UTM zone of the GCPs.
    image_size : (int, int), optional
        ``(width, height)`` of the image; by default the GCP extent.
    rmse_ddof : int
        RMSE denominator ``N - rmse_ddof`` (0: RMSE; Ok used 1).

    Returns
    -------
    (GenericModel, FitReport)

    Raises
    ------
    InputError
        Unknown model, NaN/inf coordinates, arrays of different lengths, fewer GCPs than
        :func:`minimum_gcps`, or GCPs on one line on the ground (the model is undetermined
        across it).
    """
    form = _form(name)
    lon, lat, h, col, row = _as_points(name, (gcp_lon, gcp_lat, gcp_h, gcp_col, gcp_row), "GCP")
    n = lon.size
    if n < form.min_gcps:
        raise InputError(
            f"model '{name}' needs at least {form.min_gcps} GCPs "
            f"({form.n_params} unknowns), got {n}"
        )
    if crs is None:
        crs = geodesy.utm_crs(lon, lat)
    else:
        try:
            crs = CRS.from_user_input(crs)
        except Exception as exc:
            raise CRSError(f"{name}: unusable CRS {crs!r}: {exc}") from None
        if not crs.is_projected:
            raise CRSError(f"{name}: the fitting frame must be a projected CRS, got {crs.name}")
    E, N = geodesy.lonlat_to_crs(lon, lat, crs)
    Gr = np.stack([np.asarray(E, float), np.asarray(N, float), h], -1)
    _check_spread(name, Gr[:, :2])
    g_lo, g_hi = Gr.min(0), Gr.max(0)
    img = np.stack([col, row], -1)
    if form.centre_image:
        i_off, i_scale = 0.5 * (img.min(0) + img.max(0)), _scale(img.min(0), img.max(0))
    else:  # extended DLT: the x y and y^2 terms are invariant only to pure scaling
        i_off, i_scale = np.zeros(2), np.where(np.abs(img).max(0) > 0, np.abs(img).max(0), 1.0)
    norm = _Normalization(0.5 * (g_lo + g_hi), _scale(g_lo, g_hi), i_off, i_scale)
    G = (Gr - norm.ground_offset) / norm.ground_scale
    xn, yn = (img - i_off).T / i_scale[:, None]

    if int(reweight_iterations) < 0:
        raise InputError(f"{name}: reweight_iterations must be >= 0")
    sol = form.fit(
        G, xn, yn, regularization if form.regularizable else None, int(reweight_iterations)
    )

    # affine inverse (normalised image, Z) -> (X, Y) to start localize()
    B = np.stack([np.ones(n), xn, yn, G[:, 2]], -1)
    inv, *_ = np.linalg.lstsq(B, G[:, :2], rcond=None)

    if image_size is None:
        image_size = (int(np.ceil(col.max())) + 1, int(np.ceil(row.max())) + 1)
    model = GenericModel(
        name,
        sol.params,
        crs=crs,
        normalization=norm,
        width=image_size[0],
        height=image_size[1],
        h_range=(h.min(), h.max()),
        inverse_affine=inv,
    )

    pc, pr = model.project(lon, lat, h)
    gres = np.stack([pc - col, pr - row], -1)
    gx, gy, gt = _rmse(gres, rmse_ddof)
    if check is not None:
        if len(check) != 5:
            raise InputError(f"{name}: check must be (lon, lat, h, col, row)")
        clon, clat, ch, ccol, crow = _as_points(name, check, "check-point")
        qc, qr = model.project(clon, clat, ch)
        cres = np.stack([qc - ccol, qr - crow], -1)
    else:
        cres = np.zeros((0, 2))
    cx, cy, ct = _rmse(cres, rmse_ddof)
    report = FitReport(
        name,
        n,
        cres.shape[0],
        form.n_params,
        gx,
        gy,
        gt,
        cx,
        cy,
        ct,
        sol.condition_number,
        sol.condition_number_regularized,
        sol.method,
        sol.weight,
        model.crs.to_string(),
        gres,
        cres,
    )
    return model, report
