"""Uncertainty and sensitivity (issue #17): propagation, sampling, indices, maps, command."""

import itertools

import numpy as np
import pytest
from affine import Affine
from scipy import stats

from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.ortho.grid import grid_for_model
from stereodem.ortho.uncertainty import propagation as P
from stereodem.ortho.uncertainty import sampling as S
from stereodem.ortho.uncertainty.indices import (
    efast_interference_free,
    fast_indices,
    interference_order,
    sample_frequencies,
)
from stereodem.ortho.uncertainty.maps import (
    dem_vertical_sigma,
    hirvonen_slopes,
    ortho_uncertainty_maps,
)
from stereodem.sensor.models.parameters import default_step
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation.simulate import frame_pair, pushbroom_pair

# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def rpc(data_dir):
    return RPCModel.from_file(data_dir / "pleiades" / "img_01_rpc.tif")


def _dem_under(model, h0=2300.0, relief=0.0, tilt=(0.0, 0.0)):
    lon, lat = model.footprint(h0)
    w, s, e, n = lon.min() - 0.002, lat.min() - 0.002, lon.max() + 0.002, lat.max() + 0.002
    step = 5e-5
    tr = Affine(step, 0, w, 0, -step, n)
    nx, ny = int((e - w) / step), int((n - s) / step)
    X, Y = tr @ np.meshgrid(np.arange(nx) + 0.5, np.arange(ny) + 0.5)
    Z = (
        h0
        + relief * np.sin((X - w) / 0.0015) * np.cos((Y - s) / 0.002)
        + tilt[0] * (X - w) * 1e5
        + tilt[1] * (Y - s) * 1e5
    )
    return DEM(Z.astype(np.float32), tr, "EPSG:4326", "ellipsoid")


@pytest.fixture(scope="module")
def flat(rpc):
    return _dem_under(rpc)


@pytest.fixture(scope="module")
def frame():
    cam, _ = frame_pair(32.8, 39.9, 1000.0, (512, 512))
    return cam


# --------------------------------------------------------------------------- RPC maps: closed forms


def _map(rpc, dem, sigmas, res=4.0):
    grid = grid_for_model(rpc, dem, res=res)
    names = list(sigmas)
    return grid, ortho_uncertainty_maps(
        rpc, dem, grid, np.diag([sigmas[n] ** 2 for n in names]), names
    )


def _cells(grid, maps, every=2):
    r, c = np.mgrid[0 : grid.height : every, 0 : grid.width : every]
    ok = np.isfinite(maps.sigma_horizontal[r, c])
    return c[ok].astype(float), r[ok].astype(float), ok


def test_image_shift_sigma_is_the_ground_size_of_the_shift_at_every_cell(rpc, flat):
    """Only σ(col_shift) = 1 px: σ_horizontal equals the ground distance between the pixel's
    neighbours half a pixel left and right, localised by the RPC at the DEM height (1 %)."""
    grid, maps = _map(rpc, flat, {"col_shift": 1.0})
    c, r, _ = _cells(grid, maps)
    lon, lat = grid.lonlat(c, r)
    col, row = rpc.project(lon, lat, np.full(lon.shape, 2300.0))
    pts = [
        geodesy.lonlat_to_crs(*rpc.localize(col + d, row, np.full(lon.shape, 2300.0)), grid.crs)
        for d in (-0.5, 0.5)
    ]
    truth = np.hypot(pts[1][0] - pts[0][0], pts[1][1] - pts[0][1])
    got = maps.sigma_horizontal[r.astype(int), c.astype(int)]
    assert c.size > 500
    assert np.max(np.abs(got / truth - 1)) < 0.01
    assert maps.shares == {"col_shift": pytest.approx(1.0)}


