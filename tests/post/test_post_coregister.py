"""Nuth & Kääb of the co-registration chain (:class:`stereodem.post.biascorr.NuthKaab`, the one
implementation since ``post/coregister.py`` was folded into the chain) on the bundled SRTM
tile with a known shift."""

import numpy as np
import pytest
from affine import Affine
from scipy import ndimage as ndi

from stereodem.core.dem import DEM
from stereodem.core.errors import DEMError
from stereodem.post import warp
from stereodem.post.assess import compare_on_reference_grid
from stereodem.post.biascorr import NuthKaab, _warp_shift
from stereodem.post.coreg import CoregChain
from stereodem.post.terrain import pixel_size_m


@pytest.fixture(scope="module")
def shifted():
    ref = DEM.bundled()
    z = ref.heights.astype(np.float64)
    # content moved 2.3 px east and 4.1 px north (rows run south), and 7 m up
    sh = ndi.shift(z, (-4.1, 2.3), order=3, mode="nearest") + 7.0
    sh[:8], sh[-8:], sh[:, :8], sh[:, -8:] = np.nan, np.nan, np.nan, np.nan
    return ref, DEM(sh.astype(np.float32), ref.transform, ref.crs, ref.vertical)


@pytest.mark.slow
def test_nuth_kaab_recovers_known_shift(shifted):
    ref, dem = shifted
    chain = CoregChain([NuthKaab()]).fit(ref, dem)
    p = chain.steps[0].params
    pe, pn = pixel_size_m(ref.transform, ref.crs, ref.shape)
    pe, pn = abs(pe[500, 0]), abs(pn[500, 0])
    # the chain's convention: displacement of the DEM relative to the reference, m east/north/up
    dx, dy, dz = p["dx"]["value"], p["dy"]["value"], p["dz"]["value"]
    assert abs(dx / pe - 2.3) < 0.1 and abs(dy / pn - 4.1) < 0.1
    assert abs(dz - 7.0) < 0.5
    assert 0 < p["dx"]["sigma"] < 0.1 * pe and 0 < p["dy"]["sigma"] < 0.1 * pn
    rec = chain.report()[0]
    assert p["converged"] and rec["after"]["nmad"] < 0.1 * rec["before"]["nmad"]
    # apply() removes the shift on the DEM's own grid: the corrected DEM agrees with the reference

    after = compare_on_reference_grid(chain.apply(dem), ref)
    before = compare_on_reference_grid(dem, ref)
    assert np.nanmedian(np.abs(after.dh)) < 0.05 * np.nanmedian(np.abs(before.dh))


def test_apply_before_fit_is_an_error(shifted):
    with pytest.raises(DEMError):
        NuthKaab().apply(shifted[1])


@pytest.mark.parametrize("east, north", [(13.7, -8.2), (-45.0, 30.0), (91.3, 64.9), (0.0, 0.0)])
def test_shifted_cubic_is_gdals_cubic_warp_of_a_translation(east, north):
    """The iterations' fast translation (one separable filter) against GDAL's cubic warp of
    the translated grid: the same heights to the warp's float32 rounding wherever both have
    a value; NaN (never a value GDAL lacks) on the rims of voids and edges."""
    ref = DEM.bundled()
    z = ref.heights.astype(np.float64)[200:500, 100:420].copy()
    z[120:140, 60:90] = np.nan  # a void
    t = ref.transform @ ref.transform.translation(100, 200)
    moved = warp.translated(t, ref.crs, z.shape, east, north)
    gdal = warp.to_grid(z, moved, ref.crs, t, ref.crs, z.shape, resampling="cubic")
    cols, rows = warp.shift_in_pixels(t, ref.crs, z.shape, east, north)
    fast = warp.shifted_cubic(z, cols, rows)
    both = np.isfinite(gdal) & np.isfinite(fast)
    assert both.sum() > 0.9 * z.size
    assert np.abs(fast[both] - gdal[both]).max() < 1e-6 * np.nanmax(np.abs(z)) + 1e-9
    assert not (np.isfinite(fast) & ~np.isfinite(gdal)).any()
    assert np.isnan(fast[120:140, 60:90]).all()


def test_iterations_of_a_rotated_grid_use_gdals_warp():
    """The separable-filter translation assumes a north-up grid; a rotated one is warped."""
    ref = DEM.bundled()
    z = ref.heights[200:300, 100:220]
    t = Affine(30.0, 2.0, 400000.0, 1.5, -30.0, 4500000.0)
    dem = DEM(z, t, "EPSG:32637", ref.vertical)
    got = NuthKaab()._moved(dem, 13.0, -7.0)
    np.testing.assert_array_equal(got, _warp_shift(dem, 13.0, -7.0, "cubic"))
