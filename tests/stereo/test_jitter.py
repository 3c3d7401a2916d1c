"""Attitude jitter: sum-of-sines fit, attitude injection, and the DEM correction loop."""

import argparse
import json

import cv2
import numpy as np
import pytest
import rasterio
from scipy.ndimage import map_coordinates

from stereodem import cli
from stereodem.config import config_from_dict
from stereodem.core import geodesy
from stereodem.core.errors import InputError
from stereodem.core.stats import nmad
from stereodem.dem_cli import add_parser, config_from_args
from stereodem.sensor.estimation.jitter import (
    SineSeries,
    add_series,
    along_track_profile,
    estimate_roll_jitter,
    fit_at_frequencies,
    fit_sum_of_sines,
    roll_profile,
    with_attitude_sines,
)
from stereodem.sensor.models.pushbroom import PushbroomModel
from stereodem.sensor.simulation.aster_granule import write_granule_scene
from stereodem.sensor.simulation.simulate import simulate_scene
from stereodem.stereo.jitter import (
    dem_with_jitter_correction,
    measure_vertical_parallax,
    refine_offsets,
    resample_to_model,
)
from stereodem.stereo.settings import StereoSettings


def test_fit_sum_of_sines_recovers_two_tones():
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(50.0, 53.0, 400))
    y = (
        3e-6 * np.sin(2 * np.pi * 1.5 * t + 0.7)
        + 1e-6 * np.sin(2 * np.pi * 4.2 * t + 2.0)
        + 2e-7 * (t - 51.5)
        + 1e-7 * rng.standard_normal(t.size)
    )
    y[::37] += 5e-5  # outliers
    fit = fit_sum_of_sines(t, y, n_sines=2)
    order = np.argsort(fit.frequencies)
    np.testing.assert_allclose(fit.frequencies[order], [1.5, 4.2], atol=0.02)
    np.testing.assert_allclose(fit.amplitudes[order], [3e-6, 1e-6], rtol=0.08)
    clean = 3e-6 * np.sin(2 * np.pi * 1.5 * t + 0.7) + 1e-6 * np.sin(2 * np.pi * 4.2 * t + 2.0)
    assert np.max(np.abs(fit(t) - clean)) < 3e-7


def test_attitude_sines_move_the_image_along_track():
    m = PushbroomModel.synthetic(
        40.0, 39.6, width=200, height=400, gsd=15.0, line_period=2.2e-3, along_track_tilt_deg=-27.6
    )
    amp = 5e-6
    s = SineSeries(np.array([amp]), np.array([1.0]), np.array([0.0]))
    j = with_attitude_sines(m, s)
    rows = np.array([50.0, 150.0, 250.0, 350.0])
    lon, lat = m.localize(np.full(4, 100.0), rows, np.zeros(4))
    c, r = j.project(lon, lat, np.zeros(4))
    # locally the oscillation acts as a constant pitch bias of its value at that line time
    for k in range(4):
        biased = m.with_parameters(pitch_bias=float(s(m.line_time(rows[k]))))
        cb, rb = biased.project(lon[k], lat[k], 0.0)
        assert abs(r[k] - float(rb)) < 0.02 * abs(float(rb) - rows[k]) + 1e-4
    assert np.max(np.abs(c - 100.0)) < 0.1 * np.max(np.abs(r - rows))  # mostly along track
    assert np.max(np.abs(r - rows)) > 0.1


