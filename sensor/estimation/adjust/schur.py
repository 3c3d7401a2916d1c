"""The pieces the pair bundle (:mod:`.bundle`) and the N-image bundle (:mod:`.bundle_multi`)
share: ground points from ENU corrections, prior (fictitious) observations and the reduced
normal equations (Schur complement of the 3 x 3 ground blocks, Brown 1976; Triggs et al. 2000).

State ``z = [x (u parameters), d (3 per tie point: east/north/up correction, metres)]``;
observation blocks are whitened (unit variance). Per tie point ``j``::

    S = N_pp - sum_j N_pg,j N_gg,j^-1 N_pg,j^T,    S dp = b_p - sum_j N_pg,j N_gg,j^-1 b_g,j,
    dg_j = N_gg,j^-1 (b_g,j - N_pg,j^T dp)
"""

from __future__ import annotations

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import SensorModelError

__all__ = [
    "SchurProblem",
    "ground_points",
    "prior_blocks",
    "reduced_normal",
    "solve_reduced",
    "back_substitute",
]


def ground_points(X0, basis, d):
    """Geodetic (lon, lat in degrees, ellipsoidal h in metres) of the points ``X0`` (n, 3, ECEF
    m) moved by their local east/north/up corrections ``d`` (n, 3, m; ``basis`` (n, 3, 3) the
    ENU unit vectors in ECEF, one per row)."""
    X = X0 + np.einsum("nij,ni->nj", basis, d)
    lon, lat, h = geodesy.ecef_to_geodetic(X[:, 0], X[:, 1], X[:, 2])
    return np.asarray(lon, float), np.asarray(lat, float), np.asarray(h, float)


def prior_blocks(x, x0, prior_idx, prior_sigma, u):
    """Whitened prior observations of the parameters ``x[prior_idx]`` around ``x0`` (σ
    ``prior_sigma``, parameter units): residuals ``e_p`` (p,) and Jacobian ``A_p`` (p, u)."""
    e_p = (x[prior_idx] - x0[prior_idx]) / prior_sigma
    A_p = np.zeros((len(prior_idx), u))
    A_p[np.arange(len(prior_idx)), prior_idx] = 1.0 / prior_sigma
    return e_p, A_p


def reduced_normal(b, u, starts=None):
    """Reduced normal equations from the whitened blocks ``b``: tie rows ``A_t`` (m, r, u),
    ``G_t`` (m, r, 3), ``e_t`` (m, r); GCP rows ``A_g``/``e_g``; priors ``A_p``/``e_p``. Each tie
    block is one point unless ``starts`` (n,) gives the first block of each point (blocks
    grouped by point), whose ground blocks are then summed. Returns dict ``S``, ``rhs`` and
    the per-point blocks :func:`back_substitute` needs."""
    A_t, G_t, e_t, Ag = b["A_t"], b["G_t"], b["e_t"], b["A_g"]
    GtT = np.swapaxes(G_t, 1, 2)
    N_pg = np.swapaxes(A_t, 1, 2) @ G_t  # (m, u, 3)
    N_gg = GtT @ G_t  # (m, 3, 3)
    b_g = -(GtT @ e_t[..., None])[..., 0]  # (m, 3)
    if starts is not None:  # -> (n, ...) per point
        N_pg, N_gg, b_g = (np.add.reduceat(a, starts, axis=0) for a in (N_pg, N_gg, b_g))
    At2 = A_t.reshape(A_t.shape[0] * A_t.shape[1], u)  # BLAS products over all rows
    Ag2 = Ag.reshape(Ag.shape[0] * Ag.shape[1], u)
    N_pp = At2.T @ At2 + Ag2.T @ Ag2 + b["A_p"].T @ b["A_p"]
    b_p = -(At2.T @ e_t.ravel() + Ag2.T @ b["e_g"].ravel() + b["A_p"].T @ b["e_p"])
    T = np.linalg.inv(N_gg)
    M = N_pg @ T  # (n, u, 3)
    S = N_pp - np.tensordot(M, N_pg, axes=([0, 2], [0, 2]))
    rhs = b_p - np.tensordot(M, b_g, axes=([0, 2], [0, 1]))
    return dict(S=S, rhs=rhs, T=T, M=M, N_pg=N_pg, b_g=b_g)


