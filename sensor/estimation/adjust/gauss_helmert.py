"""The Gauss–Helmert (mixed) model for GCPs whose ground coordinates are observations too.

Per point the condition equations are ``f = P(x, g + v_g) - (l + v_l) = 0`` with the image
observations ``l`` (px, covariance ``S_l``), the ground observations ``g`` (local east, north,
up metres, covariance ``S_g``) and the parameters ``x``. Linearised about the current point,
``e + G v_g - v_l + A dx = 0`` with the misclosure ``e = P(x, g) - l`` and the ground partials
``G = dP/d(E, N, U)`` (2 x 3, px/m). Minimising ``v_l^T S_l^-1 v_l + v_g^T S_g^-1 v_g`` gives
the equivalent Gauss–Markov problem in the misclosures with covariance

    M = S_l + G S_g G^T                              (2 x 2 per point)

(Koch 1999, §3.6; Bettemir 2006, §5.1: the "mixed model" with the random parameters being the
corrections to pixel coordinates and heights), and the observation residuals

    v_l = S_l M^-1 e,          v_g = -S_g G^T M^-1 e.

So the estimation runs through :mod:`.gauss_markov` on ``M^-1/2 e``; this module supplies
``G``, the whitening matrices and the back-substitution of ``v_l`` and ``v_g``.
"""

from __future__ import annotations

import numpy as np

from stereodem.core import geodesy

__all__ = [
    "ground_partials",
    "misclosure_covariance",
    "whitening",
    "observation_residuals",
    "variance_components",
    "SEPARABLE_CONDITION",
]

#: condition number of the variance-component normal matrix above which the image and ground
#: components are reported as not separable (not iterated). A near-nadir view with every GCP
#: carrying a ground sigma gives ~1e3 (G G^T nearly isotropic: both groups look alike); with
#: half the GCPs fixed on the ground it is ~1-5.
SEPARABLE_CONDITION = 100.0


def ground_partials(model, lon, lat, h, *, step_m: float = 1.0) -> np.ndarray:
    """``d(col, row) / d(east, north, up)`` in px/m at ground points, shape (n, 2, 3).

    Central differences of ``model.project`` with ``step_m`` metre offsets along the local
    east/north/up axes (the map is smooth over metres for every model of the project).
    """
    lon, lat, h = (np.atleast_1d(np.asarray(a, dtype=np.float64)).ravel() for a in (lon, lat, h))
    X = np.stack(geodesy.geodetic_to_ecef(lon, lat, h), -1)  # (n, 3)
    basis = np.asarray(geodesy.enu_basis(lon, lat)).reshape(-1, 3, 3)  # rows east, north, up
    offsets = step_m * np.concatenate([basis, -basis], axis=1)  # (n, 6, 3)
    P = (X[:, None, :] + offsets).reshape(-1, 3)
    plon, plat, ph = geodesy.ecef_to_geodetic(P[:, 0], P[:, 1], P[:, 2])
    c, r = model.project(plon, plat, ph)
    img = np.stack([c, r], -1).reshape(-1, 6, 2)  # (n, 6, 2)
    G = np.swapaxes((img[:, :3] - img[:, 3:]) / (2.0 * step_m), 1, 2)  # (n, 2, 3)
    return G


def misclosure_covariance(sigma_px, sigma_ground_m=None, G=None) -> np.ndarray:
    """``M = sigma_px^2 I + sigma_g^2 G G^T`` per point, shape (n, 2, 2) (px^2).

    ``sigma_ground_m`` NaN or None: the ground coordinates are fixed (Gauss–Markov).
    """
    s = np.asarray(sigma_px, dtype=np.float64)
    M = (s**2)[:, None, None] * np.eye(2)
    if sigma_ground_m is not None and G is not None:
        g = np.nan_to_num(np.asarray(sigma_ground_m, dtype=np.float64), nan=0.0)
        M = M + (g**2)[:, None, None] * np.einsum("nik,njk->nij", G, G)
    return M


def whitening(M) -> np.ndarray:
    """``W = L^-1`` with ``M = L L^T`` (Cholesky), so that ``W M W^T = I``; shape (n, 2, 2)."""
    return np.linalg.inv(np.linalg.cholesky(M))