@pytest.mark.slow
def test_dem_jitter_correction_removes_the_along_track_oscillation():
    """A sinusoidal 3B pitch oscillation (about +-5 m of height error) is estimated from the
    DEM residuals against the reference DEM (amplitude within 5 %, frequency within 0.01 Hz)
    and corrected: the along-track error profile loses >= 95 % of its amplitude at the jitter
    frequency."""
    sc = simulate_scene("aster", size=(500, 700), right_size=(610, 900), seed=5, jitter=(3.5, 1.5))
    f_true = sc.diagnostics["right_jitter"]["frequency_hz"]

    def amplitude(dem):
        z = dem.heights.astype(float)
        rr, cc = np.nonzero(np.isfinite(z))
        x, y = dem.transform @ (cc + 0.5, rr + 0.5)
        lon, lat = geodesy.crs_to_lonlat(np.asarray(x), np.asarray(y), dem.crs)
        dh = z[rr, cc] - sc.truth_dem.sample(lon, lat)
        t, med, n = along_track_profile(dh, sc.right_model, lon, lat, z[rr, cc])
        t, med = t[n >= 20], med[n >= 20]
        a = np.stack(
            [
                np.sin(2 * np.pi * f_true * t),
                np.cos(2 * np.pi * f_true * t),
                np.ones_like(t),
                t - t.mean(),
            ],
            -1,
        )
        c, *_ = np.linalg.lstsq(a, med, rcond=None)
        return float(np.hypot(c[0], c[1]))

    final, corrected, fits, first = dem_with_jitter_correction(
        sc.left, sc.right, sc.left_model, sc.right_model, sc.truth_dem
    )
    fit = fits["pitch"]
    before, after = amplitude(first.dem), amplitude(final.dem)
    print(
        f"jitter: injected 3.5 urad at {f_true} Hz, fitted {1e6 * fit.amplitudes[0]:.2f} urad "
        f"at {fit.frequencies[0]:.3f} Hz; along-track height error amplitude "
        f"{before:.2f} m -> {after:.2f} m"
    )
    assert 4.5 < before < 6.5  # about +-5 m of height error, as intended
    assert after <= 0.05 * before  # README: 5.3 m -> 0.09 m
    assert fit.frequencies[0] == pytest.approx(f_true, abs=0.01)
    assert fit.amplitudes[0] == pytest.approx(3.5e-6, rel=0.05)


@pytest.mark.slow
def test_dem_command_corrects_jitter_against_the_seed_dem(tmp_path):
    """`stereodem dem --seed-dem REF --jitter-correction` on a granule with injected 3B jitter
    reports the fitted oscillation and gives a DEM closer to the truth than without it."""
    sc = simulate_scene("aster", size=(500, 700), right_size=(610, 900), seed=5, jitter=(3.5, 1.5))
    g = write_granule_scene(sc, tmp_path / "scene", version=4, seed=5)
    ref = tmp_path / "scene" / "truth_dem.tif"
    errors = {}
    for flag in ("", "--jitter-correction"):
        out = tmp_path / f"d{flag}"
        argv = [
            "dem",
            str(g),
            "-o",
            str(out),
            "--seed-dem",
            str(ref),
            "--dem-vertical",
            "ellipsoid",
            "--workers",
            "1",
        ] + ([flag] if flag else [])
        assert cli.main(argv) == 0
        errors[flag] = _file_dem_nmad(out / "dem.tif", sc.truth_dem)  # NMAD (raw DEM: blunders)
        rep = json.loads((out / "dem_report.json").read_text())
    jit = rep["info"]["jitter"]["pitch"]
    assert jit["frequencies_hz"][0] == pytest.approx(
        sc.diagnostics["right_jitter"]["frequency_hz"], abs=0.1
    )
    print(f"DEM NMAD vs truth without / with jitter correction: {errors}")
    assert errors["--jitter-correction"] < errors[""], errors


# ----------------------------------------------------------------------------- roll jitter


def test_attitude_roll_sines_move_the_image_across_track():
    """A roll oscillation acts locally as a roll bias of its value at that line time and
    moves the image across the track (columns), the direction two images observe."""
    m = PushbroomModel.synthetic(
        40.0, 39.6, width=200, height=400, gsd=15.0, line_period=2.2e-3, along_track_tilt_deg=-27.6
    )
    s = SineSeries(np.array([20e-6]), np.array([1.0]), np.array([0.3]))
    j = with_attitude_sines(m, s, axis="roll")
    rows = np.array([50.0, 150.0, 250.0, 350.0])
    lon, lat = m.localize(np.full(4, 100.0), rows, np.zeros(4))
    c, r = j.project(lon, lat, np.zeros(4))
    for k in range(4):
        biased = m.with_parameters(roll_bias=float(s(m.line_time(rows[k]))))
        cb, _ = biased.project(lon[k], lat[k], 0.0)
        assert abs(c[k] - float(cb)) < 0.02 * abs(float(cb) - 100.0) + 1e-4
    assert np.max(np.abs(r - rows)) < 0.1 * np.max(np.abs(c - 100.0))  # mostly across track
    assert np.max(np.abs(c - 100.0)) > 0.5  # ~0.9 px at 20 urad


