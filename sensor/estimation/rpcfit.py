"""Terrain-independent RPC fitting: approximate any sensor model by an RPC00B model.

The recipe of Tao & Hu (2001) as used by rpcfit (Akiki et al. 2021), ASP's ``cam2rpc`` and
MMASTER: localise a 3-D grid of image points ``(col, row)`` x heights through the model,
normalise, and solve the linearised rational equations

    t * DEN(L, P, H) = NUM(L, P, H),   DEN's constant term fixed to 1,

for the 39 free coefficients of each image coordinate (78 in total) by Tikhonov-regularised
least squares, re-weighting each equation by ``1 / DEN`` of the previous solution (so that the
minimised residual is the image residual, not ``DEN`` times it) for a few iterations. The
fit is then checked on an independent grid (half a step off the training grid, at heights
between the training levels).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from stereodem.core.errors import SensorModelError
from stereodem.sensor.models.rpc import RPCModel, monomials


@dataclass
class FitReport:
    """Residuals of an RPC fit, pixels (fitted ``project`` minus the grid's image coordinates).

    ``*_rms`` is the root mean square of the 2-D residual length, ``*_max`` its maximum;
    ``*_rms_col`` and ``*_rms_row`` are per-axis RMS.
    """

    train_rms: float
    train_max: float
    train_rms_col: float
    train_rms_row: float
    check_rms: float
    check_max: float
    check_rms_col: float
    check_rms_row: float
    n_train: int
    n_check: int
    height_range: tuple
    grid: tuple
    check_grid: tuple
    regularization: float
    iterations: int

    def to_dict(self) -> dict:
        """Plain dict (JSON-serialisable) for reports."""
        d = asdict(self)
        d["height_range"] = [float(v) for v in self.height_range]
        d["grid"] = list(self.grid)
        d["check_grid"] = list(self.check_grid)
        return d


def fit_rational(x, y, z, t, *, regularization: float = 1e-12, iterations: int = 8):
    """Fit ``t ~ NUM(x, y, z) / DEN(x, y, z)`` with 20-term RPC00B cubics, ``DEN[0] = 1``.

    Parameters
    ----------
    x, y, z : array_like (n,)
        Normalised inputs in the (L, P, H) slots of the RPC00B term order (roughly in [-1, 1]).
    t : array_like (n,)
        Normalised target.
    regularization : float
        Tikhonov weight, relative to the mean squared column norm of the (weighted) design
        matrix: the penalty is ``regularization * trace(A'A)/39 * |coeffs|^2``.
    iterations : int
        Maximum number of 1/DEN re-weighting iterations (stops early when the coefficients
        settle).

    Returns
    -------
    num, den : ndarray (20,)
        Coefficients in RPC00B term order; ``den[0] == 1``.
    n_iter : int
        Iterations run.
    """
    x, y, z, t = (np.asarray(a, np.float64).ravel() for a in (x, y, z, t))
    M = monomials(x, y, z).T  # (n, 20)
    A = np.hstack([M, -t[:, None] * M[:, 1:]])  # (n, 39)
    w = np.ones(t.size)
    coef = None
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 (the count is reported)
        Aw = A * w[:, None]
        bw = t * w
        lam = regularization * np.einsum("ij,ij->", Aw, Aw) / A.shape[1]
        # Tikhonov as the stacked least-squares system [Aw; sqrt(lam) I] x = [bw; 0]
        # (SVD-based, avoids squaring the condition number in the normal equations)
        k = A.shape[1]
        new, *_ = np.linalg.lstsq(
            np.vstack([Aw, np.sqrt(lam) * np.eye(k)]), np.concatenate([bw, np.zeros(k)]), rcond=None
        )
        den = np.concatenate([[1.0], new[20:]])
        dv = M @ den
        if np.any(dv == 0) or not np.all(np.isfinite(dv)):
            raise SensorModelError("RPC fit: the fitted denominator vanishes on the grid")
        w = 1.0 / np.abs(dv)
        settled = coef is not None and np.max(np.abs(new - coef)) <= 1e-13 * max(
            1.0, np.max(np.abs(new))
        )
        coef = new
        if settled:
            break
    return coef[:20].copy(), np.concatenate([[1.0], coef[20:]]), it


def _grid_axis(n, lo, hi, *, midpoints):
    if midpoints:
        return lo + (np.arange(n) + 0.5) / n * (hi - lo)
    return np.linspace(lo, hi, n)


def _samples(model, cols, rows, hs):
    C, R, Hh = (a.ravel() for a in np.meshgrid(cols, rows, hs, indexing="ij"))
    lon, lat = model.localize(C, R, Hh)
    lon, lat = np.asarray(lon, np.float64), np.asarray(lat, np.float64)
    ok = np.isfinite(lon) & np.isfinite(lat)
    return C[ok], R[ok], Hh[ok], lon[ok], lat[ok]


def _residuals(rpc, C, R, Hh, lon, lat):
    c, r = rpc.project(lon, lat, Hh)
    dc, dr = c - C, r - R
    d = np.hypot(dc, dr)
    return (
        float(np.sqrt(np.mean(d**2))),
        float(np.max(d)),
        float(np.sqrt(np.mean(dc**2))),
        float(np.sqrt(np.mean(dr**2))),
    )


def fit_rpc(
    model,
    *,
    height_range=None,
    grid=(15, 15, 7),
    check_grid=None,
    regularization: float = 1e-12,
    iterations: int = 8,
    width=None,
    height=None,
):
    """Fit a terrain-independent RPC00B model to any
    :class:`~stereodem.sensor.models.base.SensorModel`.

    Parameters
    ----------
    model : SensorModel
        Model providing a vectorised ``localize(col, row, h)``.
    height_range : (float, float), optional
        Heights (m above the WGS84 ellipsoid) covered by the fit; default
        ``model.height_bounds()``.
    grid : (int, int, int)
        Training grid: numbers of columns, rows and height levels, spread evenly over the
        image (pixel centres 0 .. width-1, 0 .. height-1) and the height range. At least 4
        height levels are needed for the cubic height terms.
    check_grid : (int, int, int), optional
        Check grid counts; its nodes are cell centres of an even subdivision of the image and
        height range, so with the default ``grid - 1`` they lie half a step off every
        training node and between the training heights.
    regularization : float
        Relative Tikhonov weight (see :func:`fit_rational`).
    iterations : int
        Maximum number of 1/DEN re-weighting iterations.
    width, height : int, optional
        Image size; default ``model.width``, ``model.height``.

    Returns
    -------
    rpc : RPCModel
        The fitted model (image normalisation centred on the image, ground normalisation on
        the training samples' extent).
    report : FitReport
        Training and check residuals in pixels.
    """
    w = int(width or model.width)
    h = int(height or model.height)
    hlo, hhi = (
        float(v) for v in (height_range if height_range is not None else model.height_bounds())
    )
    if not (hhi > hlo):
        raise SensorModelError(f"fit_rpc: empty height range ({hlo}, {hhi})")
    grid = tuple(int(v) for v in grid)
    if len(grid) != 3 or min(grid[:2]) < 4 or grid[2] < 4:
        raise SensorModelError(f"fit_rpc: grid {grid} too small (need >= 4 nodes per axis)")
    check_grid = tuple(int(v) for v in (check_grid or (grid[0] - 1, grid[1] - 1, grid[2] - 1)))

    C, R, Hh, lon, lat = _samples(
        model,
        _grid_axis(grid[0], 0, w - 1, midpoints=False),
        _grid_axis(grid[1], 0, h - 1, midpoints=False),
        _grid_axis(grid[2], hlo, hhi, midpoints=False),
    )
    if C.size < 2 * 39:
        raise SensorModelError(f"fit_rpc: only {C.size} grid point(s) could be localised")

    lon_off, lon_scale = 0.5 * (lon.max() + lon.min()), 0.5 * (lon.max() - lon.min())
    lat_off, lat_scale = 0.5 * (lat.max() + lat.min()), 0.5 * (lat.max() - lat.min())
    h_off, h_scale = 0.5 * (hhi + hlo), 0.5 * (hhi - hlo)
    samp_off, samp_scale = 0.5 * (w - 1), 0.5 * w
    line_off, line_scale = 0.5 * (h - 1), 0.5 * h
    if lon_scale <= 0 or lat_scale <= 0:
        raise SensorModelError("fit_rpc: the grid localises to a single longitude or latitude")
    L = (lon - lon_off) / lon_scale
    P = (lat - lat_off) / lat_scale
    Hn = (Hh - h_off) / h_scale
    s_num, s_den, it_s = fit_rational(
        L, P, Hn, (C - samp_off) / samp_scale, regularization=regularization, iterations=iterations
    )
    l_num, l_den, it_l = fit_rational(
        L, P, Hn, (R - line_off) / line_scale, regularization=regularization, iterations=iterations
    )
    rpc = RPCModel(
        line_num=l_num,
        line_den=l_den,
        samp_num=s_num,
        samp_den=s_den,
        line_off=line_off,
        samp_off=samp_off,
        line_scale=line_scale,
        samp_scale=samp_scale,
        lon_off=lon_off,
        lat_off=lat_off,
        lon_scale=lon_scale,
        lat_scale=lat_scale,
        height_off=h_off,
        height_scale=h_scale,
        width=w,
        height=h,
    )

    train = _residuals(rpc, C, R, Hh, lon, lat)
    chk = _samples(
        model,
        _grid_axis(check_grid[0], 0, w - 1, midpoints=True),
        _grid_axis(check_grid[1], 0, h - 1, midpoints=True),
        _grid_axis(check_grid[2], hlo, hhi, midpoints=True),
    )
    check = _residuals(rpc, *chk)
    report = FitReport(
        train_rms=train[0],
        train_max=train[1],
        train_rms_col=train[2],
        train_rms_row=train[3],
        check_rms=check[0],
        check_max=check[1],
        check_rms_col=check[2],
        check_rms_row=check[3],
        n_train=int(C.size),
        n_check=int(chk[0].size),
        height_range=(hlo, hhi),
        grid=grid,
        check_grid=check_grid,
        regularization=float(regularization),
        iterations=max(it_s, it_l),
    )
    return rpc, report
