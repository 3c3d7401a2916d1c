"""First-order propagation of sensor-model errors to ground positions (Bettemir 2010, eqs 4–8,
14–15).

The ground point of an image pixel is where its line of sight meets the DEM. A small change
``δp`` of the model's inputs moves the pixel's image position by ``J_img δp`` (pixels) at a
fixed ground point; the ground point of the pixel then moves by ::

    δG = −A⁻¹ J_img δp,        A = ∂(col, row)/∂(E, N) on the DEM surface

where ``A`` includes the DEM slope (``∂(col,row)/∂h · ∇h``) when a DEM is given. ``(E, N)`` are
metres in the output map CRS. The inputs are named:

* the model's own adjustable parameters (``model.parameters()``; an RPC image is wrapped in
  :class:`~stereodem.sensor.models.corrected.ImageCorrectedModel` so that ``col_shift``,
  ``row_shift`` in pixels are available),
* ``dem_height`` (m): an error of the DEM height under the pixel,
* ``imaging_time`` (s): an error of the recorded acquisition time (the satellite state is read
  at the wrong epoch). Pushbroom models carry it as their ``time_offset``; frame cameras are
  advanced along their orbit.

Propagation with a full covariance ``D`` gives ``Σ = J D Jᵀ`` per point; the variance share of
input ``k`` is its covariance contribution ``J_k (D Jᵀ)_k / V``, which is Helton's
``(∂f/∂x_k)² V(x_k)/V(y)`` for a diagonal ``D`` and sums to 1 over the inputs in all cases.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import erf as _erf

from stereodem.core import geodesy
from stereodem.core.errors import InputError
from stereodem.ortho.drm import bilinear_nan
from stereodem.sensor.models.corrected import ImageCorrectedModel
from stereodem.sensor.models.frame import FrameCamera
from stereodem.sensor.models.parameters import is_adjustable, project_jacobian

#: pseudo-parameters understood on top of a model's own parameters (name -> unit)
EXTRA_PARAMETERS = {"dem_height": "m", "imaging_time": "s"}

#: central-difference steps of the pseudo-parameters and of the ground coordinates
DEM_HEIGHT_STEP = 1.0  # m
IMAGING_TIME_STEP = 1e-3  # s
GROUND_STEP = 1.0  # m

#: chi-distribution quantile of a circular normal at 90 % (CE90 = 2.1460 σ per axis)
CE90_CIRCULAR = 2.145966


#: central-difference steps by parameter unit: large enough that the image motion (≥ 10⁻³ px
#: for the sensors of the project) dominates the round-off of iterative projections, small
#: enough that the truncation error stays below 10⁻³ (tested per parameter)
UNIT_STEPS = {
    "rad": 1e-6,
    "m": 0.5,
    "s": 1e-3,
    "rad/s": 1e-7,
    "1": 1e-5,
    "px": 1.0,
    "px/px": 1e-4,
    "mm": 1e-3,
}


# ----------------------------------------------------------------------------- models


def adjustable_model(model, names=()):
    """The model to propagate through: ``model`` itself if it has adjustable parameters, else
    wrapped in an image-space correction (RPC and fitted models: ``col_shift``,
    ``row_shift`` ... in pixels). The correction applies to any model, as ``stereodem
    adjust``'s ``rpc-*`` parameter sets make it: when ``names`` (the inputs to propagate)
    include its parameters, a model with parameters of its own is wrapped too; names of
    both kinds are refused (:class:`InputError`): the wrapper does not carry the wrapped
    model's parameters."""
    names = list(names)
    corrections = [n for n in names if n in ImageCorrectedModel.PARAMETERS]
    if isinstance(model, ImageCorrectedModel):
        return model
    if is_adjustable(model):
        if not corrections:
            return model
        own = [n for n in names if n in model.parameters()]
        if own:
            raise InputError(
                f"{', '.join(corrections)} (image-space correction, px) and {', '.join(own)} "
                f"({type(model).__name__} parameters) cannot be propagated together: the "
                "correction wraps the model, whose own parameters it does not carry; give "
                "one kind"
            )
    return ImageCorrectedModel(model)


def has_time(model) -> bool:
    """Whether the model knows its imaging time (pushbroom ``time_offset`` or a frame camera)."""
    if "time_offset" in model.parameters():
        return True
    return hasattr(model, "position") and hasattr(model, "velocity")