def test_estimate_roll_jitter_recovers_a_sine_from_noisy_parallax():
    rng = np.random.default_rng(3)
    t = rng.uniform(56.0, 58.0, 60_000)
    sens = 4.2e4  # px/rad, ASTER 3B order of magnitude
    roll = 8e-6 * np.sin(2 * np.pi * 1.3 * t + 1.1)
    cross = sens * roll + 0.003 + 0.15 * rng.standard_normal(t.size)  # offset + matcher noise
    cross[::50] += 3.0  # blunders
    fit, diag = estimate_roll_jitter(t, cross, sens)
    assert fit.frequencies[0] == pytest.approx(1.3, abs=0.02)
    assert fit.amplitudes[0] == pytest.approx(8e-6, rel=0.05)
    tt = np.linspace(56.0, 58.0, 200)
    assert np.max(np.abs(fit(tt) - 8e-6 * np.sin(2 * np.pi * 1.3 * tt + 1.1))) < 1e-6
    assert diag["counts"].min() >= 20


@pytest.mark.parametrize("d_true, v_true", [(3.3, -0.35), (3.0, 0.2), (3.45, 0.1), (2.9, 0.05)])
def test_refine_offsets_is_not_pixel_locked(d_true, v_true):
    """A band-limited texture shifted by a known sub-pixel (disparity, vertical) offset: the
    gradient refinement started from the nearest whole pixels is unbiased to 0.01 px (mean
    over the tile) with a per-window scatter below 0.1 px. With OpenCV 4, whose remap rounds
    positions to 1/32 px (the shifted image here and the refinement's resampling), the bias
    measured 0.014-0.023 px: 0.025 px there."""
    rng = np.random.default_rng(0)
    left = cv2.GaussianBlur(rng.standard_normal((200, 220)).astype(np.float32), (0, 0), 1.2)
    uu, vv = np.meshgrid(np.arange(220, dtype=np.float32), np.arange(200, dtype=np.float32))
    # right(x, y) = left(x + d, y + v)  <=>  left(u, v) = right(u - d, v - v)
    right = cv2.remap(
        left,
        uu + np.float32(d_true),
        vv + np.float32(v_true),
        cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    d0 = np.full(left.shape, round(d_true), np.float32)
    v0 = np.full(left.shape, round(v_true), np.float32)
    d, v = refine_offsets(left, right, d0, v0)
    inner = (slice(20, -20), slice(20, -20))
    bias = 0.01 if int(cv2.__version__.split(".")[0]) >= 5 else 0.025
    assert abs(np.nanmean(d[inner]) - d_true) < bias
    assert abs(np.nanmean(v[inner]) - v_true) < bias
    assert np.nanmedian(np.abs(v[inner] - v_true)) < 0.1
    assert np.isfinite(v[inner]).mean() > 0.95


@pytest.mark.slow
def test_simulator_injects_roll_and_pitch_jitter():
    plain = simulate_scene(
        "aster", size=(200, 180), right_size=(240, 210), seed=3, n_points=4, noise=0.0
    )
    both = simulate_scene(
        "aster",
        size=(200, 180),
        right_size=(240, 210),
        seed=3,
        n_points=4,
        noise=0.0,
        jitter=(3.0, 1.5),
        roll_jitter=(20.0, 1.2),
    )
    d = both.diagnostics
    assert d["right_jitter"]["axis"] == "pitch" and d["right_roll_jitter"]["axis"] == "roll"
    assert d["right_roll_jitter"]["amplitude_urad"] == 20.0
    assert both.settings["roll_jitter"] == [20.0, 1.2]
    assert d["right_render_error_px"] < 0.01
    np.testing.assert_array_equal(plain.left, both.left)  # only the right camera moves
    assert not np.array_equal(plain.right, both.right)
    with pytest.raises(Exception, match="roll jitter"):
        simulate_scene("aster", size=(64, 64), roll_jitter=(5.0, 0.0))


@pytest.mark.slow
def test_cli_simulate_roll_jitter(tmp_path):
    assert (
        cli.main(
            [
                "simulate",
                "--preset",
                "aster",
                "--size",
                "120",
                "100",
                "--roll-jitter",
                "10",
                "1.5",
                "--jitter",
                "2",
                "1.0",
                "-o",
                str(tmp_path / "s"),
            ]
        )
        == 0
    )
    meta = json.loads((tmp_path / "s" / "scene.json").read_text())
    assert meta["settings"]["roll_jitter"] == [10.0, 1.5]
    assert meta["settings"]["jitter"] == [2.0, 1.0]
    assert meta["diagnostics"]["right_roll_jitter"]["frequency_hz"] == 1.5


def _nmad_vs_truth(heights, transform, crs, truth_dem):
    """NMAD (m) of DEM ``heights`` (on ``transform``/``crs``) against the truth, over valid
    cells."""
    z = np.asarray(heights, float)
    rr, cc = np.nonzero(np.isfinite(z))
    x, y = transform @ (cc + 0.5, rr + 0.5)
    lon, lat = geodesy.crs_to_lonlat(np.asarray(x), np.asarray(y), crs)
    dh = z[rr, cc] - truth_dem.sample(lon, lat)
    dh = dh[np.isfinite(dh)]
    return nmad(dh)


def _dem_nmad(products, truth_dem):
    """NMAD (m) of a stereo product's DEM against the truth."""
    g = products.dem
    return _nmad_vs_truth(g.heights, g.transform, g.crs, truth_dem)


def _file_dem_nmad(path, truth_dem):
    """NMAD (m) of a DEM GeoTIFF against the truth."""
    with rasterio.open(path) as ds:
        return _nmad_vs_truth(ds.read(1), ds.transform, ds.crs, truth_dem)


def _amplitude_at(f, t, y):
    a = np.stack(
        [np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t), np.ones_like(t), t - t.mean()], -1
    )
    c, *_ = np.linalg.lstsq(a, y, rcond=None)
    return float(np.hypot(c[0], c[1]))