def test_dem_height_sigma_is_sigma_h_times_tan_off_nadir(rpc, flat):
    """Only σ(dem_height) = 10 m over flat terrain: σ_horizontal = 10 m × tan(off-nadir angle of
    the line of sight at the ground), from the model's rays (1 %)."""
    grid, maps = _map(rpc, flat, {"dem_height": 10.0})
    c, r, _ = _cells(grid, maps)
    lon, lat = grid.lonlat(c, r)
    col, row = rpc.project(lon, lat, np.full(lon.shape, 2300.0))
    _, d = rpc.rays(col, row)
    up = np.stack(
        [
            np.cos(np.radians(lat)) * np.cos(np.radians(lon)),
            np.cos(np.radians(lat)) * np.sin(np.radians(lon)),
            np.sin(np.radians(lat)),
        ],
        -1,
    )
    cosz = np.abs(np.sum(d * up, -1))
    truth = 10.0 * np.tan(np.arccos(cosz))
    got = maps.sigma_horizontal[r.astype(int), c.astype(int)]
    assert np.median(truth) > 0.5  # a real off-nadir view, not a trivial zero
    assert np.max(np.abs(got / truth - 1)) < 0.01


def test_map_interpolation_error_is_measured_and_small(rpc):
    dem = _dem_under(rpc, relief=40.0)
    grid, maps = _map(rpc, dem, {"col_shift": 0.5, "row_shift": 0.5, "dem_height": 5.0})
    assert maps.interpolation_error < 0.005
    assert sum(maps.shares.values()) == pytest.approx(1.0)
    assert set(np.unique(maps.dominant)) <= {-1, 0, 1, 2}
    ok = np.isfinite(maps.sigma_horizontal)
    assert ok.mean() > 0.8 and np.all(maps.ce90[ok] >= maps.sigma_horizontal[ok] * 1.2)


# --------------------------------------------------------------------------- Jacobians


def test_dem_height_jacobian_matches_relocalisation(rpc):
    """∂G/∂h from the propagation engine equals the move of the pixel's ground point localised
    at h ± 5 m (independent path through ``localize``)."""
    model = P.adjustable_model(rpc)
    crs = geodesy.utm_crs(*rpc.center_lonlat(2300.0))
    col = np.array([50.0, 500.0, 950.0])
    row = np.array([80.0, 500.0, 900.0])
    lon, lat = rpc.localize(col, row, np.full(3, 2300.0))
    gj = P.ground_jacobian(model, lon, lat, np.full(3, 2300.0), ["dem_height"], crs)
    (Ep, Np), (Em, Nm) = (
        geodesy.lonlat_to_crs(*rpc.localize(col, row, np.full(3, 2300.0 + d)), crs)
        for d in (5.0, -5.0)
    )
    fd = np.stack([(Ep - Em) / 10, (Np - Nm) / 10], -1)
    assert np.allclose(gj.J[:, :, 0], fd, atol=1e-4)


def test_frame_attitude_jacobian_against_relocalisation(frame):
    """A frame camera's ∂G/∂roll (model parameters, central differences in image space, then
    −A⁻¹) equals the move of its ground point re-localised with roll ± 1 µrad."""
    crs = geodesy.utm_crs(32.8, 39.9)
    col, row = np.array([20.0, 256.0]), np.array([30.0, 400.0])
    lon, lat = frame.localize(col, row, np.full(2, 1000.0))
    gj = P.ground_jacobian(frame, lon, lat, np.full(2, 1000.0), ["roll", "x"], crs)
    d = 1e-6
    (Ep, Np), (Em, Nm) = (
        geodesy.lonlat_to_crs(
            *frame.with_parameters(roll=frame.roll + s).localize(col, row, np.full(2, 1000.0)), crs
        )
        for s in (d, -d)
    )
    fd = np.stack([(Ep - Em), (Np - Nm)], -1) / (2 * d)
    assert np.allclose(gj.J[:, :, 0], fd, rtol=1e-4)
    assert np.abs(gj.J[:, :, 0]).max() > 1e5  # ≈ 700 km lever per radian


# ----------------------------------------------------------------------- first order vs Monte Carlo


