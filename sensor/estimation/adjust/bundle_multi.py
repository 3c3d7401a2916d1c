"""Bundle adjustment of N images: every model and the tie points' ground coordinates
estimated together from tie points seen in two or more images, with optional GCPs.

The pair version (:mod:`.bundle`) generalised to tie *tracks*: a tie point is observed in any
subset of the images (``TieTracks``: one row per observation — point, image, col, row); pair
matches that share a pixel of one image are chained into one track (:func:`tracks_from_pairs`),
so a point matched 0–1 and 0–2 is one ground point seen three times.

Unknowns: the free parameters of every model (``u``, image by image) and, per tie point, a
ground correction in its local east/north/up frame (3 per point, metres, about its first
intersection). Observations: each tie observation's (col, row) (σ ``sigma_tie_px``), each
GCP's (col, row) in the image(s) where it was measured (ground fixed), parameter priors.

Solution: Gauss–Newton on the reduced normal equations (Schur complement of the 3 x 3 ground
blocks, Brown 1976; Triggs et al. 2000), vectorised over observations and points: per point
``N_gg = sum_o G_o^T G_o``, ``N_pg = sum_o A_o^T G_o`` (segment sums over its observations),
``S = N_pp - sum_j N_pg,j N_gg,j^-1 N_pg,j^T``. Cost O(m u^2 + n u^2) for m observations
and n points. Statistics from the reduced system as in the pair version: ``Q_pp = S^-1``,
hat diagonal ``h_o = b_o S^-1 b_o^T + g_o N_gg,j^-1 g_o^T`` with ``b_o = A_o - G_o M_j^T``;
data snooping rejects whole points whose largest standardised residual exceeds Baarda's
(σ known) critical value, in rounds.

Datum: tie points fix only the relative orientation of the images. GCPs fix the datum; without
them one image is held fixed (``fixed``, default the first), or priors on every parameter
hold it; otherwise the near-singular normal matrix is reported, naming the parameters. Holding
one image is not a full datum: a common height offset of the ties moves each other image along
its epipolar lines and nothing else, so without GCPs the free images' image-space corrections
get the pair's datum priors about their start values
(:data:`stereodem.sensor.estimation.adjust.bundle.DATUM_PRIOR_SIGMA_PX`), as
:func:`~stereodem.sensor.estimation.adjust.bundle.bundle_adjust` does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from stereodem.core import geodesy
from stereodem.core.errors import ConvergenceError, InputError
from stereodem.core.stats import check_sigma
from stereodem.sensor.estimation.adjust import gauss_markov as gm
from stereodem.sensor.estimation.adjust import reliability as rel
from stereodem.sensor.estimation.adjust import schur
from stereodem.sensor.estimation.adjust.bundle import (
    _datum_priors,
    _resolve,
    gcp_block,
    initial_ground,
    tie_block,
    tie_parallax,
)
from stereodem.sensor.estimation.adjust.model_sets import parameter_unit
from stereodem.sensor.estimation.adjust.result import ParameterEstimate, _num, fit_statistics, rmse
from stereodem.sensor.estimation.adjust.single import _check_arrays, _sigmas
from stereodem.sensor.io.sidecar import model_to_dict

__all__ = ["TieTracks", "tracks_from_pairs", "bundle_adjust_images", "MultiBundleResult"]


@dataclass
class TieTracks:
    """Tie observations: observation ``o`` is point ``point[o]`` measured at ``(col[o],
    row[o])`` (px) in image ``image[o]``; points are numbered 0..n-1, each seen in at least
    two different images."""

    point: np.ndarray
    image: np.ndarray
    col: np.ndarray
    row: np.ndarray

    def __post_init__(self):
        self.point = np.asarray(self.point, np.int64)
        self.image = np.asarray(self.image, np.int64)
        self.col = np.asarray(self.col, np.float64)
        self.row = np.asarray(self.row, np.float64)
        order = np.lexsort((self.image, self.point))  # observations grouped by point
        for name in ("point", "image", "col", "row"):
            setattr(self, name, getattr(self, name)[order])

    @property
    def n_points(self) -> int:
        return int(self.point.max()) + 1 if self.point.size else 0

    def __len__(self):
        return self.point.size

    def subset(self, keep_points) -> TieTracks:
        """The observations of the points where ``keep_points`` (n,) is true, renumbered."""
        keep_points = np.asarray(keep_points, bool)
        new = np.cumsum(keep_points) - 1
        sel = keep_points[self.point]
        return TieTracks(new[self.point[sel]], self.image[sel], self.col[sel], self.row[sel])

    def pairs(self) -> dict:
        """Per image pair ``(i, j)``, i < j: the ties ``(n, 4)`` (col_i, row_i, col_j, row_j) of
        the points seen in both (a point seen k times gives k(k-1)/2 pairs)."""
        out = {}
        starts = np.flatnonzero(np.r_[True, np.diff(self.point) != 0])
        counts = np.diff(np.r_[starts, self.point.size])
        for a in range(int(counts.max(initial=0))):
            for b in range(a + 1, int(counts.max(initial=0))):
                ok = counts > b
                oa, ob = starts[ok] + a, starts[ok] + b
                for i, j in set(zip(self.image[oa].tolist(), self.image[ob].tolist())):
                    s = (self.image[oa] == i) & (self.image[ob] == j)
                    t = np.column_stack(
                        [self.col[oa[s]], self.row[oa[s]], self.col[ob[s]], self.row[ob[s]]]
                    )
                    out[(i, j)] = np.concatenate([out[(i, j)], t]) if (i, j) in out else t
        return out


def tracks_from_pairs(pair_ties: dict, *, decimals: int = 2) -> TieTracks:
    """Tie tracks from pairwise matches ``{(i, j): (n, 4) col_i, row_i, col_j, row_j}``.

    Matches that share a pixel of an image (to ``10**-decimals`` px) are chained into one
    point (connected components of the match graph, :mod:`scipy.sparse.csgraph`); a chain
    that meets one image at two different pixels is inconsistent and dropped.
    """
    imgs, cols, rows, edges = [], [], [], []
    base = 0
    for (i, j), t in pair_ties.items():
        t = np.asarray(t, np.float64).reshape(-1, 4)
        if i == j:
            raise InputError(f"bundle: tie points of image {i} with itself")
        if not np.all(np.isfinite(t)):
            raise InputError(f"bundle: tie points of images {i}/{j} with NaN/inf coordinates")
        n = len(t)
        imgs += [np.full(n, i), np.full(n, j)]
        cols += [t[:, 0], t[:, 2]]
        rows += [t[:, 1], t[:, 3]]
        edges.append(np.column_stack([base + np.arange(n), base + n + np.arange(n)]))
        base += 2 * n
    if base == 0:
        return TieTracks(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    image, col, row = np.concatenate(imgs), np.concatenate(cols), np.concatenate(rows)
    key = np.column_stack([image, np.round(col * 10**decimals), np.round(row * 10**decimals)])
    _, node = np.unique(key, axis=0, return_inverse=True)
    node = node.ravel()
    e = node[np.concatenate(edges)]
    nn = int(node.max()) + 1
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nn, nn))
    _, comp = connected_components(g, directed=False)
    # one observation per node; a component must not hold two nodes of one image
    first = np.unique(node, return_index=True)[1]
    n_img, n_comp = int(image.max()) + 1, int(comp.max()) + 1
    per = np.bincount(comp * n_img + image[first], minlength=n_comp * n_img).reshape(n_comp, n_img)
    good = (per.max(axis=1) <= 1) & ((per > 0).sum(axis=1) >= 2)
    keep = good[comp[node[first]]]
    new = np.cumsum(good) - 1
    f = first[keep]
    return TieTracks(new[comp[node[f]]], image[f], col[f], row[f])


class _Problem(schur.SchurProblem):
    """The whitened N-image problem; state ``z = [x (u), d (3 n, ENU m)]``."""

    remedy = "fix one image"

    def __init__(self, models, names, priors, tracks: TieTracks, gcps, sigma_tie, gcp_sigma):
        self.models, self.names = models, names
        self.off = np.cumsum([0] + [len(nm) for nm in names])
        self.u = int(self.off[-1])
        self.x0 = np.array(
            [models[k].parameters()[nm] for k in range(len(models)) for nm in names[k]], float
        )
        self.full_names = [f"image{k}.{nm}" for k in range(len(models)) for nm in names[k]]
        allp = {f"image{k}.{nm}": v for k, pk in enumerate(priors) for nm, v in pk.items()}
        self.prior_idx = np.array([self.full_names.index(k) for k in allp], dtype=int)
        self.prior_sigma = np.array(list(allp.values()), dtype=float)
        self.tracks, self.n, self.m = tracks, tracks.n_points, len(tracks)
        self.sigma_tie = float(sigma_tie)
        self.starts = (
            np.flatnonzero(np.r_[True, np.diff(tracks.point) != 0]) if self.m else np.zeros(0, int)
        )
        self.gcps, self.gcp_sigma = gcps, gcp_sigma
        self.X0 = self._initial_ground()
        lon, lat, _ = geodesy.ecef_to_geodetic(self.X0[:, 0], self.X0[:, 1], self.X0[:, 2])
        self.basis = np.asarray(geodesy.enu_basis(lon, lat)).reshape(-1, 3, 3)

    def _initial_ground(self):
        """Each point's first two observations intersected (:func:`.bundle.initial_ground`)."""
        t = self.tracks
        if self.n == 0:
            return np.zeros((0, 3))
        a, b = self.starts, self.starts + 1
        X = np.empty((self.n, 3))
        ia, ib = t.image[a], t.image[b]
        for i, j in set(zip(ia.tolist(), ib.tolist())):
            s = (ia == i) & (ib == j)
            ties = np.column_stack([t.col[a[s]], t.row[a[s]], t.col[b[s]], t.row[b[s]]])
            X[s] = initial_ground(self.models[i], self.models[j], ties)
        return X

    def model_at(self, z, k):
        if not self.names[k]:
            return self.models[k]
        vals = z[self.off[k] : self.off[k + 1]]
        return self.models[k].with_parameters(**dict(zip(self.names[k], (float(v) for v in vals))))

    def blocks(self, z, *, jacobian=True):
        """Whitened residuals and Jacobian blocks: ``e_t`` (m, 2), ``A_t`` (m, 2, u), ``G_t``
        (m, 2, 3) per tie observation; ``e_g`` (k, 2), ``A_g`` (k, 2, u) per GCP observation;
        ``e_p``, ``A_p`` for the priors."""
        u, t = self.u, self.tracks
        lon, lat, h = self.ground(z)
        e_t = np.empty((self.m, 2))
        A_t = np.zeros((self.m, 2, u)) if jacobian else None
        G_t = np.empty((self.m, 2, 3)) if jacobian else None
        e_g, A_g = [], []
        for k in range(len(self.models)):
            mdl, names, off = self.model_at(z, k), self.names[k], self.off[k]
            sel = np.flatnonzero(t.image == k)
            if sel.size:
                pts = t.point[sel]
                e_t[sel], A, G = tie_block(
                    mdl,
                    names,
                    (lon[pts], lat[pts], h[pts]),
                    np.column_stack([t.col[sel], t.row[sel]]),
                    self.sigma_tie,
                    jacobian,
                )
                if A is not None:
                    A_t[sel, :, off : off + len(names)] = A
                if jacobian:
                    G_t[sel] = G
            p = self.gcps[k]
            if p is not None and len(p):
                s = self.gcp_sigma[k][:, None]
                gcp_block(
                    mdl,
                    names,
                    p,
                    (off, u),
                    jacobian,
                    e_g,
                    A_g,
                    lambda mis, s=s: mis / s,
                    lambda J, s=s: J / s[:, :, None],
                )
        e_g = np.concatenate(e_g) if e_g else np.zeros((0, 2))
        A_g = np.concatenate(A_g) if A_g else np.zeros((0, 2, u))
        e_p, A_p = schur.prior_blocks(z[:u], self.x0, self.prior_idx, self.prior_sigma, u)
        return dict(e_t=e_t, A_t=A_t, G_t=G_t, e_g=e_g, A_g=A_g, e_p=e_p, A_p=A_p)

    def cost(self, z) -> float:
        b = self.blocks(z, jacobian=False)
        e = np.concatenate([b["e_t"].ravel(), b["e_g"].ravel(), b["e_p"]])
        return float(e @ e) if np.all(np.isfinite(e)) else float("inf")


