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
from stereodem.post import assess, terrain
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
    footprint = assess.dem_footprint(full.dem) & np.isfinite(full.ref)
    want = st.class_stats(full.dh, lc.astype(float), names={1: "forest"}, footprint=footprint)
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


# ----------------------------------------------------------------------------- fast paths
# (issue #28: the assessment's per-block work in fewer passes; each path gives the numbers of
# the plain computation it replaced, bit for bit)


def _moments_by_numpy(x):
    """A block's moments as StreamingStats.add computed them before the fast path."""
    mean = float(x.mean())
    return (
        x.size,
        mean,
        float(np.sum((x - mean) ** 2)),
        float(np.sum(np.multiply(x, x))),
        float(np.abs(x).sum()),
    )


@pytest.mark.parametrize("covariate", [False, True])
def test_add_finite_gives_the_numpy_moments_and_bins(covariate):
    x = _data(50_000, seed=11)
    w = np.abs(np.random.default_rng(2).normal(20, 10, x.size))
    w[7::97] = np.nan
    ok = np.isfinite(x) & (np.isfinite(w) if covariate else True)
    xf, wf = x[ok], w[ok]
    acc = StreamingStats(covariate=covariate)
    acc.add(x, w if covariate else None)
    assert (acc.n, acc._mean, acc._m2, acc._sumsq, acc._sumabs) == _moments_by_numpy(xf)
    assert (acc.min, acc.max) == (xf.min(), xf.max())
    far = np.abs(xf) > acc.limit
    np.testing.assert_array_equal(np.concatenate(acc._tail), xf[far])
    idx = np.floor(xf[~far] / acc.resolution).astype(np.int64) - acc._lo
    np.testing.assert_array_equal(acc.counts, np.bincount(idx))
    if covariate:
        wn, xn = wf[~far], xf[~far]
        np.testing.assert_array_equal(acc._bx, np.bincount(idx, weights=xn))
        np.testing.assert_array_equal(acc._bwx, np.bincount(idx, weights=wn * xn))
        assert (acc._sw, acc._sww) == (float(wf.sum()), float(np.sum(wf * wf)))
    finite = StreamingStats(covariate=covariate)
    finite.add_finite(xf, wf if covariate else None)
    assert _same(finite.result(), acc.result())


def _codes_by_search(v, e):
    """Bin of each value as the class accumulator found it before: a binary search."""
    idx = np.searchsorted(e, v, side="right") - 1
    idx[np.isfinite(v) & (v == e[-1])] = e.size - 2
    return np.where(np.isfinite(v) & (idx >= 0) & (idx <= e.size - 2), idx, -1)


@pytest.mark.parametrize(
    "edges",
    [
        [0, 5, 10, 20, 30, 45, 90],  # compared edge by edge
        [-3.0, 0.5, np.inf],  # an open last class
        list(np.linspace(-40, 40, 41)),  # binary search (more edges than _COMPARE_EDGES)
        list(np.linspace(-45, 95, 300)),  # 16-bit codes
    ],
)
def test_class_codes_equal_the_binary_search_and_binned_stats(edges):
    rng = np.random.default_rng(3)
    e = np.asarray(edges, float)
    v = rng.uniform(-50, 100, (60, 70))
    fin_e = e[np.isfinite(e)]
    v.flat[: 3 * fin_e.size : 3] = fin_e  # values on every edge, the last one included
    v[5, :4] = [np.nan, np.inf, -np.inf, np.nextafter(fin_e[-1], np.inf)]
    for dtype in (np.float64, np.float32):
        vv = v.astype(dtype)
        codes, counts = assess.class_codes(vv, e)
        np.testing.assert_array_equal(codes, _codes_by_search(vv, e))
        dh = np.zeros(v.shape)
        want = [c["n_total"] for c in st.binned_stats(dh, vv, e)]
        assert list(counts) == want


def _class_entries_one_by_one(dh, v, e):
    """Per-class StreamingStats of each class's cells in order (what the accumulator keeps)."""
    codes = _codes_by_search(v, e)
    out = []
    for i in range(e.size - 1):
        sel = (codes == i) & np.isfinite(dh)
        acc = StreamingStats()
        acc.add(dh[sel])
        var = float(v[sel].sum(dtype=np.float64))
        out.append((acc.result(n_total=int((codes == i).sum())), var))
    return out


