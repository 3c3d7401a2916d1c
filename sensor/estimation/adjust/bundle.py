"""Bundle adjustment of a stereo pair: both sensor models and the tie points' ground
coordinates estimated together from tie points and optional GCPs.

Unknowns: the free parameters of the left and right models (``u``) and, per tie point, a
ground correction in its local east/north/up frame (3 per tie, metres, about the initial
intersection of its two rays). Observations: each tie's (col, row) in both images (sigma
``sigma_tie_px``), each GCP's (col, row) in the image(s) where it was measured (a GCP's ground
coordinates are fixed, or observed with ``sigma_ground_m`` through the Gauss–Helmert misclosure
covariance of :mod:`.gauss_helmert`), and parameter priors (fictitious observations).

Solution: Gauss–Newton on the sparse normal equations, the ground blocks eliminated (the
reduced normal equations / Schur complement of photogrammetric bundle adjustment, Brown 1976;
Triggs et al. 2000): with ``N_gg`` block-diagonal (3 x 3 per tie),

    S = N_pp - sum_j N_pg,j N_gg,j^-1 N_gp,j,     S dp = b_p - sum_j N_pg,j N_gg,j^-1 b_g,j,
    dg_j = N_gg,j^-1 (b_g,j - N_gp,j dp)

in O(n u^2) — vectorised over ties. ``solver="least_squares"`` runs
:func:`scipy.optimize.least_squares` on the same problem with the sparse Jacobian (LSMR
trust region), ``solver="dense"`` the dense normal equations (for comparison only: memory
O((u + 3n)^2)). Statistics always come from the reduced system: ``Q_pp = S^-1`` and, per tie,
the hat diagonal ``h_i = b_i S^-1 b_i^T + g_i N_gg^-1 g_i^T`` with ``b_i = a_i - g_i M_j^T``,
``M_j = N_pg,j N_gg,j^-1`` — so redundancy numbers, standardised residuals and data snooping
work at 20 000 ties.

Datum: without GCPs the pair fixes only its relative orientation; free parameters of only one
model (default when no GCP is given: the right one) and priors avoid the datum defect, which
is otherwise reported as a near-singular normal matrix naming the parameters. Holding the left
model is not enough: a shift of the right image *along* the epipolar lines moves every tie's
height and nothing else, so two images cannot observe it (as ``stereodem dem``'s pointing
correction says). Without GCPs the right image's image-space correction therefore gets
datum priors about its initial values (:data:`DATUM_PRIOR_SIGMA_PX` px over the image)
where none is given: the component across the epipolar lines is observed to ~0.01 px and
unaffected, the one along them stays at its initial value. (Without them, the real Pleiades
pair over La Reunion gave the right image a 318 +- 432 px row shift, shift correlation -1,
exit 0, and the DEM from the adjusted models lay 607 m below s2p's.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from stereodem.core import geodesy
from stereodem.core.errors import ConvergenceError, InputError
from stereodem.core.stats import check_sigma
from stereodem.sensor.estimation.adjust import gauss_helmert as gh
from stereodem.sensor.estimation.adjust import gauss_markov as gm
from stereodem.sensor.estimation.adjust import reliability as rel
from stereodem.sensor.estimation.adjust import schur
from stereodem.sensor.estimation.adjust.model_sets import free_parameters, parameter_unit
from stereodem.sensor.estimation.adjust.result import (
    ParameterEstimate,
    _num,
    fit_statistics,
    rmse,
)
from stereodem.sensor.estimation.adjust.single import (
    _check_arrays,
    _sigmas,
    check_points_against_model,
)
from stereodem.sensor.geo.intersect import intersect_matches
from stereodem.sensor.io.sidecar import model_to_dict
from stereodem.sensor.models.base import pair_height_bounds
from stereodem.sensor.models.parameters import project_jacobian

__all__ = ["bundle_adjust", "BundleResult", "tie_parallax"]

SOLVERS = ("schur", "least_squares", "dense")

#: Without GCPs: a-priori sigma (px across the image) of the right image's image-space
#: correction about its initial values, where no prior is given (see the module docstring).
DATUM_PRIOR_SIGMA_PX = 1.0
#: Image-space correction parameters (shifts in px, drifts in px per px) given datum priors.
_SHIFTS = ("col_shift", "row_shift")
_DRIFTS = ("col_drift_col", "col_drift_row", "row_drift_col", "row_drift_row")


def _datum_priors(model, names, priors) -> dict:
    """``priors`` plus the datum priors of a pair without GCPs (:data:`DATUM_PRIOR_SIGMA_PX`
    px for a shift, the same across the image for a drift) for the free image-space
    correction parameters that have none."""
    out = dict(priors)
    span = float(max(getattr(model, "width", 0) or 0, getattr(model, "height", 0) or 0, 1))
    for n in names:
        if n in out:
            continue
        if n in _SHIFTS:
            out[n] = DATUM_PRIOR_SIGMA_PX
        elif n in _DRIFTS:
            out[n] = DATUM_PRIOR_SIGMA_PX / span
    return out


def _resolve(model, names, priors, side):
    """(model, names, priors, set name) for one image; no names: the image is held fixed."""
    if names is None or (not isinstance(names, str) and len(names) == 0):
        return model, [], {}, None
    return free_parameters(model, names, priors, what="bundle", side=side)


class _Problem(schur.SchurProblem):
    """The whitened bundle problem; state ``z = [x (u), d (3 n_tie, ENU m)]``."""

    def __init__(self, models, names, priors, ties, gcps, sigma_tie, gcp_sigma):
        self.models = models
        self.names = names  # (names_l, names_r)
        self.u_l, self.u_r = len(names[0]), len(names[1])
        self.u = self.u_l + self.u_r
        self.x0 = np.array([models[k].parameters()[n] for k in (0, 1) for n in names[k]], float)
        self.ties = np.asarray(ties, float)  # (n, 4)
        self.n = len(self.ties)
        self.sigma_tie = float(sigma_tie)
        self.gcps = gcps  # (ControlPoints or None) x 2
        self.gcp_sigma = gcp_sigma  # (sigma arrays) x 2
        allp = {
            **{f"left.{k}": v for k, v in priors[0].items()},
            **{f"right.{k}": v for k, v in priors[1].items()},
        }
        self.full_names = [f"left.{n}" for n in names[0]] + [f"right.{n}" for n in names[1]]
        self.prior_idx = np.array([self.full_names.index(k) for k in allp], dtype=int)
        self.prior_sigma = np.array(list(allp.values()), dtype=float)
        self.X0 = self._initial_ground()
        lon, lat, _ = geodesy.ecef_to_geodetic(self.X0[:, 0], self.X0[:, 1], self.X0[:, 2])
        self.basis = np.asarray(geodesy.enu_basis(lon, lat)).reshape(-1, 3, 3)
        # GCP whitening (Gauss-Helmert misclosure covariance when ground sigmas are set)
        self.gcp_W, self.gcp_M, self.gcp_G = [], [], []
        for k in (0, 1):
            p = gcps[k]
            if p is None or len(p) == 0:
                self.gcp_W.append(None), self.gcp_M.append(None), self.gcp_G.append(None)
                continue
            ground = np.isfinite(p.sigma_ground_m) & (p.sigma_ground_m > 0)
            G = gh.ground_partials(models[k], p.lon, p.lat, p.h) if np.any(ground) else None
            M = gh.misclosure_covariance(
                gcp_sigma[k], p.sigma_ground_m if G is not None else None, G
            )
            self.gcp_W.append(gh.whitening(M)), self.gcp_M.append(M), self.gcp_G.append(G)

    # ---------------------------------------------------------------- state
    def _initial_ground(self):
        """Initial tie ground points (:func:`initial_ground`)."""
        if self.n == 0:
            return np.zeros((0, 3))
        return initial_ground(*self.models, self.ties)

    def split(self, z):
        return z[: self.u], z[self.u :].reshape(self.n, 3)

    def model_at(self, z, k):
        x = z[: self.u]
        vals = x[: self.u_l] if k == 0 else x[self.u_l :]
        if not self.names[k]:
            return self.models[k]
        return self.models[k].with_parameters(**dict(zip(self.names[k], (float(v) for v in vals))))

    # ---------------------------------------------------------------- blocks
    def blocks(self, z, *, jacobian=True):
        """Whitened residuals and Jacobian blocks at ``z``.

        Returns dict: ``e_t`` (n, 4), ``A_t`` (n, 4, u), ``G_t`` (n, 4, 3) for ties;
        ``e_g`` (m, 2), ``A_g`` (m, 2, u) for GCP observations; ``e_p`` (p,), ``A_p`` (p, u).
        """
        u, n = self.u, self.n
        lon, lat, h = self.ground(z)
        e_t = np.empty((n, 4))
        A_t = np.zeros((n, 4, u)) if jacobian else None
        G_t = np.empty((n, 4, 3)) if jacobian else None
        e_g, A_g = [], []
        for k in (0, 1):
            m = self.model_at(z, k)
            names = self.names[k]
            off = 0 if k == 0 else self.u_l
            cols = slice(2 * k, 2 * k + 2)
            if n:
                e_t[:, cols], A, G = tie_block(
                    m, names, (lon, lat, h), self.ties[:, cols], self.sigma_tie, jacobian
                )
                if A is not None:
                    A_t[:, cols, off : off + len(names)] = A
                if jacobian:
                    G_t[:, cols] = G
            p = self.gcps[k]
            if p is not None and len(p):
                W = self.gcp_W[k]
                gcp_block(
                    m,
                    names,
                    p,
                    (off, u),
                    jacobian,
                    e_g,
                    A_g,
                    lambda mis, W=W: np.einsum("nij,nj->ni", W, mis),
                    lambda J, W=W: np.einsum("nij,nju->niu", W, J),
                )
        e_g = np.concatenate(e_g) if e_g else np.zeros((0, 2))
        A_g = np.concatenate(A_g) if A_g else np.zeros((0, 2, u))
        e_p, A_p = schur.prior_blocks(z[:u], self.x0, self.prior_idx, self.prior_sigma, u)
        return dict(e_t=e_t, A_t=A_t, G_t=G_t, e_g=e_g, A_g=A_g, e_p=e_p, A_p=A_p)

    def residual(self, z):
        b = self.blocks(z, jacobian=False)
        return np.concatenate([b["e_t"].ravel(), b["e_g"].ravel(), b["e_p"]])

    def sparse_jacobian(self, b):
        """The whitened Jacobian as a CSR matrix, rows as :meth:`residual`, columns ``z``."""
        n, u = self.n, self.u
        rows_t = np.arange(4 * n).reshape(n, 4)
        # parameter columns of tie rows (only the observing image's parameters)
        pr, pc, pv = [], [], []
        for k, (lo, hi) in enumerate(((0, self.u_l), (self.u_l, u))):
            if hi > lo and n:
                r = np.repeat(rows_t[:, 2 * k : 2 * k + 2].reshape(-1), hi - lo)
                c = np.tile(np.arange(lo, hi), 2 * n)
                (
                    pr.append(r),
                    pc.append(c),
                    pv.append(b["A_t"][:, 2 * k : 2 * k + 2, lo:hi].reshape(-1)),
                )
        gr = np.repeat(rows_t.reshape(-1), 3)
        gc = (
            (u + 3 * np.arange(n)[:, None, None] + np.arange(3)[None, None, :])
            .repeat(4, 1)
            .reshape(-1)
        )
        m_g = b["A_g"].shape[0]
        Ag = b["A_g"].reshape(2 * m_g, u)
        Ap = b["A_p"]
        gcp_rows = 4 * n + np.arange(2 * m_g)
        pri_rows = 4 * n + 2 * m_g + np.arange(Ap.shape[0])
        r_all = np.concatenate(pr + [gr, np.repeat(gcp_rows, u), np.repeat(pri_rows, u)])
        c_all = np.concatenate(
            pc + [gc, np.tile(np.arange(u), 2 * m_g), np.tile(np.arange(u), Ap.shape[0])]
        )
        v_all = np.concatenate(pv + [b["G_t"].reshape(-1), Ag.reshape(-1), Ap.reshape(-1)])
        shape = (4 * n + 2 * m_g + Ap.shape[0], u + 3 * n)
        J = sp.csr_matrix((v_all, (r_all.astype(np.int64), c_all.astype(np.int64))), shape=shape)
        J.eliminate_zeros()
        return J

    # ---------------------------------------------------------------- normal equations


def initial_ground(left, right, ties) -> np.ndarray:
    """First ground points (ECEF, m) of tie points ``ties`` (n, 4: col1, row1, col2, row2):
    along each left ray, the point whose right projection is nearest the right measurement
    (the ray between two heights projected into the right image and the measurement placed on
    that segment): one ray per tie (two left localisations) and two right projections,
    instead of two full ray pairs. :class:`InputError` for rays that do not intersect."""
    t = np.asarray(ties, float)
    n = len(t)
    lo, hi = _height_span(left, right)
    o, d = left.rays(t[:, 0], t[:, 1])
    P = geodesy.intersect_height(
        np.concatenate([o, o]),
        np.concatenate([d, d]),
        np.concatenate([np.full(n, lo), np.full(n, hi)]),
    )
    Plo, Phi = P[:n], P[n:]
    lon, lat, h = geodesy.ecef_to_geodetic(P[:, 0], P[:, 1], P[:, 2])
    c, r = right.project(lon, lat, h)
    q = np.stack([c, r], -1)
    qlo, qhi = q[:n], q[n:]
    seg = qhi - qlo
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.sum((t[:, 2:] - qlo) * seg, axis=1) / np.sum(seg * seg, axis=1)
    X = Plo + s[:, None] * (Phi - Plo)
    bad = ~np.all(np.isfinite(X), axis=1)
    if np.any(bad):
        raise InputError(
            f"bundle: {int(bad.sum())} tie point(s) whose rays do not intersect "
            f"(first #{int(np.flatnonzero(bad)[0])})"
        )
    return X


def tie_block(model, names, ground, observed, sigma, jacobian):
    """One image's whitened tie rows: residuals (m, 2) of ``model`` projecting the ``ground``
    points (lon, lat in degrees, h in metres) against the ``observed`` (m, 2) (col, row) px,
    over ``sigma`` px; with ``jacobian``, the partials by the parameters ``names`` (m, 2,
    len(names); None without names) and by the points' east/north/up (m, 2, 3)."""
    lon, lat, h = ground
    A = G = None
    if jacobian and names:
        c, r, J = project_jacobian(model, lon, lat, h, names)
        A = J / sigma
    else:
        c, r = model.project(lon, lat, h)
    e = np.empty((len(observed), 2))
    e[:, 0] = (np.asarray(c) - observed[:, 0]) / sigma
    e[:, 1] = (np.asarray(r) - observed[:, 1]) / sigma
    if jacobian:
        G = _enu_partials(model, lon, lat, h, base=(c, r)) / sigma
    return e, A, G


