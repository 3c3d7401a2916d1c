"""An assessment against a reference grid far larger than the DEM (a regional lon/lat mosaic)
compares the DEM's cells as one against the reference cut around the DEM: the warp's kernel
scale is taken where the DEM lies on the reference grid, not at the grid's centre."""

import numpy as np
from affine import Affine
from pyproj import CRS

from stereodem.core.dem import DEM
from stereodem.post.assess import blockwise_comparison, compare_on_reference_grid

UTM33 = CRS.from_epsg(32633)
LONLAT = CRS.from_epsg(4326)


def _dem():
    """300 m UTM 33N cells at 60 N (150 km a side) of rough relief: the kernel's width shows."""
    rng = np.random.default_rng(3)
    z = 500 + 40 * rng.standard_normal((500, 500))
    return DEM(z.astype(np.float32), Affine(300, 0, 500000, 0, -300, 6750000), UTM33, "ellipsoid")


def _reference(west_col, north_row, cols, rows):
    """A window of a 0.05 degree lon/lat grid of lon 0..40 E, lat 0..75 N (flat at 480 m)."""
    t = Affine(0.05, 0, 0, 0, -0.05, 75) @ Affine.translation(west_col, north_row)
    return DEM(np.full((rows, cols), 480, np.float32), t, LONLAT, "ellipsoid")


def test_the_dems_cells_compare_alike_against_a_large_reference_and_one_cut_around_it():
    dem = _dem()
    big = _reference(0, 0, 800, 1500)  # centre at 20 E, 37.5 N; the DEM at 15-18 E, 59-61 N
    cut = _reference(290, 265, 70, 50)  # 14.5..18 E, 60.25..62.75 N: around the DEM
    a = compare_on_reference_grid(dem, big)
    b = compare_on_reference_grid(dem, cut)
    window = a.dh[265:315, 290:360]
    both = np.isfinite(window) & np.isfinite(b.dh)
    assert both.sum() > 500
    # the same kernel (the scale at the DEM): equal up to the warp's float rounding
    np.testing.assert_allclose(window[both], b.dh[both], atol=1e-3)
    # the blockwise path (the assessment's) takes the same scale
    stats_big = blockwise_comparison(dem, big)[0]["stats"]
    stats_cut = blockwise_comparison(dem, cut)[0]["stats"]
    assert stats_big["n"] == stats_cut["n"]
    assert abs(stats_big["nmad"] - stats_cut["nmad"]) < 1e-3