def valid_names(model) -> list[str]:
    """All input names that can be propagated for ``model`` (its parameters + pseudo-parameters)."""
    names = list(model.parameters()) + ["dem_height"]
    if has_time(model) and "time_offset" not in names:
        names.append("imaging_time")
    return names


def check_names(model, names) -> list[str]:
    """The names, or an :class:`InputError` listing the valid ones."""
    names = list(names)
    valid = valid_names(model)
    bad = [n for n in names if n not in valid]
    if bad:
        raise InputError(
            f"unknown parameter(s) {', '.join(bad)} for {type(model).__name__}; "
            f"valid: {', '.join(valid)}"
        )
    if len(set(names)) != len(names):
        raise InputError(f"parameter names repeated: {', '.join(names)}")
    return names


def advance_frame_camera(model, dt: float):
    """A frame camera whose satellite state is read ``dt`` seconds later: position and
    Earth-fixed velocity propagated along the orbit (two-body gravity plus the Coriolis and
    centrifugal terms of the rotating frame; second order in ``dt``). Attitude relative to the
    orbital frame is kept, so the look direction turns with the orbit."""
    r, v = np.asarray(model.position, float), np.asarray(model.velocity, float)
    w = np.array([0.0, 0.0, geodesy.OMEGA_EARTH])
    a = -geodesy.GM * r / np.linalg.norm(r) ** 3 - 2 * np.cross(w, v) - np.cross(w, np.cross(w, r))
    return replace(model, position=r + v * dt + 0.5 * a * dt * dt, velocity=v + a * dt)


def perturbed_model(model, values: dict):
    """``model`` with parameter offsets ``values`` applied (pseudo-parameters excluded):
    ``imaging_time`` becomes ``time_offset`` (pushbroom) or an orbit advance (frame)."""
    base = model.parameters()
    own = {k: base[k] + float(v) for k, v in values.items() if k in base}
    out = model.with_parameters(**own) if own else model
    dt = float(values.get("imaging_time", 0.0))
    if dt:
        if "time_offset" in base:
            out = out.with_parameters(time_offset=out.parameters()["time_offset"] + dt)
        else:
            out = advance_frame_camera(out, dt)
    return out


def parameter_unit(model, name) -> str | None:
    """Unit of a model parameter from the model's ``PARAMETERS`` table (None if unknown)."""
    table = getattr(model, "PARAMETERS", None)
    if not isinstance(table, dict):  # module-level table (pushbroom, ASTER)
        for cls in type(model).__mro__:
            table = getattr(sys.modules.get(cls.__module__), "PARAMETERS", None)
            if isinstance(table, dict):
                break
    if isinstance(table, dict) and name in table:
        text = str(table[name])
        return text.rsplit(",", 1)[-1].strip() if "," in text else text.strip()
    if hasattr(model, "position") and name in FrameCamera.PARAMETER_UNITS:
        return FrameCamera.PARAMETER_UNITS[name]
    return None


def propagation_steps(model, names, steps: dict | None = None) -> dict:
    """Central-difference steps for ``names``: ``steps`` first, then the model's own
    ``PARAMETER_STEPS``, then :data:`UNIT_STEPS` by the parameter's unit (else the default of
    :func:`stereodem.sensor.models.parameters.default_step`)."""
    own = dict(getattr(model, "PARAMETER_STEPS", {}) or {})
    out = {}
    for n in names:
        unit = parameter_unit(model, n)
        if n in own:
            out[n] = own[n]
        elif unit in UNIT_STEPS:
            out[n] = UNIT_STEPS[unit]
    out.update(steps or {})
    return out