def gcp_block(model, names, gcps, cols, jacobian, e_g, A_g, whiten_e, whiten_A):
    """One image's whitened GCP rows appended to ``e_g`` (residuals, (k, 2)) and, with
    ``jacobian``, ``A_g`` ((k, 2, u); ``cols = (off, u)``: the image's parameters start at
    column ``off`` of ``u``): misclosures (col, row) px of ``model`` at the ``gcps``' fixed
    ground coordinates, whitened by ``whiten_e`` / ``whiten_A``."""
    off, u = cols
    if jacobian and names:
        c, r, J = project_jacobian(model, gcps.lon, gcps.lat, gcps.h, names)
    else:
        c, r = model.project(gcps.lon, gcps.lat, gcps.h)
        J = np.zeros((len(gcps), 2, len(names)))
    e_g.append(whiten_e(np.stack([np.asarray(c) - gcps.col, np.asarray(r) - gcps.row], -1)))
    if jacobian:
        Ak = np.zeros((len(gcps), 2, u))
        Ak[:, :, off : off + len(names)] = whiten_A(J)
        A_g.append(Ak)


def _height_span(left, right):
    """Heights (m) spanned by both models' validity ranges (a 1000 m span when they are wide)."""
    lo, hi = pair_height_bounds(left, right)
    if not hi > lo:
        lo, hi = 0.0, 1000.0
    return lo, hi