def observation_residuals(e, M, sigma_px, sigma_ground_m=None, G=None):
    """Residuals of the image (px, (n, 2)) and ground (m, east/north/up, (n, 3)) observations
    from the misclosures ``e`` (n, 2); the ground ones are zero where no ground sigma is set."""
    Me = np.linalg.solve(M, e[..., None])[..., 0]
    v_l = (np.asarray(sigma_px, float) ** 2)[:, None] * Me
    v_g = np.zeros(e.shape[:-1] + (3,))
    if sigma_ground_m is not None and G is not None:
        g = np.nan_to_num(np.asarray(sigma_ground_m, float), nan=0.0)
        v_g = -(g**2)[:, None] * np.einsum("nik,ni->nk", G, Me)
    return v_l, v_g


def variance_components(W, A_w, Qxx, e, sigma_px, sigma_ground_m, G) -> dict:
    """Variance components of the image and ground observation groups (Förstner 1979; Koch
    1999, §3.6): ``sigma_k^2 = v_k^T P_k v_k / r_k`` with the group redundancies

        r_l = sum_i tr(C_i S_l,i),   r_g = sum_i tr(C_i G_i S_g,i G_i^T),
        C_i = W_i^T (I - A_i Q_xx A_i^T) W_i   (the point's block of M^-1 - M^-1 A Q A^T M^-1),

    so that ``r_l + r_g = n - u`` (parameter priors excluded). ``A_w`` (n, 2, u) are the
    whitened parameter rows of the points, ``e`` (n, 2) their misclosures (px).

    Returns ``{"image": {...}, "ground": {...}, "condition", "separable"}``: per group
    ``sigma0`` (the factor to apply to that group's a-priori sigma), ``variance``,
    ``redundancy``, ``vtpv``; ``condition`` of the 2 x 2 normal matrix of the components
    ``N_kl = sum_i tr(C_i S_k,i C_i S_l,i)`` and ``separable`` (condition below
    :data:`SEPARABLE_CONDITION`). When the
    ground covariance maps to the image as a multiple of the image covariance (``G G^T``
    isotropic, e.g. a near-nadir view) the two components cannot be told apart.
    """
    H = A_w @ Qxx @ np.swapaxes(A_w, 1, 2)  # (n, 2, 2)
    C = np.swapaxes(W, 1, 2) @ (np.eye(2) - H) @ W
    s_l = np.asarray(sigma_px, float) ** 2
    g = np.nan_to_num(np.asarray(sigma_ground_m, float), nan=0.0) ** 2
    GG = g[:, None, None] * (G @ np.swapaxes(G, 1, 2))
    r_l = float(np.sum(np.einsum("nii->n", C) * s_l))
    r_g = float(np.sum(np.einsum("nij,nji->n", C, GG)))
    M = s_l[:, None, None] * np.eye(2) + GG
    v_l, v_g = observation_residuals(e, M, np.sqrt(s_l), np.sqrt(g), G)
    with np.errstate(divide="ignore", invalid="ignore"):
        q_l = float(np.sum(np.sum(v_l**2, axis=1) / s_l))
        q_g = float(np.sum(np.where(g > 0, np.sum(v_g**2, axis=1) / np.where(g > 0, g, 1), 0.0)))
    # separability: the (block-diagonal) normal matrix of the two components, Förstner (1979)
    Sl = s_l[:, None, None] * np.eye(2)
    CSl, CSg = C @ Sl, C @ GG
    N = np.array(
        [
            [np.einsum("nij,nji->", CSl, CSl), np.einsum("nij,nji->", CSl, CSg)],
            [np.einsum("nij,nji->", CSg, CSl), np.einsum("nij,nji->", CSg, CSg)],
        ]
    )
    ev = np.linalg.eigvalsh(N)
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")
    out = {"condition": cond, "separable": bool(cond < SEPARABLE_CONDITION)}
    for name, q, r in (("image", q_l, r_l), ("ground", q_g, r_g)):
        var = q / r if r > 1e-9 else float("nan")
        out[name] = {
            "vtpv": q,
            "redundancy": r,
            "variance": var,
            "sigma0": float(np.sqrt(var)) if np.isfinite(var) else None,
        }
    return out
