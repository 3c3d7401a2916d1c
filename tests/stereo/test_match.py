"""Dense matching (stereo.match and its modules ncc, sgm, score, seed, window_stats, images):
Middlebury cones, synthetic sub-pixel shifts, vertical search, no-data, per-pixel ranges,
OpenCV SGBM conventions."""

import warnings

import cv2
import numpy as np
import pytest
import rasterio
from numpy.lib.stride_tricks import sliding_window_view as windows

from stereodem.core.errors import InputError
from stereodem.sensor.simulation.simulate import texture_path
from stereodem.stereo import score, window_stats
from stereodem.stereo.images import _image_and_finite, _percentiles
from stereodem.stereo.match import MatchResult, match_rectified, zncc_at
from stereodem.stereo.refine import _smooth_fill, refine_disparity
from stereodem.stereo.score import _zncc_left, _zncc_warped
from stereodem.stereo.seed import _fill_seed, _median_offset, _rounded_filled
from stereodem.stereo.sgm import _sgbm_padding, _to_uint8

# ----------------------------------------------------------------------------- data


@pytest.fixture(scope="module")
def cones(data_dir):
    d = data_dir / "cones"
    left = cv2.imread(str(d / "cones_left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(d / "cones_right.png"), cv2.IMREAD_GRAYSCALE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(d / "cones_disp_left.tif") as f:
            truth = f.read(1)
    occ = cv2.imread(str(d / "cones_occlusion.png"), cv2.IMREAD_GRAYSCALE)
    return left, right, truth, occ


def texture(x, y, seed=0, n=60):
    """Band-limited random texture evaluated at any (x, y): a sum of plane waves with
    frequencies 0.02-0.3 cycles/px, so that shifted images are exact (no resampling)."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(0.02, 0.3, n)
    th = rng.uniform(0, 2 * np.pi, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    out = np.zeros(np.broadcast(x, y).shape)
    for i in range(n):
        out += np.cos(2 * np.pi * f[i] * (np.cos(th[i]) * x + np.sin(th[i]) * y) + ph[i]) / np.sqrt(
            f[i]
        )
    return (100 + 10 * out).astype(np.float32)


@pytest.fixture(scope="module")
def grid():
    y, x = np.mgrid[0:200, 0:200].astype(float)
    return x, y


def shifted_pair(grid, a, b=0.0, v=0.0):
    """left = T(x, y); right such that left(x, y) ~ right(x - d, y - v), d = a + b x."""
    x, y = grid
    left = texture(x, y)
    right = texture((x + a) / (1 - b), y + v)
    return left, right, (a + b * x).astype(np.float32)


def rms(e):
    return float(np.sqrt(np.nanmean(e**2)))


# ----------------------------------------------------------------------------- cones


def cones_figures(result, truth, occ):
    nonocc = occ == 255  # Middlebury: white = non-occluded (GT is 0 only where occluded)
    d = result.disparity
    valid = np.isfinite(d)
    err = np.abs(np.where(valid, d, np.inf) - truth)
    bad_all = float(np.mean((err > 2)[nonocc]))  # invalid counted as errors
    density = float(np.mean(valid[nonocc]))
    bad_valid = float(np.mean((err > 2)[nonocc & valid]))
    return bad_all, density, bad_valid


def test_cones_occlusion_encoding(cones):
    _, _, truth, occ = cones
    assert set(np.unique(occ)) == {0, 255}
    assert np.all(occ[truth == 0] == 0)  # unknown truth is marked occluded
    assert 0.1 < np.mean(occ == 0) < 0.2  # occlusions are the minority
    assert truth.max() <= 60


@pytest.mark.parametrize(
    "kwargs, max_bad, min_density, max_bad_valid",
    [
        # measured: bad 13.4 %, density 89.9 %, bad among valid 3.7 %
        (dict(matcher="ncc", levels=0), 0.145, 0.88, 0.045),
        # measured (2 levels, margin 2): bad 23.1 %, density 79.8 %, bad among valid 3.5 %
        (dict(matcher="ncc"), 0.245, 0.78, 0.045),
        # measured: bad 5.2 %, density 97.4 %, bad among valid 2.7 %
        (dict(matcher="sgm"), 0.06, 0.96, 0.035),
    ],
)
def test_cones_error_rate(cones, kwargs, max_bad, min_density, max_bad_valid):
    left, right, truth, occ = cones
    result = match_rectified(left, right, (0, 60), **kwargs)
    assert isinstance(result, MatchResult)
    assert result.disparity.dtype == np.float32 and result.score.dtype == np.float32
    bad, density, bad_valid = cones_figures(result, truth, occ)
    assert bad <= max_bad
    assert density >= min_density
    assert bad_valid <= max_bad_valid


def test_cones_score_layer(cones):
    left, right, _, _ = cones
    for matcher in ("ncc", "sgm"):
        r = match_rectified(left, right, (0, 60), matcher=matcher, levels=0)
        s = r.score[np.isfinite(r.score)]
        assert s.size > 0.8 * r.score.size
        assert s.min() >= -1.0001 and s.max() <= 1.0001
        # valid matches correlate well
        assert np.nanmedian(r.score[np.isfinite(r.disparity)]) > 0.8


# ----------------------------------------------------------------------------- sub-pixel


@pytest.mark.parametrize("levels", [0, None])
@pytest.mark.parametrize("a, b", [(3.3, 0.0), (2.0, 0.03)])
def test_synthetic_subpixel(grid, a, b, levels):
    left, right, truth = shifted_pair(grid, a, b)
    r = match_rectified(left, right, (0, 12), levels=levels)
    err = r.disparity - truth
    assert np.isfinite(err).mean() > 0.9  # measured 0.92 (border = window + shift)
    assert rms(err) < 0.08  # measured 0.060 (const), 0.065 (ramp)
    assert np.nanmax(np.abs(err)) < 0.5


def test_pixel_locking_of_parabola(grid):
    """Parabola fit biases towards integers: measured -0.028 px at fraction 0.3 and +0.028
    at 0.7 (texture above); the V fit overshoots (+0.049 / -0.049)."""
    biases = {}
    for frac in (0.3, 0.7):
        left, right, truth = shifted_pair(grid, 3 + frac)
        for method in ("parabola", "vfit"):
            r = match_rectified(left, right, (0, 8), levels=0, subpixel=method)
            biases[method, frac] = float(np.nanmean(r.disparity - truth))
    assert -0.04 < biases["parabola", 0.3] < -0.01
    assert 0.01 < biases["parabola", 0.7] < 0.04
    assert biases["vfit", 0.3] > 0.02 and biases["vfit", 0.7] < -0.02
    assert abs(biases["parabola", 0.3]) < abs(biases["vfit", 0.3])


# ----------------------------------------------------------------------------- vertical


@pytest.mark.parametrize("v", [1.0, -1.0])
def test_vertical_search(grid, v):
    left, right, truth = shifted_pair(grid, 3.3, v=v)
    plain = match_rectified(left, right, (0, 8), levels=0)
    r = match_rectified(left, right, (0, 8), levels=0, vertical_search=1)
    assert plain.vertical is None
    assert r.vertical.dtype == np.float32
    ok = np.isfinite(r.disparity)
    assert ok.mean() > 0.9
    assert np.array_equal(ok, np.isfinite(r.vertical))
    assert abs(np.median(r.vertical[ok]) - v) < 0.02
    assert np.mean(np.abs(r.vertical[ok] - v) < 0.25) > 0.95
    assert rms(r.disparity - truth) < 0.08
    # the score improves over the search without vertical offsets
    assert np.nanmedian(r.score) > np.nanmedian(plain.score) + 0.05


def test_vertical_search_coarse_to_fine(grid):
    left, right, truth = shifted_pair(grid, 3.3, v=1.0)
    r = match_rectified(left, right, (0, 12), vertical_search=1)
    ok = np.isfinite(r.disparity)
    assert ok.mean() > 0.9
    assert abs(np.median(r.vertical[ok]) - 1.0) < 0.02


# ----------------------------------------------------------------------------- no-data


def test_nodata_is_invalid_and_does_not_contaminate(grid):
    left, right, truth = shifted_pair(grid, 3.3)
    ref = match_rectified(left, right, (0, 8), levels=0)
    left_nd = left.copy()
    right_nd = right.copy()
    left_nd[80:100, 80:100] = np.nan
    right_nd[140:160, 40:60] = np.nan
    r = match_rectified(left_nd, right_nd, (0, 8), levels=0)
    h = 3  # half window (7x7)
    assert np.all(np.isnan(r.disparity[80 - h : 100 + h, 80 - h : 100 + h]))
    assert np.all(np.isnan(r.score[80:100, 80:100]))
    # left pixels whose right window (x - d) touches the right no-data
    assert np.all(np.isnan(r.disparity[140 - h : 160 + h, 44 - h : 63 + h]))
    # away from the no-data (window + disparity + sub-pixel neighbour), results are unchanged
    far = np.ones(left.shape, bool)
    far[80 - 2 * h - 10 : 100 + 2 * h + 10, 80 - 2 * h - 10 : 100 + 2 * h + 10] = False
    far[140 - 2 * h - 10 : 160 + 2 * h + 10, 40 - 2 * h - 10 : 60 + 2 * h + 20] = False
    a, b = ref.disparity[far], r.disparity[far]
    assert np.array_equal(np.isnan(a), np.isnan(b))
    assert np.nanmax(np.abs(a - b)) < 1e-3


@pytest.mark.parametrize("matcher", ["ncc", "sgm"])
def test_nodata_pyramid_and_sgm(grid, matcher):
    left, right, truth = shifted_pair(grid, 3.3)
    left[:, :30] = np.nan  # a no-data margin, as outside a resampled footprint
    r = match_rectified(left, right, (0, 12), matcher=matcher)
    assert np.all(np.isnan(r.disparity[:, :30]))
    ok = np.isfinite(r.disparity[:, 40:])
    assert ok.mean() > 0.85
    tol = 0.08 if matcher == "ncc" else 0.25  # SGBM: 1/16 px output, no sub-pixel fit
    assert rms(r.disparity[:, 40:] - truth[:, 40:]) < tol


# ----------------------------------------------------------------------------- ranges


@pytest.mark.parametrize("matcher", ["ncc", "sgm"])
def test_negative_disparity_range(grid, matcher):
    left, right, truth = shifted_pair(grid, -6.3)
    r = match_rectified(left, right, (-12, 3), matcher=matcher)
    ok = np.isfinite(r.disparity)
    assert ok.mean() > 0.85
    # SGBM: 1/16 px output and its own interpolation, measured median -6.125
    assert abs(np.median(r.disparity[ok]) + 6.3) < (0.05 if matcher == "ncc" else 0.25)
    assert np.nanmedian(r.score[ok]) > 0.95
    # truth outside the requested range: far fewer and poorly correlated matches
    # (measured ncc: 24 % valid, median score 0.61; sgm: 64 % valid, median score 0.41)
    r2 = match_rectified(left, right, (0, 12), matcher=matcher)
    ok2 = np.isfinite(r2.disparity)
    assert ok2.mean() < (0.3 if matcher == "ncc" else 0.7)
    assert np.nanmedian(r2.score[ok2]) < (0.7 if matcher == "ncc" else 0.5)


def test_coarse_to_fine_on_ramp(grid):
    left, right, truth = shifted_pair(grid, 2.0, 0.03)
    for levels in (1, 2):
        r = match_rectified(left, right, (0, 40), levels=levels)
        assert r.info["levels"] == levels
        assert np.isfinite(r.disparity).mean() > 0.8  # measured 0.85 / 0.83
        assert rms(r.disparity - truth) < 0.09  # measured 0.079 / 0.081


def test_sgm_recovers_ramp_with_opencv_conventions(grid):
    left, right, truth = shifted_pair(grid, 2.0, 0.03)
    r = match_rectified(left, right, (0, 40), matcher="sgm")  # 41 -> numDisparities 48
    ok = np.isfinite(r.disparity)
    assert ok.mean() > 0.9  # left border kept thanks to the padding
    # OpenCV blanks x < minDisparity + numDisparities: the padding gives every column whose
    # match lies in the right image a disparity (d = 2 + 0.03 x: from x = 2 on) ...
    assert ok[:, 2:20].mean() > 0.8
    assert ok[:, 2].mean() > 0.8
    # ... and none to the columns whose match falls outside it (onto the padding; measured:
    # 1 of 200 cells of column 0 kept, a blunder of d = 0 whose match is inside)
    assert ok[:, 0].mean() < 0.05
    x = np.arange(ok.shape[1])[None, :]
    with np.errstate(invalid="ignore"):
        assert not np.any(x - r.disparity < -0.5)
    assert rms(r.disparity - truth) < 0.25
    # fractional output (1/16 px), not integers only
    assert np.mean(r.disparity[ok] != np.round(r.disparity[ok])) > 0.5


@pytest.mark.parametrize("sign", [1, -1])
def test_sgm_gives_no_match_outside_the_right_image(grid, sign):
    # a one-sided range (5..20 px, or -20..-5 with the images swapped): the first (last) 5
    # columns cannot have a match, and every match found lies inside the right image
    left, right, truth = shifted_pair(grid, 12.0)
    if sign < 0:
        left, right = right, left
    r = match_rectified(left, right, (5, 20) if sign > 0 else (-20, -5), matcher="sgm")
    d = r.disparity
    ok = np.isfinite(d)
    w = d.shape[1]
    x = np.arange(w)[None, :]
    with np.errstate(invalid="ignore"):
        assert not np.any(x - d < -0.5) and not np.any(x - d > w - 0.5)
    edge = ok[:, :5] if sign > 0 else ok[:, -5:]
    assert not edge.any()
    # the columns whose match is inside are matched (12 px: from x = 12 on, or up to w - 13)
    inside = ok[:, 12:40] if sign > 0 else ok[:, w - 40 : w - 12]
    assert inside.mean() > 0.9
    assert abs(np.median(d[ok]) - sign * 12.0) < 0.25


@pytest.mark.parametrize("rng", [(40, 41), (90, 100), (-45, -44), (-100, -90)])
def test_sgm_on_a_tile_where_no_column_can_match(rng):
    # 40 columns: every match of these ranges falls outside the right image; the result is
    # all NaN, without a "match" on the padding and without OpenCV's error on an empty
    # region (found in session 21 when the padding became what the columns need)
    g = np.random.default_rng(1)
    left, right = (g.random((30, 40)).astype(np.float32) * 100 for _ in range(2))
    r = match_rectified(left, right, rng, matcher="sgm")
    assert r.disparity.shape == left.shape and np.isnan(r.disparity).all()


def test_sgm_on_narrow_tiles_keeps_its_contract():
    # tiles with few columns that can match (w = 33, range 32..32: one column): OpenCV
    # refuses a pair not wider than minDisparity + numDisparities + blockSize // 2, so the
    # padding grows; every result is in range and its match inside the right image
    g = np.random.default_rng(2)
    for w in (2, 5, 33):
        left, right = (g.random((12, w)).astype(np.float32) * 100 for _ in range(2))
        x = np.arange(w)[None, :]
        for lo in (-40, -33, -5, 0, 4, 31, 32, 40):
            for span in (0, 15, 16):
                hi = lo + span
                d = match_rectified(left, right, (lo, hi), matcher="sgm").disparity
                assert d.shape == left.shape
                with np.errstate(invalid="ignore"):
                    assert not np.any((d < lo) | (d > hi + 0.5))
                    assert not np.any((x - d < -0.5) | (x - d > w - 0.5))


@pytest.mark.parametrize("levels", [0, 1])
def test_ncc_range_wider_than_the_tile(levels):
    # a search range wider than the tile (Pleiades over mountains without a seed DEM: +-600
    # px on a 576 px tile) has offsets where no pixel has a partner in the other image; the
    # right-view map's bookkeeping sliced those into mismatched shapes (ValueError, the tile
    # failed); every offset is now searched and the truth (-37 px) is found
    y, x = np.mgrid[0:48, 0:200].astype(float)
    left = texture(x, y)
    right = texture(x - 37.0, y)  # left(x) = right(x + 37): d = -37
    r = match_rectified(left, right, (-300, 300), levels=levels)
    d = r.disparity
    ok = np.isfinite(d)
    assert ok.mean() > 0.5
    assert np.median(d[ok]) == pytest.approx(-37.0, abs=0.1)
    with np.errstate(invalid="ignore"):
        assert not np.any((x - d < -0.5) | (x - d > 199.5))


def test_ncc_without_lr_check_on_a_pyramid(grid):
    # lr_tolerance=None (no left-right check) with coarse levels: the levels' seeds are still
    # left-right checked at 1 px (max(None, 1.0) raised a TypeError before); the result keeps
    # every match the check would have dropped
    left, right, truth = shifted_pair(grid, 12.0)
    free = match_rectified(left, right, (0, 40), levels=2, lr_tolerance=None)
    checked = match_rectified(left, right, (0, 40), levels=2)
    ok = np.isfinite(free.disparity)
    assert ok.mean() > 0.8
    assert np.all(np.isfinite(checked.disparity) <= ok)
    assert rms(free.disparity[ok] - truth[ok]) < 0.2


def test_ncc_on_narrow_tiles_keeps_its_contract():
    # narrow and short tiles, ranges beyond their width on either side or spanning them,
    # pyramid or not: no error, every result in range and its match inside the right image
    g = np.random.default_rng(5)
    for w, h in ((3, 9), (17, 8), (33, 40)):
        left, right = (g.random((h, w)).astype(np.float32) * 100 for _ in range(2))
        x = np.arange(w)[None, :]
        for lo, hi in ((-40, -30), (-5, 5), (3, 12), (20, 40), (-70, 70)):
            for levels in (0, None):
                d = match_rectified(left, right, (lo, hi), levels=levels).disparity
                assert d.shape == left.shape
                with np.errstate(invalid="ignore"):
                    assert not np.any((d < lo - 0.5) | (d > hi + 0.5))
                    assert not np.any((x - d < -0.5) | (x - d > w - 0.5))


def test_sgm_keeps_to_the_requested_range(grid):
    # truth 12 px, range 0..10: OpenCV searches 0..15 (16 disparities) and finds 12 in most
    # of the image; what lies beyond hi + 0.5 is outside the range asked for
    left, right, truth = shifted_pair(grid, 12.0)
    r = match_rectified(left, right, (0, 10), matcher="sgm")
    d = r.disparity[np.isfinite(r.disparity)]
    assert np.all(d <= 10.5)
    # the same pair in a range that holds the truth is matched
    r2 = match_rectified(left, right, (0, 15), matcher="sgm")
    assert np.isfinite(r2.disparity).mean() > 0.8


@pytest.mark.parametrize(
    "lo, hi, nd, pads",
    [(0, 63, 64, (64, 0)), (8, 63, 64, (64, 0)), (-55, 54, 112, (57, 55)), (-45, -22, 32, (0, 23))],
)
def test_sgbm_padding_covers_the_columns_that_can_match(lo, hi, nd, pads):
    assert _sgbm_padding(lo, hi, nd) == pads
    left, right = pads
    w = 500
    # OpenCV's computed columns of the padded pair, in the tile's columns
    first, end = lo + nd - left, w + right + min(lo, 0)
    # every column with a possible match (0 <= x - d < w for a d in lo..hi) is computed,
    # and with the padding one column narrower on either side, one of them would not be
    assert first <= max(lo, 0) and end >= w + min(hi, 0)
    assert left == 0 or first + 1 > max(lo, 0)
    assert right == 0 or end - 1 < w + min(hi, 0)


def test_per_pixel_range_maps(grid):
    left, right, truth = shifted_pair(grid, 2.0, 0.03)
    seed = truth + 1.0  # a seed disparity map 1 px off, +/- 3 px
    r = match_rectified(left, right, (seed - 3, seed + 3))
    assert np.isfinite(r.disparity).mean() > 0.8
    assert rms(r.disparity - truth) < 0.08  # measured 0.066
    # a range that excludes the truth: results stay inside each pixel's own range, and only
    # secondary correlation peaks of the texture remain (measured 10.8 % of pixels)
    r2 = match_rectified(left, right, (seed + 2, seed + 5))
    ok2 = np.isfinite(r2.disparity)
    assert ok2.mean() < 0.15
    d2 = r2.disparity[ok2]
    assert np.all((d2 >= seed[ok2] + 1.5) & (d2 <= seed[ok2] + 5.5))


def test_zncc_at_truth_is_high(grid):
    left, right, truth = shifted_pair(grid, 3.0)
    s = zncc_at(left, right, truth)
    assert np.nanmedian(s) > 0.99
    s_wrong = zncc_at(left, right, truth + 2)
    assert np.nanmedian(s_wrong) < 0.8


def test_texture_mask(grid):
    left, right, _ = shifted_pair(grid, 3.0)
    left[50:120, 50:120] = 100.0  # flat patch
    right[50:120, 47:117] = 100.0
    r = match_rectified(left, right, (0, 8), levels=0)
    assert np.all(np.isnan(r.disparity[60:110, 60:110]))
    assert np.all(np.isnan(r.score[60:110, 60:110]))


def test_input_errors(grid):
    left, right, _ = shifted_pair(grid, 3.0)
    with pytest.raises(InputError):
        match_rectified(left, right[:, :-1], (0, 8))
    with pytest.raises(InputError):
        match_rectified(left, right, (0, 8), matcher="census")
    with pytest.raises(InputError):
        match_rectified(left, right, (8, 0))
    with pytest.raises(InputError):
        match_rectified(left, right, (0, 8), window=6)
    with pytest.raises(InputError):
        match_rectified(left, right, (0, 8), matcher="sgm", vertical_search=1)
    with pytest.raises(InputError):
        match_rectified(np.full_like(left, np.nan), right, (0, 8))


# ----------------------------------------------------------------------------- refinement


def test_smooth_fill_bridges_wide_holes():
    """A hole much wider than the kernel takes the surrounding ramp, not the map's median."""
    yy, xx = np.mgrid[0:200, 0:200].astype(np.float32)
    d = 0.05 * xx
    holed = d.copy()
    holed[:, 120:170] = np.nan  # 50 px wide, sigma 3
    out = _smooth_fill(holed, 3.0)
    assert np.isfinite(out).all()
    err = np.abs(out - d)[:, 120:170]
    assert np.median(err) < 1.0, np.median(err)  # the median fill is 3.5 px off there
    assert np.abs(out - d)[:, 20:100].max() < 0.05  # away from the hole: the plain smoothing


def _smooth_fill_whole_image(d, sigma):
    """The hole-filling smoothing with every pass on the whole image (the plain form)."""
    ok = np.isfinite(d)
    z, m = np.where(ok, d, 0).astype(np.float32), ok.astype(np.float32)
    out, s = np.full(d.shape, np.nan, np.float32), float(sigma)
    while True:
        num = cv2.GaussianBlur(z, (0, 0), s)
        den = cv2.GaussianBlur(m, (0, 0), s)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(np.isfinite(out), out, np.where(den > 0.05, num / den, np.nan))
        if np.isfinite(out).all() or s > max(d.shape):
            break
        s *= 2.0
    return np.where(np.isfinite(out), out, np.nanmedian(d[ok])).astype(np.float32)


@pytest.mark.parametrize("holes", ["edges", "corner", "interior", "everywhere"])
def test_smooth_fill_on_the_holes_box_equals_the_whole_image_passes(holes):
    """The wider passes run on the bounding box of the holes left (plus the kernel's reach):
    the same fill as whole-image passes, to float32 rounding (OpenCV's vector and scalar
    column tails sum in different orders)."""
    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[0:300, 0:347].astype(np.float32)
    d = (0.05 * xx - 0.02 * yy + rng.normal(0, 0.2, xx.shape)).astype(np.float32)
    if holes == "edges":  # strips along two sides, as at a tile's no-data edges
        d[:, 330:] = np.nan
        d[:23] = np.nan
    elif holes == "corner":
        d[250:, 290:] = np.nan
    elif holes == "interior":
        d[100:160, 120:200] = np.nan
    else:
        d[rng.random(d.shape) < 0.3] = np.nan
        d[:, :40] = np.nan
    got, want = _smooth_fill(d, 3.0), _smooth_fill_whole_image(d, 3.0)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-5)


@pytest.fixture(scope="module")
def wavy_pair():
    """Rectified pair of an exact band-limited texture over a disparity with sub-window
    relief (4 cycles per 40 px, 1 px amplitude) on a ramp."""
    yy, xx = np.mgrid[0:160, 0:240].astype(np.float64)

    def disp(x, y):
        return 3.0 + 0.01 * x + 1.0 * np.sin(2 * np.pi * x / 40.0)

    left = texture(xx, yy, seed=3)
    # right(x - d(x)) = left(x): sample the texture at the inverse map (fixed point)
    xr = xx.copy()
    for _ in range(30):
        xr = xx + disp(xr, yy)
    right = texture(xr, yy, seed=3)
    return left, right, disp(xx, yy).astype(np.float32)


def test_refine_keeps_confirmed_detail_and_drops_noise(wavy_pair):
    """The detail gain is ~1 when the first pass resolved real sub-window relief, and small
    when its sub-window structure is noise on a smooth surface (refined error then lower
    than with the first pass's detail kept)."""
    left, right, truth = wavy_pair
    inner = np.s_[20:-20, 20:-20]
    # real relief, resolved by the first pass
    d, s, g = refine_disparity(left, right, truth, sigma=1.0, window=7)
    assert g > 0.8, g
    assert np.nanmedian(np.abs(d - truth)[inner]) < 0.1

    # smooth surface (a ramp), first pass = truth + noise correlated at the window scale
    yy, xx = np.mgrid[0:160, 0:240].astype(np.float64)
    ramp = (3.0 + 0.01 * xx).astype(np.float32)
    left2 = texture(xx, yy, seed=4)
    xr = xx + 3.0 + 0.01 * xx
    for _ in range(30):
        xr = xx + 3.0 + 0.01 * xr
    right2 = texture(xr, yy, seed=4)
    rng = np.random.default_rng(1)
    noise = cv2.GaussianBlur(rng.normal(0, 1, ramp.shape).astype(np.float32), (0, 0), 2.0)
    first = ramp + 0.5 * noise / noise.std()
    d0, _, g0 = refine_disparity(left2, right2, first, sigma=1.0, window=7)
    d1, _, g1 = refine_disparity(left2, right2, first, sigma=1.0, window=7, detail_gain=1.0)
    assert g1 == 1.0 and g0 < 0.5, g0
    e0, e1 = (np.nanstd((x - ramp)[inner]) for x in (d0, d1))
    assert e0 < 0.8 * e1, (e0, e1)


def test_rounded_seed_is_the_rounded_float_median():
    """The score layer's warp seed (uint8 median on rounded values when the span allows)
    equals rint of the float32 5x5 median of the hole-filled map, both branches."""
    rng = np.random.default_rng(3)
    for span in (60.0, 900.0):  # uint8 branch, float32 branch
        d = (np.round(rng.uniform(-span / 3, span, (70, 90)) * 16) / 16).astype(np.float32)
        d[rng.random(d.shape) < 0.05] = np.nan
        d[10, :] = np.nan  # a whole row of holes
        ref = np.rint(_fill_seed(d, 0.0))
        base, med = _median_offset(*_rounded_filled(d))
        assert np.array_equal(np.add(med, np.float32(base), dtype=np.float32), ref)


def test_sgm_stretch_and_score_match_textbook_forms():
    """The 8-bit stretch (by row blocks) and the score layer equal their textbook forms:
    round-half-up of the 1-99 % stretch in float64 (ties: see
    test_stretch_rounds_ties_up_and_saturates), and the windowed ZNCC of the left image with
    the right one gathered at the rounded median-filtered disparity."""
    rng = np.random.default_rng(4)
    left = rng.normal(100, 20, (200, 1500)).astype(np.float32)  # 3 row blocks (87 rows)
    right = rng.normal(100, 20, (200, 1500)).astype(np.float32)
    left[5, 7] = np.nan
    l8, r8 = _to_uint8(left, right)
    v = np.concatenate([left.ravel(), right.ravel()])
    lo, hi = np.percentile(v[np.isfinite(v)][:: max(1, v.size // 400_000)], [1.0, 99.0])
    ref = np.clip((right.astype(np.float64) - lo) * (255.0 / (hi - lo)) + 0.5, 0, 255)
    assert np.array_equal(r8, ref.astype(np.uint8))
    assert l8[5, 7] == 0 and np.array_equal(
        np.delete(l8.ravel(), 5 * 1500 + 7),
        np.delete(
            np.clip((left.astype(np.float64) - lo) * (255.0 / (hi - lo)) + 0.5, 0, 255).ravel(),
            5 * 1500 + 7,
        ).astype(np.uint8),
    )
    left, right = left[:, :60].copy(), right[:, :60].copy()
    left[5, 7] = 1.0
    d = rng.uniform(0, 4, left.shape).astype(np.float32)
    s = zncc_at(left, right, d)
    seed = np.rint(_fill_seed(d, 0.0)).astype(int)
    cols = np.arange(60)[None, :] - seed
    warped = np.where(
        (cols >= 0) & (cols < 60), np.take_along_axis(right, np.clip(cols, 0, 59), axis=1), np.nan
    )
    a = windows(left.astype(np.float64), (7, 7))
    b = windows(warped.astype(np.float64), (7, 7))
    a = a - a.mean(axis=(-2, -1), keepdims=True)
    b = b - b.mean(axis=(-2, -1), keepdims=True)
    ref = (a * b).sum(axis=(-2, -1)) / np.sqrt(
        (a * a).sum(axis=(-2, -1)) * (b * b).sum(axis=(-2, -1))
    )
    inner = s[3:-3, 3:-3]
    assert np.isnan(s[:3]).all() and np.isnan(s[:, -3:]).all()
    both = np.isfinite(ref)
    assert np.array_equal(np.isfinite(inner), both)
    assert np.max(np.abs(inner[both] - ref[both])) < 1e-4


def test_fast_percentiles_equal_numpy_bit_for_bit():
    """The 8-bit stretch's percentiles (rank selection between sub-sample bounds) are
    ``np.percentile``'s, bit for bit: continuous, tied, sorted and float64 samples."""
    rng = np.random.default_rng(7)
    samples = [
        rng.normal(100, 20, 400_000).astype(np.float32),
        rng.integers(0, 40, 123_457).astype(np.float32),  # many ties around the ranks
        np.sort(rng.exponential(1.0, 250_001)).astype(np.float32),
        rng.uniform(-1e6, 1e6, 99_999),
        rng.normal(0, 1, 700).astype(np.float32),  # small: NumPy itself
    ]
    for v in samples:
        for q in ((1.0, 99.0), (2.0, 98.0), (0.1, 99.9), (50.0,)):
            got, ref = _percentiles(v, q), np.percentile(v, q)
            assert got.dtype == ref.dtype and np.array_equal(got, ref), (v.dtype, v.size, q)


def _textbook_zncc(left, right, d, window=7):
    """Float64 ZNCC of each left window with the right image gathered at the rounded
    median-filtered, hole-filled disparity (NaN outside the image and at no-data), NaN at the
    image border and where ``d`` is not finite."""
    h, w = left.shape
    seed = np.rint(_fill_seed(d, 0.0)).astype(int)
    cols = np.arange(w)[None, :] - seed
    warped = np.where(
        (cols >= 0) & (cols < w), np.take_along_axis(right, np.clip(cols, 0, w - 1), axis=1), np.nan
    )
    a = windows(left.astype(np.float64), (window, window))
    b = windows(warped.astype(np.float64), (window, window))
    a = a - a.mean(axis=(-2, -1), keepdims=True)
    b = b - b.mean(axis=(-2, -1), keepdims=True)
    inner = (a * b).sum(axis=(-2, -1)) / np.sqrt(
        (a * a).sum(axis=(-2, -1)) * (b * b).sum(axis=(-2, -1))
    )
    r = window // 2
    out = np.full((h, w), np.nan)
    out[r:-r, r:-r] = inner
    out[~np.isfinite(d)] = np.nan
    return out


@pytest.mark.parametrize("band_bytes, score_rows", [(None, None), (4096, None), (None, 4)])
def test_zncc_shortcuts_give_the_general_score_and_the_textbook_zncc(
    band_bytes, score_rows, monkeypatch
):
    """The score layer's shortcuts for a right image without NaN (no NaN scan, the warp
    zero-filled outside the image, the windows reaching outside located on the column strips
    where the warp can leave the image, invalid disparities set by index) give the general
    path's score bit for bit (with a left image without NaN as well: the fused band of
    ``_zncc_band_finite``, border and outside windows set NaN once at the end), and both equal
    the float64 textbook ZNCC to 1e-4 with the same
    NaN cells: no-data (NaN patches in either image), image border, windows reaching outside
    the image (positive, negative and mixed disparities; strips that meet on a narrow image),
    invalid disparities.  ``band_bytes=4096``: the element-wise passes by bands of 11 rows or
    fewer (several bands and their edges in these small images); ``score_rows=4``: the score
    layer by row bands of 4 rows and their halos (band edges everywhere, NaN patches across
    them), on 1 and 3 threads, bit for bit."""
    if band_bytes:
        bands = window_stats._row_bands
        monkeypatch.setattr(window_stats, "_row_bands", lambda shape: bands(shape, band_bytes))
    if score_rows:
        monkeypatch.setattr(score, "SCORE_BAND_ROWS", score_rows)

    rng = np.random.default_rng(5)
    cases = (
        ((40, 90), (-6, 9)),
        ((30, 70), (0, 12)),
        ((30, 70), (-12, 0)),
        ((30, 70), (9, 9)),  # constant: the warp leaves the image right at the strips' edges
        ((30, 70), (-9, -9)),
        ((25, 16), (-9, 9)),
    )
    for shape, (dlo, dhi) in cases:
        left = rng.normal(100, 20, shape).astype(np.float32)
        right = rng.normal(100, 20, shape).astype(np.float32)
        d = rng.uniform(dlo, dhi, shape).astype(np.float32)
        d[rng.random(shape) < 0.05] = np.nan
        d[3, :] = np.nan  # a row without a valid disparity (the column-wise fill)
        lw = _zncc_left(left, 7)
        fast = _zncc_warped(lw, right, d, right_finite=True)
        general = _zncc_warped(lw, right, d, right_finite=False)
        assert np.array_equal(fast, general, equal_nan=True), shape
        assert np.array_equal(zncc_at(left, right, d), fast, equal_nan=True)
        if score_rows:  # the bands on threads: the same values
            threaded = _zncc_warped(lw, right, d, right_finite=True, threads=3)
            assert np.array_equal(threaded, fast, equal_nan=True)
        for lnan, rnan in ((False, False), (True, False), (False, True)):
            lt, rt = left.copy(), right.copy()
            if lnan:
                lt[10:13, 5:9] = np.nan
            if rnan:
                rt[12:15, 8:11] = np.nan
            s = zncc_at(lt, rt, d)
            ref = _textbook_zncc(lt, rt, d)
            both = np.isfinite(ref)
            assert np.array_equal(np.isfinite(s), both), (shape, lnan, rnan)
            assert np.max(np.abs(s[both] - ref[both]), initial=0) < 1e-4


def test_stretch_with_known_finite_images_is_the_scanned_one():
    """``_to_uint8``'s ``finite`` flags (NaN scans skipped) do not change the stretch."""
    rng = np.random.default_rng(6)
    left = rng.normal(100, 20, (50, 300)).astype(np.float32)
    right = rng.normal(90, 25, (50, 300)).astype(np.float32)
    a = _to_uint8(left, right)
    b = _to_uint8(left, right, finite=(True, True))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


def test_stretch_rounds_ties_up_and_saturates():
    """The stretch's documented rounding, half up (ties are common on integer images: here
    the percentiles 0 and 255 make the scale exactly 1, so x.5 values are ties); clipped to
    0..255, +inf -> 255, -inf -> 0, NaN -> the value of the 1 % percentile (0)."""
    a = np.zeros((40, 50), np.float32)
    a[20:] = 255.0  # 1 % -> 0, 99 % -> 255: scale 1
    a[0, :6] = [2.5, 3.5, 2.4999998, 2.5000002, -7.0, 300.0]
    a[1, :3] = [np.inf, -np.inf, np.nan]
    b8, _ = _to_uint8(a, a)
    assert list(b8[0, :6]) == [3, 4, 2, 3, 0, 255]
    assert list(b8[1, :3]) == [255, 0, 0]
    assert np.array_equal(b8[20:], np.full((20, 50), 255, np.uint8))


def _texture_pair():
    """A 400 x 300 pair cut from the bundled Landsat texture (its fully valid centre, x1.25
    bicubic), 1 DN of noise in each image, ``left(x) = right(x + 3)`` (disparity -3)."""
    with rasterio.open(texture_path()) as f:
        tex = f.read().astype(np.float32).mean(axis=0)[260:580, 100:420]  # fully valid
    tex = cv2.resize(tex, (400, 400), interpolation=cv2.INTER_CUBIC)
    rng = np.random.default_rng(0)
    left = tex[:, 5:305] + rng.normal(0, 1, (400, 300)).astype(np.float32)
    right = tex[:, 2:302] + rng.normal(0, 1, (400, 300)).astype(np.float32)
    return left, right


def test_score_keeps_its_digits_beside_a_brightness_step():
    """The score layer centres each row band by its own level: where a 12-bit scene's
    brightness steps by 2000 DN between bands (a bright half), the score keeps the float64
    ZNCC to 1e-3 outside the band holding the step (centred by the image's mean alone, float32
    ``E[x^2] - E[x]^2`` lost up to 0.1 there); inside that band the step itself limits it."""
    left, right = _texture_pair()
    left[200:] += 2000.0
    right[200:] += 2000.0
    d = np.full(left.shape, 3.0, np.float32)
    s, ref = zncc_at(left, right, d), _textbook_zncc(left, right, d)
    assert np.array_equal(np.isfinite(s), np.isfinite(ref))
    step_band = slice(128 - 4, 256 + 4)  # SCORE_BAND_ROWS = 128, and the window's reach
    away = np.ones(400, bool)
    away[step_band] = False
    ok = np.isfinite(ref) & away[:, None]
    assert np.abs(s[ok] - ref[ok]).max() < 1e-3
    assert np.isfinite(s[away]).mean() > 0.9


def test_score_keeps_its_digits_when_the_images_sit_at_different_levels():
    """The right image 3000 DN above the left (two sensors' gains and offsets, 16-bit data):
    each band's warped right side is centred by the right image's level in those rows, and
    the score keeps the float64 ZNCC to 1e-3 (centred by the left's level, it was off by up
    to 1.0); the NCC matcher centres each image by its own mean, so its disparities do not
    depend on the offset."""
    left, right = _texture_pair()
    d = np.full(left.shape, 3.0, np.float32)
    s, ref = zncc_at(left, right + 3000, d), _textbook_zncc(left, right + 3000, d)
    ok = np.isfinite(ref)
    assert np.array_equal(np.isfinite(s), ok) and ok.mean() > 0.9
    assert np.abs(s[ok] - ref[ok]).max() < 1e-3
    # left(x) = right(x + 3): disparity -3; the right image + 3000 DN only loses the digits
    # float32 has at 3000 (centred by the left's mean, 0.1 % of the disparities moved by
    # 0.9 px or more, up to 3.9, and the scores by up to 0.95)
    a = match_rectified(left, right, (-6, 0), levels=0)
    b = match_rectified(left, right + 3000, (-6, 0), levels=0)
    assert np.array_equal(np.isfinite(a.disparity), np.isfinite(b.disparity))
    ok = np.isfinite(a.disparity)
    assert ok.mean() > 0.6
    assert np.abs(a.disparity[ok] - b.disparity[ok]).max() < 0.01
    assert np.abs(a.score[ok] - b.score[ok]).max() < 0.005


def test_image_mean_replaces_the_finite_scan_only_when_it_proves_it():
    """``_image_and_finite(..., mean=True)``: a finite float32 mean proves every pixel finite
    (it is then ``np.mean`` itself, the score layer's centring constant); a NaN, an infinity
    or a sum that overflows (finite pixels of 3e38) falls back to the scan."""
    rng = np.random.default_rng(12)
    a = rng.normal(100, 20, (30, 40)).astype(np.float32)
    img, finite, m = _image_and_finite(a, "a", mean=True)
    assert finite and m is not None and m == np.mean(a) and m.dtype == np.float32
    assert _image_and_finite(a, "a")[1:] == (True, None)
    for bad in (np.nan, np.inf, -np.inf):
        b = a.copy()
        b[3, 4] = bad
        assert _image_and_finite(b, "b", mean=True)[1:] == (False, None)
    big = np.full((30, 40), 3e38, np.float32)  # finite, but the float32 sum overflows
    assert _image_and_finite(big, "big", mean=True)[1:] == (True, None)
    with pytest.raises(InputError):
        _image_and_finite(np.full((3, 3), np.nan, np.float32), "c", mean=True)