def _enu_partials(model, lon, lat, h, basis=None, step_m=1.0, base=None):
    """d(col, row)/d(east, north, up) in px/m at ground points, shape (n, 2, 3).

    Forward differences over ``step_m`` metres along the local axes, taken in geodetic
    coordinates through the ellipsoid's radii of curvature (``dlat = s / (M + h)``,
    ``dlon = s / ((N + h) cos lat)``, ``dh = s``: no datum transformation per point);
    ``base`` is the projection at the points when already known. ``basis`` is accepted for
    the fixed-frame parametrisation (the axes differ from the local ones by micro-radians).
    """
    phi = np.radians(lat)
    w = np.sqrt(1.0 - geodesy.E2 * np.sin(phi) ** 2)
    N = geodesy.A / w
    M = geodesy.A * (1.0 - geodesy.E2) / w**3
    dlon = np.degrees(step_m / ((N + h) * np.cos(phi)))
    dlat = np.degrees(step_m / (M + h))
    n = lon.size
    L = np.concatenate([lon + dlon, lon, lon])
    P = np.concatenate([lat, lat + dlat, lat])
    H = np.concatenate([h, h, h + step_m])
    c, r = model.project(L, P, H)
    if base is None:
        base = model.project(lon, lat, h)
    c0, r0 = (np.asarray(v, float) for v in base)
    dc = (np.asarray(c, float).reshape(3, n) - c0) / step_m
    dr = (np.asarray(r, float).reshape(3, n) - r0) / step_m
    return np.stack([dc.T, dr.T], 1)


