"""OpenCV's square dilation of boolean masks against SciPy's."""

import numpy as np
import pytest
from scipy import ndimage as ndi

from stereodem.core.morphology import square_dilation


@pytest.mark.parametrize("size", [1, 3, 5, 7])
def test_square_dilation_is_scipys_binary_dilation(size):
    """The same mask as ``ndi.binary_dilation`` with a square of that side, on masks touching
    the grid's edges and corners (outside counts as False), for C- and F-ordered and
    non-contiguous inputs; and ``g`` steps of the 3 x 3 dilation are one of side 2g + 1."""
    rng = np.random.default_rng(size)
    mask = rng.random((61, 47)) < 0.02
    mask[0, 0] = mask[-1, 5] = mask[7, -1] = True
    want = ndi.binary_dilation(mask, structure=np.ones((size, size), bool))
    for m in (mask, np.asfortranarray(mask), np.pad(mask, 1)[1:-1, 1:-1]):
        got = square_dilation(m, size)
        assert got.dtype == bool and got.shape == mask.shape
        np.testing.assert_array_equal(got, want)
    assert not square_dilation(np.zeros((4, 5), bool), size).any()
    g = size // 2
    if g:
        steps = ndi.binary_dilation(mask, structure=np.ones((3, 3), bool), iterations=g)
        np.testing.assert_array_equal(square_dilation(mask, 2 * g + 1), steps)