def image_jacobian(model, lon, lat, h, names, *, steps: dict | None = None):
    """Partials of the image position with respect to named inputs.

    Parameters
    ----------
    model : adjustable sensor model (see :func:`adjustable_model`)
    lon, lat, h : array_like (n,)
        Ground points, degrees and metres above the ellipsoid.
    names : list of str
        Model parameters, ``dem_height`` (m) and/or ``imaging_time`` (s).

    Returns
    -------
    col, row : ndarray (n,)
    J : ndarray (n, 2, u), pixels per unit of each input.
    """
    lon, lat, h = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, float)) for a in (lon, lat, h)))
    names = check_names(model, names)
    own = [n for n in names if n in model.parameters()]
    col, row = (np.asarray(a, float) for a in model.project(lon, lat, h))
    J = np.zeros(lon.shape + (2, len(names)))
    if own:
        _, _, Jo = project_jacobian(
            model, lon, lat, h, own, steps=propagation_steps(model, own, steps)
        )
        for k, n in enumerate(own):
            J[..., names.index(n)] = Jo[..., k]
    if "dem_height" in names:
        d = DEM_HEIGHT_STEP
        cp, rp = model.project(lon, lat, h + d)
        cm, rm = model.project(lon, lat, h - d)
        J[..., 0, names.index("dem_height")] = (np.asarray(cp) - cm) / (2 * d)
        J[..., 1, names.index("dem_height")] = (np.asarray(rp) - rm) / (2 * d)
    if "imaging_time" in names:
        d = IMAGING_TIME_STEP
        cp, rp = perturbed_model(model, {"imaging_time": d}).project(lon, lat, h)
        cm, rm = perturbed_model(model, {"imaging_time": -d}).project(lon, lat, h)
        J[..., 0, names.index("imaging_time")] = (np.asarray(cp) - cm) / (2 * d)
        J[..., 1, names.index("imaging_time")] = (np.asarray(rp) - rm) / (2 * d)
    return col, row, J


def dem_pixel_jacobian(dem, lon, lat, crs, *, d: float = 1.0):
    """DEM pixel coordinates (col, row; centres at integers) of points and their partials
    ``∂(col, row)/∂(E, N)`` with respect to the map coordinates, (n,), (n,), (n, 2, 2)."""
    E, N = geodesy.lonlat_to_crs(lon, lat, crs)
    inv = ~dem.transform

    def pix(e, n):
        x, y = geodesy.lonlat_to_crs(*geodesy.crs_to_lonlat(e, n, crs), dem.crs)
        c, r = inv @ (np.asarray(x, float), np.asarray(y, float))
        return np.asarray(c) - 0.5, np.asarray(r) - 0.5

    c0, r0 = pix(E, N)
    P = np.empty(np.shape(c0) + (2, 2))
    for k, (dE, dN) in enumerate(((d, 0.0), (0.0, d))):
        cp, rp = pix(E + dE, N + dN)
        cm, rm = pix(E - dE, N - dN)
        P[..., 0, k], P[..., 1, k] = (cp - cm) / (2 * d), (rp - rm) / (2 * d)
    return c0, r0, P


def dem_gradient_arrays(dem):
    """``(∂h/∂col, ∂h/∂row)`` of the DEM grid (m per DEM pixel): central differences, one-sided
    where one neighbour along the axis is a void or off the grid (as :func:`numpy.gradient`
    at the grid's border, and GDAL's slope), 0 along an axis with no valid neighbour (an
    isolated post), NaN on the voids. Every post with a height has a gradient: a void no
    longer takes the slope of the posts around it (NaN there, read as flat)."""
    z = np.asarray(dem.heights, dtype=np.float64)
    return axis_gradient(z, 1), axis_gradient(z, 0)


def axis_gradient(z, axis: int):
    """Gradient of ``z`` along ``axis`` per post (see :func:`dem_gradient_arrays`): central
    differences ``(d[i] + d[i - 1]) / 2`` of the steps ``d[i] = z[i + 1] - z[i]``, one-sided at
    the grid's ends, and at the posts beside a void (whose central difference is NaN: a few
    rims, mended by index) the finite step, else 0; NaN on the voids. A few full-size passes,
    float64."""
    z = np.moveaxis(np.asarray(z, np.float64), axis, 0)
    n = z.shape[0]
    g = np.zeros(z.shape)
    if n > 1:
        d = z[1:] - z[:-1]  # d[i] = z[i+1] - z[i]
        np.add(d[1:], d[:-1], out=g[1:-1])
        g[1:-1] *= 0.5
        g[0], g[-1] = d[0], d[-1]
        finite = np.isfinite(z)
        rim = np.flatnonzero(np.isnan(g) & finite)  # a neighbour is a void (or off the grid)
        if rim.size:
            i, rest = np.divmod(rim, int(np.prod(z.shape[1:], dtype=np.int64)))
            flat = d.reshape(n - 1, -1)
            fwd = np.where(i < n - 1, flat[np.minimum(i, n - 2), rest], np.nan)
            bwd = np.where(i > 0, flat[np.maximum(i - 1, 0), rest], np.nan)
            g.reshape(n, -1)[i, rest] = np.where(
                np.isfinite(fwd), fwd, np.where(np.isfinite(bwd), bwd, 0.0)
            )
        g[~finite] = np.nan
    elif n == 1:
        g[~np.isfinite(z)] = np.nan
    return np.moveaxis(g, 0, axis)


