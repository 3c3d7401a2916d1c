"""Spatial statistics of dh (issue 25): the empirical variogram and its fit against
scikit-gstat on the same samples, σ of an area mean against a Monte Carlo of correlated noise,
heteroscedasticity and the sensor-model σ's explained share."""

from __future__ import annotations

import json

import numpy as np
import pytest
from affine import Affine

import stereodem.post.spatialstats as ss
from stereodem.core.errors import InputError
from stereodem.post.spatialstats import (
    EmpiricalVariogram,
    VariogramModel,
    area_mean_sigma,
    fit_variogram,
    heteroscedasticity,
    simulate_field,
    variogram,
)

T = Affine(30.0, 0, 500000, 0, -30.0, 4500000)
CRS = "EPSG:32637"


@pytest.mark.slow
def test_empirical_variogram_and_fit_match_skgstat():
    skgstat = pytest.importorskip("skgstat")
    model = VariogramModel(np.array([600.0]), np.array([1.0]))
    f = simulate_field(model, (80, 80), 30.0, rng=3)[0]
    rng = np.random.default_rng(0)
    idx = rng.choice(f.size, 800, replace=False)
    r, c = np.divmod(idx, 80)
    xy = np.column_stack([c * 30.0, r * 30.0])
    v = f.ravel()[idx]
    V = skgstat.Variogram(xy, v, model="spherical", n_lags=15, maxlag=1800.0, bin_func="even")
    edges = np.concatenate([[0.0], np.asarray(V.bins, float)])
    emp = variogram(v, xy, edges=edges)
    np.testing.assert_allclose(emp.gamma, V.experimental, rtol=1e-9)
    same = EmpiricalVariogram(edges, np.asarray(V.bins, float), emp.gamma, np.full(15, 1e6))
    m = fit_variogram(same, n_models=1)
    assert m.ranges[0] == pytest.approx(V.parameters[0], rel=0.10)
    assert m.sills[0] == pytest.approx(V.parameters[1], rel=0.10)


def test_fit_recovers_two_ranges_of_a_simulated_field():
    model = VariogramModel(np.array([90.0, 900.0]), np.array([0.5, 0.5]))
    f = simulate_field(model, (150, 150), 30.0, rng=1, n_fields=4)
    # variogram pooled over four fields (NaN gaps between them keep pairs within one field)
    big = np.full((150, 4 * 160), np.nan)
    for k in range(4):
        big[:, k * 160 : k * 160 + 150] = f[k]
    emp = variogram(big, transform=T, crs=CRS, n_pairs=400_000, max_lag=2500.0, seed=2)
    m = fit_variogram(emp, n_models=2)
    assert m.ranges[0] == pytest.approx(90.0, rel=0.35)
    assert m.ranges[1] == pytest.approx(900.0, rel=0.35)
    assert m.sill == pytest.approx(1.0, rel=0.25)


def test_area_mean_sigma_agrees_with_monte_carlo():
    model = VariogramModel(np.array([100.0, 800.0]), np.array([1.0, 0.6]))
    shape = (40, 40)
    yy, xx = np.mgrid[0:40, 0:40]
    disc = np.hypot(yy - 19.5, xx - 19.5) * 30.0 <= 500.0
    pred = area_mean_sigma(model, disc, T, CRS, n_samples=2000)
    f = simulate_field(model, shape, 30.0, rng=7, n_fields=400)
    mc = np.std(f[:, disc].mean(axis=1), ddof=1)
    assert pred["sigma_mean"] == pytest.approx(mc, rel=0.10)
    assert pred["sigma_naive"] < 0.5 * pred["sigma_mean"]  # σ/√N is far too small here
    # per-cell σ scales the result
    twice = area_mean_sigma(model, disc, T, CRS, sigma=2.0, n_samples=2000)
    assert twice["sigma_mean"] == pytest.approx(2 * pred["sigma_mean"], rel=1e-9)


def test_heteroscedasticity_finds_dispersion_growing_with_slope_and_sensor_share():
    rng = np.random.default_rng(0)
    slope = rng.uniform(0, 40, (100, 100))
    curv = rng.normal(0, 1, (100, 100))
    sig = 0.5 + 0.05 * slope
    dh = rng.normal(0, 1, slope.shape) * sig
    h = heteroscedasticity(dh, slope, curv, sigma_model=0.7 * sig)
    nm = np.asarray(h["slope"]["nmad"])
    assert nm[-1] > 2.5 * nm[0]
    rel = np.abs(h["sigma"] / sig - 1)
    assert np.median(rel) < 0.08 and np.percentile(rel, 95) < 0.25
    sm = h["sensor_model"]
    assert sm["explained_variance_share"] == pytest.approx(0.49, rel=0.15)
    assert sm["binned_r"] > 0.9
    assert sm["nmad_standardised"] == pytest.approx(1 / 0.7, rel=0.1)
    # the sensor-based per-cell σ puts back the unexplained half: dh/σ is standard again
    z = dh / h["sigma_sensor"]
    assert np.nanstd(z) == pytest.approx(1.0, abs=0.08)
    assert np.median(np.abs(h["sigma_sensor"] / sig - 1)) < 0.1


