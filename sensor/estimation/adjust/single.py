"""Adjustment of one image's sensor model to ground control points: :func:`adjust_model`.

Observations are the measured image coordinates of the GCPs (role ``gcp``), with a-priori
standard deviations ``sigma_px`` (per point from the CSV, else the ``sigma_px`` argument); a
GCP with ``sigma_ground_m`` also observes its ground coordinates (Gauss–Helmert model,
:mod:`.gauss_helmert`). Parameter priors enter as fictitious observations. The nonlinear
least-squares problem is iterated to convergence by :mod:`.gauss_markov`; data snooping
(:mod:`.reliability`) then rejects the worst point whose standardised residual exceeds the
critical value, one at a time, re-adjusting after each rejection, and reports what it removed
and why. Check points (role ``check``) never enter the estimation.
"""

from __future__ import annotations

import math

import numpy as np

from stereodem.core.errors import InputError
from stereodem.core.stats import check_sigma
from stereodem.sensor.estimation.adjust import gauss_helmert as gh
from stereodem.sensor.estimation.adjust import gauss_markov as gm
from stereodem.sensor.estimation.adjust import reliability as rel
from stereodem.sensor.estimation.adjust.model_sets import free_parameters, parameter_unit
from stereodem.sensor.estimation.adjust.result import AdjustmentResult, fit_statistics
from stereodem.sensor.io.gcps import ControlPoints
from stereodem.sensor.models.parameters import project_jacobian

__all__ = ["adjust_model", "required_gcps", "check_points_against_model"]


def required_gcps(n_unknowns: int, n_prior: int = 0) -> int:
    """GCPs needed for ``n_unknowns`` parameters (2 observations each) with at least one
    redundant observation (so that sigma0 and the tests exist); priors count as observations."""
    return max(1, math.ceil((n_unknowns - n_prior + 1) / 2))


def _check_arrays(points: ControlPoints, what: str):
    if not isinstance(points, ControlPoints):
        raise InputError(f"{what}: points must be stereodem.sensor.io.gcps.ControlPoints")
    for k in ("lon", "lat", "h", "col", "row"):
        bad = ~np.isfinite(getattr(points, k))
        if np.any(bad):
            raise InputError(f"{what}: NaN/inf '{k}' at point(s) {', '.join(points.id[bad][:5])}")
    uniq, counts = np.unique(points.id, return_counts=True)
    if np.any(counts > 1):
        raise InputError(f"{what}: duplicate point id(s) {', '.join(uniq[counts > 1][:5])}")
    unknown = sorted(set(points.role) - {"gcp", "check"})
    if unknown:
        raise InputError(f"{what}: unknown role(s) {', '.join(unknown)} (expected gcp or check)")


def _rpc_of(model):
    while model is not None and not hasattr(model, "lat_scale"):
        model = getattr(model, "model", None)
    return model


def check_points_against_model(
    model, points: ControlPoints, what: str = "adjustment", *, margin: float = 1.0
):
    """Refuse points measured outside the image, or whose ground coordinates lie outside the
    model's validity range (RPC normalisation domain, or projecting farther than ``margin``
    image sizes outside the image); say when swapping lon and lat would fit."""
    W, H = model.width, model.height
    out = (
        (points.col < -0.5) | (points.col > W - 0.5) | (points.row < -0.5) | (points.row > H - 0.5)
    )
    if np.any(out):
        k = int(np.flatnonzero(out)[0])
        raise InputError(
            f"{what}: {int(out.sum())} point(s) measured outside the {W} x {H} image, "
            f"e.g. {points.id[k]} at col {points.col[k]:.1f}, row {points.row[k]:.1f}"
        )

    def invalid(lon, lat, h):
        rpc = _rpc_of(model)
        bad = np.zeros(lon.shape, bool)
        if rpc is not None:
            bad |= np.abs((lon - rpc.lon_off) / rpc.lon_scale) > 1.5
            bad |= np.abs((lat - rpc.lat_off) / rpc.lat_scale) > 1.5
        with np.errstate(invalid="ignore"):
            c, r = model.project(lon, lat, h)
        c, r = np.asarray(c, float), np.asarray(r, float)
        bad |= ~np.isfinite(c) | ~np.isfinite(r)
        bad |= (
            (c < -margin * W) | (c > (1 + margin) * W) | (r < -margin * H) | (r > (1 + margin) * H)
        )
        return bad

    bad = invalid(points.lon, points.lat, points.h)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        swapped = np.all(np.abs(points.lon) <= 90) and not np.any(
            invalid(points.lat, points.lon, points.h)[bad]
        )
        raise InputError(
            f"{what}: {int(bad.sum())} point(s) outside the model's validity range or far outside "
            f"the image, e.g. {points.id[k]} (lon {points.lon[k]:.6f}, lat {points.lat[k]:.6f})"
            + (" — likely swapped lon/lat" if swapped else "")
        )