@pytest.mark.slow
def test_roll_jitter_from_vertical_parallax_without_reference_dem():
    """A 10 urad, 1.5 Hz roll oscillation of 3B (about 0.4 px across the epipolar lines) is
    estimated from the residual vertical parallax of the matches alone (no reference DEM):
    amplitude within 5 %, >= 95 % of it removed from the model, the vertical parallax measured
    through the corrected model loses >= 95 % of its oscillation, and the DEM's NMAD falls by
    more than 0.5 m."""
    sc = simulate_scene(
        "aster", size=(500, 700), right_size=(610, 900), seed=5, roll_jitter=(10.0, 1.5)
    )
    inj = sc.diagnostics["right_roll_jitter"]
    f, a_true = inj["frequency_hz"], 1e-6 * inj["amplitude_urad"]
    final, corrected, fits, first = dem_with_jitter_correction(
        sc.left, sc.right, sc.left_model, sc.right_model, None, axes=("roll",)
    )
    fit = fits["roll"]
    assert fit.frequencies[0] == pytest.approx(f, abs=0.01)
    # the model: injected minus fitted roll over the 3B time span
    t = sc.right_model.line_time(np.linspace(0, sc.right_model.height - 1, 400))
    true = a_true * np.sin(2 * np.pi * f * t + inj["phase_rad"])
    left_over = _amplitude_at(f, t, true - fit(t))
    # the data: the vertical parallax through the nominal and the corrected models
    d0 = first.dem
    hr = (float(np.nanmin(d0.heights)), float(np.nanmax(d0.heights)))
    measured = {}
    for name, model in (("nominal", sc.right_model), ("corrected", corrected)):
        vp = measure_vertical_parallax(
            sc.left, sc.right, sc.left_model, model, StereoSettings(), hr, seed_dem=d0
        )
        tb, roll, _ = roll_profile(
            vp["time"],
            vp["cross_px"],
            vp["sensitivity_px_per_rad"],
            bin_seconds=8 * sc.right_model.line_period,
        )
        measured[name] = _amplitude_at(f, tb, roll)

    def errors(products):
        return _dem_nmad(products, sc.truth_dem), float(np.nanmedian(products.dem.score))

    (nmad0, score0), (nmad1, score1) = errors(first), errors(final)
    print(
        f"roll jitter: injected {1e6 * a_true:.1f} urad at {f} Hz, fitted "
        f"{1e6 * fit.amplitudes[0]:.2f} urad at {fit.frequencies[0]:.3f} Hz, left in the model "
        f"{1e6 * left_over:.2f} urad; vertical-parallax roll at {f} Hz "
        f"{1e6 * measured['nominal']:.2f} -> {1e6 * measured['corrected']:.2f} urad; DEM NMAD "
        f"{nmad0:.2f} -> {nmad1:.2f} m, median score {score0:.3f} -> {score1:.3f}"
    )
    assert measured["nominal"] > 0.8 * a_true  # the oscillation is seen
    assert fit.amplitudes[0] == pytest.approx(a_true, rel=0.05)
    assert left_over <= 0.05 * a_true  # README: 0.24 of 10 urad left
    assert measured["corrected"] <= 0.05 * measured["nominal"]
    assert nmad1 < nmad0 - 0.5 and score1 > score0  # README: 3.54 -> 2.49 m
    assert "roll" in final.info.jitter and final.info.jitter["roll"]["rounds"]


