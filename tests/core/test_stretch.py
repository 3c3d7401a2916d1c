"""The 8-bit linear stretch shared by the sparse and dense matchers."""

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