def _sigmas(points, sigma_px):
    s = points.sigma_px.copy()
    given = np.isfinite(s)
    s[~given] = 1.0 if sigma_px is None else check_sigma(sigma_px, "adjustment: sigma_px")
    if np.any(s <= 0):
        raise InputError("adjustment: sigma_px must be positive")
    known = bool(sigma_px is not None or (len(s) and np.all(given)))
    return s, known


class _Problem:
    """The whitened least-squares problem of one model and a set of GCPs."""

    def __init__(self, model, names, pts: ControlPoints, sigma, priors, x0, constraints=()):
        self.model, self.names, self.pts = model, names, pts
        self.x0 = x0
        ground = np.isfinite(pts.sigma_ground_m) & (pts.sigma_ground_m > 0)
        self.G = gh.ground_partials(model, pts.lon, pts.lat, pts.h) if np.any(ground) else None
        self.sigma = sigma
        self.sg = np.where(ground, pts.sigma_ground_m, np.nan) if self.G is not None else None
        self.M = gh.misclosure_covariance(sigma, self.sg, self.G)
        self.W = gh.whitening(self.M)
        self.meas = np.stack([pts.col, pts.row], -1)
        # fictitious observations C x = w (sigma s): priors and linear constraints
        rows, w, sd = [], [], []
        for n in names:
            if n in priors:
                p = priors[n]
                value, sig = (float(x0[names.index(n)]), p) if np.isscalar(p) else p
                r = np.zeros(len(names))
                r[names.index(n)] = 1.0
                rows.append(r), w.append(float(value)), sd.append(float(sig))
        for coeffs, value, sig in constraints:
            r = np.zeros(len(names))
            for n, c in coeffs.items():
                if n not in names:
                    raise InputError(f"adjustment: constraint on {n!r}, which is not freed")
                r[names.index(n)] = float(c)
            rows.append(r), w.append(float(value)), sd.append(float(sig))
        self.C = np.array(rows).reshape(-1, len(names))
        self.w = np.array(w, dtype=float)
        self.prior_sigma = np.array(sd, dtype=float)
        if np.any(~(self.prior_sigma > 0)):
            raise InputError("adjustment: prior / constraint standard deviations must be positive")

    def at(self, x):
        return self.model.with_parameters(**dict(zip(self.names, (float(v) for v in x))))

    def _prior_rows(self, x):
        return (self.C @ x - self.w) / self.prior_sigma

    def misclosure(self, x):
        c, r = self.at(x).project(self.pts.lon, self.pts.lat, self.pts.h)
        return np.stack([c, r], -1) - self.meas

    def residual(self, x):
        e = np.einsum("nij,nj->ni", self.W, self.misclosure(x)).ravel()
        return np.concatenate([e, self._prior_rows(x)])

    def evaluate(self, x):
        c, r, J = project_jacobian(self.at(x), self.pts.lon, self.pts.lat, self.pts.h, self.names)
        e = np.einsum("nij,nj->ni", self.W, np.stack([c, r], -1) - self.meas).ravel()
        A = np.einsum("nij,nju->niu", self.W, J).reshape(-1, len(self.names))
        P = self.C / self.prior_sigma[:, None]
        return np.concatenate([e, self._prior_rows(x)]), np.vstack([A, P])


