"""Attitude jitter: sum-of-sines fit, attitude injection, and the DEM correction loop."""
import numpy as np
import pytest

from stereodem.sensor.estimation.jitter import (SineSeries, along_track_profile, fit_sum_of_sines,
                                                with_attitude_sines)
from stereodem.sensor.geo import geodesy


def test_fit_sum_of_sines_recovers_two_tones():
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(50.0, 53.0, 400))
    y = (3e-6 * np.sin(2 * np.pi * 1.5 * t + 0.7) + 1e-6 * np.sin(2 * np.pi * 4.2 * t + 2.0)
         + 2e-7 * (t - 51.5) + 1e-7 * rng.standard_normal(t.size))
    y[::37] += 5e-5                                         # outliers
    fit = fit_sum_of_sines(t, y, n_sines=2)
    order = np.argsort(fit.frequencies)
    np.testing.assert_allclose(fit.frequencies[order], [1.5, 4.2], atol=0.02)
    np.testing.assert_allclose(fit.amplitudes[order], [3e-6, 1e-6], rtol=0.08)
    clean = 3e-6 * np.sin(2 * np.pi * 1.5 * t + 0.7) + 1e-6 * np.sin(2 * np.pi * 4.2 * t + 2.0)
    assert np.max(np.abs(fit(t) - clean)) < 3e-7


def test_attitude_sines_move_the_image_along_track():
    from stereodem.sensor.models.pushbroom import PushbroomModel
    m = PushbroomModel.synthetic(40.0, 39.6, width=200, height=400, gsd=15.0, line_period=2.2e-3,
                                 along_track_tilt_deg=-27.6)
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
    assert np.max(np.abs(c - 100.0)) < 0.1 * np.max(np.abs(r - rows))   # mostly along track
    assert np.max(np.abs(r - rows)) > 0.1


@pytest.mark.slow
def test_dem_jitter_correction_removes_the_along_track_oscillation():
    """A sinusoidal 3B pitch oscillation (about +-5 m of height error) is estimated from the
    DEM residuals against the reference DEM and corrected: the along-track error profile
    loses >= 80 % of its amplitude at the jitter frequency."""
    from stereodem.sensor.simulation.simulate import simulate_scene
    from stereodem.stereo.jitter import dem_with_jitter_correction, products_dem

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
        a = np.stack([np.sin(2 * np.pi * f_true * t), np.cos(2 * np.pi * f_true * t),
                      np.ones_like(t), t - t.mean()], -1)
        c, *_ = np.linalg.lstsq(a, med, rcond=None)
        return float(np.hypot(c[0], c[1]))

    final, corrected, fit, first = dem_with_jitter_correction(sc.left, sc.right, sc.left_model,
                                                              sc.right_model, sc.truth_dem)
    before, after = amplitude(products_dem(first)), amplitude(products_dem(final))
    print(f"jitter: injected 3.5 urad at {f_true} Hz, fitted {1e6 * fit.amplitudes[0]:.2f} urad "
          f"at {fit.frequencies[0]:.3f} Hz; along-track height error amplitude "
          f"{before:.2f} m -> {after:.2f} m")
    assert 3.0 < before < 8.0                    # about +-5 m of height error, as intended
    assert after <= 0.2 * before
    assert fit.frequencies[0] == pytest.approx(f_true, abs=0.1)


@pytest.mark.slow
def test_dem_command_corrects_jitter_against_the_seed_dem(tmp_path):
    """`stereodem dem --seed-dem REF --jitter-correction` on a granule with injected 3B jitter
    reports the fitted oscillation and gives a DEM closer to the truth than without it."""
    import json

    import rasterio

    from stereodem import cli
    from stereodem.simulate_cli import write_granule_scene
    from stereodem.sensor.simulation.simulate import simulate_scene

    sc = simulate_scene("aster", size=(500, 700), right_size=(610, 900), seed=5, jitter=(3.5, 1.5))
    g = write_granule_scene(sc, tmp_path / "scene", version=4, seed=5)
    ref = tmp_path / "scene" / "truth_dem.tif"
    errors = {}
    for flag in ("", "--jitter-correction"):
        out = tmp_path / f"d{flag}"
        argv = ["dem", str(g), "-o", str(out), "--seed-dem", str(ref), "--dem-vertical", "ellipsoid",
                "--workers", "1"] + ([flag] if flag else [])
        assert cli.main(argv) == 0
        with rasterio.open(out / "dem.tif") as ds:
            z = ds.read(1).astype(float)
            rr, cc = np.nonzero(np.isfinite(z))
            x, y = ds.transform @ (cc + 0.5, rr + 0.5)
            lon, lat = geodesy.crs_to_lonlat(np.asarray(x), np.asarray(y), ds.crs)
        dh = z[rr, cc] - sc.truth_dem.sample(lon, lat)
        dh = dh[np.isfinite(dh)]
        errors[flag] = float(1.4826 * np.median(np.abs(dh - np.median(dh))))   # NMAD (raw DEM: blunders)
        rep = json.loads((out / "dem_report.json").read_text())
    jit = rep["info"]["jitter"]
    assert jit["frequencies_hz"][0] == pytest.approx(sc.diagnostics["right_jitter"]["frequency_hz"], abs=0.1)
    print(f"DEM NMAD vs truth without / with jitter correction: {errors}")
    assert errors["--jitter-correction"] < errors[""], errors