def test_class_accumulator_groups_as_the_one_class_at_a_time_statistics():
    rng = np.random.default_rng(8)
    shape = (90, 110)
    dh = rng.standard_t(3, shape) * 2.0
    dh[rng.random(shape) < 0.2] = np.nan
    dh[0, :3] = [1500.0, -2000.0, 3.0]  # tails beyond the binned range
    e = np.array([0, 5, 10, 20, 30, 45, 90.0])
    slope = rng.uniform(0, 60, shape)
    slope.flat[:35:5] = e  # on the edges
    slope[rng.random(shape) < 0.05] = np.nan
    for v in (slope, (slope * 40).astype(np.float32)):  # float64 slope, float32 heights
        edges = e if v.dtype == np.float64 else e * 40
        fin = np.isfinite(dh)
        codes, n_cls = assess.class_codes(v, edges)
        acc = assess._ClassAccumulator(edges, unit="deg", name="slope")
        acc.add(np.arange(edges.size - 1), dh[fin], codes[fin], v[fin])
        acc.set_totals(dict(enumerate(n_cls.tolist())))  # here: every cell of the class
        for i, (want, var) in enumerate(_class_entries_one_by_one(dh, v, edges)):
            assert _same(acc.stats[i].result(n_total=acc.n_total[i]), want)
            assert acc.var_sum[i] == var
        got = acc.binned()
        ref = st.binned_stats(dh, v, edges, unit="deg", name="slope")
        for g, w in zip(got, ref):
            assert (g["class"], g["n"], g["n_total"]) == (w["class"], w["n"], w["n_total"])
            if w["n"]:
                _check_against_numpy(g, w)
                assert g["slope_mean"] == pytest.approx(w["slope_mean"], rel=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("crs", ["EPSG:32636", "EPSG:4326"])
def test_slope_of_some_rows_equals_the_whole_grid_slope(crs):
    rng = np.random.default_rng(1)
    T = (
        Affine(15.2, 0, 500000, 0, -15.2, 4e6)
        if crs != "EPSG:4326"
        else Affine(1 / 3600, 0, 30, 0, -1 / 3600, 40.3)
    )
    for shape in [(1, 5), (2, 2), (2, 7), (3, 3), (37, 29), (150, 9)]:  # 150: bands
        z = (rng.normal(size=shape) * 50 + 1000).astype(np.float32)
        z[rng.random(shape) < 0.05] = np.nan
        # the textbook form: numpy's central differences over the pixel size
        dx, dy = terrain.pixel_size_m(T, crs, shape)
        if min(shape) >= 2:
            gr, gc = np.gradient(z.astype(np.float64))
            ge, gn = gc / dx, gr / dy
            got_e, got_n = terrain.gradient(z, T, crs)
            np.testing.assert_array_equal(got_e, ge)
            np.testing.assert_array_equal(got_n, gn)
        else:
            ge, gn = terrain.gradient(z, T, crs)
        want = np.degrees(np.arctan(np.hypot(ge, gn)))
        np.testing.assert_array_equal(terrain.slope_deg(z, T, crs), want)
        for r0 in range(0, shape[0], 7 if shape[0] > 40 else 1):
            for r1 in {r0 + 1, min(r0 + 5, shape[0]), min(r0 + 70, shape[0]), shape[0]}:
                got = terrain.slope_deg(z, T, crs, rows=slice(r0, r1))
                np.testing.assert_array_equal(got, want[r0:r1])


def test_blocks_beyond_the_dem_are_not_warped_and_the_result_is_the_same(dem_pair, monkeypatch):
    """A DEM over the middle rows of a larger reference: the blocks beyond it skip the warp
    (all NaN, as the warp gives), the blocks near it are warped; the result is the same."""
    dem, ref = dem_pair
    part = DEM(
        dem.heights[90:150, 40:200].copy(),
        dem.transform @ Affine.translation(40, 90),
        dem.crs,
        dem.vertical,
        "part",
    )
    skipped = []
    misses = assess._misses

    def spy(d, t, crs, shape):
        out = misses(d, t, crs, shape)
        skipped.append(out)
        return out

    monkeypatch.setattr(assess, "_misses", spy)
    got, d1, h1 = assess.blockwise_comparison(part, ref, block_rows=16)
    assert any(skipped) and not all(skipped)
    monkeypatch.setattr(assess, "_misses", lambda *a: False)
    want, d2, h2 = assess.blockwise_comparison(part, ref, block_rows=16)
    assert _same(got, want)
    np.testing.assert_array_equal(d1.dem, d2.dem)
    np.testing.assert_array_equal(h1.counts, h2.counts)


def test_misses_only_grids_beyond_the_dem_margin(dem_pair):
    dem, _ = dem_pair
    T, (rows, cols) = dem.transform, dem.shape
    m = assess.MISS_MARGIN_CELLS
    for (r, c), miss in {
        (-11 - m, 0): True,  # above, by more than the margin
        (-10, 0): False,  # within the margin: its last row is warped
        (rows + m + 1, 0): True,
        (0, cols + m + 1): True,
        (0, -11 - m): True,
        (-10 - m, 0): False,  # its last row on the margin
        (5, 5): False,
    }.items():
        assert assess._misses(dem, T @ Affine.translation(c, r), dem.crs, (10, 10)) == miss
    # another CRS: the outline is projected (here: lon/lat)
    lon_lat = DEM(dem.heights, dem.transform, dem.crs, "geoid").bounds_lonlat()
    west, south, east, north = lon_lat
    step = (east - west) / cols
    inside = Affine(step, 0, west, 0, -step, north)
    beyond = Affine(step, 0, east + 20 * step, 0, -step, north)
    assert not assess._misses(dem, inside, "EPSG:4326", (10, 10))
    assert assess._misses(dem, beyond, "EPSG:4326", (10, 10))


def test_statistics_without_the_covariate_equal_those_of_the_values_alone():
    x = _data(40_000, seed=12)
    x = x[np.isfinite(x)]  # tails beyond the binned range kept
    w = np.random.default_rng(3).uniform(0, 60, x.size)
    fit = StreamingStats(covariate=True)
    fit.add_finite(x, w)
    alone = StreamingStats()
    alone.add_finite(x)
    got = fit.without_covariate()
    assert not got.covariate
    for name in ("n", "_mean", "_m2", "_sumsq", "_sumabs", "min", "max", "_lo"):
        assert getattr(got, name) == getattr(alone, name), name
    np.testing.assert_array_equal(got.counts, alone.counts)
    np.testing.assert_array_equal(np.concatenate(got._tail), np.concatenate(alone._tail))
    assert _same(got.result(), alone.result())
    got.merge(alone)  # a plain accumulator: merges with plain ones
    assert got.n == 2 * alone.n


def test_blockwise_many_landcover_classes_counted_in_the_footprint(dem_pair):
    """More classes than the per-class passes take (a bincount then): the same cell counts in
    the footprint as the whole-array statistics, and they share the footprint out."""
    dem, ref = dem_pair
    rows, cols = ref.shape
    lc = ((np.arange(cols)[None, :] + 7 * np.arange(rows)[:, None]) % 40).astype(float)
    got, _, _ = assess.blockwise_comparison(
        dem, ref, landcover=(lc, ref.transform, ref.crs), block_rows=17
    )
    full = assess.compare_on_reference_grid(dem, ref)
    footprint = assess.dem_footprint(full.dem) & np.isfinite(full.ref)
    want = st.class_stats(full.dh, lc, footprint=footprint)
    assert len(got["by_landcover"]) == len(want) == 40
    for g, w in zip(got["by_landcover"], want):
        assert (g["value"], g["n"], g["n_total"]) == (w["value"], w["n"], w["n_total"])
    assert sum(c["n_total"] for c in want) == got["stats"]["n_total"]


def test_a_reference_in_another_crs_is_compared_alike_in_any_blocks():
    """A DEM in UTM 33N against a reference on a turned EPSG:3413 grid at 78 N: GDAL's own
    kernel scale, per chunk, smoothed the blocks' warps more than the whole grid's (NMAD
    1.41 m at 512-row blocks for a true 0.5 m on a 2000² case); with one scale for the grid
    (assess._kernel_scale) any block size gives the whole grid's comparison, near the truth."""
    from stereodem.core import geodesy, warp

    rng = np.random.default_rng(3)
    n = 300
    yy, xx = np.mgrid[0:n, 0:n] / n
    z = (1000 + 300 * np.sin(6 * xx) * np.cos(4 * yy) + 40 * np.sin(30 * xx + 5 * yy)).astype(
        np.float32
    )
    st = Affine(60.0, 0.0, 500000.0, 0.0, -60.0, 8700000.0)
    x, y = st @ (n / 2, n / 2)
    cx, cy = geodesy.transformer("EPSG:32633", "EPSG:3413").transform(x, y)
    rt = Affine(60.0, 0.0, cx - 60 * 90, 0.0, -60.0, cy + 60 * 90)
    shape = (180, 180)
    exact = warp.to_grid(z, st, "EPSG:32633", rt, "EPSG:3413", shape, resampling="cubic")
    ref_h = (exact + rng.normal(0, 0.5, shape)).astype(np.float32)
    dem = DEM(z, st, "EPSG:32633", "ellipsoid", "dem")
    ref = DEM(ref_h, rt, "EPSG:3413", "ellipsoid", "ref")
    whole = assess.comparison_stats(assess.compare_on_reference_grid(dem, ref))["stats"]
    for rows in (512, 64, 7):
        got = assess.blockwise_comparison(dem, ref, block_rows=rows)[0]["stats"]
        assert got["n"] == whole["n"]
        assert got["mean"] == pytest.approx(whole["mean"], abs=1e-9), rows
        assert got["nmad"] == pytest.approx(whole["nmad"], abs=2e-3), rows
    assert 0.45 < whole["nmad"] < 0.9  # the 0.5 m noise and the two kernels' difference
