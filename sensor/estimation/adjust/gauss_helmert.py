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

from stereodem.sensor.geo import geodesy

__all__ = ["ground_partials", "misclosure_covariance", "whitening", "observation_residuals"]


def ground_partials(model, lon, lat, h, *, step_m: float = 1.0) -> np.ndarray:
    """``d(col, row) / d(east, north, up)`` in px/m at ground points, shape (n, 2, 3).

    Central differences of ``model.project`` with ``step_m`` metre offsets along the local
    east/north/up axes (the map is smooth over metres for every model of the project).
    """
    lon, lat, h = (np.atleast_1d(np.asarray(a, dtype=np.float64)).ravel() for a in (lon, lat, h))
    X = np.stack(geodesy.geodetic_to_ecef(lon, lat, h), -1)               # (n, 3)
    basis = np.asarray(geodesy.enu_basis(lon, lat)).reshape(-1, 3, 3)    # rows east, north, up
    offsets = step_m * np.concatenate([basis, -basis], axis=1)            # (n, 6, 3)
    P = (X[:, None, :] + offsets).reshape(-1, 3)
    plon, plat, ph = geodesy.ecef_to_geodetic(P[:, 0], P[:, 1], P[:, 2])
    c, r = model.project(plon, plat, ph)
    img = np.stack([c, r], -1).reshape(-1, 6, 2)                          # (n, 6, 2)
    G = np.swapaxes((img[:, :3] - img[:, 3:]) / (2.0 * step_m), 1, 2)    # (n, 2, 3)
    return G


def misclosure_covariance(sigma_px, sigma_ground_m=None, G=None) -> np.ndarray:
    """``M = sigma_px^2 I + sigma_g^2 G G^T`` per point, shape (n, 2, 2) (px^2).

    ``sigma_ground_m`` NaN or None: the ground coordinates are fixed (Gauss–Markov).
    """
    s = np.asarray(sigma_px, dtype=np.float64)
    M = (s ** 2)[:, None, None] * np.eye(2)
    if sigma_ground_m is not None and G is not None:
        g = np.nan_to_num(np.asarray(sigma_ground_m, dtype=np.float64), nan=0.0)
        M = M + (g ** 2)[:, None, None] * np.einsum("nik,njk->nij", G, G)
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
        v_g = -(g ** 2)[:, None] * np.einsum("nik,ni->nk", G, Me)
    return v_l, v_g
