import cv2
import numpy as np
import pytest
from scipy import ndimage as ndi

from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.post import filters as F
from stereodem.post.terrain import slope_deg


@pytest.fixture(scope="module")
def clean_dem():
    """A 30 m-like stereo DEM: a 200 x 200 crop of the bundled SRTM upsampled x3 (cubic)
    with 2 m of white noise (600 x 600 cells)."""
    z90 = DEM.bundled().heights.astype(np.float64)[300:500, 300:500]
    return ndi.zoom(z90, 3, order=3) + np.random.default_rng(0).normal(0, 2, (600, 600))


def _inject(z0, frac=0.01, seed=1):
    """1 % of cells replaced by outliers: 60 % isolated spikes/pits of 30-300 m, the rest in
    2x2 to 4x4 clumps of 30-300 m."""
    rng = np.random.default_rng(seed)
    z = z0.copy()
    bad = np.zeros(z.shape, bool)
    n = int(frac * z.size)
    nsp = int(0.6 * n)
    idx = rng.choice(z.size, nsp, replace=False)
    r, c = np.unravel_index(idx, z.shape)
    z[r, c] += rng.uniform(30, 300, nsp) * rng.choice([-1, 1], nsp)
    bad[r, c] = True
    while bad.sum() < n:
        s = rng.integers(2, 5)
        r, c = rng.integers(0, z.shape[0] - s), rng.integers(0, z.shape[1] - s)
        z[r : r + s, c : c + s] = z0[r : r + s, c : c + s] + rng.uniform(30, 300) * rng.choice(
            [-1, 1]
        )
        bad[r : r + s, c : c + s] = True
    return z, bad


def test_default_chain_removes_injected_blunders(clean_dem):
    z, bad = _inject(clean_dem)
    res = F.default_chain().apply(z)
    m = res.removed_mask
    assert m[bad].mean() >= 0.99
    assert m[~bad].mean() <= 0.01
    assert np.all(np.isnan(res.heights[m]))
    counted = sum(e.get("removed", 0) for e in res.report)
    assert counted == m.sum()
    skipped = {e["step"] for e in res.report if "skipped" in e}
    assert skipped == {"score", "ray_gap"}
    for e in res.report:
        if "removed" in e:
            assert np.sum(res.removed == e["reason"]) == e["removed"]
    # on the clean DEM the chain hardly touches anything
    assert F.default_chain().apply(clean_dem).removed_mask.mean() < 0.002


def test_score_and_ray_gap_filters():
    z = np.zeros((10, 10))
    score = np.full(z.shape, 0.9)
    score[2, 3] = 0.2
    m, reason = F.score_filter(z, score, min_score=0.5)
    assert reason == F.Reason.SCORE and m.sum() == 1 and m[2, 3]
    gap = np.random.default_rng(0).uniform(1, 2, z.shape)
    gap[5, 5] = 50.0
    m, reason = F.ray_gap_filter(z, gap)  # 3 x P75
    assert reason == F.Reason.RAY_GAP and m.sum() == 1 and m[5, 5]
    m, _ = F.ray_gap_filter(z, gap, max_gap=1.5, percentile=None)
    assert m.sum() == np.sum(gap > 1.5)
    with pytest.raises(InputError):
        F.score_filter(z, score[:5])


def test_ok_thesis_local_tests():
    r, c = np.mgrid[0:20, 0:20].astype(float)
    z = 500 + 2 * c + np.random.default_rng(0).normal(0, 0.5, (20, 20))
    z[10, 10] += 40
    m, reason = F.local_sigma_filter(z, k=2.0)
    assert reason == F.Reason.LOCAL_SIGMA and m[10, 10]
    z2 = np.full((9, 9), 100.0)
    z2[3:6, 3:6] = np.nan
    z2[4, 4] = 100.0  # surrounded by 8 voids
    z2[2, 2] = np.nan
    m, reason = F.failed_neighbours_filter(z2, min_failed=5)
    assert reason == F.Reason.FAILED_NEIGHBOURS
    assert m[4, 4] and m.sum() == 1


