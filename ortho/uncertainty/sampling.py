"""Monte Carlo propagation: Latin hypercube samples with Iman–Conover rank correlation, exact
(non-linear) ground displacements, and regression-based sensitivity measures (Bettemir 2006,
§8.1.2; Helton 1993; Iman & Conover 1982).

The samples come from :class:`scipy.stats.qmc.LatinHypercube` mapped to normal marginals; the
target rank correlation of correlated inputs is imposed by the Iman–Conover reordering (scipy
has none). Every sample is propagated through the full model: the pixel that images a ground
point under the true model is re-localised on the DEM with the perturbed model by Newton
iterations, so the result keeps the model's non-linearity.
"""

from __future__ import annotations

import numpy as np
from scipy import stats
from scipy.stats import qmc

from stereodem.core import geodesy
from stereodem.core.errors import ConvergenceError, InputError
from stereodem.ortho.uncertainty.propagation import check_names, ground_jacobian, perturbed_model


def iman_conover(X, C, *, rng=None):
    """Reorder the columns of ``X`` (s, u) so that their rank correlation approaches ``C``.

    Follows Iman & Conover (1982): van der Waerden scores ``Φ⁻¹(i/(s+1))`` randomly permuted per
    column (matrix S), ``E = corr(S) = QQᵀ``, ``C = PPᵀ``, ``S* = S Q⁻ᵀ Pᵀ``; each column of X
    takes the rank order of the matching column of S*. Marginals are unchanged.
    """
    X = np.asarray(X, float)
    s, u = X.shape
    rng = np.random.default_rng(rng)
    scores = stats.norm.ppf(np.arange(1, s + 1) / (s + 1))
    S = np.stack([rng.permutation(scores) for _ in range(u)], 1)
    P = np.linalg.cholesky(np.asarray(C, float) + 1e-12 * np.eye(u))
    Q = np.linalg.cholesky(np.corrcoef(S, rowvar=False) + 1e-12 * np.eye(u))
    Sstar = S @ np.linalg.inv(Q).T @ P.T
    ranks = np.argsort(np.argsort(Sstar, axis=0), axis=0)
    return np.take_along_axis(np.sort(X, axis=0), ranks, axis=0)


def lhs_normal(D, n: int, *, seed=0):
    """``n`` Latin hypercube samples of a zero-mean normal vector with covariance ``D``.

    Marginals are stratified normals ``N(0, D_kk)``; correlation is imposed (and the spurious
    correlation of the random pairing removed) by :func:`iman_conover` with the correlation of
    ``D``. Inputs with zero variance stay 0. Returns (n, u).
    """
    D = np.asarray(D, float)
    u = D.shape[0]
    if n < 3:
        raise InputError(f"Monte Carlo needs at least 3 samples, got {n}")
    sd = np.sqrt(np.clip(np.diag(D), 0, None))
    live = np.flatnonzero(sd > 0)
    X = np.zeros((n, u))
    if live.size == 0:
        return X
    U = qmc.LatinHypercube(d=live.size, seed=seed).random(n)
    Z = stats.norm.ppf(U)
    C = D[np.ix_(live, live)] / np.outer(sd[live], sd[live])
    if live.size > 1:
        Z = iman_conover(Z, C, rng=seed)
    X[:, live] = Z * sd[live]
    return X


def _local_metric(lon, lat, crs, d: float = 1e-5):
    """∂(E, N)/∂(lon, lat) of the map CRS at points, (n, 2, 2) metres per degree."""
    M = np.empty(np.shape(lon) + (2, 2))
    for k, (a, b) in enumerate(((d, 0.0), (0.0, d))):
        Ep, Np = geodesy.lonlat_to_crs(lon + a, lat + b, crs)
        Em, Nm = geodesy.lonlat_to_crs(lon - a, lat - b, crs)
        M[..., 0, k] = (np.asarray(Ep) - Em) / (2 * d)
        M[..., 1, k] = (np.asarray(Np) - Nm) / (2 * d)
    return M


