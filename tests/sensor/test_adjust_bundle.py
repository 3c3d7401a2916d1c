"""Bundle adjustment of a stereo pair (issue #15): vertical parallax removed from a biased
pair, absolute placement with 6 GCPs, solvers, reliability, tie blunders, hostile inputs."""

import json
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from stereodem.core import geodesy
from stereodem.core.errors import InputError, SensorModelError
from stereodem.sensor.estimation.adjust import bundle_adjust, write_report
from stereodem.sensor.geo.intersect import intersect_matches
from stereodem.sensor.io.gcps import ControlPoints
from stereodem.sensor.simulation.simulate import pushbroom_pair, simulate_scene
from stereodem.stereo.pipeline import make_dem
from stereodem.stereo.settings import RectificationSettings, StereoSettings
from stereodem.stereo.sparse import sparse_matches

LEFT_BIAS = dict(roll_bias=-2e-5, pitch_bias=3e-5, yaw_bias=5e-5)
RIGHT_BIAS = dict(roll_bias=4e-5, pitch_bias=-5e-5, yaw_bias=1e-4)  # ~30-70 m on the ground


@pytest.fixture(scope="module")
def pair():
    """An ASTER-like along-track pair (nadir and 27.6 deg backward, 15 m GSD): the truth."""
    return pushbroom_pair(-121.7, 46.85, 1500.0, (2000, 2000), (0.0, -27.6))


def sample(pair, n, rng, h=(800.0, 2500.0)):
    """Ground points seen by both true models: (lon, lat, h) and exact (c1, r1, c2, r2)."""
    L, R = pair
    c = rng.uniform(20, 1980, n)
    r = rng.uniform(20, 1980, n)
    hh = rng.uniform(*h, n)
    lon, lat = L.localize(c, r, hh)
    c2, r2 = R.project(lon, lat, hh)
    ok = (c2 > 0) & (c2 < R.width - 1) & (r2 > 0) & (r2 < R.height - 1)
    return lon[ok], lat[ok], hh[ok], np.stack([c[ok], r[ok], c2[ok], r2[ok]], -1)


def noisy_ties(pair, n, sigma, rng):
    *_, t = sample(pair, n, rng)
    return t + rng.normal(0, sigma, t.shape)


def gcp_pair(pair, n, sigma, rng, n_check=0):
    lon, lat, h, t = sample(pair, n + n_check, rng)
    role = np.array(["gcp"] * n + ["check"] * (len(lon) - n))
    mk = lambda k: ControlPoints.from_arrays(  # noqa: E731
        lon,
        lat,
        h,
        t[:, 2 * k] + rng.normal(0, sigma, len(lon)),
        t[:, 2 * k + 1] + rng.normal(0, sigma, len(lon)),
        role=role,
    )
    return mk(0), mk(1)


def test_bundle_removes_vertical_parallax(pair):
    """Ties only, the right model biased: with the left model as datum, the adjustment of the
    right attitude removes the parallax — ray gaps fall from tens of metres to the noise, tie
    residuals to below their a-priori sigma, sigma0 ~ 1."""
    L, R = pair
    rng = np.random.default_rng(0)
    ties = noisy_ties(pair, 300, 0.3, rng)
    res = bundle_adjust(
        L, R.with_parameters(**RIGHT_BIAS), ties, names=(None, "attitude-bias"), sigma_tie_px=0.3
    )
    before, after = res.parallax_before, res.parallax_after
    assert before["reprojection_rms_px"] > 5 * 0.3
    assert after["reprojection_rms_px"] < 0.3
    assert after["ray_gap_rms_m"] < 0.15 * before["ray_gap_rms_m"]
    assert 0.85 < res.sigma0 < 1.15 and res.chi2_test["passed"]
    assert res.names == ["right.roll_bias", "right.pitch_bias", "right.yaw_bias"]
    # the truth's own parallax with these ties is the floor
    truth = intersect_matches(L, R, *ties.T)
    assert after["ray_gap_rms_m"] < 1.2 * np.sqrt(np.mean(truth.ray_gap**2))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.slow
def test_bundle_with_6_gcps_places_the_pair(pair, seed):
    """Both models biased, 300 ties (0.3 px) and 6 GCPs (0.1 px, surveyed targets) measured in
    both images: the heights intersected from exact image coordinates of 400 truth points with
    the adjusted models have a median error below 0.2 GSD (the DEM's systematic error from the
    orientation; matching noise excluded), from several GSD before."""
    L, R = pair
    gsd = L.gsd()
    rng = np.random.default_rng(seed)
    Lb, Rb = L.with_parameters(**LEFT_BIAS), R.with_parameters(**RIGHT_BIAS)
    ties = noisy_ties(pair, 300, 0.3, rng)
    P1, P2 = gcp_pair(pair, 6, 0.1, rng, n_check=10)
    res = bundle_adjust(
        Lb,
        Rb,
        ties,
        names=("attitude-bias", "attitude-bias"),
        gcps=(P1, P2),
        sigma_tie_px=0.3,
        sigma_px=0.1,
    )
    lon, lat, h, t = sample(pair, 400, np.random.default_rng(99))
    before = intersect_matches(Lb, Rb, *t.T)
    after = intersect_matches(res.left, res.right, *t.T)
    assert abs(np.median(before.h - h)) > 3 * gsd
    assert abs(np.median(after.h - h)) < 0.2 * gsd
    # planimetry too (metres on the ground)

    e, n, _ = geodesy.ecef_to_enu(*after.ecef.T, lon, lat, h)
    assert np.hypot(np.median(e), np.median(n)) < 0.2 * gsd
    assert res.check_rmse_px < 3 * 0.1 * np.sqrt(2) + 0.5  # check points in px, both images
    rep = res.to_report()
    assert rep["n_gcp"] == 12 and rep["n_check"] == 2 * len(P1.select("check"))


