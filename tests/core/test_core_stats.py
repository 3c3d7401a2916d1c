"""core.stats: the shared NMAD and the warning-free NaN median of stacks."""

import subprocess
import sys
import warnings

import numpy as np

from stereodem.core.stats import nanmedian, nmad


def test_nanmedian_equals_numpys_with_nan_where_a_slice_is_empty_and_no_warning():
    rng = np.random.default_rng(3)
    a = rng.normal(100, 5, (7, 6, 5)).astype(np.float32)
    a[rng.random(a.shape) < 0.4] = np.nan
    a[:, 2, 3] = np.nan  # an empty cell
    a[:, 0, :] = np.nan  # an empty row of cells
    empties = []
    for axis in (0, 1, 2):
        empty = np.isnan(a).all(axis=axis)
        with warnings.catch_warnings():  # numpy warns for the empty slices
            warnings.simplefilter("ignore", RuntimeWarning)
            numpys = np.nanmedian(a, axis=axis)
        got = nanmedian(a, axis=axis)
        assert got.dtype == numpys.dtype and np.array_equal(got, numpys, equal_nan=True)
        empties.append(int(empty.sum()))
    assert empties[0] > 0 and empties[2] > 0  # empty slices along two of the axes
    # nothing empty: numpy's own call; all empty: all NaN
    full = rng.normal(0, 1, (5, 4))
    assert np.array_equal(nanmedian(full, axis=0), np.median(full, axis=0))
    assert np.isnan(nanmedian(np.full((3, 4), np.nan), axis=0)).all()
    # the per-cell NMAD goes through it
    n = nmad(a, axis=0)
    assert np.isnan(n[2, 3]) and np.isfinite(n[1, 1])


def test_nanmedian_of_empty_slices_warns_nothing_even_as_errors():
    """Run with every warning an error, in a fresh interpreter (no filter left by others)."""
    code = (
        "import numpy as np\n"
        "from stereodem.core.stats import nanmedian, nmad\n"
        "a = np.full((3, 2), np.nan); a[:, 0] = [1.0, 2.0, 4.0]\n"
        "print(nanmedian(a, axis=0).tolist(), nmad(a, axis=0).tolist())\n"
    )
    res = subprocess.run(
        [sys.executable, "-W", "error", "-c", code], capture_output=True, text=True, check=True
    )
    assert res.stdout.strip() == "[2.0, nan] [1.4826, nan]"
