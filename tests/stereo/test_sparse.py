"""Sparse matches, relative pointing and terrain heights (stereo.sparse / pointing / terrain)."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from helpers.rpc_scene import rpc_steep_pair

from stereodem.core import geodesy
from stereodem.core.stats import nmad
from stereodem.core.threads import thread_budget
from stereodem.sensor.models.corrected import ImageCorrectedModel
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation.simulate import simulate_scene
from stereodem.stereo.pointing import cross_residuals, relative_pointing
from stereodem.stereo.sparse import (
    SparseMatchError,
    refine_matches,
    sparse_matches,
    to_uint8,
    zncc_scores,
)
from stereodem.stereo.sparse_stage import height_pileup, run_sparse_stage
from stereodem.stereo.terrain import terrain_heights, tile_height_range


def _shared_pair():
    """The real Pleiades pair beside the repository (any parent's shared/data), or skip."""
    for parent in Path(__file__).resolve().parents:
        pair = parent / "shared" / "data" / "s2p_pleiades" / "pair"
        if pair.is_dir():
            return pair
    pytest.skip("shared/data/s2p_pleiades is not present (only in the development workspace)")


@pytest.fixture(scope="module")
def scene():
    # ASTER geometry over alpine terrain (1 700-2 900 m); the models' height range is
    # -500..9 000 m, so the terrain lies ~2 000 m from its middle
    return simulate_scene("aster", size=(400, 400), seed=3)


@pytest.fixture(scope="module")
def biased(scene):
    """The right model delivered with a 6 px cross-track (col) and 3 px along-track (row)
    error, and the sparse matches checked with it."""
    given = ImageCorrectedModel(scene.right_model, col_shift=6.0, row_shift=3.0)
    return given, sparse_matches(scene.left, scene.right, scene.left_model, given)


def _overlap_truth(scene, step=10):
    """True heights at left pixels that the right image also sees."""
    c, r = np.meshgrid(
        np.arange(0, scene.left_model.width, step, dtype=float),
        np.arange(0, scene.left_model.height, step, dtype=float),
    )
    loc = scene.left_model.localize_dem(c.ravel(), r.ravel(), scene.truth_dem, h0=2000.0)
    c2, r2 = scene.right_model.project(loc.lon, loc.lat, loc.h)
    inside = (
        (c2 >= 0)
        & (c2 <= scene.right_model.width - 1)
        & (r2 >= 0)
        & (r2 <= scene.right_model.height - 1)
        & np.isfinite(loc.h)
    )
    return loc.lon[inside], loc.lat[inside], loc.h[inside]


# ----------------------------------------------------------------------------- sparse


def test_matches_lie_on_the_true_epipolar_curves(scene):
    m = sparse_matches(scene.left, scene.right, scene.left_model, scene.right_model)
    assert len(m) > 300
    assert abs(m.offset_cross) < 0.2  # unbiased models: no offset found
    # through the true models every kept match is within the tolerance of its curve
    r = cross_residuals(
        scene.left_model, scene.right_model, m.col1, m.row1, m.col2, m.row2, m.height_range
    )
    assert np.all(np.abs(r) <= 2.0)
    assert nmad(r) < 0.3


def test_matches_found_despite_offset_of_tens_of_pixels(scene):
    given = ImageCorrectedModel(scene.right_model, col_shift=-25.0, row_shift=12.0)
    m = sparse_matches(scene.left, scene.right, scene.left_model, given)
    assert len(m) > 300
    # the consensus offset across the curves is the cross-track part of the error (normal ~ -col)
    nbar = m.normal.mean(0)
    assert abs(m.offset_cross - float(np.dot(nbar, [25.0, -12.0]))) < 0.3


def test_any_dtype_voids_and_reduced_scale(scene):
    left = scene.left.astype(np.float32) * 13.7 + 1000.0
    left[:, :60] = np.nan  # a void band
    right16 = scene.right.astype(np.uint16) * 16
    m = sparse_matches(left, right16, scene.left_model, scene.right_model, max_size=220)
    assert m.info["scale"] < 0.6
    assert len(m) > 50
    assert m.col1.min() > 60  # nothing detected on the void
    # positions are in full-resolution pixels: the true models agree to about a pixel
    r = cross_residuals(
        scene.left_model, scene.right_model, m.col1, m.row1, m.col2, m.row2, m.height_range
    )
    assert np.median(np.abs(r)) < 0.6


def test_to_uint8_stretch():
    a = np.linspace(0, 4000, 10000, dtype=np.float64).reshape(100, 100)
    a[0, 0] = np.nan
    b, valid = to_uint8(a)
    assert b.dtype == np.uint8 and not valid[0, 0] and valid.sum() == a.size - 1
    assert b[50, 50] in range(120, 136) and b[-1, -1] == 255


def test_match_refinement_is_the_same_on_one_thread_or_several():
    """The refinement scores its matches in bands on the thread budget's threads: the same
    numbers as on one thread, and the known shift found."""
    rng = np.random.default_rng(8)
    left = cv2.GaussianBlur(rng.random((600, 600)).astype(np.float32), (5, 5), 1.5) * 255
    right = np.roll(left, (3, 5), axis=(0, 1))  # right(x + 5, y + 3) = left(x, y)
    x1 = rng.random((300, 2)) * 500 + 50
    x2 = x1 + [5.0, 3.0] + rng.normal(0, 1.0, x1.shape)
    out = {}
    for n in (1, 2, 3):
        with thread_budget(n):
            out[n] = refine_matches(left, right, x1, x2, search=4)
    for n in (2, 3):
        assert all(np.array_equal(a, b) for a, b in zip(out[1], out[n]))
    y1, y2, score, keep = out[1]
    err = np.abs(y2 - y1 - [5.0, 3.0])  # parabola peaks on blurred noise: ~0.015 px typical
    assert keep.sum() > 250 and np.median(err) < 0.03 and err.max() < 0.15


def test_textureless_images_give_one_line_error(scene):
    flat = np.full((200, 200), 7, np.uint8)
    with pytest.raises(SparseMatchError) as e:
        sparse_matches(flat, flat, scene.left_model, scene.right_model)
    assert "\n" not in str(e.value) and "sparse matching" in str(e.value)


# ----------------------------------------------------------------------------- pointing


def test_pointing_recovers_the_cross_epipolar_bias(scene, biased):
    given, m = biased
    pc = relative_pointing(m, scene.left_model, given)
    assert pc.kind == "translation" and not pc.along_observed
    # the observable part: the bias projected on the normal of the epipolar curves
    nbar = m.normal.mean(0)
    nbar /= np.linalg.norm(nbar)
    corr = np.array([pc.parameters["col_shift"], pc.parameters["row_shift"]])
    assert abs(np.dot(nbar, corr + [6.0, 3.0])) <= 0.1
    assert abs(pc.parameters["col_shift"] + 6.0) <= 0.1  # cross-track = col here
    assert abs(pc.before["median"]) > 5.5 and abs(pc.after["median"]) < 0.1
    assert pc.after["nmad"] < 0.5 and pc.warning is None


def test_pointing_with_reference_dem_recovers_both_components(scene, biased):
    given, m = biased
    pc = relative_pointing(m, scene.left_model, given, reference_dem=scene.truth_dem)
    assert pc.along_observed
    assert abs(pc.parameters["col_shift"] + 6.0) <= 0.1
    assert abs(pc.parameters["row_shift"] + 3.0) <= 0.1
    # applied to the delivered model, the correction gives back the true one
    lon, lat, h = _overlap_truth(scene, step=40)
    c0, r0 = scene.right_model.project(lon, lat, h)
    c1, r1 = pc.model.project(lon, lat, h)
    assert np.max(np.hypot(c1 - c0, r1 - r0)) <= 0.1


def test_pointing_affine_when_the_matches_support_it(scene):
    # a cross-track drift of 2 px across the image rows on top of a 4 px shift
    given = ImageCorrectedModel(scene.right_model, col_shift=4.0, col_drift_row=2.0 / 400)
    m = sparse_matches(scene.left, scene.right, scene.left_model, given)
    auto = relative_pointing(m, scene.left_model, given)
    trans = relative_pointing(m, scene.left_model, given, affine=False)
    assert auto.kind == "affine" and trans.kind == "translation"
    assert auto.after["nmad"] < trans.after["nmad"]
    # the corrected cross-track position agrees with the truth over the image to 0.1 px
    lon, lat, h = _overlap_truth(scene, step=40)
    c0, _ = scene.right_model.project(lon, lat, h)
    c1, _ = auto.model.project(lon, lat, h)
    assert np.max(np.abs(c1 - c0)) <= 0.1


def test_pointing_warns_when_residual_stays_large(scene, biased):
    given, m = biased
    rng = np.random.default_rng(0)
    noisy = m.subset(np.arange(len(m)))
    noisy.col2 = noisy.col2 + rng.normal(0, 1.5, len(m))
    noisy.cross = cross_residuals(
        scene.left_model, given, noisy.col1, noisy.row1, noisy.col2, noisy.row2, m.height_range
    )
    pc = relative_pointing(noisy, scene.left_model, given)
    assert pc.after["nmad"] > 0.5
    assert pc.warning is not None and "0.5 px" in pc.warning


def test_pointing_too_few_matches(scene, biased):
    given, m = biased
    with pytest.raises(SparseMatchError) as e:
        relative_pointing(m.subset(np.arange(4)), scene.left_model, given)
    assert "only 4" in str(e.value) and "\n" not in str(e.value)


# ----------------------------------------------------------------------------- terrain


@pytest.mark.slow
def test_height_range_contains_the_true_terrain(scene):
    m = sparse_matches(scene.left, scene.right, scene.left_model, scene.right_model)
    th = terrain_heights(m, scene.left_model, scene.right_model)
    lon, lat, h = _overlap_truth(scene)
    lo, hi = th.height_range
    assert lo <= h.min() and hi >= h.max()
    # far tighter than the models' range, and far from its middle
    assert hi - lo < 0.2 * 9500
    assert abs(0.5 * (lo + hi) - 4250) > 1500
    # the seed surface sets each 100 x 100 px tile's range: together they hold the true
    # terrain of the overlap, and are narrower than the global range
    c, r = scene.left_model.project(lon, lat, h)
    held, widths = np.zeros(h.size, bool), []
    for c0 in range(0, 400, 100):
        for r0 in range(0, 400, 100):
            tlo, thi = tile_height_range(scene.left_model, (c0, r0, c0 + 99, r0 + 99), th)
            widths.append(thi - tlo)
            here = (c >= c0 - 0.5) & (c < c0 + 99.5) & (r >= r0 - 0.5) & (r < r0 + 99.5)
            held[here] = (h[here] >= tlo) & (h[here] <= thi)
    assert held.mean() >= 0.99
    assert np.median(widths) < 0.8 * (hi - lo)


def test_terrain_too_few_points(scene, biased):
    given, m = biased
    with pytest.raises(SparseMatchError) as e:
        terrain_heights(m.subset(np.arange(7)), scene.left_model, given)
    msg = str(e.value)
    assert "only 7" in msg and "height range" in msg and "\n" not in msg


# ----------------------------------------------------------------------------- real pair


@pytest.mark.slow
def test_real_pleiades_pair():
    pair = _shared_pair()
    images = [rasterio.open(pair / n).read(1) for n in ("img_01.tif", "img_02.tif")]
    left, right = (RPCModel.from_file(pair / n) for n in ("img_01.tif", "img_02.tif"))
    with rasterio.open(pair / "expected_dsm.tif") as ds:
        dsm = ds.read(1)
    dsm = dsm[np.isfinite(dsm)]
    m = sparse_matches(images[0], images[1], left, right)
    assert len(m) > 500  # ~970 with the default 512 px detection scale
    pc = relative_pointing(m, left, right)
    assert pc.after["nmad"] < 0.5 and abs(pc.after["median"]) < 0.1
    th = terrain_heights(m, left, pc.model)
    lo, hi = th.height_range
    # s2p's DSM of the pair (ellipsoidal heights) lies inside the range found; the RPCs'
    # height offset (1 295 m) is 1 000 m away from the terrain
    assert lo <= np.percentile(dsm, 0.5) and hi >= np.percentile(dsm, 99.5)
    assert hi - lo < 400
    assert not (lo <= np.mean(left.height_bounds()) <= hi)


# ----------------------------------------------------------------------------- the stage


def test_sparse_stage_corrects_and_bounds_the_biased_pair(scene):
    given = ImageCorrectedModel(scene.right_model, col_shift=6.0, row_shift=3.0)
    st = run_sparse_stage(
        scene.left, scene.right, scene.left_model, given, reference_dem=scene.truth_dem
    )
    lon, lat, h = _overlap_truth(scene, step=40)
    c0, r0 = scene.right_model.project(lon, lat, h)
    c1, r1 = st.right_model.project(lon, lat, h)
    assert np.max(np.hypot(c1 - c0, r1 - r0)) <= 0.1
    lon, lat, h = _overlap_truth(scene)
    assert st.height_range[0] <= h.min() and st.height_range[1] >= h.max()
    s = st.summary()
    assert s["matches"]["n"] == len(st.matches) and s["pointing"]["kind"] == "translation"
    assert set(s["seconds"]) == {"matching", "pointing", "terrain", "total"}


def test_height_pileup():
    rng = np.random.default_rng(1)
    good = rng.normal(500, 50, 10000)  # terrain well inside 0..1000
    assert not height_pileup(good, (0, 1000))["suspect"]
    stuck = np.concatenate([good[:7000], np.full(3000, 1.0)])  # 30 % at the lower bound
    r = height_pileup(stuck, (0, 1000))
    assert (
        r["suspect"] and r["low_share"] == pytest.approx(0.3, abs=0.01) and r["high_share"] < 0.01
    )


def seen_by_both(dem, left, right, step=4):
    """(lon, lat, h) of the cells of a truth MapRaster that both images see."""
    rows, cols = dem.data.shape
    cc, rr = np.meshgrid(np.arange(0, cols, step) + 0.5, np.arange(0, rows, step) + 0.5)
    x, y = dem.transform @ (cc, rr)
    h = dem.data[(rr - 0.5).astype(int), (cc - 0.5).astype(int)].astype(float)
    lon, lat = geodesy.crs_to_lonlat(x, y, dem.crs)
    ok = np.isfinite(h)
    for m in (left, right):
        c, r = m.project(lon, lat, h)
        ok &= (c >= 0) & (r >= 0) & (c <= m.width - 1) & (r <= m.height - 1)
    return lon[ok], lat[ok], h[ok]


@pytest.mark.slow
def test_real_rpc_geometry_over_steep_terrain_far_from_the_height_offset():
    L, R, left, right, truth = rpc_steep_pair()
    st = run_sparse_stage(L, R, left, right)
    lon, lat, h = seen_by_both(truth, left, right)
    lo, hi = st.height_range
    assert lo <= h.min() and hi >= h.max()
    # the terrain is ~1 100 m above the RPCs' height offset (1 295 m), outside the range found
    assert h.min() - left.height_off > 900 and lo > left.height_off + 500
    assert abs(st.pointing.parameters["col_shift"]) < 0.05  # no pointing error simulated


@pytest.mark.slow
def test_repeatable(scene):
    a = sparse_matches(scene.left, scene.right, scene.left_model, scene.right_model)
    b = sparse_matches(scene.left, scene.right, scene.left_model, scene.right_model)
    assert len(a) == len(b) and np.array_equal(a.col2, b.col2) and a.offset_cross == b.offset_cross


def test_zncc_scores_equal_direct_correlation_with_voids():
    """The batched FFT + box-sum ZNCC of the sparse refinement equals the direct per-shift
    ZNCC (mean-removed patches) to 1e-10, and is NaN exactly where a window holds a void."""
    rng = np.random.default_rng(4)
    n, half, search = 40, 7, 5
    w, k = 2 * half + 1, 2 * search + 1
    S = 100.0 + 20.0 * rng.normal(size=(n, w + k - 1, w + k - 1))
    T = S[:, 3 : 3 + w, 6 : 6 + w] + rng.normal(size=(n, w, w))
    S[0, 2, 2] = np.nan  # a void in one search window
    T[1, 4, 4] = np.nan  # a void in one template
    got = zncc_scores(T, S)
    want = np.full((n, k, k), np.nan)
    for dy in range(k):
        for dx in range(k):
            P = S[:, dy : dy + w, dx : dx + w]
            P = P - P.mean(axis=(1, 2), keepdims=True)
            Tc = T - T.mean(axis=(1, 2), keepdims=True)
            want[:, dy, dx] = (Tc * P).sum((1, 2)) / np.sqrt(
                (Tc * Tc).sum((1, 2)) * (P * P).sum((1, 2))
            )
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    assert np.isnan(got[0, :3, :3]).all() and not np.isnan(got[0, 3:, 3:]).any()
    assert np.isnan(got[1]).all()
    ok = np.isfinite(want)
    assert np.max(np.abs(got[ok] - want[ok])) < 1e-10
    assert (got[2:].reshape(n - 2, -1).argmax(1) == 3 * k + 6).all()  # the true shift wins


@pytest.mark.slow
def test_keypoints_on_two_threads_equal_the_serial_ones(scene):
    # the two images are detected concurrently when the budget allows: same matches
    a = sparse_matches(scene.left, scene.right, scene.left_model, scene.right_model, threads=1)
    b = sparse_matches(scene.left, scene.right, scene.left_model, scene.right_model, threads=2)
    assert len(a) > 20 and a.info["keypoints"] == b.info["keypoints"]
    for k in ("col1", "row1", "col2", "row2", "score"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
