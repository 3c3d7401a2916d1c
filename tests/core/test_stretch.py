"""The 8-bit linear stretch shared by the sparse and dense matchers."""

import cv2
import numpy as np
import pytest

from stereodem.core import stretch
from stereodem.core.stretch import linear_to_uint8
from stereodem.stereo.sparse import to_uint8


def _whole_image(a, lo, scale):
    """The formula on the whole image at once in float64 (what the bands must reproduce)."""
    t = np.asarray(a, np.float64) - np.float64(lo)
    t *= scale
    t += 0.5
    np.clip(t, 0.0, 255.0, out=t)
    with np.errstate(invalid="ignore"):  # NaN: unspecified, the callers set their own value
        return t.astype(np.uint8)


@pytest.mark.parametrize("buffer_bytes", [1 << 20, 8 * 300 * 7, 8])  # one band, 7 rows, 1 row
def test_bands_give_the_whole_image_formula(monkeypatch, buffer_bytes):
    monkeypatch.setattr(stretch, "_BUFFER_BYTES", buffer_bytes)
    rng = np.random.default_rng(3)
    a = rng.normal(120, 60, (53, 300)).astype(np.float32)  # 53 rows: a partial last band
    a[0, :4] = [np.inf, -np.inf, -1e30, 1e30]
    a[1, :50] = np.float32(10.0) + np.arange(50, dtype=np.float32) / np.float32(2.0)  # ties
    lo, scale = np.float32(10.0), 1.0
    got = linear_to_uint8(a, lo, scale)
    assert np.array_equal(got, _whole_image(a, lo, scale))
    assert list(got[1, :4]) == [0, 1, 1, 2]  # 10, 10.5, 11, 11.5: ties go up
    assert list(got[0, :4]) == [255, 0, 0, 255]
    lo, scale = np.float32(31.7), 255.0 / 171.3
    assert np.array_equal(linear_to_uint8(a, lo, scale), _whole_image(a, lo, scale))
    assert linear_to_uint8(np.zeros((0, 5), np.float32), 0.0, 1.0).shape == (0, 5)


def test_sparse_stretch_is_the_percentile_formula_with_voids_at_zero(monkeypatch):
    monkeypatch.setattr(stretch, "_BUFFER_BYTES", 8 * 256 * 5)  # several bands
    rng = np.random.default_rng(4)
    a = rng.gamma(3.0, 40.0, (97, 256)).astype(np.float32)
    a[5, 7] = np.nan
    a[6, 8] = np.inf
    b, valid = to_uint8(a)
    v = a[np.isfinite(a)]
    lo, hi = np.percentile(v[:: v.size // 400_000] if v.size > 400_000 else v, (1.0, 99.0))
    want = _whole_image(a, lo, 255.0 / float(hi - lo))
    want[~np.isfinite(a)] = 0
    assert np.array_equal(b, want)
    assert not valid[5, 7] and not valid[6, 8] and valid.sum() == a.size - 2
    assert b[5, 7] == 0 and b[6, 8] == 0 and b.max() == 255


def test_float32_certified_path_is_the_float64_formula():
    """A float32 image takes the certified road (OpenCV's float32 stretch with the offset
    moved down and up by its error bound, the float64 formula where the two differ): the same
    bits as the formula on exact ties (x.5 at scale 1: the float32 road alone rounds them to
    even), integer images, large offsets, +-inf, +-3e38 and subnormals; NaN stays
    unspecified. Where the bound is too loose (a 1e6 offset with a range of 1) the float64
    road is taken, with the same result."""
    rng = np.random.default_rng(11)
    ties = (rng.integers(-20, 600, (40, 200)) / 2).astype(np.float32)
    ints = rng.integers(0, 4096, (37, 150)).astype(np.float32)
    wild = rng.normal(100, 50, (33, 170)).astype(np.float32)
    m = rng.random(wild.shape)
    wild[m < 0.05] = np.inf
    wild[(m > 0.05) & (m < 0.1)] = -np.inf
    wild[(m > 0.1) & (m < 0.15)] = 3e38
    wild[(m > 0.15) & (m < 0.2)] = -3e38
    wild[(m > 0.2) & (m < 0.25)] = 1e-42
    wild[(m > 0.25) & (m < 0.3)] = np.nan
    far = (2e3 + rng.uniform(-30, 60, (20, 90))).astype(np.float32)  # lo * scale 1.7e4
    cases = [
        (ties, 3.0, 1.0),
        (ties, np.float32(2.0), 0.5),
        (ints, 17.0, 255.0 / 3001.0),
        (wild, 20.25, 255.0 / 150.0),
        (far, 2e3, 255.0 / 30.0),
    ]
    for a, lo, scale in cases:
        out = np.empty(a.shape, np.uint8)
        assert stretch._float32_certified(a, lo, scale, out)
        want = _whole_image(a, lo, scale)
        ok = ~np.isnan(a)
        assert np.array_equal(out[ok], want[ok]), (lo, scale)
        assert np.array_equal(linear_to_uint8(a, lo, scale)[ok], want[ok])
    assert list(linear_to_uint8(ties[:1, :0], 0.0, 1.0).shape) == [1, 0]
    # the float32 road alone would round ties to even: the corrections are needed
    half = np.array([[0.5, 1.5, 2.5, 3.5]], np.float32)
    assert linear_to_uint8(half, 0.0, 1.0).tolist() == [[1, 2, 3, 4]]
    assert cv2.convertScaleAbs(half, alpha=1.0, beta=0.0).tolist() == [[0, 2, 2, 4]]
    big = (1e6 + rng.uniform(-1, 2, (10, 50))).astype(np.float32)
    assert not stretch._float32_certified(big, 1e6, 255.0, np.empty(big.shape, np.uint8))
    assert np.array_equal(linear_to_uint8(big, 1e6, 255.0), _whole_image(big, 1e6, 255.0))