@pytest.mark.slow
def test_first_order_and_monte_carlo_agree_for_a_near_linear_case(rpc):
    dem = _dem_under(rpc, relief=30.0)
    model = P.adjustable_model(rpc)
    crs = geodesy.utm_crs(*rpc.center_lonlat(2300.0))
    lon, lat = rpc.localize(
        np.array([100.0, 500, 900]), np.array([100.0, 600, 950]), np.full(3, 2300.0)
    )
    h = dem.sample(lon, lat)
    names = ["col_shift", "row_shift", "dem_height"]
    D = np.diag([1.0, 0.5**2, 15.0**2])
    pu = P.first_order(model, lon, lat, h, names, D, crs, dem=dem)
    X, dE, dN = S.monte_carlo(model, lon, lat, h, names, D, crs, samples=1000, dem=dem, seed=1)
    mc = np.sqrt(dE.var(0, ddof=1) + dN.var(0, ddof=1))
    assert np.all(np.abs(mc / pu.sigma_horizontal - 1) < 0.02)


@pytest.mark.slow
def test_strongly_nonlinear_case_gap_is_stated(frame):
    """A 0.15 rad pitch σ on an oblique frame camera (15° pitch): first order under-estimates
    σ_horizontal by about 4 %. Monte Carlo agrees (1 %) with the exact σ of the same non-linear
    function by 80-point Gauss quadrature over ±4.5σ, and both are ≥ 3 % above first order."""
    crs = geodesy.utm_crs(32.8, 39.9)
    lon, lat = frame.localize(np.array([10.0, 256.0]), np.array([10.0, 256.0]), np.full(2, 1000.0))
    h = np.full(2, 1000.0)
    sig = 0.15
    pu = P.first_order(frame, lon, lat, h, ["pitch"], np.diag([sig**2]), crs)
    X, dE, dN = S.monte_carlo(frame, lon, lat, h, ["pitch"], np.diag([sig**2]), crs, samples=1000)
    mc = np.sqrt(dE.var(0, ddof=1) + dN.var(0, ddof=1))
    t, wt = np.polynomial.legendre.leggauss(80)  # ±4.5σ (the ±8σ of Gauss–Hermite
    z = 4.5 * t  # would look past the horizon)
    w = wt * np.exp(-0.5 * z * z)
    w = w / w.sum()
    qE, qN = S.ground_displacements(frame, lon, lat, h, ["pitch"], (sig * z)[:, None], crs)
    var = lambda q: (w[:, None] * (q - (w[:, None] * q).sum(0)) ** 2).sum(0)
    exact = np.sqrt(var(qE) + var(qN))
    gap = mc / pu.sigma_horizontal - 1
    assert np.all(np.abs(mc / exact - 1) < 0.01)
    assert np.all(gap > 0.03) and np.all(exact / pu.sigma_horizontal - 1 > 0.03)


@pytest.mark.slow
def test_correlated_inputs_first_order_matches_monte_carlo_and_shares_sum_to_one(frame):
    crs = geodesy.utm_crs(32.8, 39.9)
    lon, lat = frame.localize(np.array([100.0, 400.0]), np.array([50.0, 300.0]), np.full(2, 1000.0))
    h = np.full(2, 1000.0)
    names = ["roll", "pitch", "x", "imaging_time"]
    sd = np.array([5e-6, 5e-6, 3.0, 1e-3])
    R = np.array([[1, 0.6, 0, 0], [0.6, 1, -0.5, 0], [0, -0.5, 1, 0], [0, 0, 0, 1.0]])
    D = R * np.outer(sd, sd)
    pu = P.first_order(frame, lon, lat, h, names, D, crs)
    total = sum(pu.shares.values())
    assert np.allclose(total, 1.0)
    # Helton's eq 7 written out term by term, covariance terms included
    J = pu.jacobian.J
    vE = sum(J[:, 0, i] * J[:, 0, j] * D[i, j] for i in range(4) for j in range(4))
    vN = sum(J[:, 1, i] * J[:, 1, j] * D[i, j] for i in range(4) for j in range(4))
    assert np.allclose(pu.sigma_horizontal, np.sqrt(vE + vN), rtol=1e-12)
    pu0 = P.first_order(frame, lon, lat, h, names, np.diag(sd**2), crs)
    assert np.all(
        np.abs(pu.sigma_horizontal / pu0.sigma_horizontal - 1) > 0.01
    )  # correlation matters
    X, dE, dN = S.monte_carlo(frame, lon, lat, h, names, D, crs, samples=1000, seed=3)
    mc = np.sqrt(dE.var(0, ddof=1) + dN.var(0, ddof=1))
    assert np.all(np.abs(mc / pu.sigma_horizontal - 1) < 0.02)