def ground_displacements(
    model, lon, lat, h, names, X, crs, *, dem=None, tol_px: float = 1e-6, max_iterations: int = 100
):
    """Exact ground displacements (E, N metres) of the pixels imaging ``(lon, lat, h)`` for each
    row of input offsets ``X`` (s, u) in the order of ``names``.

    For each sample, the pixel ``p₀ = project(lon, lat, h)`` of the true model is re-localised
    with the perturbed model (``dem_height`` added to the DEM height) by Newton iterations in
    longitude/latitude with the true model's Jacobian; the point follows the DEM when one is
    given. Returns ``dE, dN`` of shape (s, n).
    """
    names = check_names(model, names)
    lon, lat, h = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, float)) for a in (lon, lat, h)))
    X = np.atleast_2d(np.asarray(X, float))
    c0, r0 = (np.asarray(a, float) for a in model.project(lon, lat, h))
    d = 1e-5
    A = np.empty(lon.shape + (2, 2))
    for k, (a, b) in enumerate(((d, 0.0), (0.0, d))):
        hp = dem.sample(lon + a, lat + b) if dem is not None else h
        hm = dem.sample(lon - a, lat - b) if dem is not None else h
        cp, rp = model.project(lon + a, lat + b, hp)
        cm, rm = model.project(lon - a, lat - b, hm)
        A[..., 0, k] = (np.asarray(cp) - cm) / (2 * d)
        A[..., 1, k] = (np.asarray(rp) - rm) / (2 * d)
    Ainv = np.linalg.inv(A)
    M = _local_metric(lon, lat, crs)
    k_h = names.index("dem_height") if "dem_height" in names else None
    out = np.empty((X.shape[0], 2) + lon.shape)
    worst = 0.0
    for s, x in enumerate(X):
        m = perturbed_model(model, {n: v for n, v in zip(names, x) if n != "dem_height"})
        dh = x[k_h] if k_h is not None else 0.0
        lo, la = lon.copy(), lat.copy()
        for _ in range(max_iterations):
            hh = dem.sample(lo, la) if dem is not None else h
            c, r = m.project(lo, la, hh + dh)
            res = np.stack([np.asarray(c) - c0, np.asarray(r) - r0], -1)
            step = np.einsum("...ij,...j->...i", Ainv, res)
            lo, la = lo - step[..., 0], la - step[..., 1]
            err = np.nanmax(np.abs(res)) if res.size else 0.0
            if err < tol_px:
                break
        worst = max(worst, float(err))
        dl = np.stack([lo - lon, la - lat], -1)
        out[s] = np.moveaxis(np.einsum("...ij,...j->...i", M, dl), -1, 0)
    if worst > 1e-3:
        raise ConvergenceError(
            f"Monte Carlo re-localisation did not converge ({worst:.3g} px left)"
        )
    return out[:, 0], out[:, 1]


def _cheb_design(x, lo, hi, deg):
    t = np.clip(2 * (np.asarray(x, float) - lo) / max(hi - lo, 1e-12) - 1, -1, 1)
    return np.polynomial.chebyshev.chebvander(t, deg)


def image_shift_field(
    model, lon, lat, h, names, X, *, nodes: int = 9, h_nodes: int = 3, n_check: int = 4
):
    """Exact image shifts ``δp = project_perturbed(lon, lat, h + δh) − project(lon, lat, h)`` of
    many points for many samples, through a smooth field: δp is computed exactly at
    ``nodes × nodes × h_nodes`` Chebyshev nodes over the points' extent and fitted there by a
    tensor Chebyshev polynomial (degrees nodes−1, nodes−1, h_nodes−1), then evaluated at the
    points for all samples at once. The fit's error is measured against exact shifts at all
    points for ``n_check`` samples. Returns ``(dcol, drow, error_px)``, (s, n) arrays.
    """
    names = list(names)
    k_h = names.index("dem_height") if "dem_height" in names else None
    dh = X[:, k_h] if k_h is not None else np.zeros(len(X))
    lo_b = (lon.min(), lon.max())
    la_b = (lat.min(), lat.max())
    h_b = (float(np.min(h) + min(dh.min(), 0)), float(np.max(h) + max(dh.max(), 0)) + 1e-3)
    cheb = lambda a, b, k: 0.5 * (a + b) + 0.5 * (b - a) * np.cos(np.pi * (np.arange(k) + 0.5) / k)
    NL, NA, NH = np.meshgrid(
        cheb(*lo_b, nodes), cheb(*la_b, nodes), cheb(*h_b, h_nodes), indexing="ij"
    )
    NL, NA, NH = NL.ravel(), NA.ravel(), NH.ravel()

    def design(lo_, la_, hh):
        a = _cheb_design(lo_, *lo_b, nodes - 1)
        b = _cheb_design(la_, *la_b, nodes - 1)
        c = _cheb_design(hh, *h_b, h_nodes - 1)
        return np.einsum("ni,nj,nk->nijk", a, b, c).reshape(len(lo_), -1)

    fit = np.linalg.pinv(design(NL, NA, NH))
    c0, r0 = (np.asarray(a, float) for a in model.project(NL, NA, NH))
    dn = np.empty((len(X), 2, NL.size))
    for s, x in enumerate(X):
        m = perturbed_model(model, {n: v for n, v in zip(names, x) if n != "dem_height"})
        c, r = m.project(NL, NA, NH)
        dn[s, 0], dn[s, 1] = np.asarray(c) - c0, np.asarray(r) - r0
    # the true model's own height dependence is exact too: add its change over δh at the points
    cp0, rp0 = (np.asarray(a, float) for a in model.project(lon, lat, h))
    B = design(lon, lat, h)
    out_c = np.empty((len(X), lon.size))
    out_r = np.empty((len(X), lon.size))
    # a sample's shift at (lon, lat, h + δh) relative to the true model at (lon, lat, h + δh),
    # plus the true model's own change from h to h + δh (first order in δh through ∂p/∂h)
    d = 1.0
    cp, rp = model.project(lon, lat, h + d)
    cm, rm = model.project(lon, lat, h - d)
    pc_h, pr_h = (np.asarray(cp) - cm) / (2 * d), (np.asarray(rp) - rm) / (2 * d)
    coef = np.einsum("mq,sq->sm", fit, dn[:, 0])
    out_c[:] = coef @ B.T
    coef = np.einsum("mq,sq->sm", fit, dn[:, 1])
    out_r[:] = coef @ B.T
    if k_h is not None:
        out_c += dh[:, None] * pc_h
        out_r += dh[:, None] * pr_h
    err = 0.0
    for s in range(min(n_check, len(X))):
        x = X[s]
        m = perturbed_model(model, {n: v for n, v in zip(names, x) if n != "dem_height"})
        c, r = m.project(lon, lat, h + dh[s])
        ce, re = np.asarray(c) - cp0, np.asarray(r) - rp0
        err = max(err, float(np.nanmax(np.hypot(out_c[s] - ce, out_r[s] - re))))
    return out_c, out_r, err