def solve_reduced(R, full_names, max_condition, what="bundle", remedy="fix one model"):
    """``(dp, S^-1, condition number)`` of the reduced system ``R`` (equilibrated eigen
    decomposition). A condition number above ``max_condition`` raises
    :class:`SensorModelError` naming the parameters of the weakest direction."""
    S = R["S"]
    if S.shape[0] == 0:
        return np.zeros(0), np.zeros((0, 0)), 1.0
    d = np.sqrt(np.diag(S))
    d = np.where(d > 0, d, 1.0)
    w, V = np.linalg.eigh(S / np.outer(d, d))
    cond = float(w[-1] / w[0]) if w[0] > 0 else float("inf")
    if cond > max_condition:
        v = V[:, 0] ** 2
        names = [full_names[k] for k in np.argsort(v)[::-1] if v[k] >= 0.1]
        raise SensorModelError(
            f"{what}: near-singular normal matrix (condition number {cond:.3g}); cannot "
            f"separate {', '.join(names)} — add GCPs, {remedy} or add priors"
        )
    Sinv = (V / w) @ V.T / np.outer(d, d)
    return Sinv @ R["rhs"], Sinv, cond


def back_substitute(R, dp, Sinv):
    """The Gauss–Newton step ``dz = [dp, dg]`` and its standard deviations (cofactors, same
    order) from the reduced system ``R`` solved for ``dp`` with ``S^-1 = Sinv``."""
    rg = R["b_g"] - np.tensordot(R["N_pg"], dp, axes=([1], [0]))
    dg = (R["T"] @ rg[..., None])[..., 0]
    sp_ = np.sqrt(np.maximum(np.diag(Sinv), 1e-300))
    MS = np.tensordot(R["M"], Sinv, axes=([1], [0]))  # (n, 3, u)
    qgg = np.einsum("nii->ni", R["T"]) + np.sum(MS * np.swapaxes(R["M"], 1, 2), axis=2)
    sg = np.sqrt(np.maximum(qgg, 1e-300))
    return np.concatenate([dp, dg.ravel()]), np.concatenate([sp_, sg.ravel()])


class SchurProblem:
    """What the pair and N-image bundle problems share: the state ``z = [x (u), d (3 n)]``, the
    ground points and the Gauss–Newton step from the reduced normal equations. Subclasses set
    ``u``, ``n``, ``x0``, ``X0``, ``basis``, ``full_names`` and ``blocks(z)``; ``starts`` (first
    tie block of each point, None: one block per point) and ``remedy`` (the datum advice of the
    near-singular error)."""

    starts = None
    remedy = "fix one model"

    def z0(self):
        return np.concatenate([self.x0, np.zeros(3 * self.n)])

    def ground(self, z):
        """(lon, lat, h) of the tie points at ``z`` (degrees, metres)."""
        return ground_points(self.X0, self.basis, z[self.u :].reshape(self.n, 3))

    def reduced(self, b):
        """Reduced normal equations ``S dp = rhs`` and the per-point blocks."""
        return reduced_normal(b, self.u, self.starts)

    def solve_reduced(self, R, max_condition):
        return solve_reduced(R, self.full_names, max_condition, remedy=self.remedy)

    def step(self, b, max_condition):
        """``(dz, its standard deviations, R, S^-1, condition number)`` at the blocks ``b``."""
        R = self.reduced(b)
        dp, Sinv, cond = self.solve_reduced(R, max_condition)
        dz, sig = back_substitute(R, dp, Sinv)
        return dz, sig, R, Sinv, cond
