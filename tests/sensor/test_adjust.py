"""Adjustment of one sensor model from GCPs (issue #15): RPC bias compensation on a real RPC,
statistics (sigma0, chi-square, covariance vs the spread of repeated estimates), reliability
identities, data snooping, hostile inputs, GCP files."""

import json
import re

import numpy as np
import pytest
from scipy import stats
from scipy.linalg import null_space

from stereodem.adjust_images import tie_csv_rows
from stereodem.core import geodesy
from stereodem.core.errors import ConvergenceError, InputError, SensorModelError
from stereodem.sensor.estimation.adjust import (
    MODEL_SETS,
    AdjustmentResult,
    adjust_model,
    register_model_set,
    required_gcps,
)
from stereodem.sensor.estimation.adjust import gauss_markov as gm
from stereodem.sensor.estimation.adjust import reliability as rel
from stereodem.sensor.io.gcps import ControlPoints, read_gcps, write_gcps
from stereodem.sensor.models.corrected import ImageCorrectedModel
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation.simulate import pushbroom_pair


@pytest.fixture(scope="module")
def rpc(data_dir):
    return RPCModel.from_file(data_dir / "pleiades" / "img_01_rpc.tif")


def ground_points(model, n, rng, margin=5):
    """Random image points localised at random heights inside the model's height range."""
    c = rng.uniform(margin, model.width - 1 - margin, n)
    r = rng.uniform(margin, model.height - 1 - margin, n)
    lo, hi = model.height_bounds()
    mid, half = 0.5 * (lo + hi), 0.25 * (hi - lo)
    h = rng.uniform(mid - half, mid + half, n)
    lon, lat = model.localize(c, r, h)
    return lon, lat, h


def observe(truth, lon, lat, h, sigma, rng, role=None):
    c, r = truth.project(lon, lat, h)
    return ControlPoints.from_arrays(
        lon, lat, h, c + rng.normal(0, sigma, c.size), r + rng.normal(0, sigma, c.size), role=role
    )


BIAS = dict(col_shift=3.2, row_shift=-1.7, row_drift_row=2e-5, col_drift_row=-1e-5)


def test_rpc_bias_compensation_real_rpc(rpc):
    """Real Pleiades RPC with an injected bias: check-point RMSE at the noise level."""
    rng = np.random.default_rng(3)
    truth = ImageCorrectedModel(rpc, **BIAS)
    lon, lat, h = ground_points(rpc, 40, rng)
    sigma = 0.3
    pts = observe(truth, lon, lat, h, sigma, rng, role=np.where(np.arange(40) < 15, "gcp", "check"))
    before = np.hypot(*(np.stack(rpc.project(lon, lat, h)) - np.stack([pts.col, pts.row])))
    res = adjust_model(rpc, pts, "rpc-shift-drift", sigma_px=sigma)
    assert isinstance(res, AdjustmentResult) and res.converged and res.outliers == []
    assert isinstance(res.model, ImageCorrectedModel)
    # noise level of a radial residual: sigma * sqrt(2); a check point also carries the
    # propagated parameter error, so allow its expectation plus sampling spread
    assert np.sqrt(np.mean(before**2)) > 5 * sigma * np.sqrt(2)  # the bias dominates
    assert res.check_rmse_px < 1.3 * sigma * np.sqrt(2)
    assert res.check_rmse_px > 0.7 * sigma * np.sqrt(2)
    for name in ("col_shift", "row_shift", "row_drift_row", "col_drift_row"):
        k = res.names.index(name)
        assert abs(res.values[k] - BIAS[name]) < 4 * res.std[k]


