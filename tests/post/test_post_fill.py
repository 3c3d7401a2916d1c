import numpy as np
from scipy import ndimage as ndi

from stereodem.core.morphology import square_dilation
from stereodem.post import fill


def _plane(n=80):
    r, c = np.mgrid[0:n, 0:n].astype(float)
    return 100 + 0.5 * c - 0.3 * r + 0.004 * (c - 40) ** 2


def test_small_holes_filled_large_left_and_flagged():
    z = _plane()
    h = z.copy()
    h[10:15, 10:15] = np.nan  # 25 cells: small
    h[40:60, 40:60] = np.nan  # 400 cells: large
    res = fill.fill_holes(h, max_hole_size=200)
    small = np.zeros(z.shape, bool)
    small[10:15, 10:15] = True
    assert np.all(res.filled[small] == fill.FILLED_IDW)
    assert np.max(np.abs(res.heights[small] - z[small])) < 0.5
    assert np.all(np.isnan(res.heights[40:60, 40:60]))
    assert res.report["left_void"] == 400 and res.report["filled_idw"] == 25
    assert np.all(res.filled[~small] == 0)
    assert np.array_equal(res.heights[~np.isnan(h)], h[~np.isnan(h)].astype(np.float32))


def test_large_hole_from_fallback_with_blended_seam():
    z = _plane()
    h = z.copy()
    h[30:60, 30:60] = np.nan
    fallback = z - 12.0  # fallback DEM offset by a datum-like bias
    res = fill.fill_holes(h, max_hole_size=200, fallback=fallback)
    hole = np.isnan(h)
    assert np.all(res.filled[hole] == fill.FILLED_FALLBACK)
    # the offset is taken from the rim, so no 12 m step at the seam
    assert np.max(np.abs(res.heights[hole] - z[hole])) < 0.5
    naive = np.where(hole, fallback, h)
    assert np.max(np.abs(np.diff(naive, axis=1))) > 10
    assert np.max(np.abs(np.diff(res.heights.astype(float), axis=1))) < 2


def test_grow_and_gaussian_smoothing():
    z = _plane()
    h = z.copy()
    h[20, 20] = np.nan
    res = fill.fill_holes(h, grow=1)
    assert res.report["filled_idw"] == 9
    noisy = z + np.random.default_rng(0).normal(0, 2, z.shape)
    noisy[5, 5] = np.nan
    sm = fill.gaussian_smooth(noisy, passes=2)
    assert np.isnan(sm[5, 5])
    inner = (slice(5, -5), slice(5, -5))
    assert np.nanstd((sm - z)[inner]) < 0.6 * np.nanstd((noisy - z)[inner])


def test_hole_sizes_and_rims_are_scipys():
    """The holes (OpenCV's 8-connected labelling, with sizes) and their rims (OpenCV's
    dilation) are the components and dilations SciPy gives: the same cells filled, the same
    counts, on holes touching the grid's edges and corners too."""
    rng = np.random.default_rng(5)
    z = rng.normal(100, 5, (180, 150))
    z[ndi.binary_dilation(rng.random(z.shape) < 0.01, iterations=2)] = np.nan
    z[:4, :6] = z[-3:, -9:] = np.nan  # holes at the corners
    eight = np.ones((3, 3), bool)
    void = ~np.isfinite(z)
    lab, n = ndi.label(void, structure=eight)
    sizes = np.bincount(lab.ravel())
    small = (sizes < 30)[lab] & void
    r = fill.fill_holes(z, max_hole_size=30)
    assert r.report["holes"] == n and r.report["small_holes"] == int((sizes[1:] < 30).sum())
    np.testing.assert_array_equal(r.filled == fill.FILLED_IDW, small)
    assert 0 < small.sum() < void.sum()
    np.testing.assert_array_equal(
        square_dilation(void, 3), ndi.binary_dilation(void, structure=eight)
    )