def test_imaging_time_lever_is_the_ground_track_speed(frame):
    """σ(imaging_time) = 1 ms moves the ground point by about the ground-track speed × 1 ms
    (≈ 6.5–7 m for a 686 km orbit)."""
    crs = geodesy.utm_crs(32.8, 39.9)
    lon, lat = frame.localize(np.array([256.0]), np.array([256.0]), np.array([1000.0]))
    pu = P.first_order(frame, lon, lat, np.array([1000.0]), ["imaging_time"], np.diag([1e-6]), crs)
    r = np.linalg.norm(frame.position)
    v_in = np.linalg.norm(frame.velocity + np.cross([0, 0, geodesy.OMEGA_EARTH], frame.position))
    ground_inertial = v_in * (r - 686e3) / r
    assert 0.8 * ground_inertial * 1e-3 < pu.sigma_horizontal[0] < 1.2 * ground_inertial * 1e-3


# --------------------------------------------------------------------------- sampling pieces


def test_iman_conover_imposes_rank_correlation_and_keeps_marginals():
    D = np.array([[4.0, 1.4, 0.0], [1.4, 1.0, -0.3], [0.0, -0.3, 0.25]])
    X = S.lhs_normal(D, 2000, seed=5)
    C = D / np.sqrt(np.outer(np.diag(D), np.diag(D)))
    rho = stats.spearmanr(X).correlation
    assert np.allclose(rho, C, atol=0.04)
    assert np.allclose(X.std(0, ddof=1), np.sqrt(np.diag(D)), rtol=0.01)
    # LHS: every one of the 2000 strata of each marginal holds exactly one sample
    u = stats.norm.cdf(X / np.sqrt(np.diag(D)))
    assert all(np.unique(np.floor(u[:, k] * 2000)).size == 2000 for k in range(3))


def test_regression_measures_on_a_known_linear_model():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(4000, 3)) * [1.0, 2.0, 0.5]
    y = 3 * X[:, 0] - X[:, 1] + 0.0 * X[:, 2] + rng.normal(scale=0.5, size=4000)
    b, r2 = S.src(X, y)
    sd_y = y.std(ddof=1)
    assert np.allclose(b, [3 * 1.0 / sd_y, -2.0 / sd_y, 0.0], atol=0.02)
    assert 0.95 < r2 < 1
    pc = S.pcc(X, y)
    assert pc[0] > 0.98 and pc[1] < -0.95 and abs(pc[2]) < 0.05
    pr = S.prcc(X, y)
    assert pr[0] > 0.9 and pr[1] < -0.85 and abs(pr[2]) < 0.05


def test_ce90_closed_forms_and_monte_carlo():
    s = 2.0
    assert P.ce90(np.diag([s * s, s * s])) == pytest.approx(2.145966 * s, rel=1e-4)
    assert P.ce90(np.diag([s * s, 0.0])) == pytest.approx(1.644854 * s, rel=1e-3)
    C = np.array([[9.0, 2.5], [2.5, 2.0]])
    r = P.ce90(C)
    pts = np.random.default_rng(1).multivariate_normal([0, 0], C, 400_000)
    assert np.mean(np.hypot(*pts.T) <= r) == pytest.approx(0.9, abs=0.002)