def field_displacements(model, lon, lat, h, names, X, crs, *, dem=None, nodes: int = 9):
    """Ground displacements of many points from :func:`image_shift_field`: exact in the inputs
    (the perturbed model is evaluated, non-linearity included) and linear in the true model's
    ground → image map over the displacement, ``δG = −A⁻¹ δp`` with ``A`` on the DEM surface.
    For displacements of a few pixels the neglected term is second order (≈ δp²/footprint).
    Returns ``dE, dN`` (s, n) and the measured field error (px)."""
    dc, dr, err = image_shift_field(model, lon, lat, h, names, X, nodes=nodes)
    gj = ground_jacobian(model, lon, lat, h, [], crs, dem=dem)
    Ainv = np.linalg.inv(gj.A)  # (n, 2, 2) metres per pixel
    dE = -(Ainv[:, 0, 0] * dc + Ainv[:, 0, 1] * dr)
    dN = -(Ainv[:, 1, 0] * dc + Ainv[:, 1, 1] * dr)
    return dE, dN, err


def monte_carlo(model, lon, lat, h, names, D, crs, *, samples: int = 1000, dem=None, seed=0):
    """Monte Carlo ground displacements for input covariance ``D`` (order of ``names``).

    Returns ``(X, dE, dN)``: the (s, u) input sample and the (s, n) displacements in metres."""
    X = lhs_normal(D, samples, seed=seed)
    dE, dN = ground_displacements(model, lon, lat, h, names, X, crs, dem=dem)
    return X, dE, dN


# ----------------------------------------------------------------------------- regression measures


def _standardise(a):
    a = np.asarray(a, float)
    sd = a.std(0, ddof=1)
    return (a - a.mean(0)) / np.where(sd > 0, sd, 1.0), sd > 0


def src(X, y):
    """Standardised regression coefficients of ``y`` (s,) or (s, m) on the inputs ``X`` (s, u),
    and the regression's R². Inputs with zero variance get 0."""
    Xs, live = _standardise(X)
    y2 = np.asarray(y, float).reshape(len(X), -1)
    ys, _ = _standardise(y2)
    b = np.zeros((X.shape[1], y2.shape[1]))
    b[live] = np.linalg.lstsq(Xs[:, live], ys, rcond=None)[0]
    fit = Xs @ b
    r2 = 1 - ((ys - fit) ** 2).sum(0) / np.maximum((ys**2).sum(0), 1e-300)
    return b.reshape((X.shape[1],) + np.shape(y)[1:]), r2.reshape(np.shape(y)[1:])


def pcc(X, y):
    """Partial correlation coefficients of each input with ``y`` (s,), removing the linear
    effect of the other inputs: ``-P_ky/√(P_kk P_yy)`` with ``P`` the inverse correlation
    matrix of ``[X, y]``. Inputs with zero variance get 0. Returns (u,)."""
    X = np.asarray(X, float)
    live = X.std(0) > 0
    Z = np.column_stack([X[:, live], np.asarray(y, float)])
    P = np.linalg.pinv(np.corrcoef(Z, rowvar=False))
    out = np.zeros(X.shape[1])
    out[live] = -P[:-1, -1] / np.sqrt(P[:-1, :-1].diagonal() * P[-1, -1])
    return out


def prcc(X, y):
    """Partial rank correlation coefficients: :func:`pcc` on rank-transformed data."""
    return pcc(stats.rankdata(X, axis=0), stats.rankdata(y))


def regression_summary(X, dE, dN, names):
    """SRC, PCC, PRCC and R² of E and N displacements at one point (dict for JSON)."""
    out = {}
    for comp, y in (("east", dE), ("north", dN)):
        b, r2 = src(X, y)
        out[comp] = {
            "r2": float(r2),
            "src": dict(zip(names, map(float, b))),
            "pcc": dict(zip(names, map(float, pcc(X, y)))),
            "prcc": dict(zip(names, map(float, prcc(X, y)))),
        }
    return out