def test_jitter_config_axes():
    """``[jitter] axes``: roll needs no reference DEM, pitch and both need the seed DEM, and
    an unknown axis is refused; ``--jitter-correction`` alone still means pitch."""
    raw = {"inputs": {"left": "a.tif", "right": "b.tif"}, "output": {"dir": "o"}}
    cfg = config_from_dict({**raw, "jitter": {"enabled": True, "axes": "roll"}})
    assert cfg.jitter.axis_names == ("roll",)
    for axes in ("pitch", "both"):
        with pytest.raises(InputError, match="seed DEM"):
            config_from_dict({**raw, "jitter": {"enabled": True, "axes": axes}})
    with pytest.raises(InputError, match="axes"):
        config_from_dict({**raw, "jitter": {"enabled": True, "axes": "yaw"}})

    sub = argparse.ArgumentParser().add_subparsers()
    p = add_parser(sub)
    args = p.parse_args(["a.tif", "b.tif", "-o", "o", "--seed-dem", "s.tif", "--jitter-correction"])
    assert config_from_args(args).jitter.axis_names == ("pitch",)
    args = p.parse_args(["a.tif", "b.tif", "-o", "o", "--jitter-correction", "roll"])
    cfg = config_from_args(args)
    assert cfg.jitter.enabled and cfg.jitter.axis_names == ("roll",)


@pytest.mark.slow
def test_dem_command_corrects_roll_jitter_without_reference(tmp_path):
    """`stereodem dem GRANULE --jitter-correction roll` (no seed DEM) on a granule with injected
    3B roll jitter reports the fitted oscillation and gives a DEM closer to the truth."""
    sc = simulate_scene(
        "aster", size=(500, 700), right_size=(610, 900), seed=5, roll_jitter=(10.0, 1.5)
    )
    g = write_granule_scene(sc, tmp_path / "scene", version=4, seed=5)
    errors, reports = {}, {}
    for flag in ([], ["--jitter-correction", "roll", "--point-cloud", "las"]):
        out = tmp_path / ("roll" if flag else "plain")
        argv = ["dem", str(g), "-o", str(out), "--workers", "1", "--force"] + flag
        assert cli.main(argv) == 0
        errors[out.name] = _file_dem_nmad(out / "dem.tif", sc.truth_dem)
        reports[out.name] = json.loads((out / "dem_report.json").read_text())
    roll = reports["roll"]["info"]["jitter"]["roll"]
    assert roll["frequencies_hz"][0] == pytest.approx(1.5, abs=0.05)
    assert roll["amplitudes"][0] == pytest.approx(10e-6, rel=0.2)
    print(f"DEM NMAD vs truth without / with roll correction: {errors}")
    assert errors["roll"] < errors["plain"], errors
    # the point cloud (wired with the jitter correction): the final DEM's points, on it
    laspy = pytest.importorskip("laspy")
    las = laspy.read(tmp_path / "roll" / "dem.las")
    assert reports["roll"]["point_cloud"]["n_points"] == reports["roll"]["n_points"] == len(las)
    with rasterio.open(tmp_path / "roll" / "dem.tif") as ds:
        a = ds.read(1).astype(np.float64)
        col, row = ~ds.transform @ (np.asarray(las.x), np.asarray(las.y))
    d = np.asarray(las.z) - map_coordinates(a, [row - 0.5, col - 0.5], order=1, cval=np.nan)
    d = d[np.isfinite(d)]
    med, bias = float(np.median(np.abs(d))), float(np.median(d))
    print(f"points vs the corrected DEM: median |z - dem| {med:.3f} m, median {bias:+.3f} m")
    assert d.size > 0.97 * len(las) and med < 1.5 and abs(bias) < 0.2, (med, bias)