# --------------------------------------------------------------------------- FAST / Sobol


def test_thesis_fast_frequency_set_is_interference_free_to_order_4():
    thesis = [145, 177, 199, 41, 67, 105, 219, 229, 235, 243, 247]
    order = interference_order(thesis, max_order=7)
    assert order == 6  # e.g. −3·145 + 229 + 247 − 41 = 0
    assert order > 4 + 1
    # brute force over all coefficient vectors with entries in -6..6 (an independent search):
    # the lowest-order combination of this set has order 6, so none up to 4

    f = [11, 21, 27, 35, 39]
    brute = min(
        sum(map(abs, a))
        for a in itertools.product(range(-6, 7), repeat=len(f))
        if any(a) and sum(x * w for x, w in zip(a, f)) == 0
    )
    assert brute == 6
    assert interference_order(f, max_order=8) == brute
    assert interference_order(f, max_order=4) is None
    assert interference_order([1, 2]) == 3  # 2·1 − 2 = 0, order 3


def test_salib_efast_design_is_interference_free_to_order_4():
    """The frequencies SALib's eFAST sampler really puts on the search curves (read back from
    the samples by FFT) read the first 4 harmonics cleanly."""
    from SALib.sample import fast_sampler  # optional (the uncertainty extra)

    N, M, u = 1000, 4, 5
    problem = {"num_vars": u, "names": list("abcde"), "bounds": [[0, 1]] * u}
    X = fast_sampler.sample(problem, N, M=M, seed=0)
    for i in range(u):
        block = X[i * N : (i + 1) * N]
        w = [sample_frequencies(block[:, j], N) for j in range(u)]
        comp = [w[j] for j in range(u) if j != i]
        assert w[i] > max(comp)
        assert efast_interference_free(w[i], comp, M, N)
    assert not efast_interference_free(12, [3, 4], 4, 1000)  # 3·4 = 12 interferes


def test_fast_indices_match_first_order_shares_for_a_linear_case(rpc, flat):
    model = P.adjustable_model(rpc)
    crs = geodesy.utm_crs(*rpc.center_lonlat(2300.0))
    lon, lat = rpc.localize(np.array([300.0]), np.array([700.0]), np.array([2300.0]))
    names = ["col_shift", "row_shift", "dem_height"]
    D = np.diag([1.0, 0.3**2, 4.0**2])
    pu = P.first_order(model, lon, lat, np.array([2300.0]), names, D, crs)
    r = fast_indices(model, lon, lat, np.array([2300.0]), names, D, crs, samples=300, M=4)
    for k, n in enumerate(r["names"]):
        assert r["S1"]["horizontal"][k, 0] == pytest.approx(pu.shares[n][0], abs=0.03)
    assert r["S1"]["horizontal"][:, 0].sum() <= 1.02


# --------------------------------------------------------------------------- DEM vertical σ


def test_hirvonen_slopes_recover_plane_and_quadratic_gradients():
    res = 30.0
    r, c = np.mgrid[0:40, 0:50]
    E, N = c * res, -r * res
    z = 100 + 0.12 * E - 0.05 * N + 2e-5 * E * E + 1e-5 * E * N
    gE, gN = hirvonen_slopes(z, res)
    inner = (slice(6, -6), slice(6, -6))
    assert np.allclose(gE[inner], (0.12 + 4e-5 * E + 1e-5 * N)[inner], atol=1e-9)
    assert np.allclose(gN[inner], (-0.05 + 1e-5 * E)[inner], atol=1e-9)