def dem_gradient(dem, lon, lat, crs, *, arrays=None):
    """Terrain gradient ``(∂h/∂E, ∂h/∂N)`` (m/m) at points: the DEM's central-difference
    gradient, bilinear between posts, turned into map axes by the DEM-pixel Jacobian."""
    gc, gr = arrays if arrays is not None else dem_gradient_arrays(dem)
    c, r, P = dem_pixel_jacobian(dem, lon, lat, crs)
    return slope_from_pixels(gc, gr, c, r, P)


def slope_from_pixels(gc, gr, c, r, P):
    """Map-axis gradient from the DEM-pixel gradient arrays sampled at (c, r) with the pixel
    Jacobian ``P = ∂(c, r)/∂(E, N)``; 0 where the DEM has no value."""
    a, b = np.nan_to_num(bilinear_nan(gc, c, r)), np.nan_to_num(bilinear_nan(gr, c, r))
    return a * P[..., 0, 0] + b * P[..., 1, 0], a * P[..., 0, 1] + b * P[..., 1, 1]


def ground_covariance(A, ph, grad, M):
    """``A_eff⁻¹ M A_eff⁻ᵀ`` with ``A_eff = A + ∂p/∂h ∇hᵀ``: an image-space covariance (or
    contribution) ``M`` (..., 2, 2) in px² moved to the ground (m²) for image Jacobian ``A``
    (..., 2, 2), height partial ``ph`` (..., 2) and terrain gradient ``grad`` (..., 2)."""
    a = A[..., 0, 0] + ph[..., 0] * grad[..., 0]
    b = A[..., 0, 1] + ph[..., 0] * grad[..., 1]
    c = A[..., 1, 0] + ph[..., 1] * grad[..., 0]
    d = A[..., 1, 1] + ph[..., 1] * grad[..., 1]
    det = a * d - b * c
    with np.errstate(all="ignore"):
        i00, i01, i10, i11 = d / det, -b / det, -c / det, a / det
    m00, m01, m11 = M[..., 0, 0], M[..., 0, 1], M[..., 1, 1]
    # G = inv @ M @ inv.T
    t00 = i00 * m00 + i01 * m01
    t01 = i00 * m01 + i01 * m11
    t10 = i10 * m00 + i11 * m01
    t11 = i10 * m01 + i11 * m11
    g00 = t00 * i00 + t01 * i01
    g01 = t00 * i10 + t01 * i11
    g11 = t10 * i10 + t11 * i11
    return g00, g01, g11


def image_side(
    model, lon, lat, h, names, D, crs, *, groups: dict | None = None, steps: dict | None = None
):
    """The smooth, terrain-free part of the propagation at ground points.

    Returns a dict: ``col``, ``row`` (n,), ``A = ∂(col,row)/∂(E,N)`` (n, 2, 2) at fixed height,
    ``ph = ∂(col,row)/∂h`` (n, 2), ``S = J D Jᵀ`` (n, 2, 2) the image-space covariance of all
    inputs (px²) and ``C`` {source: (n, 2, 2)} each source's contribution to ``S`` (they sum to
    ``S``). With the terrain gradient, :func:`ground_covariance` moves them to the ground.
    """
    lon, lat, h = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, float)) for a in (lon, lat, h)))
    names = list(names)
    col, row, Ji = image_jacobian(model, lon, lat, h, names, steps=steps)
    gj = ground_jacobian(model, lon, lat, h, [], crs)
    cp, rp = model.project(lon, lat, h + DEM_HEIGHT_STEP)
    cm, rm = model.project(lon, lat, h - DEM_HEIGHT_STEP)
    ph = np.stack([np.asarray(cp) - cm, np.asarray(rp) - rm], -1) / (2 * DEM_HEIGHT_STEP)
    DJ = np.einsum("kl,nil->nik", D, Ji)  # (n, 2, u): Σ_l D_kl J_il
    groups = groups or {n: [n] for n in names}
    idx = {n: k for k, n in enumerate(names)}
    C = {}
    for g, members in groups.items():
        ks = [idx[m] for m in members if m in idx]
        Cg = np.einsum("nik,njk->nij", Ji[..., ks], DJ[..., ks])
        C[g] = 0.5 * (Cg + np.swapaxes(Cg, -1, -2))
    return {"col": col, "row": row, "A": gj.A, "ph": ph, "S": propagate(Ji, D), "C": C}