def test_slope_reference_and_patch_filters():
    d = DEM.bundled()
    z = d.heights.astype(np.float64)[:200, :200].copy()
    t = d.transform
    m, reason = F.slope_filter(z, t, d.crs, max_slope=30.0)

    assert reason == F.Reason.SLOPE and m.sum() == np.sum(slope_deg(z, t, d.crs) > 30.0)
    ref = z + 5.0
    zz = z.copy()
    zz[50, 60] += 150
    m, reason = F.reference_filter(zz, ref, max_diff=50.0)
    assert reason == F.Reason.REFERENCE and m.sum() == 1 and m[50, 60]
    # a 3 x 3 island in a void, and a 2 x 2 clump 500 m above the terrain
    zz = z.copy()
    zz[100:130, 100:130] = np.nan
    zz[110:113, 110:113] = z[110:113, 110:113]
    zz[20:22, 20:22] += 500
    m, reason = F.small_patch_filter(zz, max_size=10)
    assert reason == F.Reason.SMALL_PATCH
    assert m[110:113, 110:113].all() and m[20:22, 20:22].all() and m.sum() == 13


def test_chain_config_and_unknown_step():
    chain = F.FilterChain(
        [("spike", {"k": 4.0}), {"name": "small_patch", "params": {"max_size": 5}}]
    )
    assert chain.params == [
        {"step": "spike", "params": {"k": 4.0}},
        {"step": "small_patch", "params": {"max_size": 5}},
    ]
    with pytest.raises(InputError):
        F.FilterStep("magic")


def test_nearest_fill_is_exact_near_the_data_and_the_same_on_any_threads():
    """The spike filter's void fill works in fixed bands of rows: every void cell within 3
    cells of a valid one (what the 5 x 5 prediction and 7 x 7 median read) gets the height of
    a valid cell at the nearest distance of the whole grid's transform; the bands do not
    depend on the threads, so 1 and 3 threads give the same array."""
    rng = np.random.default_rng(4)
    rows, cols = 3 * F.FILL_BAND_ROWS + 37, 300
    r, c = np.mgrid[0:rows, 0:cols]
    z = (r * 1000 + c).astype(np.float64)  # each height names its cell
    void = ndi.binary_dilation(rng.random((rows, cols)) < 0.004, iterations=4)
    void |= (r - 0.6 * c) > 0.55 * rows  # a large void corner, as outside a footprint
    void[F.FILL_BAND_ROWS - 20 : F.FILL_BAND_ROWS + 30, :] = True  # across a band edge
    z[void] = np.nan
    saved = cv2.getNumThreads()
    try:
        filled = {}
        for n in (1, 3):
            cv2.setNumThreads(n)
            filled[n] = F._fill_nearest(z)
    finally:
        cv2.setNumThreads(saved)
    np.testing.assert_array_equal(filled[1], filled[3])
    out = filled[1]
    assert np.array_equal(out[~void], z[~void])
    near = ndi.binary_dilation(~void, structure=np.ones((3, 3)), iterations=3) & void
    assert near.sum() > 5000
    src_r, src_c = np.divmod(out[near].astype(np.int64), 1000)
    assert not void[src_r, src_c].any()  # a valid cell's height
    got = np.hypot(src_r - r[near], src_c - c[near])
    best = ndi.distance_transform_edt(void)[near]
    np.testing.assert_allclose(got, best, rtol=0, atol=1e-12)


def test_small_patch_jump_limit_and_mask_do_not_depend_on_the_threads():
    """The jump limit is the percentile of all the grid's jumps, gathered in row bands on
    threads: the same limit as the whole grid's (given explicitly here), and the same mask on
    1 and 3 threads."""
    rng = np.random.default_rng(8)
    r, c = np.mgrid[0:700, 0:400]
    z = 800 + 0.3 * r + 40 * np.sin(c / 30.0) + rng.normal(0, 0.5, r.shape)
    z[rng.random(z.shape) < 0.02] = np.nan
    islands = rng.random(z.shape) < 0.001  # small clumps standing off the terrain
    z[ndi.binary_dilation(islands, iterations=1)] += 300
    jx, jy = np.abs(np.diff(z, axis=1)), np.abs(np.diff(z, axis=0))
    j = np.concatenate([jx[np.isfinite(jx)], jy[np.isfinite(jy)]])
    limit = max(10.0, 2.0 * float(np.percentile(j, 99.0)))
    saved = cv2.getNumThreads()
    try:
        masks = {}
        for n in (1, 3):
            cv2.setNumThreads(n)
            masks[n] = F.small_patch_filter(z)[0]
        explicit = F.small_patch_filter(z, max_jump=limit)[0]
    finally:
        cv2.setNumThreads(saved)
    assert masks[1].sum() > 50  # the clumps are found
    np.testing.assert_array_equal(masks[1], masks[3])
    np.testing.assert_array_equal(masks[1], explicit)


