"""Hostile inputs, ninth round (session 32): option values found by a sweep of every command's
options with NaN, infinity, -1, 0, 1e308, 99999999999 and text.

* ``adjust --sigma-px nan`` passed the ``<= 0`` check and weighted every GCP by NaN; 1e308 made
  every weight 0; ``--sigma-tie-px`` was not checked at all; ``compare-models --sigma-px 0``
  was taken as "not given" (1 px) and NaN / infinity were taken. One rule now
  (:func:`stereodem.core.stats.check_sigma`), and the commands' ``--sigma-px`` /
  ``--sigma-tie-px`` refuse them as usage errors.
* ``compare-models --seed -1`` was NumPy's traceback, ``--n-check -1`` drew all points but one
  as check points, and an unknown ``--reference`` was taken when no splits were asked for.
* ``adjust --max-iterations 99999999999`` overflowed MINPACK's C int (a traceback).
* a single-image ``adjust`` ignored ``--ties``, ``--match``, ``--gcps2``, ``--out2``, ``--set``,
  ``--sigma-tie-px`` and ``IMAGE2`` without a word, and a pair bundle ignored ``--fix`` and
  ``--image-gcps``.
* ``simulate --size 99999999999 ...`` was killed by the OOM killer (the orbit's per-line
  ephemeris), ``--jitter 1 1e308`` was an OverflowError traceback, ``--jitter 1e308 1`` and
  ``--noise 1e308`` rendered images of nothing but clipped values.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers.cli_scene import assert_clear_error, run_cli, write_sim_scene

from stereodem.core.errors import InputError
from stereodem.core.stats import check_sigma
from stereodem.sensor.estimation.adjust import adjust_model, gauss_markov
from stereodem.sensor.estimation.adjust.bundle import bundle_adjust
from stereodem.sensor.estimation.adjust.bundle_multi import bundle_adjust_images
from stereodem.sensor.estimation.compare import compare, compare_splits, split_points
from stereodem.sensor.estimation.jitter import SineSeries, with_attitude_sines
from stereodem.sensor.io.gcps import ControlPoints, read_gcps
from stereodem.sensor.io.sidecar import load_model
from stereodem.sensor.simulation.simulate import simulate_scene, simulate_views

NOT_SIGMAS = [float("nan"), float("inf"), 0.0, -1.0, 1e308]


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return write_sim_scene(tmp_path_factory.mktemp("sim"))


@pytest.mark.parametrize("sigma", NOT_SIGMAS)
def test_a_sigma_that_is_no_standard_deviation_is_refused_by_every_adjustment(sigma, sim):
    with pytest.raises(InputError, match=r"sigma_px must be a finite standard deviation > 0"):
        check_sigma(sigma, "sigma_px")
    model, points = load_model(sim / "left.model.json"), read_gcps(sim / "points.csv")
    with pytest.raises(InputError, match=r"sigma_px must be a finite standard deviation"):
        adjust_model(model, points, "attitude-bias", sigma_px=sigma)
    with pytest.raises(InputError, match=r"sigma_tie_px must be a finite standard deviation"):
        bundle_adjust(None, None, np.zeros((0, 4)), sigma_tie_px=sigma)
    with pytest.raises(InputError, match=r"sigma_px must be a finite standard deviation"):
        bundle_adjust(None, None, np.zeros((0, 4)), sigma_px=sigma)
    with pytest.raises(InputError, match=r"sigma_tie_px must be a finite standard deviation"):
        bundle_adjust_images([None, None], None, sigma_tie_px=sigma)
    # compare-models took 0 for "not given" (sigma0 relative to 1 px), NaN and inf as given
    with pytest.raises(InputError, match=r"sigma_px must be a finite standard deviation"):
        compare(model, points, ["poly2d-1"], [6], sigma_px=sigma)


def test_a_standard_deviation_is_taken(sim):
    assert check_sigma(0.3, "s") == 0.3 and check_sigma(1e100, "s") == 1e100
    model, points = load_model(sim / "left.model.json"), read_gcps(sim / "points.csv")
    res = adjust_model(model, points, "attitude-bias", sigma_px=0.5)
    assert np.isfinite(res.sigma0) and res.gcp_rmse_px < 1.0


@pytest.mark.parametrize("value", ["nan", "inf", "0", "-1", "abc", "1e-300", "5e-324", "1e308"])
@pytest.mark.parametrize(
    "command, flag",
    [("adjust", "--sigma-px"), ("compare-models", "--sigma-px"), ("adjust", "--sigma-tie-px")],
)
def test_sigma_options_refuse_what_is_no_standard_deviation(
    command, flag, value, sim, tmp_path, capsys
):
    argv = [command, sim / "left.tif", "--gcps", sim / "points.csv"]
    argv += ["--model", "bundle"] if flag == "--sigma-tie-px" else []
    argv += ["--model", "attitude-bias"] if command == "adjust" and flag == "--sigma-px" else []
    with pytest.raises(SystemExit) as e:  # a usage error, as argparse reports every one
        run_cli(capsys, [*argv, "-o", tmp_path / "o", f"{flag}={value}"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" not in err
    # the rule of check_sigma (1e-300 got past the option's own check: a ZeroDivisionError)
    assert f"argument {flag}: " in err
    assert ("expected a number" in err) == (value == "abc")
    assert ("finite standard deviation > 0" in err) == (value != "abc")
    assert not (tmp_path / "o").exists()


def test_compare_models_seed_n_check_and_reference_are_checked(sim, tmp_path, capsys):
    base = [
        "compare-models",
        sim / "left.tif",
        "--gcps",
        sim / "points.csv",
        "--models",
        "poly2d-1",
        "--counts",
        "6",
        "-o",
        tmp_path / "c",
    ]
    code, _, err = run_cli(capsys, [*base, "--seed=-1"])
    assert_clear_error(code, err, "compare-models", r"seed must be a whole number >= 0, got -1")
    code, _, err = run_cli(capsys, [*base, "--n-check=-1"])
    assert_clear_error(code, err, "compare-models", r"check points must be a whole number >= 1")
    code, _, err = run_cli(capsys, [*base, "--reference", "nan"])
    assert_clear_error(code, err, "compare-models", r"unknown model 'nan'")
    assert not (tmp_path / "c").exists()
    # the library: the seed before it is combined with the split's number; the check points
    # drawn from a file without roles must leave GCPs
    model, points = load_model(sim / "left.model.json"), read_gcps(sim / "points.csv")
    no_roles = ControlPoints.from_arrays(*points.arrays())
    with pytest.raises(InputError, match=r"seed must be a whole number >= 0"):
        compare_splits(model, points, ["poly2d-1"], [6], reference="poly2d-1", seed=-1)
    with pytest.raises(InputError, match=r"check points must be a whole number >= 1, got -1"):
        compare_splits(model, points, ["poly2d-1"], [6], reference="poly2d-1", n_check=-1)
    with pytest.raises(InputError, match=rf"{len(points)} point\(s\) cannot give {len(points)}"):
        split_points(no_roles, len(points))
    pool, icp = split_points(no_roles, 5, seed=3)
    assert len(icp) == 5 and len(pool) == len(points) - 5


@pytest.mark.parametrize("n", [10**11, 10_001, -1, 1.5])
def test_max_iterations_beyond_the_bound_is_refused(n):
    # before: 99999999999 overflowed MINPACK's C int inside SciPy's least_squares (traceback)
    with pytest.raises(InputError, match=r"max_iterations must be a whole number from 0 to 10000"):
        gauss_markov.check_max_iterations(n)
    assert gauss_markov.check_max_iterations(10_000) == 10_000


@pytest.mark.parametrize(
    "extra, culprit",
    [
        (["--ties", "t.csv"], "--ties"),
        (["--match", "a.match"], "--match"),
        (["--gcps2", "g.csv"], "--gcps2"),
        (["--out2", "o2.json"], "--out2"),
        (["--set", "rpc-affine"], "--set"),
        (["--sigma-tie-px", "0.3"], "--sigma-tie-px"),
    ],
)
def test_a_single_image_adjustment_refuses_the_bundle_options(
    extra, culprit, sim, tmp_path, capsys
):
    # before: each was ignored without a word (exit 0, a model adjusted from --gcps alone)
    argv = ["adjust", sim / "left.tif", "--gcps", sim / "points.csv", "--model", "attitude-bias"]
    code, _, err = run_cli(capsys, [*argv, "-o", tmp_path / "m.json", *extra])
    assert_clear_error(code, err, "adjust", rf"{culprit}: only --model bundle reads it")
    assert not (tmp_path / "m.json").exists()
    code, _, err = run_cli(
        capsys, [*argv[:2], sim / "right.tif", *argv[2:], "-o", tmp_path / "m.json"]
    )
    assert_clear_error(code, err, "adjust", r"IMAGE2: only --model bundle reads it")


@pytest.mark.parametrize("extra", [["--fix", "1"], ["--image-gcps", "2=g.csv"]])
def test_a_pair_bundle_refuses_the_n_image_options(extra, sim, tmp_path, capsys):
    argv = ["adjust", sim / "left.tif", sim / "right.tif", "--model", "bundle"]
    argv += ["-o", tmp_path / "l.json", "--out2", tmp_path / "r.json", *extra]
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(code, err, "adjust", rf"{extra[0]}: only a bundle of three or more images")
    assert not (tmp_path / "l.json").exists()


def test_simulate_refuses_a_size_beyond_memory_before_building_the_orbit(tmp_path, capsys):
    # before: killed by the OOM killer (exit -9) while the orbit's per-line ephemeris was made
    for argv in (
        ["--size", "99999999999", "99999999999"],
        ["--size", "600", "600", "--right-size", "600", "99999999999"],
    ):
        out = tmp_path / "s"
        code, _, err = run_cli(capsys, ["simulate", *argv, "-o", out])
        assert_clear_error(code, err, "simulate", r"a simulated pair of .* needs .* of memory")
        assert not out.exists()
    with pytest.raises(InputError, match=r"3 simulated views of .* needs .* of memory"):
        simulate_views(size=(10**9, 10**9))


@pytest.mark.parametrize(
    "jitter, pattern",
    [
        (
            ["1", "1e308"],
            r"an attitude oscillation of 1e\+308 Hz is faster than half the line rate",
        ),
        (
            ["1e308", "1"],
            r"pitch jitter amplitude must be a finite number of microradians up to 10000",
        ),
        (["1", "nan"], r"pitch jitter frequency must be a positive number of Hz"),
    ],
)
def test_simulate_refuses_a_jitter_that_is_no_attitude_oscillation(
    jitter, pattern, tmp_path, capsys
):
    # before: 1e308 Hz was an OverflowError traceback (the attitude spline's sample count),
    # 1e308 microradians rendered an image of nothing
    out = tmp_path / "s"
    argv = ["simulate", "--size", "64", "64", "--jitter", *jitter, "-o", out]
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(code, err, "simulate", pattern)
    assert not out.exists()


def test_an_attitude_oscillation_beyond_the_line_rate_is_refused(sim):
    model = load_model(sim / "right.model.json")
    line_rate = 1.0 / abs(model.line_time(1) - model.line_time(0))
    ok = SineSeries(np.array([1e-6]), np.array([0.4 * line_rate]), np.array([0.0]))
    assert with_attitude_sines(model, ok).attitude is not None
    fast = SineSeries(np.array([1e-6]), np.array([0.6 * line_rate]), np.array([0.0]))
    with pytest.raises(InputError, match=r"faster than half the line rate"):
        with_attitude_sines(model, fast)


@pytest.mark.parametrize("noise, bits", [("300", 8), ("1e308", 16), ("70000", 16)])
def test_simulate_refuses_a_noise_beyond_the_full_scale(noise, bits, tmp_path, capsys):
    out = tmp_path / "s"
    argv = ["simulate", "--size", "64", "64", f"--noise={noise}", "--bits", str(bits), "-o", out]
    code, _, err = run_cli(capsys, argv)
    full = 2**bits - 1
    assert_clear_error(
        code, err, "simulate", rf"noise must be .* {bits}-bit full scale \({full} DN\)"
    )
    assert not out.exists()
    with pytest.raises(InputError, match=r"full scale"):
        simulate_scene("frame", size=(64, 64), noise=float(noise), bits=bits)


def test_compare_models_reports_its_progress(sim):
    # --splits 99999999999 ran for ever without a sign of life; each fit and each split is
    # counted now (the command line's bars, stages "compare" and "splits")
    model, points = load_model(sim / "left.model.json"), read_gcps(sim / "points.csv")
    calls = []
    recs = compare(
        model, points, ["poly2d-1", "poly3d-1"], [6, 8], progress=lambda *a: calls.append(a)
    )
    assert len(recs) == 4 and calls == [(1, 4), (2, 4), (3, 4), (4, 4)]
    calls.clear()
    compare_splits(
        model,
        points,
        ["poly2d-1"],
        [6],
        reference="poly2d-1",
        n_check=5,
        n_splits=3,
        progress=lambda *a: calls.append(a),
    )
    assert calls == [(1, 3), (2, 3), (3, 3)]
