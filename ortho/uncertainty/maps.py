"""Uncertainty maps: orthoimage σ_E, σ_N, σ_horizontal, CE90 and dominant source on the ortho
grid, and the vertical σ of a stereo DEM.

Both are evaluated on a coarse lattice of the output grid and interpolated, as the ortho map
(:func:`stereodem.ortho.drm.build_backward_map`) does: the interpolation error is measured
against exact evaluations at lattice mid-cells and random cells, and the lattice is refined
until it is below the tolerance. The first-order orthoimage maps interpolate the terrain-free
fields in (x, y, h) and apply each cell's own DEM height and slope
(:mod:`stereodem.ortho.uncertainty.first_order_maps`).

The DEM vertical σ follows Bettemir (2010, eqs 9–13): the space-intersection σ of the height
(matching precision and both models' covariances through the intersection Jacobian) and the
horizontal error turned into height by the local slope of a Hirvonen-weighted quadratic
surface, ``σ_v² = σ_h,int² + (∂h/∂E σ_E)² + (∂h/∂N σ_N)²``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from stereodem.core import geodesy, jsonutil
from stereodem.core.dem import ELLIPSOID, write_layer
from stereodem.core.errors import InputError
from stereodem.core.raster import write_geotiff, write_text_atomic
from stereodem.core.stats import generator
from stereodem.ortho.choices import UNCERTAINTY_METHODS, check_samples
from stereodem.ortho.drm import build_backward_map, crop_dem
from stereodem.ortho.uncertainty.first_order_maps import _node_lattice, _weights, first_order_maps
from stereodem.ortho.uncertainty.indices import fast_indices
from stereodem.ortho.uncertainty.propagation import (
    adjustable_model,
    axis_gradient,
    ce90,
    check_names,
    check_psd,
    first_order,
    ground_jacobian,
    image_jacobian,
    propagate,
)
from stereodem.ortho.uncertainty.sampling import monte_carlo, src

log = logging.getLogger(__name__)

METHODS = UNCERTAINTY_METHODS


# ---------------------------------------------------------------------------- lattice interpolation


def _interp(L, Wy, Wx, dtype=np.float32):
    """Bilinear interpolation of a lattice field (ny, nx) to the full grid, NaN-aware (a cell
    is NaN when any of its four nodes is)."""
    ok = np.isfinite(L)
    Wy_, Wx_ = Wy.astype(dtype, copy=False), Wx.astype(dtype, copy=False)
    out = Wy_ @ (np.where(ok, L, 0.0).astype(dtype) @ Wx_.T)
    if not ok.all():
        den = Wy_ @ (ok.astype(dtype) @ Wx_.T)
        out[den < 0.999] = np.nan
    return out


def _bilinear_at(L, nodes_x, nodes_y, u, v):
    Wx = _weights(0, nodes_x, u)
    Wy = _weights(0, nodes_y, v)
    return np.einsum("ni,ij,nj->n", Wy, L, Wx)


# ----------------------------------------------------------------------------- ortho maps


@dataclass
class UncertaintyMaps:
    """Orthoimage uncertainty on a map grid.

    ``sigma_east``, ``sigma_north``, ``sigma_horizontal``, ``ce90`` (rows, cols) float32 metres
    (NaN outside the image or the DEM); ``dominant`` int16 index into ``sources`` (−1 no data);
    ``shares`` source -> fraction of the image's total horizontal variance (sums to 1).
    """

    grid: object
    method: str
    names: list
    sources: list
    sigma_east: np.ndarray
    sigma_north: np.ndarray
    ce90: np.ndarray
    dominant: np.ndarray
    shares: dict
    step: int
    interpolation_error: float
    source_maps: dict = field(default_factory=dict, repr=False)
    details: dict = field(default_factory=dict, repr=False)

    @property
    def sigma_horizontal(self):
        return np.hypot(self.sigma_east, self.sigma_north)

    def summary(self) -> dict:
        sh = self.sigma_horizontal
        ok = np.isfinite(sh)
        pct = (lambda q: float(np.nanpercentile(sh, q))) if ok.any() else (lambda q: float("nan"))
        return {
            "method": self.method,
            "parameters": self.names,
            "sources": self.sources,
            "shares": {k: float(v) for k, v in self.shares.items()},
            "sigma_horizontal_m": {"min": pct(0), "median": pct(50), "max": pct(100)},
            "ce90_m_median": float(np.nanmedian(self.ce90)) if ok.any() else float("nan"),
            "lattice_step_cells": self.step,
            "interpolation_error_relative": self.interpolation_error,
            "grid": {
                "width": self.grid.width,
                "height": self.grid.height,
                **self.grid.res_report(),  # res, res_unit (res_m only on a metre grid)
                "crs": self.grid.crs.to_string(),
            },
            **self.details,
        }

    def write(self, out_dir, *, overwrite: bool = False, source_maps: bool = False) -> list:
        """Write ``sigma_{horizontal,east,north}.tif``, ``ce90.tif``, ``dominant_source.tif``,
        ``sensitivity.json`` (and ``share_<source>.tif`` with ``source_maps``) into
        ``out_dir``; returns the paths."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        t, crs = self.grid.transform, self.grid.crs
        paths = []
        # band descriptions and units, as every other product carries (the σ are ground
        # metres whatever the grid's CRS)
        for name, arr, description in (
            ("sigma_horizontal", self.sigma_horizontal, "horizontal sigma, hypot(east, north)"),
            ("sigma_east", self.sigma_east, "sigma east"),
            ("sigma_north", self.sigma_north, "sigma north"),
            ("ce90", self.ce90, "CE90 (90 % circular error)"),
        ):
            paths.append(
                write_geotiff(
                    out / f"{name}.tif",
                    arr.astype(np.float32),
                    t,
                    crs,
                    float("nan"),
                    overwrite=overwrite,
                    descriptions=description,
                    units="metre",
                )
            )
        codes = ", ".join(f"{i} {s}" for i, s in enumerate(self.sources))
        paths.append(
            write_geotiff(
                out / "dominant_source.tif",
                self.dominant.astype(np.int16),
                t,
                crs,
                -1,
                overwrite=overwrite,
                descriptions=f"dominant source of the variance (code: {codes})",
                units="1",
            )
        )
        if source_maps:
            for k, arr in self.source_maps.items():
                paths.append(
                    write_geotiff(
                        out / f"share_{k}.tif",
                        arr.astype(np.float32),
                        t,
                        crs,
                        float("nan"),
                        overwrite=overwrite,
                        descriptions=f"share of the horizontal variance from {k} (per cell)",
                        units="1",
                    )
                )
        doc = self.summary()
        doc["dominant_source_codes"] = {i: s for i, s in enumerate(self.sources)}
        paths.append(
            write_text_atomic(
                out / "sensitivity.json",
                jsonutil.dumps(jsonutil.stamped(doc), indent=2),
                overwrite=overwrite,
            )
        )
        return paths


