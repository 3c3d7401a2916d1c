"""``DEM.reproject`` (xdem's): a new DEM on another grid, by GDAL's warper
(``core.warp.to_grid``), voids kept, the vertical reference carried, one-line refusals."""

import numpy as np
import pytest
from affine import Affine
from pyproj import CRS

from stereodem import DEM, MapGrid
from stereodem.core.errors import InputError, NoOverlapError

UTM37 = Affine(30, 0, 499000, 0, -30, 4400000)  # near 39.7 N, 39 E: at UTM 37/38's boundary


def _smooth(vertical="geoid", **kw):
    """A smooth surface (100 m of relief over wavelengths of 5-6 km) with a void."""
    y, x = np.mgrid[0:200, 0:200]
    h = (1000 + 50 * np.sin(x / 30) + 30 * np.cos(y / 25) + 0.2 * x).astype(np.float32)
    h[50:55, 60:70] = np.nan
    return DEM(h, UTM37, "EPSG:32637", vertical, "smooth.tif", **kw)


def test_to_another_utm_zone_and_back_agrees_within_interpolation_error():
    d = _smooth()
    other = d.reproject(crs="EPSG:32638")
    assert other.crs == CRS.from_epsg(32638)
    assert (other.transform.a, other.transform.e) == (30.0, -30.0)  # metres to metres: kept
    assert other.vertical == "geoid"
    back = d.reproject(crs="EPSG:32638").reproject(d)
    assert back.transform == d.transform and back.shape == d.shape
    diff = np.abs(back.heights - d.heights)[3:-3, 3:-3]
    void = np.zeros(d.shape, bool)
    void[50:55, 60:70] = True
    assert np.isnan(back.heights[void]).all()  # voids stay voids
    far = np.ones(d.shape, bool)
    far[45:60, 55:75] = False  # cells whose supports, in both warps, miss the void
    far = far[3:-3, 3:-3]
    assert np.isfinite(diff[far]).all()
    # two bilinear warps of a surface of up to 1.7 m per cell: within 0.2 m, half within 4 cm
    assert diff[far].max() < 0.2 and np.median(diff[far]) < 0.04
    # the longitude/latitude of a cell centre gives one height in both DEMs
    lon, lat = 39.0, 39.72
    assert other.sample(lon, lat, reference=None) == pytest.approx(
        d.sample(lon, lat, reference=None), abs=0.1
    )


def test_onto_another_dems_grid_gives_that_grid_exactly():
    d = _smooth()
    grid = MapGrid(Affine(0.0005, 0, 38.99, 0, -0.0005, 39.74), 80, 60, "EPSG:4326")
    ref = DEM(np.zeros(grid.shape, np.float32), grid.transform, grid.crs, "ellipsoid")
    for target in (ref, grid):
        out = d.reproject(target, resampling="cubic")
        assert out.transform == grid.transform and out.shape == grid.shape
        assert out.crs == grid.crs
        assert out.vertical == "geoid"  # the grid is ref's, the heights stay this DEM's
    coarse = d.reproject(res=90.0, bounds=(500000, 4395000, 503000, 4398000))
    assert coarse.transform == Affine(90, 0, 500000, 0, -90, 4398000)
    assert coarse.shape == (34, 34)


@pytest.mark.parametrize("vertical", ["geoid", "ellipsoid", None])
def test_the_vertical_reference_and_layers_are_carried(vertical):
    sigma = np.full((200, 200), 0.5, np.float32)
    count = np.arange(200 * 200, dtype=np.int32).reshape(200, 200)
    d = _smooth(vertical, sigma=sigma, count=count)
    out = d.reproject(crs="EPSG:32638")
    assert out.vertical == vertical and out.path == "smooth.tif"
    assert np.nanmax(np.abs(out.sigma - 0.5)) < 1e-6
    assert out.count.dtype == np.int32
    assert set(np.unique(out.count)) - {0} <= set(count.ravel())  # nearest: values, not means


def test_a_geoid_other_than_egm96_is_carried():
    geoid = CRS.from_epsg(3855)  # EGM2008 height
    out = _smooth("geoid", geoid_crs=geoid).reproject(res=60.0)
    assert out.geoid_crs == geoid and out.vertical == "geoid"


def test_a_crs_saying_the_other_vertical_reference_is_refused():
    with pytest.raises(InputError, match="smooth.tif: reproject crs .* says geoid heights"):
        _smooth("ellipsoid").reproject(crs="EPSG:32638+5773")
    assert _smooth("geoid").reproject(crs="EPSG:32638+5773").crs == CRS.from_epsg(32638)


def test_impossible_requests_get_one_line():
    d = _smooth()
    with pytest.raises(NoOverlapError, match=r"smooth.tif \(lon/lat .*does not overlap"):
        d.reproject(bounds=(600000, 4300000, 610000, 4310000))
    far = MapGrid(Affine(30, 0, 499000, 0, -30, 4500000), 10, 10, "EPSG:32637")
    with pytest.raises(NoOverlapError, match="does not overlap the target grid"):
        d.reproject(far)
    with pytest.raises(InputError, match="smooth.tif: reproject onto ref's grid or onto"):
        d.reproject(d, crs="EPSG:32638")
    with pytest.raises(InputError, match="smooth.tif: resampling must be one of"):
        d.reproject(res=60.0, resampling="lanczos")
    with pytest.raises(InputError, match="smooth.tif: res must be positive"):
        d.reproject(res=-30.0)
    with pytest.raises(InputError, match="smooth.tif: empty or invalid bounds"):
        d.reproject(bounds=(500000, 4398000, 499000, 4399000))
    with pytest.raises(InputError, match="smooth.tif: reprojecting onto .* cells needs"):
        d.reproject(res=1e-4)


def test_a_warp_between_two_crss_puts_cells_where_the_exact_transformation_says():
    """rasterio's ``reproject`` interpolates the coordinate transformation along each row
    (GDAL's approximate transformer, 0.125 px): between UTM 33N and EPSG:3413 at 78 N that
    displaced the warped grid by 0.6-1 m (100 m cells) on average, one sign along a row, which
    co-registration took for a shift; ``to_grid`` holds it to 0.001 px. (What is left is GDAL's
    bilinear kernel, widened for a grid turned by 60 degrees: up to 0.02 px, of either sign
    from one cell to the next.)"""
    from pyproj import Transformer

    from stereodem.core.warp import to_grid

    res, n = 100.0, 400
    centre = {
        c: Transformer.from_crs(4326, c, always_xy=True).transform(15, 78) for c in (3413, 32633)
    }
    src_t = Affine(res, 0, centre[3413][0] - 22000, 0, -res, centre[3413][1] + 22000)
    dst_t = Affine(res, 0, centre[32633][0] - 15000, 0, -res, centre[32633][1] + 15000)
    r, c = np.mgrid[0 : n + 40, 0 : n + 40]
    xs, ys = src_t @ (c + 0.5, r + 0.5)  # each source cell's own coordinates, as heights
    r, c = np.mgrid[0:300, 0:300]
    ex, ey = Transformer.from_crs(32633, 3413, always_xy=True).transform(
        *(dst_t @ (c + 0.5, r + 0.5))
    )
    for value, exact in ((xs, ex), (ys, ey)):
        got = to_grid(
            value, src_t, "EPSG:3413", dst_t, "EPSG:32633", (300, 300), dst_dtype=np.float64
        )
        err = got - exact  # bilinear reproduces a linear function: the position error, metres
        assert np.isfinite(err).all()
        assert abs(err.mean()) < 0.1 and np.abs(err).max() < 2.5  # was: mean -1.0 / 0.6, max 8