def test_bundle_solvers_agree_and_redundancy(data_dir):
    """On the real Pleiades RPC pair (both biased in image space, rpc-shift-drift each): the
    reduced normal equations, scipy's sparse least_squares and the dense normal equations reach
    the same solution; sum of redundancy numbers = n - u (ties' ground coordinates counted);
    the biases are recovered within their sigma."""
    sys.path.insert(0, str(data_dir.parents[1] / "benchmarks"))
    from bench_adjust import problem  # found through the sys.path entry above

    Lb, Rb, ties, gcps = problem(150, 8, seed=3)
    kw = dict(
        names=("rpc-shift-drift", "rpc-shift-drift"),
        gcps=gcps,
        sigma_tie_px=0.3,
        sigma_px=0.1,
        snooping=False,
    )
    out = {
        s: bundle_adjust(Lb, Rb, ties, solver=s, **kw) for s in ("schur", "least_squares", "dense")
    }
    ref = out["schur"]
    for s in ("least_squares", "dense"):
        assert np.all(np.abs(out[s].values - ref.values) < 0.05 * ref.std), s
        np.testing.assert_allclose(out[s].std, ref.std, rtol=1e-3)
    n_obs = 4 * len(ties) + 2 * (len(gcps[0]) + len(gcps[1]))
    assert ref.dof == n_obs - 8 - 3 * len(ties) and len(ref.names) == 8
    total = np.nansum(ref.tie_redundancy) + sum(np.nansum(r) for r in ref.gcp_redundancy)
    assert total == pytest.approx(ref.dof, abs=1e-6)
    # truth: every parameter 0 (the biases were put on the delivered models)
    truth = np.zeros(len(ref.names))
    start = ref.initial_values
    assert np.all(np.abs(ref.values - truth) < 4 * ref.std)
    assert np.any(np.abs(start - truth) > 10 * ref.std)
    assert 0.8 < ref.sigma0 < 1.2


def test_bundle_schur_equals_dense(data_dir):
    """Fast check: the reduced normal equations give the dense solution and covariance."""
    sys.path.insert(0, str(data_dir.parents[1] / "benchmarks"))
    from bench_adjust import problem  # found through the sys.path entry above

    Lb, Rb, ties, gcps = problem(40, 6, seed=5)
    kw = dict(
        names=("rpc-shift", "rpc-shift-drift"),
        gcps=gcps,
        sigma_tie_px=0.3,
        sigma_px=0.1,
        snooping=False,
    )
    a = bundle_adjust(Lb, Rb, ties, solver="schur", **kw)
    b = bundle_adjust(Lb, Rb, ties, solver="dense", **kw)
    assert np.all(np.abs(a.values - b.values) < 1e-3 * a.std)
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(a.tie_std_m, b.tie_std_m, rtol=1e-6)


@pytest.mark.slow
def test_bundle_rejects_tie_blunders(pair):
    """Five mismatched ties (4 px across track, the testable direction of an along-track pair)
    are rejected by tie snooping and no good one is."""
    L, R = pair
    rng = np.random.default_rng(8)
    ties = noisy_ties(pair, 200, 0.3, rng)
    bad = rng.choice(len(ties), 5, replace=False)
    ties[bad, 2] += 4.0 * rng.choice([-1, 1], 5)
    res = bundle_adjust(
        L, R.with_parameters(**RIGHT_BIAS), ties, names=(None, "attitude-bias"), sigma_tie_px=0.3
    )
    assert set(np.flatnonzero(res.tie_rejected)) == set(bad)
    assert "5 tie point(s)" in res.outliers[0]["id"]
    # uncontrolled along-track coordinates are not tested (w NaN), controlled ones are
    kept = ~res.tie_rejected
    assert np.all(np.isnan(res.tie_w[kept][:, 3])) and np.all(np.isfinite(res.tie_w[kept][:, 2]))