@dataclass
class MultiBundleResult(ParameterEstimate):
    """Result of :func:`bundle_adjust_images` (``to_report()`` is ``adjust_report.json``).

    ``models``: the adjusted models; ``tie_residuals_px`` (m, 2) per tie observation (of
    ``tracks``, rejected points included, from the final models); ``tie_rejected`` (n,) per
    point; ``ray_gaps_before``/``ray_gaps_after``: per image pair, the rays' closest-approach
    distances and reprojection discrepancies of the ties the two images share
    (:func:`.bundle.tie_parallax`).
    """

    models: list
    model_sets: list
    tracks: TieTracks
    tie_residuals_px: np.ndarray
    tie_rejected: np.ndarray
    tie_h: np.ndarray
    tie_ray_gap_m: np.ndarray
    gcp_residuals_px: list
    check_residuals_px: list
    fixed: list = field(default_factory=list)
    gcp_points: list = field(default_factory=list)
    check_points: list = field(default_factory=list)
    ray_gaps_before: dict = field(default_factory=dict)
    ray_gaps_after: dict = field(default_factory=dict)

    @property
    def model(self):
        return self.models[0]

    @property
    def tie_rmse_px(self) -> float:
        kept = ~self.tie_rejected[self.tracks.point]
        return rmse(self.tie_residuals_px[kept])

    def point_ray_gaps(self) -> dict:
        """Distances (m) of the kept tie observations' rays from their adjusted points: RMS and
        median over all, and RMS per image (the N-ray analogue of a pair's ray gap; unlike
        the pairwise gaps it sees a disagreement along the epipolar lines too)."""
        kept = ~self.tie_rejected[self.tracks.point]
        g = self.tie_ray_gap_m

        def rms(v):
            v = v[np.isfinite(v)]
            return _num(np.sqrt(np.mean(v**2))) if v.size else None

        return {
            "rms_m": rms(g[kept]),
            "median_m": _num(np.nanmedian(g[kept])) if kept.any() else None,
            "rms_m_per_image": [
                rms(g[kept & (self.tracks.image == k)]) for k in range(len(self.models))
            ],
        }

    def image_rmse_px(self) -> list:
        kept = ~self.tie_rejected[self.tracks.point]
        return [
            rmse(self.tie_residuals_px[kept & (self.tracks.image == k)])
            for k in range(len(self.models))
        ]

    def to_report(self) -> dict:
        kept = ~self.tie_rejected
        n_obs_kept = int((~self.tie_rejected[self.tracks.point]).sum())

        def pair_key(k):
            return f"{k[0]}-{k[1]}"

        return {
            "model": {f"image{k}": model_to_dict(m) for k, m in enumerate(self.models)},
            "model_set": "bundle",
            "model_sets": {f"image{k}": s for k, s in enumerate(self.model_sets)},
            "fixed_images": self.fixed,
            "solver": "schur",
            **self._estimate_report(len(self.names) + 3 * int(kept.sum())),
            "points": [],
            "gcp_rmse_px": _num(
                rmse(np.concatenate([r for r in self.gcp_residuals_px if r is not None]))
                if any(r is not None for r in self.gcp_residuals_px)
                else float("nan")
            ),
            "check_rmse_px": _num(
                rmse(np.concatenate([r for r in self.check_residuals_px if r is not None]))
                if any(r is not None for r in self.check_residuals_px)
                else float("nan")
            ),
            "n_gcp": int(sum(len(r) for r in self.gcp_residuals_px if r is not None)),
            "n_check": int(sum(len(r) for r in self.check_residuals_px if r is not None)),
            "ties": {
                "n": int(len(kept)),
                "rejected": int(self.tie_rejected.sum()),
                "observations": int(len(self.tracks)),
                "observations_kept": n_obs_kept,
                "rmse_px": _num(self.tie_rmse_px),
                "rmse_px_per_image": [_num(v) for v in self.image_rmse_px()],
            },
            "point_ray_gaps": self.point_ray_gaps(),
            "ray_gaps_before": {pair_key(k): v for k, v in self.ray_gaps_before.items()},
            "ray_gaps_after": {pair_key(k): v for k, v in self.ray_gaps_after.items()},
            "outliers": [o["id"] for o in self.outliers],
            **self._test_report(),
            "convergence_criterion": (
                f"max |dz_k| / sigma_k < {self.tolerance:g} (parameters and tie ground coordinates)"
            ),
            "regularization": None,
        }

    def figures(self, *, max_points: int = 2000):
        """Per image ``{"image<k>": (report, width, height)}`` for the residual figures: its
        kept tie observations (at most ``max_points``) and GCP/check residuals."""
        base = self.to_report()
        kept = ~self.tie_rejected[self.tracks.point]
        out = {}
        for k, m in enumerate(self.models):
            idx = np.flatnonzero(kept & (self.tracks.image == k))
            idx = (
                idx[np.linspace(0, idx.size - 1, min(idx.size, max_points)).astype(int)]
                if idx.size
                else idx
            )
            pts = [
                {
                    "id": f"tie{int(self.tracks.point[o])}",
                    "role": "tie",
                    "col": float(self.tracks.col[o]),
                    "row": float(self.tracks.row[o]),
                    "residual_px": [float(v) for v in self.tie_residuals_px[o]],
                    "outlier": False,
                }
                for o in idx
            ]
            for role, res, pts_k in (
                ("gcp", self.gcp_residuals_px[k], self.gcp_points[k]),
                ("check", self.check_residuals_px[k], self.check_points[k]),
            ):
                if res is None:
                    continue
                pts += [
                    {
                        "id": str(pts_k.id[i]),
                        "role": role,
                        "col": float(pts_k.col[i]),
                        "row": float(pts_k.row[i]),
                        "residual_px": [float(v) for v in res[i]],
                        "outlier": False,
                    }
                    for i in range(len(res))
                ]
            out[f"image{k}"] = ({**base, "points": pts}, m.width, m.height)
        return out