@dataclass
class BundleResult(ParameterEstimate):
    """Result of :func:`bundle_adjust` (``to_report()`` is the bundle's ``adjust_report.json``).

    ``tie_residuals_px`` is (n_tie, 4): left col, row, right col, row (model − measured) of
    every tie (rejected ones included, from the final models); ``tie_w``/``tie_redundancy``
    likewise, NaN for rejected ties. ``tie_lon/lat/h`` and ``tie_std_m`` (E, N, U) are the
    adjusted ground points. GCP arrays per image follow the ``gcps`` given.
    """

    left: object
    right: object
    tie_residuals_px: np.ndarray
    tie_w: np.ndarray
    tie_redundancy: np.ndarray
    tie_lon: np.ndarray
    tie_lat: np.ndarray
    tie_h: np.ndarray
    tie_std_m: np.ndarray
    tie_rejected: np.ndarray
    gcps: tuple
    gcp_residuals_px: tuple
    gcp_w: tuple
    gcp_redundancy: tuple
    checks: tuple
    check_residuals_px: tuple
    solver: str
    model_sets: tuple = (None, None)
    parallax_before: dict = field(default_factory=dict)
    parallax_after: dict = field(default_factory=dict)
    #: "converged" (criterion met) or "stalled" (line search stopped below STATIONARY_SIGMA)
    status: str = "converged"
    max_correction: float = float("nan")  #: last max |dz_k| / sigma_k

    @property
    def models(self):
        return self.left, self.right

    @property
    def tie_rmse_px(self) -> float:
        """RMSE of the kept tie observations over both images (px per image point)."""
        r = self.tie_residuals_px[~self.tie_rejected].reshape(-1, 2)
        return rmse(r)

    @property
    def gcp_rmse_px(self) -> float:
        res = [
            r[~_mask(g, self.outliers, side)]
            for r, g, side in zip(self.gcp_residuals_px, self.gcps, ("left", "right"))
            if g is not None
        ]
        return rmse(np.concatenate(res)) if res else float("nan")

    @property
    def check_rmse_px(self) -> float:
        res = [r for r in self.check_residuals_px if r is not None and len(r)]
        return rmse(np.concatenate(res)) if res else float("nan")

    def _points(self, k, side):
        out = []
        g = self.gcps[k]
        if g is not None:
            bad = _mask(g, self.outliers, side)
            for i in range(len(g)):
                out.append(
                    {
                        "id": str(g.id[i]),
                        "role": "gcp",
                        "image": side,
                        "col": float(g.col[i]),
                        "row": float(g.row[i]),
                        "residual_px": [_num(v) for v in self.gcp_residuals_px[k][i]],
                        "w": [_num(v) for v in self.gcp_w[k][i]],
                        "r": [_num(v) for v in self.gcp_redundancy[k][i]],
                        "mdb_px": None,
                        "ground_residual_m": None,
                        "outlier": bool(bad[i]),
                    }
                )
        c = self.checks[k]
        if c is not None:
            for i in range(len(c)):
                out.append(
                    {
                        "id": str(c.id[i]),
                        "role": "check",
                        "image": side,
                        "col": float(c.col[i]),
                        "row": float(c.row[i]),
                        "residual_px": [_num(v) for v in self.check_residuals_px[k][i]],
                        "w": None,
                        "r": None,
                        "mdb_px": None,
                        "ground_residual_m": None,
                        "outlier": False,
                    }
                )
        return out

    def to_report(self) -> dict:
        kept = ~self.tie_rejected
        return {
            "model": {"left": model_to_dict(self.left), "right": model_to_dict(self.right)},
            "model_set": "bundle",
            "model_sets": {"left": self.model_sets[0], "right": self.model_sets[1]},
            "solver": self.solver,
            **self._estimate_report(len(self.names) + 3 * int(kept.sum())),
            "points": self._points(0, "left") + self._points(1, "right"),
            "gcp_rmse_px": _num(self.gcp_rmse_px),
            "check_rmse_px": _num(self.check_rmse_px),
            "n_gcp": int(
                sum(len(g) for g in self.gcps if g is not None)
                - sum(o.get("kind") == "gcp" for o in self.outliers)
            ),
            "n_check": int(sum(len(c) for c in self.checks if c is not None)),
            "ties": {
                "n": int(len(self.tie_rejected)),
                "rejected": int(self.tie_rejected.sum()),
                "rmse_px": _num(self.tie_rmse_px),
                "rmse_left_col_row_px": [_num(v) for v in _axis(self.tie_residuals_px[kept, :2])],
                "rmse_right_col_row_px": [_num(v) for v in _axis(self.tie_residuals_px[kept, 2:])],
                "max_abs_w": _num(np.nanmax(np.abs(self.tie_w))) if kept.any() else None,
                "ground_std_m_median": [_num(v) for v in np.nanmedian(self.tie_std_m[kept], 0)]
                if kept.any()
                else None,
            },
            "parallax_before": self.parallax_before,
            "parallax_after": self.parallax_after,
            "outliers": [o["id"] for o in self.outliers if o.get("kind") == "gcp"],
            **self._test_report(),
            "status": self.status,
            "max_correction": _num(self.max_correction),
            "convergence_criterion": (
                f"max |dz_k| / sigma_k < {self.tolerance:g} (parameters and tie ground coordinates)"
            ),
            "regularization": None,
            "redundancy_sum": _num(
                np.nansum(self.tie_redundancy)
                + sum(np.nansum(r) for r in self.gcp_redundancy if r is not None)
            ),
        }

    def figures(self):
        """Per-image reports for the residual figures: ``{side: (report, width, height)}``."""
        base = self.to_report()
        out = {}
        for k, (side, m) in enumerate((("left", self.left), ("right", self.right))):
            pts = [p for p in base["points"] if p["image"] == side]
            kept = ~self.tie_rejected
            n = min(int(kept.sum()), 2000)  # draw at most 2000 ties
            idx = np.flatnonzero(kept)[:n]
            for i in idx:
                res = self.tie_residuals_px[i, 2 * k : 2 * k + 2]
                pts.append(
                    {
                        "id": f"tie{i}",
                        "role": "tie",
                        "col": float(self._tie_obs[i, 2 * k]),
                        "row": float(self._tie_obs[i, 2 * k + 1]),
                        "residual_px": [float(res[0]), float(res[1])],
                        "outlier": False,
                    }
                )
            out[side] = ({**base, "points": pts}, m.width, m.height)
        return out