@pytest.mark.slow
def test_spread_of_estimates_matches_reported_sigma(rpc):
    """Repeated noise draws: the spread of the estimates matches the reported sigma (15 %),
    sigma0 averages 1 when the a-priori sigma is the true noise, the chi-square test keeps
    about 1 - alpha of the draws."""
    rng = np.random.default_rng(11)
    truth = ImageCorrectedModel(rpc, **BIAS)
    lon, lat, h = ground_points(rpc, 12, rng)
    c, r = truth.project(lon, lat, h)
    sigma, draws = 0.5, 300
    est, std, s0, passed = [], [], [], 0
    for _ in range(draws):
        pts = ControlPoints.from_arrays(
            lon, lat, h, c + rng.normal(0, sigma, c.size), r + rng.normal(0, sigma, c.size)
        )
        res = adjust_model(rpc, pts, "rpc-affine", sigma_px=sigma, snooping=False)
        est.append(res.values)
        std.append(res.std)
        s0.append(res.sigma0)
        passed += res.chi2_test["passed"]
    est, std = np.array(est), np.array(std)
    true = np.array([BIAS.get(n, 0.0) for n in res.names])
    spread = est.std(axis=0, ddof=1)
    ratio = spread / std.mean(axis=0)
    assert np.all(np.abs(ratio - 1) < 0.15), dict(zip(res.names, ratio))
    # unbiased: mean error within 4 standard errors of the mean
    assert np.all(np.abs(est.mean(0) - true) < 4 * spread / np.sqrt(draws))
    assert abs(np.mean(s0) - 1) < 0.05
    assert 0.9 < passed / draws <= 1.0