def _ray_gaps(models, tracks, *, max_points: int = 2000) -> dict:
    """:func:`.bundle.tie_parallax` of every image pair sharing tie points."""
    return {
        k: tie_parallax(models[k[0]], models[k[1]], t, max_points=max_points)
        for k, t in sorted(tracks.pairs().items())
    }


def bundle_adjust_images(
    models,
    tracks: TieTracks,
    *,
    names="rpc-shift",
    gcps=None,
    fixed=None,
    priors=None,
    sigma_tie_px: float = 0.5,
    sigma_px=None,
    max_iterations: int = 20,
    tolerance: float = 1e-2,
    snooping: bool = True,
    alpha: float = 0.001,
    max_tie_rounds: int = 5,
    max_condition: float = gm.MAX_CONDITION,
    ray_gaps: bool = True,
) -> MultiBundleResult:
    """Bundle adjustment of N images (see the module docstring).

    Parameters
    ----------
    models : list of sensor models
    tracks : TieTracks
        Tie observations (:func:`tracks_from_pairs` builds them from pairwise matches).
    names : str, list
        A model-set name for every image (``"rpc-shift"``...), or one entry per image (a
        model-set name, a list of parameter names, or None to hold that image fixed).
    gcps : list of ControlPoints or None, optional
        Per image, its GCPs (role ``gcp``, ground fixed) and check points (role ``check``).
    fixed : int or list of int, optional
        Images held fixed. Default: the first image when no GCP is given (the datum), none
        otherwise.
    priors : list of dict, optional
        Per image, ``{parameter: sigma}`` priors (fictitious observations of the start values).
    sigma_tie_px : float
        A-priori σ of a tie observation's image coordinates (px).
    ray_gaps : bool
        Measure the per-pair ray gaps before and after (a diagnostic; 2000 ties per pair) and
        every ray's distance from its adjusted point (``tie_ray_gap_m``; NaN without).
    """
    sigma_tie_px = check_sigma(sigma_tie_px, "sigma_tie_px")
    if sigma_px is not None:
        sigma_px = check_sigma(sigma_px, "sigma_px")
    n_img = len(models)
    if n_img < 2:
        raise InputError(f"bundle: needs at least two images, got {n_img}")
    max_iterations = gm.check_max_iterations(max_iterations)
    gcps = list(gcps) if gcps is not None else [None] * n_img
    priors = list(priors) if priors is not None else [None] * n_img
    if len(gcps) != n_img or len(priors) != n_img:
        raise InputError(
            f"bundle: {n_img} images but {len(gcps)} GCP sets / {len(priors)} prior sets"
        )
    per = [names] * n_img if isinstance(names, str) or names is None else list(names)
    if len(per) != n_img:
        raise InputError(f"bundle: {n_img} images but {len(per)} parameter sets")
    has_gcp = any(g is not None and np.any(g.role == "gcp") for g in gcps)
    if fixed is None:
        fixed = [] if has_gcp else [0]
    fixed = sorted({int(fixed)} if np.isscalar(fixed) else {int(k) for k in fixed})
    if any(not 0 <= k < n_img for k in fixed):
        raise InputError(f"bundle: fixed image index out of range 0..{n_img - 1}: {fixed}")
    for k in fixed:
        per[k] = None
    if len(tracks) and (tracks.image.max() >= n_img or tracks.image.min() < 0):
        raise InputError(
            f"bundle: tie observations of image {int(tracks.image.max())}, but {n_img} images"
        )
    resolved = [
        _resolve(m, nm, pr, f"image {k}") for k, (m, nm, pr) in enumerate(zip(models, per, priors))
    ]
    ms = [r[0] for r in resolved]
    nms = [r[1] for r in resolved]
    prs = [r[2] for r in resolved]
    if not has_gcp:  # a common height offset of the ties moves every free image along its
        # epipolar lines: datum priors about the start values, as in the pair's bundle
        prs = [_datum_priors(m, nm, pr) for m, nm, pr in zip(ms, nms, prs)]
    sets = [r[3] for r in resolved]
    gcp_sets, chk_sets, sig_sets, known_all = [], [], [], []
    for k, g in enumerate(gcps):
        if g is None:
            gcp_sets.append(None), chk_sets.append(None), sig_sets.append(None)
            continue
        _check_arrays(g, f"bundle (image {k} GCPs)")
        gg, cc = g.select("gcp"), g.select("check")
        s, known = _sigmas(gg, sigma_px)
        gcp_sets.append(gg), chk_sets.append(cc), sig_sets.append(s), known_all.append(known)
    sigma_known = all(known_all) if known_all else True
    u = sum(len(n) for n in nms)
    n_obs = (
        2 * len(tracks)
        + sum(2 * len(g) for g in gcp_sets if g is not None)
        + sum(len(p) for p in prs)
    )
    if n_obs - u - 3 * tracks.n_points < 1:
        raise InputError(
            f"bundle: {u} free parameter(s) and {tracks.n_points} tie point(s) need more "
            f"observations: have {n_obs}, need at least {u + 3 * tracks.n_points + 1}"
        )
    before = _ray_gaps(ms, tracks) if ray_gaps and len(tracks) else {}
    active = np.ones(tracks.n_points, bool)
    outliers, x_prev, rounds = [], None, 0
    thr = rel.baarda_threshold(alpha)
    while True:
        sub = tracks.subset(active)
        prob = _Problem(ms, nms, prs, sub, gcp_sets, sigma_tie_px, sig_sets)
        z, sol = _solve(prob, max_iterations, tolerance, max_condition, x_prev)
        b, R, Sinv = sol["b"], sol["R"], sol["Sinv"]
        e_all = np.concatenate([b["e_t"].ravel(), b["e_g"].ravel(), b["e_p"]])
        dof = e_all.size - prob.u - 3 * prob.n
        vtpv = float(e_all @ e_all)
        sigma0 = math.sqrt(vtpv / dof) if dof > 0 else float("nan")
        if not snooping or rounds >= max_tie_rounds or prob.n == 0:
            break
        # hat diagonal of tie observations (reduced form), standardised residuals per point
        Mo = R["M"][sub.point]  # (m, u, 3)
        Bt = b["A_t"] - b["G_t"] @ np.swapaxes(Mo, 1, 2)
        h_t = np.sum((Bt @ Sinv) * Bt, axis=2) + np.sum(
            (b["G_t"] @ R["T"][sub.point]) * b["G_t"], axis=2
        )
        scale = 1.0 if sigma_known else sigma0
        w_t = rel.standardized_residuals(b["e_t"], np.clip(1 - h_t, 0, 1), scale)
        stat = np.zeros(prob.n)
        np.maximum.at(stat, sub.point, np.nan_to_num(np.nanmax(np.abs(w_t), axis=1), nan=0.0))
        bad = stat > thr
        if not bad.any() or prob.n - bad.sum() < 2:
            break
        active[np.flatnonzero(active)[bad]] = False
        rounds += 1
        x_prev = z[: prob.u]
    if (~active).any():
        outliers.append(
            {
                "id": f"{int((~active).sum())} tie point(s)",
                "kind": "tie",
                "statistic": None,
                "threshold": thr,
                "reason": f"standardised residual above {thr:.2f} in "
                f"{rounds} round(s) of tie-point snooping",
            }
        )
    final = [prob.model_at(z, k) for k in range(n_img)]
    # residuals of every observation from the final models (rejected points re-intersected
    # from their first two observations)
    lon, lat, h = (np.full(tracks.n_points, np.nan) for _ in range(3))
    lon[active], lat[active], h[active] = prob.ground(z)
    if (~active).any():
        rej = _Problem(
            final,
            [[] for _ in final],
            [{} for _ in final],
            tracks.subset(~active),
            [None] * n_img,
            sigma_tie_px,
            [None] * n_img,
        )
        lon[~active], lat[~active], h[~active] = rej.ground(rej.z0())
    res = np.full((len(tracks), 2), np.nan)
    for k, m in enumerate(final):
        s = tracks.image == k
        if s.any():
            c, r = m.project(lon[tracks.point[s]], lat[tracks.point[s]], h[tracks.point[s]])
            res[s] = np.column_stack([np.asarray(c) - tracks.col[s], np.asarray(r) - tracks.row[s]])
    gap = np.full(len(tracks), np.nan)  # distance of each ray from its point, m
    X = np.column_stack(geodesy.geodetic_to_ecef(lon, lat, h))
    for k, m in enumerate(final):
        s = np.flatnonzero(tracks.image == k) if ray_gaps else np.zeros(0, int)
        if s.size:
            o, d = m.rays(tracks.col[s], tracks.row[s])
            gap[s] = np.linalg.norm(np.cross(X[tracks.point[s]] - o, d), axis=1)
    gres, cres = [], []
    for k, m in enumerate(final):
        for sets_, out in ((gcp_sets, gres), (chk_sets, cres)):
            p = sets_[k]
            if p is None or not len(p):
                out.append(None)
                continue
            c, r = m.project(p.lon, p.lat, p.h)
            out.append(np.column_stack([np.asarray(c) - p.col, np.asarray(r) - p.row]))
    scale = 1.0 if sigma_known else sigma0
    cov = Sinv * scale**2
    units = [
        parameter_unit(ms[int(nm.split(".", 1)[0][5:])], nm.split(".", 1)[1])
        for nm in prob.full_names
    ]
    return MultiBundleResult(
        names=prob.full_names,
        values=z[: prob.u],
        initial_values=prob.x0,
        std=np.sqrt(np.diag(cov)) if prob.u else np.zeros(0),
        units=units,
        covariance=cov,
        condition=sol["cond"],
        **fit_statistics(vtpv, dof, e_all.size, sigma_known),
        models=final,
        model_sets=sets,
        tracks=tracks,
        tie_residuals_px=res,
        tie_rejected=~active,
        tie_h=h,
        tie_ray_gap_m=gap,
        gcp_residuals_px=gres,
        check_residuals_px=cres,
        outliers=outliers,
        iterations=sol["iterations"],
        converged=True,
        tolerance=tolerance,
        test={
            "name": "baarda",
            "alpha": alpha,
            "threshold": float(thr),
            "snooping": bool(snooping),
        },
        fixed=fixed,
        gcp_points=gcp_sets,
        check_points=chk_sets,
        ray_gaps_before=before,
        ray_gaps_after=_ray_gaps(final, tracks.subset(active)) if ray_gaps and active.any() else {},
    )