def _axis(res):
    res = np.asarray(res, float).reshape(-1, 2)
    return np.sqrt(np.mean(res**2, axis=0)) if len(res) else np.array([np.nan, np.nan])


def _mask(pts, outliers, side):
    bad = {o["id"] for o in outliers if o.get("kind") == "gcp" and o.get("image") == side}
    return np.array([i in bad for i in pts.id], dtype=bool)


def tie_parallax(left, right, ties, *, max_points: int = 2000) -> dict:
    """Consistency of tie points with a pair of models: RMS and median of the closest-approach
    distance of their rays (m), and the RMS reprojection discrepancy (px) of each image point
    from the other image's ray at the intersection (the "vertical parallax" left once heights
    are free). At most ``max_points`` ties (evenly spaced in the list) are used."""
    t = np.asarray(ties, float)
    if len(t) > max_points:  # a diagnostic: an evenly spread subset is enough
        t = t[np.linspace(0, len(t) - 1, max_points).astype(int)]
    inter = intersect_matches(left, right, t[:, 0], t[:, 1], t[:, 2], t[:, 3])
    cl, rl = left.project(inter.lon, inter.lat, inter.h)
    cr, rr = right.project(inter.lon, inter.lat, inter.h)
    d = np.stack([cl - t[:, 0], rl - t[:, 1], cr - t[:, 2], rr - t[:, 3]], -1)
    return {
        "ray_gap_rms_m": float(np.sqrt(np.nanmean(inter.ray_gap**2))),
        "ray_gap_median_m": float(np.nanmedian(inter.ray_gap)),
        "reprojection_rms_px": rmse(d.reshape(-1, 2)),
    }