def test_dem_vertical_sigma_pleiades_pair(data_dir):
    """Pleiades pair (real RPCs): the matching term scales with the disparity σ and the score;
    on a tilted plane the slope term is |∇h|·σ_horizontal."""
    left = RPCModel.from_file(data_dir / "pleiades" / "img_01_rpc.tif")
    right = RPCModel.from_file(data_dir / "pleiades" / "img_02_rpc.tif")
    lon0, lat0 = left.center_lonlat(2300.0)
    crs = geodesy.utm_crs(lon0, lat0)
    E0, N0 = geodesy.lonlat_to_crs(lon0, lat0, crs)
    tr = Affine(2.0, 0, E0 - 100, 0, -2.0, N0 + 100)
    r, c = np.mgrid[0:100, 0:100]
    z = 2300 + 0.2 * (c * 2.0) + 0.1 * (-r * 2.0)
    dem = DEM(z.astype(np.float32), tr, crs, "ellipsoid")
    a = dem_vertical_sigma(left, right, dem, sigma_disparity=0.2)
    b = dem_vertical_sigma(left, right, dem, sigma_disparity=0.4)
    assert np.allclose(b.sigma_intersection, 2 * a.sigma_intersection, rtol=1e-5)
    # independent prediction: a 1 m climb along the left pixel's ray moves its right image by
    # k px, so a disparity error of 0.2 px is 0.2 / k m of height (0.38 m here). The module's
    # least-squares intersection of both images (disparity along the right image's motion per
    # vertical metre, not exactly along the left ray's epipolar line) gives 13 % less.
    c0, r0 = left.project(lon0, lat0, 2300.0)
    p = [
        np.array(
            right.project(
                *left.localize(np.atleast_1d(c0), np.atleast_1d(r0), np.atleast_1d(hh)), hh
            )
        )
        for hh in (2300.0, 2301.0)
    ]
    predicted = 0.2 / float(np.linalg.norm(p[1] - p[0]))
    assert np.nanmedian(a.sigma_intersection) == pytest.approx(predicted, rel=0.2)
    score = np.full(z.shape, 0.9)
    score[:50] = 0.6
    s = dem_vertical_sigma(left, right, dem, sigma_disparity=0.2, score=score)
    assert np.nanmedian(s.sigma_intersection[60:]) == pytest.approx(
        np.nanmedian(a.sigma_intersection[60:]), rel=1e-5
    )
    assert np.nanmedian(s.sigma_intersection[:40]) > 2 * np.nanmedian(a.sigma_intersection[:40])
    inner = (slice(10, -10), slice(10, -10))
    slope = np.sqrt((0.2 * a.sigma_east) ** 2 + (0.1 * a.sigma_north) ** 2)
    assert np.allclose(a.sigma_slope[inner], slope[inner], rtol=1e-3)
    assert np.all(a.sigma_vertical[inner] >= a.sigma_intersection[inner])
    assert a.interpolation_error < 0.01


@pytest.mark.parametrize("kind", ["frame", "pushbroom"])
def test_central_difference_steps_are_stable_for_every_parameter(kind, frame):
    """For every input of a frame camera and of a pushbroom model, the ground Jacobian with the
    project's step agrees with the one at a step ten times smaller (truncation and round-off
    both small), and no input is dead (all partials non-zero somewhere)."""
    if kind == "frame":
        model = frame
        lon, lat = frame.localize(
            np.array([30.0, 256.0, 480.0]), np.array([20.0, 256.0, 490.0]), np.full(3, 1000.0)
        )
        lon0, lat0 = 32.8, 39.9
    else:
        model, _ = pushbroom_pair(32.8, 39.9, 1000.0, (400, 400), (0.0, -27.6))
        lon, lat = model.localize(
            np.array([30.0, 200.0, 380.0]), np.array([20.0, 200.0, 390.0]), np.full(3, 1000.0)
        )
        lon0, lat0 = 32.8, 39.9
    crs = geodesy.utm_crs(lon0, lat0)
    names = P.valid_names(model)
    h = np.full(3, 1000.0)
    gj = P.ground_jacobian(model, lon, lat, h, names, crs)

    vals = model.parameters()
    chosen = P.propagation_steps(model, list(vals))
    fine = {n: 0.1 * chosen.get(n, default_step(n, vals[n])) for n in vals}
    old = (P.DEM_HEIGHT_STEP, P.IMAGING_TIME_STEP)
    try:
        P.DEM_HEIGHT_STEP, P.IMAGING_TIME_STEP = 0.1, 1e-4
        gj2 = P.ground_jacobian(model, lon, lat, h, names, crs, steps=fine)
    finally:
        P.DEM_HEIGHT_STEP, P.IMAGING_TIME_STEP = old
    for k, n in enumerate(names):
        a, b = gj.J[..., k], gj2.J[..., k]
        scale = np.abs(a).max()
        assert scale > 0, n
        assert np.max(np.abs(a - b)) < 2e-3 * scale, n


