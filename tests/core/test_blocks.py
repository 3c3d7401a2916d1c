"""Row bands on threads (post.blocks): the same values as the whole-grid call, so the post
stage's rasters do not depend on the thread count."""

import cv2
import numpy as np
import pytest
from affine import Affine
from rasterio.crs import CRS
from scipy import ndimage as ndi

from stereodem.core.blocks import by_rows, each_item, percentile_of_parts, row_bands
from stereodem.post.fill import fill_holes, gaussian_smooth
from stereodem.post.filters import default_chain


def test_row_bands_cover_the_rows_once():
    for rows, threads in ((1000, 3), (130, 4), (5, 2), (1024, 16)):
        b = row_bands(rows, threads)
        assert b[0][0] == 0 and b[-1][1] == rows and len(b) <= threads
        assert all(x[1] == y[0] for x, y in zip(b, b[1:]))


@pytest.mark.parametrize("threads", [2, 3, 7])
def test_local_filters_in_bands_equal_the_whole_grid(threads):
    rng = np.random.default_rng(0)
    a = rng.normal(size=(901, 257))
    a[rng.random(a.shape) < 0.01] = np.nan
    k = rng.normal(size=(5, 5))
    for fn, halo in (
        (lambda b: ndi.correlate(np.nan_to_num(b), k, mode="nearest"), 2),
        (lambda b: ndi.gaussian_filter(np.nan_to_num(b), 1.3, mode="nearest"), 5),
        (lambda b: ndi.convolve(np.isnan(b).astype(float), np.ones((3, 3)), mode="constant"), 1),
    ):
        assert np.array_equal(by_rows(fn, a, halo=halo, threads=threads), fn(a))
    # a halo too small is visible: the test can fail
    g = lambda b: ndi.gaussian_filter(np.nan_to_num(b), 1.3, mode="nearest")
    assert not np.array_equal(by_rows(g, a, halo=1, threads=threads), g(a))


def _dem(rows=600, cols=300, seed=1):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:rows, 0:cols]
    z = 1500 + 200 * np.sin(x / 40.0) * np.cos(y / 55.0) + rng.normal(0, 1.5, (rows, cols))
    spikes = rng.integers(0, z.size, 400)
    z.ravel()[spikes] += rng.normal(0, 60, spikes.size)
    z[rng.random(z.shape) < 0.002] = np.nan
    z[200:215, 100:130] = np.nan
    score = np.clip(rng.normal(0.8, 0.2, z.shape), -1, 1)
    return z.astype(np.float32), score.astype(np.float32)


def test_filters_and_fill_do_not_depend_on_the_thread_count():
    z, score = _dem()
    out = {}
    saved = cv2.getNumThreads()
    try:
        for n in (1, 2, 4):
            cv2.setNumThreads(n)
            res = default_chain().apply(
                z,
                score=score,
                ray_gap=np.zeros_like(z),
                transform=Affine(30, 0, 500000, 0, -30, 4000000),
                crs=CRS.from_epsg(32611),
            )
            fr = fill_holes(res.heights, max_hole_size=400)
            out[n] = (res.removed, fr.heights, gaussian_smooth(fr.heights))
    finally:
        cv2.setNumThreads(saved)
    assert out[1][0].any()  # the spikes were found
    for n in (2, 4):
        for a, b in zip(out[1], out[n]):
            assert np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_percentile_of_parts_is_numpys_percentile_of_all_the_values(threads):
    """The order statistics come from each part's largest (or smallest) values, the
    interpolation is NumPy's linear one: bit for bit np.percentile of the concatenation, with
    ties, parts of any size (empty ones too) and the extreme percentiles."""
    rng = np.random.default_rng(threads)
    # the order statistics are the same on any threads: the many-case sweep runs once, the
    # threaded cases check the parts' selection on their threads
    for trial in range(400 if threads == 1 else 60):
        n = int(rng.integers(1, 300))
        v = rng.normal(size=n)
        if trial % 3 == 0:
            v = np.round(v * 3)  # many ties
        parts = np.split(v, np.sort(rng.integers(0, n + 1, int(rng.integers(0, 4)))))
        for q in (0.0, 1.0, 49.9, 50.0, 90.0, 99.0, 100.0, float(rng.uniform(0, 100))):
            got = percentile_of_parts(parts, q, threads=threads)
            assert got == float(np.percentile(v, q)), (n, q)
    with pytest.raises(ValueError):
        percentile_of_parts([np.array([])], 50.0)


def test_each_item_keeps_the_items_order_on_any_number_of_threads():
    for threads in (1, 2, 5):
        assert each_item(lambda i: i * i, range(7), threads=threads) == [i * i for i in range(7)]
    assert each_item(lambda i: i, [], threads=2) == []