def _as_ties(ties):
    if ties is None:
        return np.zeros((0, 4))
    if hasattr(ties, "col1"):  # stereodem.stereo.sparse.SparseMatches
        ties = np.stack([ties.col1, ties.row1, ties.col2, ties.row2], -1)
    t = np.asarray(ties, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 4:
        raise InputError(
            f"bundle: tie points must be an (n, 4) array col1,row1,col2,row2, got shape {t.shape}"
        )
    bad = ~np.all(np.isfinite(t), axis=1)
    if np.any(bad):
        raise InputError(f"bundle: {int(bad.sum())} tie point(s) with NaN/inf coordinates")
    return t


def bundle_adjust(
    left,
    right,
    ties,
    *,
    names=("rpc-shift", "rpc-shift"),
    gcps=(None, None),
    sigma_tie_px: float = 0.5,
    sigma_px=None,
    priors=(None, None),
    max_iterations: int = 20,
    tolerance: float = 1e-2,
    snooping: bool = True,
    alpha: float = 0.001,
    power: float = 0.80,
    solver: str = "schur",
    max_condition: float = gm.MAX_CONDITION,
    max_tie_rounds: int = 5,
    chi2_alpha: float = 0.05,
    check_inputs: bool = True,
) -> BundleResult:
    """Bundle adjustment of a stereo pair (see the module docstring).

    Parameters
    ----------
    left, right : sensor models
    ties : (n, 4) array ``col1, row1, col2, row2`` (px), or a
        :class:`stereodem.stereo.sparse.SparseMatches`
    names : (left, right)
        Per image: a model-set name, a list of parameter names, or None/[] to hold the model
        fixed. Without GCPs the left one is held fixed whatever is given (the datum).
    gcps : (ControlPoints or None, ControlPoints or None)
        GCPs (role ``gcp``) and check points (role ``check``) measured in each image.
    sigma_tie_px : float
        A-priori standard deviation of a tie point's image coordinates (px).
    sigma_px : float, optional
        GCP image sigma for points without one in the file; see :func:`adjust_model`.
    solver : {"schur", "least_squares", "dense"}
    snooping : bool
        Data snooping: ties whose largest standardised residual exceeds the critical value are
        rejected together in rounds (at most ``max_tie_rounds``); then GCPs one at a time.

    Returns
    -------
    BundleResult
    """
    sigma_tie_px = check_sigma(sigma_tie_px, "sigma_tie_px")
    if sigma_px is not None:
        sigma_px = check_sigma(sigma_px, "sigma_px")
    if solver not in SOLVERS:
        raise InputError(f"bundle: unknown solver {solver!r} (known: {', '.join(SOLVERS)})")
    max_iterations = gm.check_max_iterations(max_iterations)
    t = _as_ties(ties)
    gcps = tuple(gcps)
    has_gcp = any(g is not None and np.any(g.role == "gcp") for g in gcps)
    names = list(names)
    if not has_gcp:
        names[0] = None
    ml, nl, pl, setl = _resolve(left, names[0], priors[0], "left")
    mr, nr, pr, setr = _resolve(right, names[1], priors[1], "right")
    if not has_gcp:  # the right image's shift along the epipolar lines is a height offset
        pr = _datum_priors(mr, nr, pr)
    gcp_sets, chk_sets, sig_sets, known_all = [], [], [], []
    if len(gcps) != 2:
        raise InputError("bundle: gcps must be a pair (left, right); use None for an image without")
    for k, (g, m) in enumerate(zip(gcps, (ml, mr))):
        if g is None:
            gcp_sets.append(None), chk_sets.append(None), sig_sets.append(None)
            continue
        _check_arrays(g, f"bundle ({('left', 'right')[k]} GCPs)")
        if check_inputs:
            check_points_against_model(m, g, f"bundle ({('left', 'right')[k]} GCPs)")
        gg, cc = g.select("gcp"), g.select("check")
        s, known = _sigmas(gg, sigma_px)
        gcp_sets.append(gg), chk_sets.append(cc), sig_sets.append(s), known_all.append(known)
    sigma_known = all(known_all) if known_all else True  # ties: sigma_tie_px is a-priori
    if len(t) == 0 and not has_gcp:
        raise InputError("bundle: no tie points and no GCPs")
    u = len(nl) + len(nr)
    n_obs = 4 * len(t) + sum(2 * len(g) for g in gcp_sets if g is not None) + len(pl) + len(pr)
    if n_obs - u - 3 * len(t) < 1:
        raise InputError(
            f"bundle: {u} free parameter(s) and {len(t)} tie point(s) need more "
            f"observations: have {n_obs}, need at least {u + 3 * len(t) + 1}"
        )
    delta0 = rel.noncentrality(alpha, power)
    active_t = np.ones(len(t), bool)
    active_g = [None if g is None else np.ones(len(g), bool) for g in gcp_sets]
    outliers, z_prev, rounds = [], None, 0
    before = tie_parallax(ml, mr, t) if len(t) else {}
    while True:
        sub = [None if g is None else g.subset(a) for g, a in zip(gcp_sets, active_g)]
        subs = [None if s is None else s[a] for s, a in zip(sig_sets, active_g)]
        prob = _Problem((ml, mr), (nl, nr), (pl, pr), t[active_t], sub, sigma_tie_px, subs)
        z, sol = _solve(prob, solver, max_iterations, tolerance, max_condition, x_start=z_prev)
        b = sol["b"]  # blocks at the solution (from the last check)
        R = sol["R"]
        Sinv = sol["Sinv"]
        e_all = np.concatenate([b["e_t"].ravel(), b["e_g"].ravel(), b["e_p"]])
        m_obs = e_all.size
        dof = m_obs - prob.u - 3 * prob.n
        vtpv = float(e_all @ e_all)
        sigma0 = math.sqrt(vtpv / dof) if dof > 0 else float("nan")
        # hat diagonal: ties (reduced form), GCPs and priors (parameters only)
        A_t, G_t = b["A_t"], b["G_t"]
        Bt = A_t - G_t @ np.swapaxes(R["M"], 1, 2)  # (n, 4, u)
        h_t = np.sum((Bt @ Sinv) * Bt, axis=2) + np.sum((G_t @ R["T"]) * G_t, axis=2)
        Ag = b["A_g"]
        h_g = np.sum((Ag @ Sinv) * Ag, axis=2)
        r_t, r_g = np.clip(1 - h_t, 0, 1), np.clip(1 - h_g, 0, 1)
        scale = 1.0 if sigma_known else sigma0
        w_t = rel.standardized_residuals(b["e_t"], r_t, scale)
        w_g = rel.standardized_residuals(b["e_g"], r_g, scale)
        thr = rel.baarda_threshold(alpha) if sigma_known else rel.pope_threshold(alpha, dof)
        if not snooping or not np.isfinite(thr):
            break
        stat_t = np.nan_to_num(np.nanmax(np.abs(w_t), axis=1), nan=0.0) if prob.n else np.zeros(0)
        bad_t = stat_t > thr
        if np.any(bad_t) and rounds < max_tie_rounds and prob.n - bad_t.sum() >= 2:
            idx = np.flatnonzero(active_t)[bad_t]
            active_t[idx] = False
            rounds += 1
            z_prev = z[: prob.u]
            continue
        # GCPs: one at a time, the largest
        stat_g = np.nan_to_num(np.nanmax(np.abs(w_g), axis=1), nan=0.0) if len(w_g) else np.zeros(0)
        if len(stat_g) and stat_g.max() > thr:
            k = int(np.argmax(stat_g))
            owners = [
                (j, i) for j, a in enumerate(active_g) if a is not None for i in np.flatnonzero(a)
            ]
            j, i = owners[k]
            trial = [a.copy() if a is not None else None for a in active_g]
            trial[j][i] = False
            left_after = sum(int(a.sum()) for a in trial if a is not None)
            if (
                2 * left_after
                + 4 * int(active_t.sum())
                + len(pl)
                + len(pr)
                - u
                - 3 * int(active_t.sum())
                >= 1
            ):
                side = ("left", "right")[j]
                outliers.append(
                    {
                        "id": str(gcp_sets[j].id[i]),
                        "kind": "gcp",
                        "image": side,
                        "statistic": float(stat_g[k]),
                        "threshold": thr,
                        "reason": f"|{'w' if sigma_known else 'tau'}| = {stat_g[k]:.2f} > "
                        f"{thr:.2f} in the {side} image "
                        f"({'Baarda data snooping' if sigma_known else 'Pope tau test'}, "
                        f"alpha = {alpha:g} per observation)",
                    }
                )
                active_g = trial
                z_prev = z[: prob.u]
                continue
        break
    if (~active_t).any():
        outliers.append(
            {
                "id": f"{int((~active_t).sum())} tie point(s)",
                "kind": "tie",
                "statistic": None,
                "threshold": thr,
                "reason": f"standardised residual above {thr:.2f} in {rounds} round(s) "
                "of tie-point snooping",
            }
        )
    # ------------------------------------------------------------ result
    L, Rm = prob.model_at(z, 0), prob.model_at(z, 1)
    x = z[: prob.u]
    n_all = len(t)
    tie_res = np.full((n_all, 4), np.nan)
    tie_w = np.full((n_all, 4), np.nan)
    tie_r = np.full((n_all, 4), np.nan)
    tie_w[active_t], tie_r[active_t] = w_t, r_t
    lon, lat, h = (np.full(n_all, np.nan) for _ in range(3))
    lon[active_t], lat[active_t], h[active_t] = prob.ground(z)
    if n_all:
        # kept ties at their adjusted ground points; rejected ones re-intersected with the
        # final models
        glon, glat, gh_ = lon.copy(), lat.copy(), h.copy()
        if (~active_t).any():
            tr = t[~active_t]
            inter = intersect_matches(L, Rm, tr[:, 0], tr[:, 1], tr[:, 2], tr[:, 3])
            glon[~active_t], glat[~active_t], gh_[~active_t] = inter.lon, inter.lat, inter.h
        cl, rl = L.project(glon, glat, gh_)
        cr, rr = Rm.project(glon, glat, gh_)
        tie_res = np.stack([cl - t[:, 0], rl - t[:, 1], cr - t[:, 2], rr - t[:, 3]], -1)
    std_g = np.full((n_all, 3), np.nan)
    std_g[active_t] = sol["sigma"][prob.u :].reshape(-1, 3) * scale
    gres, gw, gr_, cres = [], [], [], []
    off = 0
    for k, (g, a, c) in enumerate(zip(gcp_sets, active_g, chk_sets)):
        m = (L, Rm)[k]
        if g is None:
            gres.append(None), gw.append(None), gr_.append(None), cres.append(None)
            continue
        cc, rr_ = m.project(g.lon, g.lat, g.h)
        gres.append(np.stack([cc - g.col, rr_ - g.row], -1))
        ww, rrr = np.full((len(g), 2), np.nan), np.full((len(g), 2), np.nan)
        na = int(a.sum())
        ww[a], rrr[a] = w_g[off : off + na], r_g[off : off + na]
        off += na
        gw.append(ww), gr_.append(rrr)
        if c is not None and len(c):
            qc, qr = m.project(c.lon, c.lat, c.h)
            cres.append(np.stack([qc - c.col, qr - c.row], -1))
        else:
            cres.append(np.zeros((0, 2)))
    cov = Sinv * scale**2
    units = [
        parameter_unit((ml, mr)[0 if n.startswith("left.") else 1], n.split(".", 1)[1])
        for n in prob.full_names
    ]
    res = BundleResult(
        left=L,
        right=Rm,
        names=prob.full_names,
        values=x,
        initial_values=prob.x0,
        std=np.sqrt(np.diag(cov)),
        units=units,
        covariance=cov,
        condition=sol["cond"],
        **fit_statistics(vtpv, dof, m_obs, sigma_known, chi2_alpha),
        tie_residuals_px=tie_res,
        tie_w=tie_w,
        tie_redundancy=tie_r,
        tie_lon=lon,
        tie_lat=lat,
        tie_h=h,
        tie_std_m=std_g,
        tie_rejected=~active_t,
        gcps=tuple(gcp_sets),
        gcp_residuals_px=tuple(gres),
        gcp_w=tuple(gw),
        gcp_redundancy=tuple(gr_),
        checks=tuple(chk_sets),
        check_residuals_px=tuple(cres),
        outliers=outliers,
        iterations=sol["iterations"],
        converged=sol["converged"],
        tolerance=tolerance,
        status=sol["status"],
        max_correction=float(sol["max_correction"]),
        test=rel.outlier_test(sigma_known, alpha, power, thr, delta0, snooping),
        solver=solver,
        model_sets=(setl, setr),
        parallax_before=before,
        parallax_after=tie_parallax(L, Rm, t[active_t]) if active_t.any() else {},
    )
    res._tie_obs = t
    return res


def _solve(prob, solver, max_iterations, tolerance, max_condition, x_start=None):
    """Iterate to convergence; returns ``(z, info)`` with the reduced system at the solution."""
    z = prob.z0()
    if x_start is not None:  # parameters carried over from a previous round of snooping
        z[: prob.u] = x_start
    it = 0
    if solver == "least_squares" and max_iterations > 0:

        def jac(zz):
            return prob.sparse_jacobian(prob.blocks(zz))

        # scipy's default tolerances (1e-8); the Gauss-Newton steps below then bring it to the
        # stated criterion, so every solver stops at the same max |dz|/sigma < tolerance
        sol = least_squares(
            prob.residual,
            z,
            jac=jac,
            method="trf",
            tr_solver="lsmr",
            x_scale="jac",
            max_nfev=4 * max_iterations + 10,
        )
        z, it = sol.x, int(sol.njev or sol.nfev)
    worst, stalled = np.inf, False
    # after scipy's run, up to five Gauss-Newton steps to meet the stated criterion
    limit = it + 5 if solver == "least_squares" else max_iterations
    for _ in range(max_iterations + 6):
        b = prob.blocks(z)
        if solver == "dense":
            dz, sig, R, Sinv, cond = _dense_step(prob, b, max_condition)
        else:
            dz, sig, R, Sinv, cond = prob.step(b, max_condition)
        worst = float(np.max(np.abs(dz) / sig)) if dz.size else 0.0
        if worst < tolerance or it >= limit:
            break
        e = np.concatenate([b["e_t"].ravel(), b["e_g"].ravel(), b["e_p"]])
        cost = float(e @ e)
        step = 1.0
        for _ in range(10):
            zn = z + step * dz
            en = prob.residual(zn)
            if np.all(np.isfinite(en)) and float(en @ en) <= cost * (1 + 1e-9) + 1e-12:
                break
            step *= 0.5
        else:
            # the line search cannot lower the sum of squares any more: accepted when the
            # correction is below STATIONARY_SIGMA, but reported as stalled, not converged
            stalled = worst < gm.STATIONARY_SIGMA
            break
        z = zn
        it += 1
    if worst >= tolerance and not stalled:
        raise ConvergenceError(
            f"bundle: no convergence in {it} iteration(s) (last correction "
            f"{worst:.3g} sigma; criterion max |dz|/sigma < {tolerance:g})"
        )
    converged = worst < tolerance
    return z, {
        "R": R,
        "Sinv": Sinv,
        "cond": cond,
        "sigma": sig,
        "iterations": it,
        "b": b,
        "converged": converged,
        "status": "converged" if converged else "stalled",
        "max_correction": worst,
    }


def _dense_step(prob, b, max_condition):
    """The same Gauss-Newton step from the dense normal equations (comparison only)."""
    J = prob.sparse_jacobian(b).toarray()
    e = np.concatenate([b["e_t"].ravel(), b["e_g"].ravel(), b["e_p"]])
    # the reduced system first: a rank-deficient bundle gets the condition-number error that
    # names the inseparable parameters, not a LinAlgError from the dense solve
    R = prob.reduced(b)
    _, Sinv, cond = prob.solve_reduced(R, max_condition)
    N = J.T @ J
    dz = np.linalg.solve(N, -J.T @ e)
    Q = np.linalg.inv(N)
    return dz, np.sqrt(np.maximum(np.diag(Q), 1e-300)), R, Sinv, cond