def test_image_shift_field_matches_exact_relocalisation_without_terrain(frame):
    """The many-point Monte Carlo path (exact perturbed model at Chebyshev nodes, fitted field,
    local ground map) gives the same per-sample displacements as per-sample Newton
    re-localisation when the terrain is the constant height (1e-3 relative), and its measured
    field error is tiny."""
    crs = geodesy.utm_crs(32.8, 39.9)
    cc, rr = np.meshgrid(np.linspace(0, 511, 12), np.linspace(0, 511, 12))
    lon, lat = frame.localize(cc.ravel(), rr.ravel(), np.full(cc.size, 1000.0))
    h = np.full(lon.shape, 1000.0)
    names = ["roll", "pitch", "yaw", "x", "imaging_time", "dem_height", "k1"]
    D = np.diag([1e-10, 1e-10, 1e-10, 25.0, 1e-6, 100.0, 1e-12])  # displacements of a few pixels
    X = S.lhs_normal(D, 40, seed=2)
    e1, n1 = S.ground_displacements(frame, lon, lat, h, names, X, crs)
    e2, n2, err = S.field_displacements(frame, lon, lat, h, names, X, crs)
    assert err < 1e-3
    scale = np.hypot(e1, n1).max()
    assert scale > 20
    assert np.max(np.hypot(e1 - e2, n1 - n2)) < 1e-3 * scale


def test_sampling_methods_on_the_map(rpc, flat):
    grid = grid_for_model(rpc, flat, res=8.0)
    names = ["col_shift", "row_shift", "dem_height"]
    D = np.diag([1.0, 0.25, 16.0])
    fo = ortho_uncertainty_maps(rpc, flat, grid, D, names)
    mc = ortho_uncertainty_maps(rpc, flat, grid, D, names, "monte-carlo", samples=300)
    ok = np.isfinite(fo.sigma_horizontal) & np.isfinite(mc.sigma_horizontal)
    assert ok.mean() > 0.8
    assert np.nanmax(np.abs(mc.sigma_horizontal[ok] / fo.sigma_horizontal[ok] - 1)) < 0.02
    for k in names:
        assert mc.shares[k] == pytest.approx(fo.shares[k], abs=0.02)


def test_hirvonen_slopes_beside_a_void_are_the_dems_own():
    """A window reaching a void gave NaN, and the DEM's vertical σ (run's
    dem_sigma_vertical.tif) a ring of nodata 5 posts wide around every hole; one reaching the
    grid's edge half a plane's slope. There the slope is now the DEM's own difference
    (one-sided beside the void or the edge): exact on a plane."""
    res = 30.0
    r, c = np.mgrid[0:40, 0:50]
    z = 100 + 0.12 * c * res + 0.05 * r * res  # rows run south: dh/dN = -0.05
    z[18:22, 20:25] = np.nan
    gE, gN = hirvonen_slopes(z, res)
    assert np.array_equal(np.isfinite(gE), np.isfinite(z)) and np.array_equal(
        np.isfinite(gN), np.isfinite(z)
    )
    ok = np.isfinite(z)
    assert np.allclose(gE[ok], 0.12) and np.allclose(gN[ok], -0.05)