@dataclass
class GroundJacobian:
    """Partials of ground positions with respect to named inputs.

    Attributes
    ----------
    J : ndarray (n, 2, u)
        ``J[i, 0, k] = ∂E_i/∂p_k`` and ``J[i, 1, k] = ∂N_i/∂p_k``, metres per unit of ``p_k``
        (E, N in ``crs``).
    A : ndarray (n, 2, 2)
        ``∂(col, row)/∂(E, N)`` on the DEM surface (pixels per metre).
    """

    names: list
    J: np.ndarray
    A: np.ndarray
    col: np.ndarray
    row: np.ndarray
    crs: object = None


def ground_jacobian(
    model, lon, lat, h, names, crs, *, dem=None, steps: dict | None = None
) -> GroundJacobian:
    """Jacobian of the ground position of the pixels imaging ``(lon, lat, h)``.

    Parameters
    ----------
    model : adjustable sensor model
    lon, lat, h : array_like (n,)
        Ground points (degrees, metres above the ellipsoid).
    names : list of str
        Inputs (see :func:`valid_names`).
    crs : CRS-like
        Projected map CRS of E, N (metres).
    dem : DEM, optional
        If given, the point moves on the DEM surface (its slope enters ``A``).
    """
    lon, lat, h = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, float)) for a in (lon, lat, h)))
    col, row, Ji = image_jacobian(model, lon, lat, h, names, steps=steps)
    E, N = geodesy.lonlat_to_crs(lon, lat, crs)
    d = GROUND_STEP
    A = np.empty(lon.shape + (2, 2))
    for k, (dE, dN) in enumerate(((d, 0.0), (0.0, d))):
        lp, ap = geodesy.crs_to_lonlat(E + dE, N + dN, crs)
        lm, am = geodesy.crs_to_lonlat(E - dE, N - dN, crs)
        cp, rp = model.project(lp, ap, h)
        cm, rm = model.project(lm, am, h)
        A[..., 0, k] = (np.asarray(cp) - cm) / (2 * d)
        A[..., 1, k] = (np.asarray(rp) - rm) / (2 * d)
    if dem is not None and len(lon):
        gE, gN = dem_gradient(dem, lon, lat, crs)
        cp, rp = model.project(lon, lat, h + DEM_HEIGHT_STEP)
        cm, rm = model.project(lon, lat, h - DEM_HEIGHT_STEP)
        ph = np.stack([np.asarray(cp) - cm, np.asarray(rp) - rm], -1) / (2 * DEM_HEIGHT_STEP)
        A = A + ph[..., :, None] * np.stack([gE, gN], -1)[..., None, :]
    with np.errstate(all="ignore"):
        Jg = -np.linalg.solve(A, Ji)
    return GroundJacobian(list(names), Jg, A, col, row, crs)


# ----------------------------------------------------------------------------- covariance algebra


def covariance_matrix(names, sigmas: dict | None = None, covariance=None) -> np.ndarray:
    """The input covariance in the order of ``names``: a full matrix, or diagonal from σ's.

    Raises :class:`InputError` for a negative or non-finite σ and for a matrix that is not
    symmetric positive semi-definite."""
    u = len(names)
    if covariance is not None:
        D = np.asarray(covariance, float)
        if D.shape != (u, u):
            raise InputError(f"covariance is {D.shape}, expected {u} x {u} for {', '.join(names)}")
    else:
        sigmas = sigmas or {}
        s = np.array([float(sigmas.get(n, 0.0)) for n in names])
        bad = [n for n, v in zip(names, s) if not np.isfinite(v) or v < 0]
        if bad:
            raise InputError(
                "sigma must be finite and non-negative: "
                f"{', '.join(f'{n}={sigmas[n]}' for n in bad)}"
            )
        D = np.diag(s**2)
    check_psd(D, names)
    return D