def _test_statistics(sol, n_act: int, dof: int, sigma_known: bool):
    """Statistics of a Gauss-Markov solution ``sol`` (:func:`.gauss_markov.solve`) whose first
    ``2 n_act`` whitened residuals are the image observations (col, row) of ``n_act`` points:
    ``vtpv`` (weighted sum of squared residuals), ``sigma0`` (a-posteriori standard deviation of
    unit weight; NaN without degrees of freedom ``dof``), the redundancy numbers ``r`` and the
    standardised residuals ``w`` (both (n_act, 2); ``w`` scaled by ``sigma0`` when the a-priori
    sigma is not known: Pope's tau)."""
    vtpv = float(sol.e @ sol.e)
    sigma0 = math.sqrt(vtpv / dof) if dof > 0 else float("nan")
    r = rel.redundancy_numbers(sol.A, sol.Qxx)[: 2 * n_act].reshape(n_act, 2)
    e_w = sol.e[: 2 * n_act].reshape(n_act, 2)
    w = rel.standardized_residuals(e_w, r, 1.0 if sigma_known else sigma0)
    return vtpv, sigma0, r, w


def adjust_model(
    model,
    points: ControlPoints,
    names,
    *,
    sigma_px=None,
    max_iterations: int = 20,
    tolerance: float = 1e-2,
    snooping: bool = True,
    alpha: float = 0.001,
    power: float = 0.80,
    priors: dict | None = None,
    regularization=None,
    max_rejections: int | None = None,
    chi2_alpha: float = 0.05,
    max_condition: float = gm.MAX_CONDITION,
    check_inputs: bool = True,
    variance_components: str | None = None,
    constraints=(),
    what: str = "adjustment",
) -> AdjustmentResult:
    """Estimate parameters of a sensor model from GCPs, with statistics and data snooping.

    Parameters
    ----------
    model : adjustable sensor model (``parameters()``/``with_parameters()``)
    points : stereodem.sensor.io.gcps.ControlPoints
        GCPs (role ``gcp``) and independent check points (role ``check``).
    names : list of str or str
        Parameters to free, or the name of a registered model set
        (:mod:`.model_sets`: ``rpc-shift``, ``rpc-affine``, ``frame-eo``, ``attitude-bias`` ...),
        which may also wrap the model (an RPC in an image-space correction) and add priors.
    sigma_px : float, optional
        A-priori standard deviation of the image observations (px) for points without a
        ``sigma_px`` in the file. When neither is given sigma is unknown: 1 px is assumed,
        the covariance is scaled by the estimated sigma0^2 and Pope's tau test replaces
        Baarda's test.
    max_iterations, tolerance : see :func:`.gauss_markov.solve` (criterion
        ``max |dx_k| / sigma_k < tolerance``).
    snooping : bool
        Iterative outlier rejection (Baarda data snooping / Pope's tau test), one point at a
        time, while at least :func:`required_gcps` points remain.
    alpha, power : float
        Significance level of the test per observation and power for the minimal detectable
        bias (``delta_0`` = 4.13 for 0.001 and 0.80).
    priors : dict, optional
        ``{name: sigma}``: a-priori standard deviation of a parameter about its initial value,
        or ``{name: (value, sigma)}`` about a given value (fictitious observations).
    constraints : sequence of ``(coefficients, value, sigma)``, optional
        Linear parameter constraints ``sum_k c_k x_k = value`` entered as fictitious
        observations with standard deviation ``sigma`` (a sigma 1e-3..1e-5 times the
        parameters' own makes it practically hard; much smaller ones make the normal matrix
        near-singular; Bettemir 2006 §6.2 constrained the focal length this way), e.g.
        ``({"focal_mm": 1.0}, 177.2, 1e-6)`` or ``({"roll_bias": 1, "yaw_bias": -1}, 0, 1e-7)``.
    regularization : None, "lcurve", "gcv" or float
        Tikhonov regularisation for rank-deficient problems (default: refuse them).
    max_rejections : int, optional
        Upper bound on rejected points (default: as many as the redundancy allows).
    chi2_alpha : float
        Significance level of the global chi-square test of sigma0.
    variance_components : None, "estimate" or "iterate"
        With GCPs whose ground coordinates are observations (``sigma_ground_m``): estimate
        the variance components of the image and ground groups
        (:func:`.gauss_helmert.variance_components`, in ``result.variance_components``), or
        iterate: rescale both groups' sigmas by their estimated factors and re-adjust until the
        factors are within 2 % of 1 (at most 10 times; the sigmas used are reported).

    Returns
    -------
    AdjustmentResult

    Raises
    ------
    InputError
        Too few GCPs (saying how many are needed), points outside the image or the model's
        validity range (saying when lon/lat look swapped), duplicate ids, NaNs.
    SensorModelError
        Near-singular normal matrix (with the condition number and the inseparable parameters).
    ConvergenceError
        No convergence.
    """
    model, names, priors, set_name = free_parameters(model, names, priors, what=what)
    if len(set(names)) != len(names):
        raise InputError(f"{what}: a parameter is named twice in {names}")
    bad_prior = [n for n in priors if n not in names]
    if bad_prior:
        raise InputError(f"{what}: priors given for parameters not freed: {', '.join(bad_prior)}")
    _check_arrays(points, what)
    gcp, chk = points.select("gcp"), points.select("check")
    constraints = [(dict(c), float(v), float(sd)) for c, v, sd in constraints]
    u, n_prior = len(names), len(priors) + len(constraints)
    need = required_gcps(u, n_prior)
    if len(gcp) < need:
        raise InputError(
            f"{what}: {u} free parameter(s) ({', '.join(names)}) need at least {need} "
            f"GCPs (2 observations each plus one redundant), got {len(gcp)}"
        )
    if check_inputs:
        check_points_against_model(model, points, what)
    sigma, sigma_known = _sigmas(gcp, sigma_px)
    known = model.parameters()
    x0 = np.array([known[n] for n in names], dtype=np.float64)
    delta0 = rel.noncentrality(alpha, power)
    active = np.ones(len(gcp), bool)
    outliers = []
    limit = len(gcp) if max_rejections is None else int(max_rejections)
    x_start = x0

    def solve(prob, x_start):
        return gm.solve(
            prob.evaluate,
            x_start,
            names,
            residual=prob.residual,
            max_iterations=max_iterations,
            tolerance=tolerance,
            regularization=regularization,
            max_condition=max_condition,
            what=what,
        )

    while True:
        prob = _Problem(model, names, gcp.subset(active), sigma[active], priors, x0, constraints)
        sol = solve(prob, x_start)
        m_obs = sol.e.size
        dof = m_obs - u
        n_act = int(active.sum())
        vtpv, sigma0, r, w = _test_statistics(sol, n_act, dof, sigma_known)
        scale = 1.0 if sigma_known else sigma0
        thr = rel.baarda_threshold(alpha) if sigma_known else rel.pope_threshold(alpha, dof)
        if not (snooping and len(outliers) < limit and n_act - 1 >= need and np.isfinite(thr)):
            break
        stat = np.nanmax(np.abs(w), axis=1) if np.any(np.isfinite(w)) else np.zeros(n_act)
        stat = np.nan_to_num(stat, nan=0.0)
        k = int(np.argmax(stat))
        if stat[k] <= thr:
            break
        idx = np.flatnonzero(active)[k]
        axis = "col" if abs(np.nan_to_num(w[k, 0])) >= abs(np.nan_to_num(w[k, 1])) else "row"
        test = "Baarda data snooping" if sigma_known else "Pope tau test"
        outliers.append(
            {
                "id": str(gcp.id[idx]),
                "statistic": float(stat[k]),
                "threshold": thr,
                "reason": f"|{'w' if sigma_known else 'tau'}| = {stat[k]:.2f} > {thr:.2f} "
                f"in {axis} ({test}, alpha = {alpha:g} per observation)",
            }
        )
        active[idx] = False
        x_start = sol.x

    # ------------------------------------------------------------ variance components
    vc = None
    if variance_components not in (None, "estimate", "iterate"):
        raise InputError(f"{what}: variance_components must be None, 'estimate' or 'iterate'")
    if variance_components and prob.G is not None:
        scale_l = scale_g = 1.0
        for _ in range(10 if variance_components == "iterate" else 1):
            A_w = sol.A[: 2 * n_act].reshape(n_act, 2, u)
            vc = gh.variance_components(
                prob.W, A_w, sol.Qxx, prob.misclosure(sol.x), prob.sigma, prob.sg, prob.G
            )
            f_l, f_g = vc["image"]["sigma0"], vc["ground"]["sigma0"]
            if (
                variance_components == "estimate"
                or not (f_l and f_g)
                or not vc["separable"]
                or (abs(f_l - 1) < 0.02 and abs(f_g - 1) < 0.02)
            ):
                break
            scale_l, scale_g = scale_l * f_l, scale_g * f_g
            sub = gcp.subset(active)
            sub.sigma_ground_m = sub.sigma_ground_m * scale_g
            prob = _Problem(model, names, sub, sigma[active] * scale_l, priors, x0, constraints)
            sol = solve(prob, sol.x)
            vtpv, sigma0, r, w = _test_statistics(sol, n_act, dof, sigma_known)
        vc["sigma_scale_applied"] = {"image": scale_l, "ground": scale_g}

    # ------------------------------------------------------------ result
    adjusted = prob.at(sol.x)
    cov = sol.Qxx * (scale**2)
    n = len(gcp)
    full = lambda a, k: _scatter(a, active, n, k)  # noqa: E731
    sig_obs = np.sqrt(np.stack([prob.M[:, 0, 0], prob.M[:, 1, 1]], -1)) * scale
    mdb = rel.minimal_detectable_bias(sig_obs, r, delta0)
    ext = rel.external_reliability(r, delta0)
    mis_all = _project_residuals(adjusted, gcp)
    _, v_g = gh.observation_residuals(prob.misclosure(sol.x), prob.M, prob.sigma, prob.sg, prob.G)
    ground = np.zeros((n, 3))
    ground[active] = v_g
    chk_res = _project_residuals(adjusted, chk) if len(chk) else np.zeros((0, 2))
    return AdjustmentResult(
        model=adjusted,
        names=names,
        values=sol.x,
        initial_values=x0,
        std=np.sqrt(np.diag(cov)),
        units=[parameter_unit(adjusted, nm) for nm in names],
        covariance=cov,
        condition=sol.condition,
        **fit_statistics(vtpv, dof, m_obs, sigma_known, chi2_alpha),
        gcp_ids=gcp.id,
        check_ids=chk.id,
        gcp_points=gcp,
        check_points=chk,
        residuals_px=mis_all,
        check_residuals_px=chk_res,
        ground_residuals_m=ground,
        redundancy=full(r, 2),
        w=full(w, 2),
        mdb=full(mdb, 2),
        external_reliability=full(ext, 2),
        outliers=outliers,
        iterations=sol.iterations,
        converged=sol.converged,
        status=sol.status,
        max_correction=float(sol.max_correction),
        tolerance=tolerance,
        test=rel.outlier_test(sigma_known, alpha, power, thr, delta0, snooping),
        model_set=set_name,
        priors=priors,
        regularization=sol.regularization,
        initial_model=model,
        variance_components=vc,
    )


def _scatter(a, active, n, k):
    out = np.full((n, k), np.nan)
    out[active] = a
    return out


def _project_residuals(model, pts):
    c, r = model.project(pts.lon, pts.lat, pts.h)
    return np.stack([np.asarray(c, float) - pts.col, np.asarray(r, float) - pts.row], -1)
