import numpy as np
import pytest
from scipy import ndimage as ndi

from stereodem.post.coregister import NuthKaab
from stereodem.post.terrain import pixel_size_m
from stereodem.sensor.geo.dem import DEM
from stereodem.sensor.errors import DEMError


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
    nk = NuthKaab().fit(ref, dem)
    p = nk.params
    pe, pn = pixel_size_m(ref.transform, ref.crs, ref.shape)
    pe, pn = abs(pe[500, 0]), abs(pn[500, 0])
    assert abs(p["dx_px"] - 2.3) < 0.1 and abs(p["dy_px"] - 4.1) < 0.1
    assert abs(p["dx"] - 2.3 * pe) < 0.1 * pe and abs(p["dy"] - 4.1 * pn) < 0.1 * pn
    assert abs(p["dz"] - 7.0) < 0.5
    assert p["converged"] and p["nmad_after"] < 0.1 * p["nmad_before"]
    # apply() removes the shift: the corrected DEM agrees with the reference
    from stereodem.post.assess import compare_on_reference_grid
    after = compare_on_reference_grid(nk.apply(dem), ref)
    before = compare_on_reference_grid(dem, ref)
    assert np.nanmedian(np.abs(after.dh)) < 0.05 * np.nanmedian(np.abs(before.dh))


def test_apply_before_fit_is_an_error(shifted):
    with pytest.raises(DEMError):
        NuthKaab().apply(shifted[1])