def test_reliability_identities_and_mdb_scaling(rpc):
    """Sum r_i = n - u; delta_0 = 4.13 for alpha 0.001 / power 0.80; external reliability
    delta_0i = 4.13 sqrt(Q_ii / r_i) with Q_ii the hat diagonal (Bettemir Table B.33)."""
    assert rel.noncentrality(0.001, 0.80) == pytest.approx(4.13, abs=0.005)
    assert rel.baarda_threshold(0.001) == pytest.approx(3.29, abs=0.005)
    rng = np.random.default_rng(5)
    lon, lat, h = ground_points(rpc, 25, rng)
    pts = observe(ImageCorrectedModel(rpc, **BIAS), lon, lat, h, 0.4, rng)
    res = adjust_model(rpc, pts, "rpc-affine", sigma_px=0.4, snooping=False)
    n, u = 2 * len(pts), len(res.names)
    assert np.nansum(res.redundancy) == pytest.approx(n - u, abs=1e-9)
    assert res.dof == n - u
    Q = 1 - res.redundancy
    np.testing.assert_allclose(
        res.external_reliability, 4.13 * np.sqrt(Q / res.redundancy), rtol=2e-3
    )
    # internal reliability: sigma delta_0 / sqrt(r_i) in pixels
    np.testing.assert_allclose(res.mdb, 0.4 * rel.noncentrality() / np.sqrt(res.redundancy))
    # the seed's own numbers: r 0.5447 -> 3.7761, r 0.8549 -> 1.7016 (Table B.33)
    np.testing.assert_allclose(
        rel.external_reliability([0.5447, 0.8549], 4.13), [3.7761, 1.7016], atol=2e-3
    )
    # standardised residuals are the whitened residuals over sqrt(r)
    e = res.residuals_px / 0.4
    np.testing.assert_allclose(res.w, e / np.sqrt(res.redundancy), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("sigma_known", [True, False])
def test_one_blunder_among_25_gcps(rpc, sigma_known):
    """One 4 px blunder among 25 GCPs is flagged (Baarda with a known sigma, Pope's tau with an
    unknown one) and no good point is."""
    flagged_good, missed = 0, 0
    for seed in range(6):
        rng = np.random.default_rng(100 + seed)
        lon, lat, h = ground_points(rpc, 25, rng)
        pts = observe(ImageCorrectedModel(rpc, **BIAS), lon, lat, h, 0.3, rng)
        k = rng.integers(25)
        pts.row[k] += 4.0 * rng.choice([-1, 1])
        res = adjust_model(rpc, pts, "rpc-shift-drift", sigma_px=0.3 if sigma_known else None)
        ids = [o["id"] for o in res.outliers]
        missed += pts.id[k] not in ids
        flagged_good += len(set(ids) - {pts.id[k]})
        assert res.test["name"] == ("baarda" if sigma_known else "pope")
        if ids:
            assert "row" in res.outliers[0]["reason"] and res.outlier_mask.sum() == len(ids)
    assert missed == 0 and flagged_good == 0


def test_gauss_helmert_ground_observations(rpc):
    """GCPs with ground sigmas: the misclosure covariance grows, sigma0 stays ~1 when the
    ground coordinates carry the stated noise, and the ground residuals come back in metres."""
    rng = np.random.default_rng(21)
    lon, lat, h = ground_points(rpc, 30, rng)
    truth = ImageCorrectedModel(rpc, **BIAS)
    tc, tr = truth.project(lon, lat, h)
    sg = 1.0  # m, each of E, N, U

    X = np.stack(geodesy.geodetic_to_ecef(lon, lat, h), -1)
    B = geodesy.enu_basis(lon, lat)
    X = X + np.einsum("nkj,nk->nj", B, rng.normal(0, sg, (30, 3)))
    nlon, nlat, nh = geodesy.ecef_to_geodetic(X[:, 0], X[:, 1], X[:, 2])
    s0 = []
    for ground_sigma in (None, sg):
        pts = ControlPoints.from_arrays(
            nlon,
            nlat,
            nh,
            tc + rng.normal(0, 0.2, 30),
            tr + rng.normal(0, 0.2, 30),
            sigma_px=0.2,
            sigma_ground_m=ground_sigma,
        )
        res = adjust_model(rpc, pts, "rpc-shift", snooping=False)
        s0.append(res.sigma0)
    assert s0[0] > 1.5  # ground noise ignored: sigma0 too large
    assert 0.7 < s0[1] < 1.3  # Gauss-Helmert: consistent
    assert np.any(res.ground_residuals_m != 0) and res.ground_residuals_m.shape == (30, 3)
    # near-nadir, every GCP with a ground sigma: G G^T ~ isotropic, the image and ground
    # variance components look alike and are reported as not separable (no iteration)
    vc = adjust_model(
        rpc, pts, "rpc-shift", snooping=False, variance_components="iterate"
    ).variance_components
    assert not vc["separable"] and vc["sigma_scale_applied"] == {"image": 1.0, "ground": 1.0}


def test_report_content(rpc, tmp_path):
    rng = np.random.default_rng(2)
    lon, lat, h = ground_points(rpc, 20, rng)
    pts = observe(
        ImageCorrectedModel(rpc, **BIAS),
        lon,
        lat,
        h,
        0.3,
        rng,
        role=np.where(np.arange(20) < 14, "gcp", "check"),
    )
    rep = adjust_model(rpc, pts, "rpc-shift", sigma_px=0.3).to_report()
    json.dumps(rep)
    for key in (
        "model",
        "sigma0",
        "parameters",
        "covariance",
        "points",
        "gcp_rmse_px",
        "check_rmse_px",
        "outliers",
    ):
        assert key in rep
    assert rep["model"]["type"] == "image_corrected"
    assert [p["name"] for p in rep["parameters"]] == ["col_shift", "row_shift"]
    assert rep["parameters"][0]["unit"] == "px"
    assert len(rep["covariance"]) == 2 and len(rep["points"]) == 20
    assert {p["role"] for p in rep["points"]} == {"gcp", "check"}


# ------------------------------------------------------------------------- hostile inputs
def _pts(rpc, n=10, seed=0, **kw):
    rng = np.random.default_rng(seed)
    lon, lat, h = ground_points(rpc, n, rng)
    return observe(ImageCorrectedModel(rpc, **BIAS), lon, lat, h, 0.3, rng, **kw)


def test_too_few_gcps_says_how_many(rpc):
    pts = _pts(rpc, 3)
    assert required_gcps(6) == 4
    with pytest.raises(InputError, match="6 free parameter.*need at least 4 GCPs.*got 3"):
        adjust_model(rpc, pts, "rpc-affine")


def test_points_outside_image_and_swapped(rpc):
    pts = _pts(rpc)
    pts.col[2] = rpc.width + 50
    with pytest.raises(InputError, match="outside the 1024 x 1024 image.*P003"):
        adjust_model(rpc, pts, "rpc-shift")
    pts = _pts(rpc)
    pts.lon, pts.lat = pts.lat.copy(), pts.lon.copy()
    with pytest.raises(InputError, match="validity range.*likely swapped lon/lat"):
        adjust_model(rpc, pts, "rpc-shift")
    pts = _pts(rpc)
    pts.lon[0] += 5.0
    with pytest.raises(InputError, match="validity range") as exc:
        adjust_model(rpc, pts, "rpc-shift")
    assert "swapped" not in str(exc.value)


def test_duplicates_nans_unknown_names(rpc):
    pts = _pts(rpc)
    pts.id[3] = pts.id[4]
    with pytest.raises(InputError, match="duplicate point id.*P005"):
        adjust_model(rpc, pts, "rpc-shift")
    pts = _pts(rpc)
    pts.h[1] = np.nan
    with pytest.raises(InputError, match="NaN.*'h'.*P002"):
        adjust_model(rpc, pts, "rpc-shift")
    with pytest.raises(InputError, match="unknown model set 'rpc-shfit'"):
        adjust_model(rpc, _pts(rpc), "rpc-shfit")
    with pytest.raises(SensorModelError, match="no adjustable parameters"):
        adjust_model(rpc, _pts(rpc), ["col_shift"])
    with pytest.raises(InputError, match="unknown parameter.*colshift"):
        adjust_model(ImageCorrectedModel(rpc), _pts(rpc), ["colshift"])


def _assert_names_span_a_null_direction(message, rpc, pts, model_set):
    """What the near-singular message guarantees, whatever the LAPACK build: the parameters it
    names are the dominant part of a null direction of the design matrix, so their columns are
    linearly dependent, and each of them has a component in the null space. (Which vector of a
    null space of dimension > 1 the SVD returns is the library's choice: all GCPs on one row
    make both col_shift/col_drift_row and row_shift/row_drift_row inseparable.)"""
    named = re.search(r"cannot separate (.+?) —", message).group(1).split(", ")
    names = list(MODEL_SETS[model_set].names)
    assert named and set(named) <= set(names), message
    J = ImageCorrectedModel(rpc).project_partials(pts.lon, pts.lat, pts.h, names)
    A = J.reshape(-1, len(names))
    A = A / np.linalg.norm(A, axis=0)  # the solver's column equilibration
    N = null_space(A, rcond=1e-9)
    assert N.shape[1] >= 1
    cols = [names.index(n) for n in named]
    assert np.linalg.matrix_rank(A[:, cols], tol=1e-9) < len(cols), message
    assert np.all(np.linalg.norm(N[cols], axis=1) > 0.1), message


def test_near_singular_names_the_parameters(rpc):
    """All GCPs on one image row: the row drift and the row shift cannot be separated."""
    pts = _pts(rpc, 12)
    rng = np.random.default_rng(0)
    c = rng.uniform(10, 1000, 12)
    lon, lat = rpc.localize(c, np.full(12, 500.0), pts.h)
    pts = ControlPoints.from_arrays(lon, lat, pts.h, *rpc.project(lon, lat, pts.h))
    with pytest.raises(SensorModelError, match=r"condition number [0-9.e+]+\).*separate") as err:
        adjust_model(rpc, pts, "rpc-shift-drift")
    _assert_names_span_a_null_direction(str(err.value), rpc, pts, "rpc-shift-drift")
    # regularisation (L-curve) makes it solvable
    res = adjust_model(rpc, pts, "rpc-shift-drift", regularization="lcurve", snooping=False)
    assert res.regularization > 0 and np.all(np.isfinite(res.values))


def test_gcv_on_a_rank_deficient_set_has_finite_statistics(rpc):
    """All GCPs on one image row make row_shift and row_drift_row exactly collinear (rank
    deficient): GCV-weighted Tikhonov still solves it through SVDs (no LinAlgError from an
    inverted normal matrix), with finite covariances and the GCPs fitted; a zero weight is no
    regularisation and is refused like the unregularised problem."""
    pts = _pts(rpc, 12)
    rng = np.random.default_rng(1)
    c = rng.uniform(10, 1000, 12)
    lon, lat = rpc.localize(c, np.full(12, 500.0), pts.h)
    truth = ImageCorrectedModel(rpc, col_shift=0.8, row_shift=-0.6)
    pts = ControlPoints.from_arrays(lon, lat, pts.h, *truth.project(lon, lat, pts.h))
    res = adjust_model(rpc, pts, "rpc-shift-drift", regularization="gcv", snooping=False)
    assert res.regularization > 0
    assert res.condition > 1e12  # the set really is (near-)rank-deficient
    assert np.all(np.isfinite(res.covariance)) and np.all(np.isfinite(res.std))
    assert res.gcp_rmse_px < 0.05
    with pytest.raises(
        SensorModelError, match=r"near-singular.*regularisation weight 0\).*separate"
    ) as err:
        adjust_model(rpc, pts, "rpc-shift-drift", regularization=0.0, snooping=False)
    _assert_names_span_a_null_direction(str(err.value), rpc, pts, "rpc-shift-drift")


def test_linear_algebra_failure_is_a_sensor_model_error():
    """A LinAlgError inside the solve (here the model's own ``np.linalg.solve`` on a matrix that
    its parameters make singular) comes out as SensorModelError naming the parameters."""
    b = np.array([1.0, 2.0])

    def evaluate(x):
        y = np.linalg.solve(np.array([[x[0], x[1]], [x[0], x[1]]]), b)
        return y - 1.0, np.eye(2)

    with pytest.raises(SensorModelError, match=r"linear algebra failed \(Singular matrix\).*a, b"):
        gm.solve(evaluate, [1.0, 2.0], ["a", "b"], regularization="gcv")


def test_non_convergence_is_an_error(rpc):
    with pytest.raises(ConvergenceError, match=r"no convergence in \d+ iteration.*criterion"):
        # the affine correction is linear: one iteration solves it, but a second is needed
        # to verify the criterion
        adjust_model(rpc, _pts(rpc, 12), "rpc-affine", max_iterations=1, tolerance=0.0)


def test_model_set_registry_is_extensible(rpc):
    name = "test-col-only"
    register_model_set(
        name, lambda m: ImageCorrectedModel(m), ("col_shift",), description="test", replace=True
    )
    try:
        res = adjust_model(rpc, _pts(rpc), name, sigma_px=0.3)
        assert res.names == ["col_shift"] and res.model_set == name
        with pytest.raises(InputError, match="already registered"):
            register_model_set(name, lambda m: m, ("x",))
    finally:
        MODEL_SETS.pop(name)


def test_priors_are_fictitious_observations(rpc):
    pts = _pts(rpc, 10)
    free = adjust_model(rpc, pts, "rpc-shift", sigma_px=0.3, snooping=False)
    tight = adjust_model(
        rpc, pts, "rpc-shift", sigma_px=0.3, snooping=False, priors={"col_shift": 1e-4}
    )
    k = tight.names.index("col_shift")
    assert abs(tight.values[k]) < 1e-3 and tight.std[k] < 1e-4
    assert tight.dof == free.dof + 1
    about = adjust_model(
        rpc, pts, "rpc-shift", sigma_px=0.3, snooping=False, priors={"col_shift": (2.0, 1e-4)}
    )
    assert abs(about.values[k] - 2.0) < 1e-3
    # a linear constraint (practically hard: sigma 1e-4 of the parameters' own) between two
    con = adjust_model(
        rpc,
        pts,
        "rpc-shift",
        sigma_px=0.3,
        snooping=False,
        constraints=[({"col_shift": 1.0, "row_shift": 1.0}, 1.0, 1e-5)],
    )
    assert abs(con.values.sum() - 1.0) < 1e-4 and con.dof == free.dof + 1
    assert abs(free.values.sum() - 1.0) > 0.5  # not what the data alone give
    with pytest.raises(InputError, match="constraint on 'row_drift_row'"):
        adjust_model(rpc, pts, "rpc-shift", constraints=[({"row_drift_row": 1.0}, 0.0, 1e-6)])


# ------------------------------------------------------------------------- GCP files
def test_gcp_csv_format(tmp_path, rpc):
    pts = _pts(rpc, 6, role=np.array(["gcp", "gcp", "check", "gcp", "check", "gcp"]))
    pts.sigma_px[:] = 0.5
    pts.sigma_ground_m[1] = 2.0
    path = write_gcps(tmp_path / "p.csv", pts)
    back = read_gcps(path)
    np.testing.assert_allclose(back.lon, pts.lon, atol=1e-10)
    assert back.role.tolist() == pts.role.tolist()
    np.testing.assert_allclose(back.sigma_px, 0.5)
    assert back.sigma_ground_m[1] == 2.0 and np.isnan(back.sigma_ground_m[0])
    header = path.read_text().splitlines()[0]
    assert header == "id,lon,lat,h,col,row,sigma_px,sigma_ground_m,role"
    # EGM96 heights
    geo = read_gcps(path, vertical="geoid")

    np.testing.assert_allclose(geo.h - back.h, geodesy.geoid_undulation(back.lon, back.lat))
    assert np.all(np.abs(geo.h - back.h) > 1)


@pytest.mark.parametrize(
    "text, match",
    [
        ("id,lon,lat,h,col,row\na,1,2,3,4,5\na,1,2,3,4,6\n", "duplicate point id.*a"),
        ("id,lon,lat,h,col,row\na,1,2,3,4,5\nb,1,nan,3,4,6\n", "1 missing/NaN.*'lat'.*line 3"),
        ("id,lon,lat,h,col,row\na,-21.1,155.4,3,4,5\n", "out of range.*likely swapped lon/lat"),
        ("id,lon,lat,h,col,row\na,100,95,3,4,5\n", "out of range"),
        ("id,lon,lat,h,col,row,sigma_px\na,1,2,3,4,5,-1\n", "positive standard deviations"),
        ("id,lon,lat,h,col\na,1,2,3,4\n", "missing GCP column.*row"),
    ],
)
def test_gcp_csv_errors(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=f"bad.csv: .*{match}"):
        read_gcps(path)
    if "100,95" in text:
        assert "swapped" not in str(pytest.raises(InputError, read_gcps, path).value)


@pytest.mark.parametrize(
    "data",
    [
        bytes(range(256)) * 8,  # binary
        "id,lon,lat,h,col,row\nPointé,1,2,3,4,5\n".encode("latin-1"),  # not UTF-8
    ],
    ids=["binary", "latin1"],
)
def test_gcp_csv_that_is_not_utf8_text_is_an_input_error(tmp_path, data):
    """A GCP (or tie-point) file that is binary or in another encoding: an InputError naming
    the file (was a UnicodeDecodeError traceback)."""
    path = tmp_path / "bad.csv"
    path.write_bytes(data)
    with pytest.raises(InputError, match="bad.csv: not a UTF-8 text CSV.*GCP file"):
        read_gcps(path)
    with pytest.raises(InputError, match="bad.csv: not a UTF-8 text CSV.*tie-point file"):
        tie_csv_rows(path, ["col1", "row1", "col2", "row2"])


def test_gcp_csv_with_a_byte_order_mark_reads_as_without(tmp_path):
    """Spreadsheets save "CSV UTF-8" with a byte-order mark: it was read into the first
    column's name ("\ufeffid"), and the file refused for a missing 'id' column."""
    text = "id,lon,lat,h,col,row,role\na,1,2,3,4,5,gcp\nb,1.5,2.5,3,6,7,check\n"
    (tmp_path / "plain.csv").write_text(text, encoding="utf-8")
    (tmp_path / "bom.csv").write_text(text, encoding="utf-8-sig")
    a, b = read_gcps(tmp_path / "plain.csv"), read_gcps(tmp_path / "bom.csv")
    for f in ("id", "lon", "lat", "h", "col", "row", "role"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


@pytest.mark.slow
def test_variance_components_image_and_ground(rpc):
    """Half the GCPs surveyed (ground fixed), half from a map whose stated 15 m sigma is three
    times too pessimistic (true 5 m): iterated variance components recover the factor 1/3 for
    the ground group and 1 for the image group; the group redundancies add up to n - u."""
    pb = pushbroom_pair(-121.7, 46.85, 1500.0, (2000, 2000), (0.0, -27.6))[1]
    rng = np.random.default_rng(2)
    n = 120
    c, r = rng.uniform(0, 1999, n), rng.uniform(0, 1999, n)
    h = rng.uniform(800, 2500, n)
    lon, lat = pb.localize(c, r, h)
    X = np.stack(geodesy.geodetic_to_ecef(lon, lat, h), -1)
    mapped = np.arange(n) >= n // 2
    X[mapped] += np.einsum(
        "nkj,nk->nj", geodesy.enu_basis(lon, lat)[mapped], rng.normal(0, 5.0, (mapped.sum(), 3))
    )
    nlon, nlat, nh = geodesy.ecef_to_geodetic(X[:, 0], X[:, 1], X[:, 2])
    pts = ControlPoints.from_arrays(
        nlon,
        nlat,
        nh,
        c + rng.normal(0, 0.3, n),
        r + rng.normal(0, 0.3, n),
        sigma_px=0.3,
        sigma_ground_m=np.where(mapped, 15.0, np.nan),
    )
    est = adjust_model(pb, pts, "attitude-bias", snooping=False, variance_components="estimate")
    vc = est.variance_components
    assert vc["separable"]
    assert vc["image"]["redundancy"] + vc["ground"]["redundancy"] == pytest.approx(
        est.dof, rel=1e-6
    )
    res = adjust_model(pb, pts, "attitude-bias", snooping=False, variance_components="iterate")
    f = res.variance_components["sigma_scale_applied"]
    assert abs(f["ground"] - 1 / 3) < 0.06 and abs(f["image"] - 1) < 0.15
    assert abs(res.sigma0 - 1) < 0.05
    assert res.to_report()["variance_components"]["separable"]


def test_gauss_newton_reports_stalled_not_converged():
    """A residual with a jagged term the Jacobian does not describe: near the optimum the
    Gauss-Newton correction (here 0.01..0.1 sigma) no longer lowers the sum of squares. The
    solution is accepted but reported as stalled, not converged; without the jagged term the
    same problem meets the criterion."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(40, 3))
    obs = A @ np.array([1.0, -2.0, 0.5]) + rng.normal(size=40)
    W = rng.normal(size=(40, 3)) * 1e4
    out = {}
    for amp in (0.0, 0.02):

        def res(x, amp=amp):
            return A @ x - obs + amp * np.sin(W @ x)

        out[amp] = gm.solve(
            lambda x, res=res: (res(x), A), np.zeros(3), ["a", "b", "c"], residual=res
        )
    assert out[0.0].status == "converged" and out[0.0].converged
    assert out[0.0].max_correction < 0.01
    s = out[0.02]
    assert s.status == "stalled" and not s.converged
    assert 0.01 <= s.max_correction < gm.STATIONARY_SIGMA


def test_test_quantiles_are_those_of_scipy_stats():
    """The thresholds and the variance test take their quantiles from scipy.special, as
    scipy.stats computes them (the same numbers, without its import)."""
    for alpha in (0.001, 0.01, 0.05):
        assert rel.baarda_threshold(alpha) == pytest.approx(
            stats.norm.ppf(1 - alpha / 2), rel=1e-14
        )
        for f in (2, 3, 10, 1000):
            t = stats.t.ppf(1 - alpha / 2, f - 1)
            pope = np.sqrt(f) * t / np.sqrt(f - 1 + t * t)
            assert rel.pope_threshold(alpha, f) == pytest.approx(pope, rel=1e-14)
    assert rel.noncentrality(0.001, 0.8) == pytest.approx(
        stats.norm.ppf(0.9995) + stats.norm.ppf(0.8), rel=1e-14
    )
    for dof in (1, 7, 300):
        for vtpv in (0.3 * dof, dof, 1.8 * dof):
            out = rel.variance_test(vtpv, dof, alpha=0.05)
            lo, hi = stats.chi2.ppf([0.025, 0.975], dof)
            assert out["lower"] == pytest.approx(lo, rel=1e-14)
            assert out["upper"] == pytest.approx(hi, rel=1e-14)
            cdf = stats.chi2.cdf(vtpv, dof)
            assert out["p_value"] == pytest.approx(2 * min(cdf, 1 - cdf), rel=1e-14)
