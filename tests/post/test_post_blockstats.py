"""Block-by-block assessment statistics (issue #14 item 5: the assessment in blocks) against
numpy on whole arrays: exact sums, quantiles within the stated histogram error."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from affine import Affine
from scipy import ndimage as ndi
from threadpoolctl import threadpool_limits

from stereodem.core.dem import DEM
from stereodem.post import assess
from stereodem.post import stats as st
from stereodem.post.blockstats import QUANTILE_ERROR, RESOLUTION, StreamingStats, quantile_error
from stereodem.post.filters import _median_at, _nanmedian_last

EXACT = ("n", "mean", "std", "rmse", "mae", "min", "max", "le90_gauss", "le95_gauss")
QUANTILES = ("median", "p16", "p84", "le90", "le95")


def _data(n=300_000, seed=0):
    """Heavy-tailed differences with NaNs, infinities and blunders beyond the binned range."""
    rng = np.random.default_rng(seed)
    x = rng.standard_t(3, n) * 3.0 + 0.4
    x[rng.random(n) < 0.15] = np.nan
    x[:6] = [4500.0, -2500.0, 1200.0, np.inf, -np.inf, -1100.0]
    return x


def _check_against_numpy(got, want, *, tol=QUANTILE_ERROR):
    for k in EXACT:
        assert got[k] == pytest.approx(want[k], rel=1e-10, abs=1e-12), k
    for k in QUANTILES:
        assert abs(got[k] - want[k]) <= tol["quantiles"] * (1 + 1e-9), k
    assert abs(got["nmad"] - want["nmad"]) <= tol["nmad"] * (1 + 1e-9)


@pytest.mark.parametrize("n_blocks", [1, 7, 50])
def test_streamed_stats_equal_numpy_within_the_stated_error(n_blocks):
    x = _data()
    acc = StreamingStats()
    for part in np.array_split(x, n_blocks):
        acc.add(part)
    got, want = acc.result(n_total=x.size), st.error_stats(x)
    assert got["n"] == want["n"] == int(np.isfinite(x).sum())
    assert got["valid_pct"] == pytest.approx(want["valid_pct"], rel=1e-12)
    _check_against_numpy(got, want)


def test_quantile_error_follows_the_resolution():
    """A coarser histogram: still within its own (larger) stated bound, and the bound is
    reached in order of magnitude (so the bound is not vacuous)."""
    x = np.random.default_rng(4).normal(0.0, 5.0, 200_000)
    res = 0.05
    acc = StreamingStats(resolution=res)
    for part in np.array_split(x, 3):
        acc.add(part)
    got, want = acc.result(), st.error_stats(x)
    _check_against_numpy(got, want, tol=quantile_error(res))
    worst = max(abs(got[k] - want[k]) for k in QUANTILES)
    assert worst > 0.01 * res


def test_quantiles_of_exactly_representable_values_and_tails():
    """Values beyond the binned range are kept exactly: extreme quantiles of them are exact."""
    x = np.concatenate([np.full(10, 1.0), np.array([2000.0, 3000.0, -5000.0])])
    acc = StreamingStats()
    acc.add(x)
    assert acc.quantile(1.0) == 3000.0 and acc.quantile(0.0) == -5000.0
    assert abs(acc.quantile(0.5) - 1.0) <= RESOLUTION / 2
    assert acc.abs_quantile(1.0) == 5000.0


def test_histogram_counts_and_outside_counts():
    x = _data(50_000, seed=2)
    acc = StreamingStats()
    acc.add(x)
    edges = np.linspace(-10, 10, 41)
    got = acc.histogram(edges)
    fin = x[np.isfinite(x)]
    want = np.histogram(fin, bins=edges)[0]
    # a value can only change bins when it lies within half a histogram bin of an edge
    near = int((np.min(np.abs(fin[:, None] - edges[None, :]), axis=1) <= RESOLUTION / 2).sum())
    assert np.abs(got - want).sum() <= near
    below, above = acc.count_outside(-10, 10)
    assert below == pytest.approx((fin < -10).sum(), abs=near)
    assert above == pytest.approx((fin > 10).sum(), abs=near)


def test_empty_accumulator_gives_nan_statistics():
    acc = StreamingStats()
    acc.add(np.full(5, np.nan))
    r = acc.result(n_total=5)
    assert (
        r["n"] == 0 and r["valid_pct"] == 0 and np.isnan(r["nmad"]) and np.isnan(acc.quantile(0.5))
    )


def test_abs_deviation_fit_equals_error_vs_slope():
    rng = np.random.default_rng(7)
    slope = rng.uniform(0, 50, 200_000)
    dh = rng.normal(0.3, 1 + 0.1 * slope)
    dh[rng.random(dh.size) < 0.1] = np.nan
    slope[rng.random(dh.size) < 0.05] = np.nan
    dh[:2] = [3000.0, -1500.0]  # exact tail values, with a slope
    slope[:2] = [10.0, 20.0]
    acc = StreamingStats(covariate=True)
    for a, b in zip(np.array_split(dh, 5), np.array_split(slope, 5)):
        acc.add(a, b)
    want = st.error_vs_slope(dh, slope)
    got = acc.abs_deviation_fit(float(acc.quantile(0.5)))
    assert got["n"] == want["n"]
    assert got["slope"] == pytest.approx(want["slope_m_per_deg"], rel=1e-4)
    assert got["intercept"] == pytest.approx(want["intercept_m"], abs=2 * RESOLUTION)
    assert got["r"] == pytest.approx(want["r"], rel=1e-4)


@pytest.fixture(scope="module")
def dem_pair():
    """A 240 x 260 reference (real SRTM relief) with voids, and a noisy DEM over part of it."""
    b = DEM.bundled()
    ref_h = b.heights[100:340, 200:460].astype(np.float32).copy()
    ref_h[50:60, 70:90] = np.nan  # reference voids: slope NaN around them
    rng = np.random.default_rng(1)
    z = ref_h + rng.normal(0, 2.0, ref_h.shape).astype(np.float32)
    z[:, :30] = np.nan
    z[200:, :] = np.nan
    z[120:140, 100:130] = np.nan
    z[5, 40] += 1500.0  # a blunder beyond the binned range
    T = Affine(30.0, 0.0, 600000.0, 0.0, -30.0, 4390000.0)
    return (DEM(z, T, "EPSG:32637", "geoid", "dem"), DEM(ref_h, T, "EPSG:32637", "geoid", "ref"))


@pytest.mark.parametrize("block_rows", [1, 17, 64, 10_000])
@pytest.mark.slow
def test_blockwise_assessment_equals_the_whole_array_one(dem_pair, block_rows):
    dem, ref = dem_pair
    whole = assess.comparison_stats(assess.compare_on_reference_grid(dem, ref))
    got, display, hist = assess.blockwise_comparison(dem, ref, block_rows=block_rows)
    assert got["stats"]["n"] == whole["stats"]["n"] and hist.n == whole["stats"]["n"]
    assert got["stats"]["n_total"] == whole["stats"]["n_total"]
    _check_against_numpy(got["stats"], whole["stats"])
    for key in ("by_slope", "by_elevation"):
        assert len(got[key]) == len(whole[key])
        for g, w in zip(got[key], whole[key]):
            assert (g["class"], g["n"], g["n_total"]) == (w["class"], w["n"], w["n_total"])
            if w["n"]:
                _check_against_numpy(g, w)
                name = "slope_mean" if key == "by_slope" else "elevation_mean"
                assert g[name] == pytest.approx(w[name], rel=1e-9)
    assert got["slope_fit"]["n"] == whole["slope_fit"]["n"]
    assert got["slope_fit"]["slope_m_per_deg"] == pytest.approx(
        whole["slope_fit"]["slope_m_per_deg"], rel=1e-3
    )
    assert got["slope_fit"]["r"] == pytest.approx(whole["slope_fit"]["r"], rel=1e-3)
    # the display arrays are every k-th cell of the whole comparison
    full = assess.compare_on_reference_grid(dem, ref)
    np.testing.assert_array_equal(display.dh, full.dh)  # 240 rows: k = 1
    np.testing.assert_allclose(display.slope, full.slope, rtol=1e-12, equal_nan=True)


def test_blockwise_display_is_decimated(dem_pair):
    dem, ref = dem_pair
    full = assess.compare_on_reference_grid(dem, ref)
    _, display, _ = assess.blockwise_comparison(dem, ref, block_rows=13, display_cells=60)
    k = int(np.ceil(max(ref.shape) / 60))
    np.testing.assert_array_equal(display.dh, full.dh[::k, ::k])
    assert display.transform == ref.transform @ Affine.scale(k)


def test_blockwise_landcover_classes(dem_pair):
    dem, ref = dem_pair
    lc = np.where(np.arange(ref.shape[1])[None, :] < 150, 1, 2) * np.ones(ref.shape, int)
    lc[:40] = 3
    full = assess.compare_on_reference_grid(dem, ref)
    got, _, _ = assess.blockwise_comparison(
        dem,
        ref,
        landcover=(lc, ref.transform, ref.crs),
        landcover_names={1: "forest"},
        block_rows=25,
    )
    want = st.class_stats(full.dh, lc.astype(float), names={1: "forest"})
    assert (
        [c["class"] for c in got["by_landcover"]]
        == [c["class"] for c in want]
        == ["forest", "2", "3"]
    )
    for g, w in zip(got["by_landcover"], want):
        assert (g["n"], g["n_total"]) == (w["n"], w["n_total"])
        _check_against_numpy(g, w)


# ----------------------------------------------------------------------------- filter helpers
# (the spike filter's block NMAD and its median at replaced cells, vectorised for speed:
# they must give numpy's / scipy's values exactly)


def test_vectorised_block_nanmedian_equals_numpy():
    rng = np.random.default_rng(5)
    t = rng.normal(0, 3, (40, 30, 64))
    t[rng.random(t.shape) < 0.4] = np.nan
    t[3, 4] = np.nan  # a block without any value
    t[5, 6, 1:] = np.nan  # one value
    t[7, 8, 2:] = np.nan  # two values: mean of both
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        want = np.nanmedian(t, axis=2)
    np.testing.assert_array_equal(_nanmedian_last(t), want)


def test_median_at_cells_equals_scipy_median_filter():
    rng = np.random.default_rng(6)
    z = rng.normal(1000, 20, (150, 170))
    cells = rng.random(z.shape) < 0.05
    cells[0, :] = cells[:, -1] = True  # edges use the nearest-value padding
    rr, cc = np.nonzero(cells)
    got = _median_at(z, rr, cc, 7)
    want = ndi.median_filter(z, size=7, mode="nearest")
    np.testing.assert_array_equal(got, want[cells])


def test_blockwise_assessment_does_not_depend_on_threads(dem_pair):
    dem, ref = dem_pair
    one, d1, h1 = assess.blockwise_comparison(dem, ref, block_rows=16, threads=1)
    two, d2, h2 = assess.blockwise_comparison(dem, ref, block_rows=16, threads=3)
    assert one == two or _same(one, two)
    np.testing.assert_array_equal(d1.dh, d2.dh)
    np.testing.assert_array_equal(h1.counts, h2.counts)


def _same(a, b):
    """Equal nested report dicts (NaN equal to NaN)."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and np.isnan(a):
        return isinstance(b, float) and np.isnan(b)
    return a == b


def test_merged_accumulators_equal_one_accumulator():
    x = _data(100_000, seed=9)
    one = StreamingStats()
    for part in np.array_split(x, 4):
        one.add(part)
    parts = []
    for part in np.array_split(x, 4):
        p = StreamingStats()
        p.add(part)
        parts.append(p)
    merged = parts[0]
    for p in parts[1:]:
        merged.merge(p)
    assert _same(one.result(), merged.result())
    with pytest.raises(ValueError):
        merged.merge(StreamingStats(resolution=0.5))


def test_sums_do_not_depend_on_the_blas_thread_count():
    # vector dot products in BLAS (OpenBLAS's ddot splits long vectors over its threads) made
    # the slope fit's last bits follow --workers; the sums are numpy's pairwise ones now
    x = _data(n=200_000, seed=4)
    w = np.abs(x) * 3.0 + 1.0
    results = []
    for n in (1, 3, 4):
        with threadpool_limits(limits=n, user_api="blas"):
            acc = StreamingStats(covariate=True)
            acc.add(x, w)
            results.append((acc.result(), acc.abs_deviation_fit(float(acc.quantile(0.5)))))
    assert results[0][1]["n"] > 100_000
    for r in results[1:]:
        assert repr(r) == repr(results[0])