@pytest.mark.slow
def test_pitch_and_roll_jitter_together():
    """Both axes at once (pitch 3.5 urad at 1.5 Hz against the reference, roll 10 urad at
    1.1 Hz from the vertical parallax): each fit finds its own oscillation and the DEM
    improves."""
    sc = simulate_scene(
        "aster",
        size=(500, 700),
        right_size=(610, 900),
        seed=5,
        jitter=(3.5, 1.5),
        roll_jitter=(10.0, 1.1),
    )
    final, corrected, fits, first = dem_with_jitter_correction(
        sc.left, sc.right, sc.left_model, sc.right_model, sc.truth_dem, axes=("pitch", "roll")
    )
    assert fits["pitch"].frequencies[0] == pytest.approx(1.5, abs=0.05)
    assert fits["roll"].frequencies[0] == pytest.approx(1.1, abs=0.05)
    assert fits["roll"].amplitudes[0] == pytest.approx(10e-6, rel=0.2)
    assert fits["pitch"].amplitudes[0] == pytest.approx(3.5e-6, rel=0.2)

    before, after = _dem_nmad(first, sc.truth_dem), _dem_nmad(final, sc.truth_dem)
    print(
        f"pitch + roll jitter: fits {fits['pitch'].to_dict()['amplitudes']} / "
        f"{fits['roll'].to_dict()['amplitudes']}; DEM NMAD {before:.2f} -> {after:.2f} m"
    )
    assert after < before


def test_resample_to_model_follows_the_attitude_oscillation():
    """On ramp images (cubic interpolation reproduces them exactly) the resampled values are
    the positions the corrected camera sees each nominal pixel's ground point at: within
    0.005 px of the exact model everywhere the oscillation moves it by up to ~0.9 px."""
    m = PushbroomModel.synthetic(
        40.0, 39.6, width=300, height=500, gsd=15.0, line_period=2.2e-3, along_track_tilt_deg=-27.6
    )
    actual = with_attitude_sines(
        m, SineSeries(np.array([20e-6]), np.array([1.5]), np.array([0.4])), axis="roll"
    )
    cc, rr = np.meshgrid(np.arange(300, dtype=np.float32), np.arange(500, dtype=np.float32))
    col_ramp = resample_to_model(cc, m, actual, 1500.0)
    row_ramp = resample_to_model(rr, m, actual, 1500.0)
    rng = np.random.default_rng(2)
    r = rng.integers(5, 495, 300).astype(float)
    c = rng.integers(5, 295, 300).astype(float)
    lon, lat = m.localize(c, r, np.full(c.size, 1500.0))
    ce, re = actual.project(lon, lat, np.full(c.size, 1500.0))
    ri, ci = r.astype(int), c.astype(int)
    assert np.max(np.abs(col_ramp[ri, ci] - ce)) < 0.005
    assert np.max(np.abs(row_ramp[ri, ci] - re)) < 0.005
    assert np.max(np.abs(ce - c)) > 0.5  # the oscillation is there


def test_fit_at_fixed_frequencies_and_phasor_sum():
    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(56.0, 58.0, 300))
    y = (
        2e-6 * np.sin(2 * np.pi * 1.3 * t + 0.4)
        + 3e-8 * (t - 57)
        + 5e-8 * rng.standard_normal(t.size)
    )
    y[::29] += 4e-5  # outliers
    fit = fit_at_frequencies(t, y, [1.3])
    assert fit.amplitudes[0] == pytest.approx(2e-6, rel=0.03)
    assert fit.phases[0] == pytest.approx(0.4, abs=0.03)
    a = SineSeries(np.array([1.0, 0.3]), np.array([1.3, 2.0]), np.array([0.2, 5.0]))
    b = SineSeries(np.array([0.5, 0.1]), np.array([1.3, 2.0]), np.array([1.0, 1.0]))
    np.testing.assert_allclose(add_series(a, b)(t), a(t) + b(t), atol=1e-12)
    with pytest.raises(Exception, match="same frequencies"):
        add_series(a, SineSeries(np.array([1.0]), np.array([1.0]), np.array([0.0])))


@pytest.mark.parametrize("values", [["5", "0"], ["nan", "1"]])
def test_cli_simulate_bad_roll_jitter_is_one_line_error(tmp_path, capsys, values):
    out = tmp_path / "sim"
    assert (
        cli.main(
            [
                "simulate",
                "--preset",
                "aster",
                "--size",
                "64",
                "64",
                "--roll-jitter",
                *values,
                "-o",
                str(out),
            ]
        )
        == 1
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "roll jitter" in err[0] and "Traceback" not in err[0]
    assert not out.exists() or not any(out.iterdir())