def _same(a, b):
    """Equal to the bit: arrays by their bytes, the rest by its JSON text (NaN included)."""
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and a.tobytes() == b.tobytes()
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return json.dumps(a) == json.dumps(b)


@pytest.mark.parametrize("with_model", [False, True])
def test_heteroscedasticity_is_the_same_on_any_number_of_threads(monkeypatch, with_model):
    """The bins and the per-cell interpolation on threads, in pieces: the numbers of one
    piece on one thread, to the bit (issue 28)."""
    rng = np.random.default_rng(1)
    slope = rng.uniform(0, 40, (120, 90))
    curv = rng.normal(0, 1, slope.shape)
    sig = 0.5 + 0.05 * slope
    dh = rng.normal(0, 1, slope.shape) * sig
    dh[::7, ::5] = np.nan
    slope[3] = np.nan
    kw = {"sigma_model": 0.7 * sig} if with_model else {}
    whole = heteroscedasticity(dh, slope, curv, threads=1, **kw)  # one piece (CHUNK > cells)
    monkeypatch.setattr(ss, "CHUNK", 1000)  # 11 pieces of the cells, 10 of the stable ones
    for threads in (1, 2, 3):
        assert _same(heteroscedasticity(dh, slope, curv, threads=threads, **kw), whole)


def test_area_mean_sigma_of_a_sigma_that_does_not_fit_the_area_is_one_line():
    """A per-cell σ of another grid's shape, or (n,) coordinates instead of (n, 2), raised
    numpy's "operands could not be broadcast" ValueError / an IndexError from inside."""
    model = VariogramModel(np.array([100.0]), np.array([1.0]))
    area = np.zeros((40, 40), bool)
    area[10:20, 10:20] = True
    with pytest.raises(InputError, match=r"sigma of shape \(10, 10\) does not fit the area"):
        area_mean_sigma(model, area, T, CRS, sigma=np.ones((10, 10)))
    with pytest.raises(InputError, match=r"\(n, 2\) coordinates in metres, got shape \(5,\)"):
        area_mean_sigma(model, np.arange(5.0))
    xy = np.column_stack([np.arange(5.0) * 30, np.zeros(5)])
    with pytest.raises(InputError, match=r"sigma of shape \(4,\) does not fit"):
        area_mean_sigma(model, xy, sigma=np.ones(4))
    assert area_mean_sigma(model, xy, sigma=np.ones(5))["n_cells"] == 5


def test_blunders_do_not_set_the_variogram_and_the_sigma_of_area_means():
    """A few blunders among standardised dh (0.3 % of the cells at 40-400 σ: what a filtered
    stereo DEM keeps) made the Matheron variogram's sill hundreds and its range hundreds of
    km, and the error analysis's σ of an area mean tens of metres on a DEM of NMAD 2.3 m
    (``stereodem assess --error-analysis --outlines`` on the simulated pair). They are left out
    of the variogram (``drop_outliers``, 4 NMAD, as xdem): sill ~1, the σ of the mean as
    without them."""
    from stereodem.core.dem import DEM
    from stereodem.post.error_analysis import ErrorAnalysisJob, analyse
    from stereodem.post.volumes import rate_error_model

    model = VariogramModel(np.array([150.0]), np.array([1.0]))
    f = simulate_field(model, (120, 120), 30.0, rng=5)[0]
    rng = np.random.default_rng(1)
    bad = rng.choice(f.size, int(0.003 * f.size), replace=False)
    dirty = f.copy()
    dirty.ravel()[bad] = rng.choice([-1, 1], bad.size) * rng.uniform(40, 400, bad.size)
    z, n = ss.drop_outliers(dirty)
    assert n >= bad.size and np.isnan(z.ravel()[bad]).all() and np.isfinite(dirty).all()
    assert ss.drop_outliers(np.ones(50))[1] == 0  # a constant field has no blunder

    # the stack's rate error model: rate / rate_sigma on stable terrain
    from stereodem.core.grid import MapGrid

    grid = MapGrid(T, 120, 120, CRS)
    m, _, _ = rate_error_model(dirty, np.ones_like(dirty), np.ones(dirty.shape, bool), grid)
    assert m.sill == pytest.approx(1.0, rel=0.3) and max(m.ranges) < 2000.0

    # the error analysis of a DEM: the bundled SRTM tile plus this error, 2 m a σ
    full = DEM.bundled()
    ref = DEM(full.heights[:120, :120].copy(), full.transform, full.crs, "geoid")
    dem = DEM(ref.heights + (2.0 * dirty).astype(np.float32), ref.transform, ref.crs, "geoid")
    section, _ = analyse(dem, ref, ErrorAnalysisJob(n_pairs=200_000))
    vg = section["variogram"]
    assert vg["model"]["sill"] == pytest.approx(1.0, rel=0.3)
    assert max(vg["model"]["ranges_m"]) < 5000.0  # 5 cells of the tile: about 450 m
    assert vg["outliers_left_out"]["cells"] >= bad.size