def check_psd(D, names=None, *, what: str = "covariance"):
    """Raise :class:`InputError` unless ``D`` is finite, symmetric and positive semi-definite."""
    D = np.asarray(D, float)
    if not np.all(np.isfinite(D)):
        raise InputError(f"{what} has non-finite entries")
    if D.size == 0:
        return D
    scale = max(float(np.max(np.abs(D))), 1e-300)
    if np.max(np.abs(D - D.T)) > 1e-9 * scale:
        raise InputError(f"{what} is not symmetric")
    d = np.sqrt(np.clip(np.diag(D), 0, None))
    dd = np.where(d > 0, d, 1.0)
    ev = np.linalg.eigvalsh(D / np.outer(dd, dd))  # scale-free test on the correlations
    if np.any(np.diag(D) < 0) or ev.min() < -1e-9:
        k = int(np.argmin(ev))
        raise InputError(
            f"{what} is not positive semi-definite (smallest eigenvalue of the "
            f"correlation matrix {ev[k]:.3g})"
        )
    return D


def propagate(J, D):
    """``Σ = J D Jᵀ`` for every point: J (..., m, u), D (u, u) -> (..., m, m)."""
    return np.einsum("...ik,kl,...jl->...ij", J, D, J)


def variance_shares(J, D, groups: dict | None = None, names=None):
    """Each input's (or group's) share of the variance of every output component.

    Parameters
    ----------
    J : ndarray (..., m, u)
    D : ndarray (u, u)
    groups : dict name -> list of input names, optional (default: one group per input)
    names : list of the u input names (needed with ``groups``)

    Returns
    -------
    shares : dict group -> ndarray (..., m): ``J_k (D Jᵀ)_k / V`` summed over the group; the
        shares of all groups sum to 1 where V > 0 (NaN where V = 0).
    """
    contrib = J * np.einsum("kl,...jl->...jk", D, J)  # (..., m, u)
    V = contrib.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = contrib / np.where(V > 0, V, np.nan)[..., None]
    if groups is None:
        names = names or [f"p{k}" for k in range(J.shape[-1])]
        return {n: frac[..., k] for k, n in enumerate(names)}
    idx = {n: k for k, n in enumerate(names)}
    return {
        g: frac[..., [idx[m] for m in members if m in idx]].sum(-1) for g, members in groups.items()
    }


def horizontal_shares(J, D, names, groups: dict | None = None):
    """Shares of the horizontal variance ``σ_E² + σ_N²`` per input (or group), (...,) arrays."""
    contrib = (J * np.einsum("kl,...jl->...jk", D, J)).sum(-2)  # (..., u)
    V = contrib.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = contrib / np.where(V > 0, V, np.nan)[..., None]
    groups = groups or {n: [n] for n in names}
    idx = {n: k for k, n in enumerate(names)}
    return {g: frac[..., [idx[m] for m in members]].sum(-1) for g, members in groups.items()}


# ----------------------------------------------------------------------------- circular error


def ce90(cov, *, p: float = 0.9, nodes: int = 48, iterations: int = 48):
    """Circular error: radius holding probability ``p`` of a zero-mean bivariate normal.

    Exact for any 2 × 2 covariance (elliptical errors): with eigenvalues λ₁ ≥ λ₂,
    ``P(r) = ∫ φ(z) erf(√((r² − λ₁z²)/(2λ₂))) dz`` over ``|z| ≤ r/√λ₁`` (Gauss–Legendre on the
    substitution ``z = (r/√λ₁) sin t``), solved for r by bisection. cov (..., 2, 2) -> (...).
    """
    erf = _erf
    cov = np.asarray(cov, float)
    lam = np.linalg.eigvalsh(cov)  # ascending
    l1 = np.clip(lam[..., 1], 0, None)
    l2 = np.clip(lam[..., 0], 1e-30 + 1e-14 * l1, None)
    s1 = np.sqrt(l1)
    t, w = np.polynomial.legendre.leggauss(nodes)
    t, w = 0.5 * np.pi * t, 0.5 * np.pi * w  # t in (-π/2, π/2)

    def prob(r):
        zmax = r / np.where(s1 > 0, s1, 1.0)
        z = zmax[..., None] * np.sin(t)
        rem = np.clip(r[..., None] ** 2 - l1[..., None] * z * z, 0, None)
        f = np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi) * erf(np.sqrt(rem / (2 * l2[..., None])))
        return (f * (zmax[..., None] * np.cos(t)) * w).sum(-1)

    lo = np.zeros_like(l1)
    hi = CE90_CIRCULAR * np.sqrt(l1 + l2) * 1.5 + 1e-300
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        below = prob(mid) < p
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    out = 0.5 * (lo + hi)
    return np.where(l1 > 0, out, 0.0)