@pytest.mark.slow  # over 0.5 s: out of the fast subset (CI runs it)
def test_bundle_accepts_sparse_matches_and_writes_report(pair, tmp_path):
    L, R = pair
    rng = np.random.default_rng(1)
    t = noisy_ties(pair, 80, 0.3, rng)
    matches = SimpleNamespace(col1=t[:, 0], row1=t[:, 1], col2=t[:, 2], row2=t[:, 3])
    res = bundle_adjust(
        L,
        R.with_parameters(**RIGHT_BIAS),
        matches,
        names=(None, ["roll_bias", "yaw_bias"]),
        sigma_tie_px=0.3,
    )
    paths = write_report(res, tmp_path)
    rep = json.loads(paths["json"].read_text())
    assert rep["model_set"] == "bundle" and set(rep["model"]) == {"left", "right"}
    assert rep["ties"]["n"] == 80 and rep["parallax_after"]["reprojection_rms_px"] < 0.3
    for side in ("left", "right"):
        assert paths[f"figure_{side}"].read_bytes()[:4] == b"\x89PNG"
    assert "right.roll_bias" in paths["markdown"].read_text()


def test_bundle_hostile_inputs(pair):
    L, R = pair
    t = noisy_ties(pair, 30, 0.3, np.random.default_rng(2))
    with pytest.raises(InputError, match=r"\(n, 4\)"):
        bundle_adjust(L, R, t[:, :3], names=(None, "attitude-bias"))
    bad = t.copy()
    bad[4, 1] = np.nan
    with pytest.raises(InputError, match="1 tie point.*NaN"):
        bundle_adjust(L, R, bad, names=(None, "attitude-bias"))
    with pytest.raises(InputError, match="unknown solver"):
        bundle_adjust(L, R, t, names=(None, "attitude-bias"), solver="cholmod")
    # all ties at one spot of the image: roll and yaw biases move it the same way
    rng = np.random.default_rng(0)
    c, r, h = (
        1500 + rng.normal(0, 0.5, 20),
        500 + rng.normal(0, 0.5, 20),
        rng.uniform(800, 2500, 20),
    )
    lon, lat = L.localize(c, r, h)
    spot = np.stack([c, r, *R.project(lon, lat, h)], -1) + rng.normal(0, 0.3, (20, 4))
    with pytest.raises(
        SensorModelError,
        match=r"condition number [0-9.e+]+\); cannot separate "
        r"right.(roll|yaw)_bias, right.(roll|yaw)_bias",
    ):
        bundle_adjust(L, R, spot, names=(None, ["roll_bias", "yaw_bias"]))
    with pytest.raises(SensorModelError, match="cannot separate"):  # not a LinAlgError
        bundle_adjust(L, R, spot, names=(None, ["roll_bias", "yaw_bias"]), solver="dense")
    with pytest.raises(InputError, match="unknown right parameter"):
        bundle_adjust(L, R, t, names=(None, ["pitch_bais"]))
    with pytest.raises(InputError, match="no tie points and no GCPs"):
        bundle_adjust(L, R, np.zeros((0, 4)), names=(None, "attitude-bias"))


@pytest.mark.slow
def test_bundle_with_6_gcps_gives_a_dem_within_0_2_gsd():
    """The issue's DEM criterion end to end on a rendered pair: both models biased (tens of
    metres), automatic SIFT tie points, 6 GCPs measured to 0.1 px; the DEM made with the
    adjusted models has a median error against the truth below 0.2 GSD (it is several GSD
    with the biased models)."""
    sc = simulate_scene("aster", size=(500, 500), seed=4)
    L, R = sc.left_model, sc.right_model
    gsd = L.gsd()
    Lb, Rb = L.with_parameters(**LEFT_BIAS), R.with_parameters(**RIGHT_BIAS)
    rng = np.random.default_rng(4)
    # 6 GCPs on the true terrain, measured in both images to 0.1 px
    c, r = rng.uniform(40, 460, 6), rng.uniform(40, 460, 6)
    loc = L.localize_dem(c, r, sc.truth_dem, h0=2000.0)
    c2, r2 = R.project(loc.lon, loc.lat, loc.h)
    mk = lambda cc, rr: ControlPoints.from_arrays(  # noqa: E731
        loc.lon, loc.lat, loc.h, cc + rng.normal(0, 0.1, 6), rr + rng.normal(0, 0.1, 6)
    )
    ties = sparse_matches(sc.left, sc.right, Lb, Rb)
    res = bundle_adjust(
        Lb,
        Rb,
        ties,
        names=("attitude-bias", "attitude-bias"),
        gcps=(mk(c, r), mk(c2, r2)),
        sigma_tie_px=0.3,
        sigma_px=0.1,
    )
    lo, hi = sc.truth_dem.height_range()
    settings = StereoSettings(RectificationSettings(height_range=(lo - 300, hi + 300)))

    def median_error(left, right):
        dem = make_dem(sc.left, sc.right, left, right, settings).dem
        x, y = dem.grid.cell_centres()
        truth = sc.truth_dem.sample(*geodesy.crs_to_lonlat(x, y, dem.crs))
        d = (dem.heights - truth)[np.isfinite(dem.heights) & np.isfinite(truth)]
        return float(np.median(d)), d.size

    before, n0 = median_error(Lb, Rb)
    after, n1 = median_error(res.left, res.right)
    print(
        f"DEM median error vs truth: biased models {before:+.2f} m, after the bundle with 6 GCPs "
        f"{after:+.2f} m (GSD {gsd:.1f} m, {len(ties)} automatic ties)"
    )
    assert abs(before) > 2 * gsd
    assert abs(after) < 0.2 * gsd and n1 > 0.5 * n0