def test_small_patch_blobs_across_row_bands_are_measured_whole():
    """A blob larger than max_size that a row band cuts into pieces smaller than max_size is
    kept on any threads (each band reads max_size + 1 rows beyond its own), and a small blob
    at a band's edge is still removed: the masks equal the single-band one."""
    z = np.full((400, 40), np.nan)
    z[195:207, 10] = 100.0  # 12 cells in one column across row 200 (two bands' boundary)
    z[196:204, 20] = 100.0  # 8 cells across the same boundary: a small patch
    z[300:303, 5:8] = 50.0  # 9 cells inside a band
    saved = cv2.getNumThreads()
    try:
        masks = {}
        for n in (1, 2, 3):
            cv2.setNumThreads(n)
            masks[n] = F.small_patch_filter(z, max_size=10, max_jump=5.0)[0]
    finally:
        cv2.setNumThreads(saved)
    assert not masks[1][195:207, 10].any()
    assert masks[1][196:204, 20].all() and masks[1][300:303, 5:8].all()
    np.testing.assert_array_equal(masks[1], masks[2])
    np.testing.assert_array_equal(masks[1], masks[3])


def test_spike_repredicts_only_where_a_window_reaches_a_replaced_cell():
    """The iterations predict again only the cells whose window reaches a replaced cell
    (SciPy's correlation evaluated there, bit for bit) and keep the first pass's flags
    elsewhere: the same mask as predicting the whole grid again at each iteration."""
    rng = np.random.default_rng(15)
    r, c = np.mgrid[0:300, 0:260]
    z = 500 + 0.4 * r + 30 * np.sin(c / 25.0) + rng.normal(0, 0.4, r.shape)
    z[rng.random(z.shape) < 0.03] = np.nan
    spikes = rng.random(z.shape) < 0.01  # single spikes and pits of any size
    z[spikes] += rng.normal(0, 40, spikes.sum())
    z[ndi.binary_dilation(rng.random(z.shape) < 0.003)] += 60  # clumps: several iterations
    z[:3, 100:104] += 50  # spikes at the grid's edge (the nearest-value border)

    kern = F._quadratic_kernel(2)
    rows, cols = np.nonzero(rng.random(z.shape) < 0.1)
    a = np.nan_to_num(z, nan=500.0)
    np.testing.assert_array_equal(
        F._correlate_at(a, rows, cols, kern), ndi.correlate(a, kern, mode="nearest")[rows, cols]
    )

    def whole_grid(z, k=5.0, min_deviation=5.0, iterations=4):  # every iteration on all cells
        valid = np.isfinite(z)
        zf = F._fill_nearest(z)
        res = zf - ndi.correlate(zf, kern, mode="nearest")
        limit = np.maximum(k * F._block_scale(res, valid, 32), min_deviation)
        flag = valid & (np.abs(res) > limit)
        work, replaced, n = zf.copy(), None, 0
        for _ in range(iterations - 1):
            if not flag.any():
                break
            todo = flag if replaced is None else flag & ~replaced
            rr, cc = np.nonzero(todo)
            work[rr, cc] = F._median_at(zf, rr, cc, 7)
            replaced = flag if replaced is None else replaced | flag
            new = valid & (np.abs(zf - ndi.correlate(work, kern, mode="nearest")) > limit)
            n += 1
            if np.array_equal(new, flag):
                break
            flag = new
        return flag, n

    expected, passes = whole_grid(z)
    assert passes >= 2 and expected.sum() > 100
    np.testing.assert_array_equal(F.spike_filter(z)[0], expected)