_CE90_N = 400
_CE90_TABLE = None


def _ce90_table():
    """``g(ρ)`` at ``ρ = 0, 1/400 … 1`` (exact :func:`ce90` of ``diag(1, ρ²)``) and its steps."""
    global _CE90_TABLE
    if _CE90_TABLE is None:
        rho = np.linspace(0.0, 1.0, _CE90_N + 1)
        cov = np.zeros((rho.size, 2, 2))
        cov[:, 0, 0], cov[:, 1, 1] = 1.0, rho**2
        g = ce90(cov)
        _CE90_TABLE = (g, np.append(np.diff(g), 0.0))
    return _CE90_TABLE


def ce90_from_cov(a, b, c):
    """CE90 of 2 × 2 covariances ``[[a, b], [b, c]]`` (arrays, float32 or float64; the result
    has their type): ``√λ₁ · g(√(λ₂/λ₁))`` with ``g`` tabulated once from the exact :func:`ce90`
    at 401 equally spaced ratios and interpolated linearly (error < 10⁻⁵ relative)."""
    g, dg = _ce90_table()
    dt = np.result_type(a, b, c)
    g, dg = g.astype(dt), dg.astype(dt)
    half = 0.5 * (a + c)
    rad = 0.5 * (a - c)
    rad *= rad
    rad += b * b
    np.sqrt(rad, out=rad)
    l1 = half + rad
    half -= rad
    np.maximum(half, 0, out=half)  # λ₂
    x = half / np.maximum(l1, np.finfo(dt).tiny)
    np.sqrt(x, out=x)
    x *= _CE90_N  # ρ in table steps
    with np.errstate(invalid="ignore"):
        i = x.astype(np.int32)  # NaN input -> any index, NaN result
    x -= i
    out = dg.take(i, mode="clip")
    out *= x
    out += g.take(i, mode="clip")
    np.maximum(l1, 0, out=l1)
    np.sqrt(l1, out=l1)
    out *= l1
    return out


# ----------------------------------------------------------------------------- results


@dataclass
class PointUncertainty:
    """First-order uncertainty of ground points.

    ``sigma_east``, ``sigma_north``, ``sigma_horizontal``, ``ce90`` in metres (n,);
    ``cov`` (n, 2, 2) m²; ``shares`` name -> (n,) fraction of ``σ_E² + σ_N²``."""

    names: list
    sigma_east: np.ndarray
    sigma_north: np.ndarray
    cov: np.ndarray
    shares: dict
    jacobian: GroundJacobian = field(repr=False, default=None)

    @property
    def sigma_horizontal(self):
        return np.hypot(self.sigma_east, self.sigma_north)

    @property
    def ce90(self):
        return ce90(self.cov)


def first_order(
    model,
    lon,
    lat,
    h,
    names,
    D,
    crs,
    *,
    dem=None,
    groups: dict | None = None,
    steps: dict | None = None,
) -> PointUncertainty:
    """First-order σ of the ground positions at ``(lon, lat, h)`` for input covariance ``D``
    (order of ``names``); see the module docstring."""
    gj = ground_jacobian(model, lon, lat, h, names, crs, dem=dem, steps=steps)
    C = propagate(gj.J, D)
    shares = horizontal_shares(gj.J, D, list(names), groups)
    return PointUncertainty(
        list(names),
        np.sqrt(np.clip(C[..., 0, 0], 0, None)),
        np.sqrt(np.clip(C[..., 1, 1], 0, None)),
        C,
        shares,
        gj,
    )