def _ellipsoidal(dem):
    return dem if dem.vertical == ELLIPSOID else dem.to_reference(ELLIPSOID)


def _node_fields(model, dem, grid, U, V, D, names, groups, method, samples, seed):
    """σ_E, σ_N, C_EN, image col/row and per-source horizontal variance at lattice nodes."""
    lon, lat = grid.lonlat(U.ravel(), V.ravel())
    h = dem.sample(lon, lat)
    srcs = list(groups) if groups else list(names)
    out = np.full((U.size, 5 + len(srcs)), np.nan)
    ok = np.isfinite(h)
    if not ok.any():
        return out.reshape(U.shape + (-1,)), srcs
    lo, la, hh = lon[ok], lat[ok], h[ok]
    if method == "first-order":
        pu = first_order(model, lo, la, hh, names, D, grid.crs, dem=dem, groups=groups)
        C, gj = pu.cov, pu.jacobian
        Vtot = C[:, 0, 0] + C[:, 1, 1]
        share = np.stack([pu.shares[s] for s in srcs], -1)
        col, row = gj.col, gj.row
    else:
        col, row = (np.asarray(a, float) for a in model.project(lo, la, hh))
        if method == "monte-carlo":
            X, dE, dN = monte_carlo(
                model, lo, la, hh, names, D, grid.crs, samples=samples, dem=dem, seed=seed
            )
            bE, _ = src(X, dE)
            bN, _ = src(X, dN)
            idx = {n: k for k, n in enumerate(names)}
            members = groups or {n: [n] for n in names}
            VE, VN = dE.var(0, ddof=1), dN.var(0, ddof=1)
            sh_E = np.stack([(bE[[idx[m] for m in members[s]]] ** 2).sum(0) for s in srcs], -1)
            sh_N = np.stack([(bN[[idx[m] for m in members[s]]] ** 2).sum(0) for s in srcs], -1)
        else:
            r = fast_indices(
                model, lo, la, hh, names, D, grid.crs, samples=samples, dem=dem, seed=seed
            )
            idx = {n: k for k, n in enumerate(r["names"])}
            members = groups or {n: [n] for n in names}
            VE, VN = r["variance"]
            pick = lambda S, s: sum((S[idx[m]] for m in members[s] if m in idx), np.zeros(lo.size))
            sh_E = np.stack([pick(r["S1"]["east"], s) for s in srcs], -1)
            sh_N = np.stack([pick(r["S1"]["north"], s) for s in srcs], -1)
            dE = dN = None
        tot = sh_E * VE[:, None] + sh_N * VN[:, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            share = tot / tot.sum(-1, keepdims=True)
        C = np.zeros((lo.size, 2, 2))
        C[:, 0, 0], C[:, 1, 1] = VE, VN
        if dE is not None:
            C[:, 0, 1] = C[:, 1, 0] = ((dE - dE.mean(0)) * (dN - dN.mean(0))).sum(0) / (len(dE) - 1)
        Vtot = VE + VN
    vals = np.column_stack(
        [np.sqrt(C[:, 0, 0]), np.sqrt(C[:, 1, 1]), C[:, 0, 1], col, row, share * Vtot[:, None]]
    )
    out[ok] = vals
    return out.reshape(U.shape + (-1,)), srcs


def ortho_uncertainty_maps(
    model,
    dem,
    grid,
    covariance,
    names,
    method: str = "first-order",
    *,
    samples: int = 1000,
    groups: dict | None = None,
    step: int | None = None,
    tolerance: float = 1e-3,
    n_check: int = 400,
    seed: int = 0,
    source_maps: bool = False,
    threads: int | None = None,
) -> UncertaintyMaps:
    """Per-cell horizontal uncertainty of the orthoimage of ``model`` over ``dem`` on ``grid``.

    Parameters
    ----------
    model : SensorModel
        Any model; RPC and fitted models are wrapped in an image-space correction
        (``col_shift``, ``row_shift`` ... in pixels).
    dem : DEM
        The DEM of the orthorectification (converted to ellipsoidal heights).
    grid : stereodem.ortho.grid.MapGrid
        The ortho grid (e.g. :func:`stereodem.ortho.grid.grid_for_model`).
    covariance : array_like (u, u)
        Input covariance in the order of ``names`` (units of each input squared).
    names : list of str
        Inputs (:func:`stereodem.ortho.uncertainty.propagation.valid_names`).
    method : {"first-order", "monte-carlo", "fast"}
    samples : int
        Monte Carlo samples, or FAST points per search curve.
    groups : dict, optional
        Source groups ``{group: [names]}`` for shares and the dominant source.
    step : int, optional
        Lattice spacing in cells; default chosen by refinement until the measured relative
        interpolation error (first-order: of σ_E, σ_N and σ_horizontal, against exact per-cell
        propagation) is below ``tolerance``. The sampling methods use the same lattice, with at
        most 16 × 16 nodes.
    tolerance : float
        Bound on that relative error (default 10⁻³); the measured value is
        ``UncertaintyMaps.interpolation_error``.
    source_maps : bool
        Keep each source's share map (full grid, float32 each); the dominant source is always
        computed.
    threads : int, optional
        Threads for the first-order blocks (default: the process's thread budget,
        :func:`stereodem.core.blocks.default_threads`; the maps do not depend on it).

    Returns
    -------
    UncertaintyMaps
    """
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose {', '.join(METHODS)}")
    if method != "first-order":
        check_samples(samples, "samples")
    model = adjustable_model(model, names)
    names = check_names(model, names)
    D = check_psd(np.asarray(covariance, float))
    if D.shape != (len(names), len(names)):
        raise InputError(f"covariance is {D.shape}, expected {len(names)} x {len(names)}")
    if groups:
        missing = sorted(set(names) - {m for v in groups.values() for m in v})
        if missing:
            groups = {**groups, **{m: [m] for m in missing}}
    dem = _ellipsoidal(dem)
    if method == "first-order":
        return first_order_maps(
            model,
            dem,
            grid,
            D,
            names,
            groups,
            step=step,
            tolerance=tolerance,
            n_check=n_check,
            seed=seed,
            source_maps=source_maps,
            threads=threads,
        )
    rng = generator(seed)
    big = max(grid.width, grid.height)
    st = int(step or min(64, max(1, 2 ** int(np.ceil(np.log2(max(big, 2) / 2))))))
    fixed = step is not None
    # the cells with a DEM height (the orthoimage's rule, ortho.drm.bilinear_nan); a lattice
    # node without one takes its nearest node's fields (_fill_nodes), so that a node in a hole
    # does not blank every cell around it (a NaN node made the cells of its four lattice
    # squares nodata: a ring of up to a lattice step around each void)
    has_height = _height_mask(model, dem, grid)
    while True:
        uu, vv = _node_lattice(grid, st)
        U, V = np.meshgrid(uu, vv)
        F, srcs = _node_fields(
            model, dem, grid, U, V, D, names, groups, "first-order", samples, seed
        )
        F = _fill_nodes(F)
        # measured interpolation error: exact first-order σ_h at mid-cells and random cells
        ny, nx = U.shape
        m = min(n_check // 2, (ny - 1) * (nx - 1))
        cell = rng.choice((ny - 1) * (nx - 1), size=m, replace=False)
        cu = 0.5 * (uu[cell % (nx - 1)] + uu[cell % (nx - 1) + 1])
        cv = 0.5 * (vv[cell // (nx - 1)] + vv[cell // (nx - 1) + 1])
        cu = np.concatenate([cu, rng.uniform(0, grid.width - 1, m)])
        cv = np.concatenate([cv, rng.uniform(0, grid.height - 1, m)])
        Fc, _ = _node_fields(
            model,
            dem,
            grid,
            cu[:, None],
            cv[:, None],
            D,
            names,
            groups,
            "first-order",
            samples,
            seed,
        )
        exact = np.hypot(Fc[:, 0, 0], Fc[:, 0, 1])
        inter = np.hypot(
            _bilinear_at(F[..., 0], uu, vv, cu, cv), _bilinear_at(F[..., 1], uu, vv, cu, cv)
        )
        ok = np.isfinite(exact) & np.isfinite(inter) & (exact > 0)
        err = float(np.max(np.abs(inter[ok] - exact[ok]) / exact[ok])) if ok.any() else 0.0
        log.debug("uncertainty lattice step %d: relative interpolation error %.2e", st, err)
        if fixed or err <= tolerance or st <= 1:
            break
        st //= 2
    details = {"n_lattice_nodes": int(U.size)}
    if method != "first-order":
        k = max(1, int(np.ceil(max(uu.size, vv.size) / 16)))
        if k > 1:
            uu2 = uu[::k] if uu[::k][-1] == uu[-1] else np.append(uu[::k], uu[-1])
            vv2 = vv[::k] if vv[::k][-1] == vv[-1] else np.append(vv[::k], vv[-1])
            uu, vv = uu2, vv2
            U, V = np.meshgrid(uu, vv)
            details["sampling_lattice_note"] = "sampling methods use at most 16 x 16 nodes"
        F, srcs = _node_fields(model, dem, grid, U, V, D, names, groups, method, samples, seed)
        F = _fill_nodes(F)
        details.update(n_lattice_nodes=int(U.size), samples=int(samples))
    Wx, Wy = _weights(grid.width, uu), _weights(grid.height, vv)
    sE, sN = _interp(F[..., 0], Wy, Wx), _interp(F[..., 1], Wy, Wx)
    col, row = _interp(F[..., 3], Wy, Wx), _interp(F[..., 4], Wy, Wx)
    outside = ~(
        (col >= -0.5) & (col <= model.width - 0.5) & (row >= -0.5) & (row <= model.height - 0.5)
    )
    outside |= ~has_height
    sE[outside] = sN[outside] = np.nan
    c90 = np.full(sE.shape, np.nan, np.float32)
    good = np.isfinite(sE)
    c90_nodes = ce90(
        np.stack(
            [np.stack([F[..., 0] ** 2, F[..., 2]], -1), np.stack([F[..., 2], F[..., 1] ** 2], -1)],
            -2,
        )
    )
    c90[good] = _interp(np.where(np.isfinite(F[..., 0]), c90_nodes, np.nan), Wy, Wx)[good]
    contrib = F[..., 5:]
    total = np.nansum(contrib, axis=(0, 1))
    shares = {
        s: float(total[k] / total.sum()) if total.sum() > 0 else float("nan")
        for k, s in enumerate(srcs)
    }
    dom = np.full(sE.shape, -1, np.int16)
    best = np.full(sE.shape, -np.inf, np.float32)
    kept = {}
    Vsum = np.nansum(contrib, -1)
    for k, s in enumerate(srcs):
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = _interp(contrib[..., k] / np.where(Vsum > 0, Vsum, np.nan), Wy, Wx)
        frac[~good] = np.nan
        if source_maps:
            kept[s] = frac
        better = np.isfinite(frac) & (frac > best)
        dom[better], best[better] = k, frac[better]
    return UncertaintyMaps(
        grid, method, names, srcs, sE, sN, c90, dom, shares, st, err, kept, details
    )


def _height_mask(model, dem, grid) -> np.ndarray:
    """Cells of ``grid`` with a height in ``dem``: the orthoimage's map and rule
    (:func:`stereodem.ortho.drm.build_backward_map`, :func:`stereodem.ortho.drm.bilinear_nan`)."""
    bm = build_backward_map(model, grid, crop_dem(dem, grid))
    H, W = grid.shape
    rows = max(16, min(H, 262_144 // max(W, 1)))
    out = np.zeros((H, W), bool)
    for r0 in range(0, H, rows):
        out[r0 : r0 + rows] = np.isfinite(bm.block(r0, min(H, r0 + rows))[2])
    return out


def _fill_nodes(F):
    """Lattice fields ``(ny, nx, k)`` with each node that has none (no DEM height there)
    given its nearest valid node's (the cells' own voids are masked separately)."""
    bad = ~np.isfinite(F[..., 0])
    if not bad.any() or bad.all():
        return F
    idx = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
    return F[idx[0], idx[1]]


# ----------------------------------------------------------------------------- DEM vertical σ


def hirvonen_weights(size: int, res, c: float = 12.2) -> np.ndarray:
    """Hirvonen covariance ``1/(1 + (l/c)²)`` of the ``size × size`` window posts at distance
    ``l`` (m) from the centre, as least-squares weights (Bettemir 2010, eq 9)."""
    rx, ry = (res, res) if np.isscalar(res) else res
    k = np.arange(size) - (size - 1) / 2
    X, Y = np.meshgrid(k * rx, -k * ry)
    return 1.0 / (1.0 + (np.hypot(X, Y) / c) ** 2)


def hirvonen_slope_kernels(size: int, res, c: float = 12.2):
    """Correlation kernels giving ``(∂h/∂E, ∂h/∂N)`` at a window's centre from the weighted
    least-squares quadratic ``h = a0 + a1 N + a2 E + a3 N² + a4 E² + a5 N E`` (eqs 10–11):
    rows of ``(XᵀWX)⁻¹XᵀW``, the same for every cell of a regular grid."""
    rx, ry = (res, res) if np.isscalar(res) else res
    k = np.arange(size) - (size - 1) / 2
    E, N = np.meshgrid(k * rx, -k * ry)  # row 0 is north
    E, N = E.ravel(), N.ravel()
    X = np.column_stack([np.ones_like(E), N, E, N * N, E * E, N * E])
    W = hirvonen_weights(size, res, c).ravel()
    coef = np.linalg.solve(X.T @ (W[:, None] * X), X.T * W)
    return coef[2].reshape(size, size), coef[1].reshape(size, size)


def hirvonen_slopes(heights, res, *, c: float = 12.2, size: int = 11):
    """Slopes ``(∂h/∂E, ∂h/∂N)`` (m/m) of every DEM cell (a north-up grid of posting ``res``,
    metres) from the Hirvonen-weighted quadratic surface over its ``size × size``
    neighbourhood; where that window reaches a void or the grid's edge, the DEM's own
    differences (:func:`stereodem.ortho.uncertainty.propagation.axis_gradient`: central,
    one-sided beside the void or the edge, as numpy.gradient), so that every cell with a
    height has a slope (a window reaching a void gave NaN: a ring of nodata ``size // 2``
    posts wide around every hole; one padded at the edge halved a plane's slope); NaN on the
    voids."""
    z = np.asarray(heights, float)
    bad = ~np.isfinite(z)
    zf = np.where(bad, 0.0, z)
    kE, kN = hirvonen_slope_kernels(size, res, c)
    gE = ndimage.correlate(zf, kE, mode="nearest")
    gN = ndimage.correlate(zf, kN, mode="nearest")
    rx, ry = (res, res) if np.isscalar(res) else res
    part = ndimage.maximum_filter(bad, size=size, mode="constant", cval=True)
    gE[part] = axis_gradient(z, 1)[part] / rx
    gN[part] = -axis_gradient(z, 0)[part] / ry  # rows run south
    return gE, gN


def disparity_sigma(score, *, sigma_ref: float = 0.2, score_ref: float = 0.9):
    """Matching precision (px) from the correlation score ρ: the signal-to-noise relation of
    normalised cross-correlation, ``SNR² = ρ/(1 − ρ)``, gives ``σ_d ∝ √((1 − ρ)/ρ)``, scaled so
    that ``σ_d(score_ref) = sigma_ref``."""
    rho = np.clip(np.asarray(score, float), 1e-3, 1 - 1e-6)
    return sigma_ref * np.sqrt((1 - rho) / rho) / np.sqrt((1 - score_ref) / score_ref)


def intersection_gains(left, right, lon, lat, h, crs, *, left_names=(), right_names=()):
    """Space-intersection Jacobians at ground points.

    With ``B = ∂(c₁, r₁, c₂, r₂)/∂(E, N, h)`` (4 × 3) the least-squares intersection moves by
    ``G = (BᵀB)⁻¹Bᵀ`` per pixel of observation error. Returns ``G`` (n, 3, 4), the image
    Jacobians of the two models' inputs (n, 2, u₁), (n, 2, u₂) and the right image's epipolar
    direction (unit vector of ``∂(c₂, r₂)/∂h``), (n, 2).
    """
    lon, lat, h = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, float)) for a in (lon, lat, h)))
    B = np.empty(lon.shape + (4, 3))
    for m_i, m in enumerate((left, right)):
        gj = ground_jacobian(m, lon, lat, h, ["dem_height"], crs)
        B[..., 2 * m_i : 2 * m_i + 2, :2] = gj.A
        B[..., 2 * m_i : 2 * m_i + 2, 2] = -np.einsum("...ij,...j->...i", gj.A, gj.J[..., 0])
    G = np.linalg.solve(np.einsum("...ki,...kj->...ij", B, B), np.swapaxes(B, -1, -2))
    J1 = (
        image_jacobian(left, lon, lat, h, list(left_names))[2]
        if left_names
        else np.zeros(lon.shape + (2, 0))
    )
    J2 = (
        image_jacobian(right, lon, lat, h, list(right_names))[2]
        if right_names
        else np.zeros(lon.shape + (2, 0))
    )
    e = B[..., 2:, 2] / np.linalg.norm(B[..., 2:, 2], axis=-1, keepdims=True)
    return G, J1, J2, e


@dataclass
class DEMUncertainty:
    """Vertical σ of a DEM (metres, the DEM's grid): ``sigma_vertical`` total,
    ``sigma_intersection`` (matching + models), ``sigma_slope`` (horizontal error × slope)."""

    sigma_vertical: np.ndarray
    sigma_intersection: np.ndarray
    sigma_slope: np.ndarray
    sigma_east: np.ndarray
    sigma_north: np.ndarray
    interpolation_error: float

    def write(self, dem_path, dem, *, overwrite=False):
        """Write ``<dem stem>_sigma_vertical.tif`` beside the DEM (its ``sigma`` layer,
        :data:`stereodem.core.dem.LAYERS`); returns the path."""
        return write_layer(
            dem_path, "sigma", self.sigma_vertical, dem.transform, dem.crs, overwrite=overwrite
        )


def dem_vertical_sigma(
    left,
    right,
    dem,
    *,
    left_covariance=None,
    left_names=(),
    right_covariance=None,
    right_names=(),
    score=None,
    sigma_disparity: float = 0.2,
    score_ref: float = 0.9,
    hirvonen_c: float = 12.2,
    window: int = 11,
    step: int = 16,
) -> DEMUncertainty:
    """Per-cell vertical σ of a stereo DEM (projected CRS, metres).

    Parameters
    ----------
    left, right : SensorModel
        The pair's models (RPC models get the image-shift parameters).
    dem : DEM
        The stereo DEM (its grid is the output grid; its heights give the slopes).
    left_covariance, right_covariance : (u, u) array_like, optional
        Covariances of ``left_names`` / ``right_names`` (model inputs; not ``dem_height``).
    score : ndarray, optional
        Matching score (NCC) per DEM cell; the disparity σ is :func:`disparity_sigma` of it
        (``sigma_disparity`` px everywhere when absent).
    """
    if dem.crs.is_geographic:
        raise InputError("dem_vertical_sigma needs a DEM in a projected CRS (metres)")
    left, right = adjustable_model(left, left_names), adjustable_model(right, right_names)
    left_names, right_names = list(left_names), list(right_names)
    for m, nm in ((left, left_names), (right, right_names)):
        check_names(m, nm)
        if "dem_height" in nm:
            raise InputError("dem_height is not an input of a stereo DEM")
    D1 = check_psd(
        np.asarray(
            left_covariance if left_covariance is not None else np.zeros((0, 0)), float
        ).reshape(len(left_names), len(left_names))
    )
    D2 = check_psd(
        np.asarray(
            right_covariance if right_covariance is not None else np.zeros((0, 0)), float
        ).reshape(len(right_names), len(right_names))
    )
    z = np.asarray(dem.heights, float)
    H, W = z.shape
    res = (abs(dem.transform.a), abs(dem.transform.e))
    uu = np.unique(np.append(np.arange(0, W, step), W - 1)).astype(float)
    vv = np.unique(np.append(np.arange(0, H, step), H - 1)).astype(float)
    if uu.size < 2:
        uu = np.array([0.0, 1.0])
    if vv.size < 2:
        vv = np.array([0.0, 1.0])

    def evaluate(u, v):
        x, y = dem.transform @ (u + 0.5, v + 0.5)
        lon, lat = geodesy.crs_to_lonlat(x, y, dem.crs)
        h = dem.sample(lon, lat)
        h = np.where(np.isfinite(h), h, np.nanmedian(z))
        G, J1, J2, e = intersection_gains(
            left, right, lon, lat, h, dem.crs, left_names=left_names, right_names=right_names
        )
        Cobs = np.zeros(lon.shape + (4, 4))
        Cobs[..., :2, :2] = propagate(J1, D1) if left_names else 0.0
        Cobs[..., 2:, 2:] = propagate(J2, D2) if right_names else 0.0
        Sx = np.einsum("...ik,...kl,...jl->...ij", G, Cobs, G)
        gd = np.einsum("...ik,...k->...i", G[..., :, 2:], e)  # per px of disparity
        return np.stack(
            [Sx[..., 0, 0], Sx[..., 1, 1], Sx[..., 2, 2], gd[..., 0], gd[..., 1], gd[..., 2]], -1
        )

    U, V = np.meshgrid(uu, vv)
    F = evaluate(U.ravel(), V.ravel()).reshape(U.shape + (6,))
    rng = np.random.default_rng(0)
    cu, cv = rng.uniform(0, W - 1, 200), rng.uniform(0, H - 1, 200)
    Fc = evaluate(cu, cv)
    Fi = np.stack([_bilinear_at(F[..., k], uu, vv, cu, cv) for k in range(6)], -1)
    scale = np.maximum(np.abs(Fc), 1e-12 + 1e-6 * np.abs(Fc).max(0))
    err = float(np.max(np.abs(Fi - Fc) / scale))
    Wx, Wy = _weights(W, uu), _weights(H, vv)
    full = [_interp(F[..., k], Wy, Wx, np.float64) for k in range(6)]
    sd = (
        disparity_sigma(score, sigma_ref=sigma_disparity, score_ref=score_ref)
        if score is not None
        else np.full(z.shape, float(sigma_disparity))
    )
    vE = full[0] + (sd * full[3]) ** 2
    vN = full[1] + (sd * full[4]) ** 2
    vH = full[2] + (sd * full[5]) ** 2
    gE, gN = hirvonen_slopes(z, res, c=hirvonen_c, size=window)
    slope = np.sqrt(gE**2 * vE + gN**2 * vN)
    total = np.sqrt(vH + slope**2)
    void = ~np.isfinite(z)
    for a in (total, slope):
        a[void] = np.nan
    f32 = lambda a: np.where(void, np.nan, a).astype(np.float32)
    return DEMUncertainty(
        f32(total), f32(np.sqrt(vH)), f32(slope), f32(np.sqrt(vE)), f32(np.sqrt(vN)), err
    )