def _solve(prob, max_iterations, tolerance, max_condition, x_start=None):
    """Gauss–Newton with step halving on the reduced system; ``(z, info)`` at the solution."""
    z = prob.z0()
    if x_start is not None:
        z[: prob.u] = x_start
    worst, it = np.inf, 0
    for _ in range(max_iterations + 1):
        b = prob.blocks(z)
        dz, sig, R, Sinv, cond = prob.step(b, max_condition)
        worst = float(np.max(np.abs(dz) / sig)) if dz.size else 0.0
        if worst < tolerance or it >= max_iterations:
            break
        e = np.concatenate([b["e_t"].ravel(), b["e_g"].ravel(), b["e_p"]])
        cost, step = float(e @ e), 1.0
        for _ in range(10):
            zn = z + step * dz
            if prob.cost(zn) <= cost * (1 + 1e-9) + 1e-12:
                break
            step *= 0.5
        else:
            if worst < gm.STATIONARY_SIGMA:
                worst = 0.0
            break
        z = zn
        it += 1
    if worst >= tolerance:
        raise ConvergenceError(
            f"bundle: no convergence in {it} iteration(s) (last correction "
            f"{worst:.3g} sigma; criterion max |dz|/sigma < {tolerance:g})"
        )
    return z, {"R": R, "Sinv": Sinv, "cond": cond, "sigma": sig, "iterations": it, "b": b}
