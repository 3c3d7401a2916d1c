"""``core.warp.to_grid`` between two CRSs: the source is read in place (a GDAL dataset on the
array's memory), not written whole into an in-memory GeoTIFF per call, which made every block
of a blockwise warp cost the whole source. The values are those of that former path, bit for
bit, whatever the block, the resampling, the types, the threads and the wrap across 180 E."""

import warnings

import numpy as np
import pytest
from affine import Affine
from helpers.warp_before import to_grid_before as _before

from stereodem.core import geodesy, warp


def _now(*args, **kw):
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        out = warp.to_grid(*args, **kw)
    assert not shown, [str(w.message) for w in shown]  # no NotGeoreferenced, no mode warning
    return out


def _same(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=True)


def _surface(rows, cols, seed=0):
    """Relief with noise (the kernels' smoothing shows) and a void."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:rows, 0:cols] / max(rows, cols)
    z = 1000 + 300 * np.sin(6 * x) * np.cos(4 * y) + 50 * np.sin(40 * x + 3 * y)
    z = (z + rng.normal(0, 2, z.shape)).astype(np.float32)
    z[rows // 3 : rows // 3 + 12, cols // 2 : cols // 2 + 9] = np.nan
    return z


def _polar_grid(src_t, src_shape, res, shape):
    """An EPSG:3413 grid of ``shape`` cells of ``res`` m on the middle of a UTM 33N source at
    78 N: turned by about 58 degrees against it, partly beyond its edges."""
    x, y = src_t @ (src_shape[1] / 2, src_shape[0] / 2)
    cx, cy = geodesy.transformer("EPSG:32633", "EPSG:3413").transform(x, y)
    return Affine(res, 0, cx - res * shape[1] * 0.55, 0, -res, cy + res * shape[0] / 2)


#: destination row blocks: single rows, odd sizes, the whole grid
BLOCKS = ((0, 1), (1, 2), (5, 18), (18, 82), (82, 150), (0, 150))


@pytest.mark.parametrize("resampling", warp.RESAMPLING_METHODS)
@pytest.mark.parametrize("src_res, dst_res", [(60, 60), (20, 90), (90, 30)])
def test_blocks_between_two_crss_are_warped_as_before(resampling, src_res, dst_res):
    side = 1.2 * 160 * dst_res / src_res  # the turned grid's corners beyond the source
    src_shape = (round(side), round(1.1 * side))
    z = _surface(*src_shape)
    st = Affine(src_res, 0, 500000, 0, -src_res, 8700000)
    dt = _polar_grid(st, src_shape, dst_res, (150, 160))
    for (r0, r1), threads in zip(BLOCKS, (1, 2, 1, 3, 1, 2)):
        args = (z, st, "EPSG:32633", dt @ Affine.translation(0, r0), "EPSG:3413", (r1 - r0, 160))
        now = _now(*args, resampling=resampling, threads=threads)
        assert _same(now, _before(*args, resampling=resampling, threads=threads)), (r0, r1)
        assert np.isfinite(now).any() and (r1 - r0 < 10 or not np.isfinite(now).all())


def test_types_views_and_compound_crss_are_warped_as_before():
    z = _surface(120, 130)
    st = Affine(60, 0, 500000, 0, -60, 8700000)
    dt = _polar_grid(st, z.shape, 60, (100, 110))
    classes = (np.nan_to_num(z) // 100).astype(np.uint8)
    cases = [
        # classes, nearest, kept as integers without no-data (post.masks' rasters)
        ((classes,), dict(resampling="nearest", src_nodata=None, dst_dtype=np.uint8)),
        # int8 (GDAL's MEM driver before 3.7 lacks it: widened), onto float64 (land cover)
        ((classes.astype(np.int8),), dict(resampling="nearest", dst_dtype=np.float64)),
        ((z.astype(np.float64),), dict(resampling="cubic")),
        ((z.astype(np.float16),), dict(dst_dtype=np.float64)),
    ]
    for (a,), kw in cases:
        args = (a, st, "EPSG:32633", dt, "EPSG:3413", (100, 110))
        assert _same(_now(*args, **kw), _before(*args, **kw)), (a.dtype, kw)
    # a strided view (every other column) and a compound CRS (heights above EGM96)
    args = (z[:, ::2], Affine(120, 0, 500000, 0, -60, 8700000), "EPSG:32633+5773")
    args += (dt, "EPSG:3413", (100, 110))
    assert _same(_now(*args), _before(*args))
    # lon/lat <-> UTM
    ll = Affine(0.002, 0, 14.0, 0, -0.0005, 78.3)
    utm = Affine(30, 0, 445000, 0, -30, 8693000)
    for args in (
        (z, ll, "EPSG:4326", utm, "EPSG:32633", (90, 100)),
        (z, utm, "EPSG:32633", ll, "EPSG:4326", (90, 100)),
    ):
        assert _same(_now(*args, resampling="cubic"), _before(*args, resampling="cubic"))


def test_a_global_grid_is_warped_across_the_antimeridian_as_before():
    """A global lon/lat grid onto projected grids across 180 E (extended by its other edge:
    a new array, read in place as the caller's)."""
    t = Affine(0.05, 0, -180.0, 0, -0.05, 70.0)
    lon, lat = t @ np.meshgrid(np.arange(7200) + 0.5, np.arange(60) + 0.5)
    z = (1000 + 50 * np.sin(np.radians(lon) * 20) + 800 * (lat - 65)).astype(np.float32)
    for crs, res in (("EPSG:3413", 500.0), ("EPSG:3832", 1000.0)):
        x0, y0 = geodesy.transformer("EPSG:4326", crs).transform(179.5, 68.5)
        dt = Affine(res, 0, x0 - 20 * res, 0, -res, y0 + 20 * res)
        for r0, r1 in ((0, 40), (0, 7), (7, 40)):
            args = (z, t, "EPSG:4326", dt @ Affine.translation(0, r0), crs, (r1 - r0, 40))
            now = _now(*args, resampling="cubic")
            assert np.isfinite(now).all()  # both sides of 180
            assert _same(now, _before(*args, resampling="cubic"))


def test_threads_do_not_change_a_warp_between_two_crss():
    """GDAL's warper now gets the thread count (``NUM_THREADS``: it was nested in a dict that
    rasterio passed on as one unknown option); each thread warps whole rows of the same
    chunk, so the values are those of one thread."""
    z = _surface(400, 420)
    st = Affine(60, 0, 500000, 0, -60, 8700000)
    dt = _polar_grid(st, z.shape, 60, (380, 400))
    args = (z, st, "EPSG:32633", dt, "EPSG:3413", (380, 400))
    one = _now(*args, threads=1)
    assert _same(one, _before(*args))
    for n in (2, 4):
        assert _same(_now(*args, threads=n), one)


def test_the_source_is_read_in_place():
    """The warp's GDAL dataset is the array's memory, not a copy: what the array holds when
    it is read is what GDAL reads (a block of a large grid costs the block)."""
    z = np.arange(12 * 14, dtype=np.float32).reshape(1, 12, 14)
    with warp._array_dataset(z, Affine(30, 0, 500000, 0, -30, 8700000)) as ds:
        assert ds.mode == "r" and ds.transform == Affine(30, 0, 500000, 0, -30, 8700000)
        z[0, 3, 4] = -1.0
        assert ds.read(1)[3, 4] == -1.0
        assert np.array_equal(ds.read(), z)


def test_kernel_scales_are_the_cells_size_ratio():
    """Destination cells per source cell along the source's axes: 1 for the same cells, 1/3
    for cells 3 times as large; a turn of the grid alone leaves them at about 1 (UTM 33N's and
    EPSG:3413's scale factors at 78 N differ by ~2 %)."""
    st = Affine(30, 0, 500000, 0, -30, 8700000)
    assert warp.kernel_scales(st, "EPSG:32633", st, "EPSG:32633", (100, 100)) == (1.0, 1.0)
    coarse = Affine(90, 0, 500000, 0, -90, 8700000)
    xs, ys = warp.kernel_scales(st, "EPSG:32633", coarse, "EPSG:32633", (100, 100))
    assert xs == pytest.approx(1 / 3) and ys == pytest.approx(1 / 3)
    dt = _polar_grid(st, (600, 600), 30, (150, 160))
    xs, ys = warp.kernel_scales(st, "EPSG:32633", dt, "EPSG:3413", (150, 160))
    assert 0.95 < xs < 1.0 and 0.95 < ys < 1.0 and xs == pytest.approx(ys, rel=1e-4)


@pytest.mark.parametrize("resampling", ["bilinear", "cubic"])
def test_blocks_with_the_grids_kernel_scale_are_the_whole_grids_warp(resampling):
    """GDAL's own kernel scale is per chunk (the bounding box of its source window): row
    blocks of a turned grid were warped differently from the whole grid and from each other.
    With the whole grid's scale (kernel_scales) every block size gives the whole grid."""
    src_shape = (260, 280)
    z = _surface(*src_shape)
    st = Affine(60, 0, 500000, 0, -60, 8700000)
    shape = (150, 160)
    dt = _polar_grid(st, src_shape, 60, shape)
    scale = warp.kernel_scales(st, "EPSG:32633", dt, "EPSG:3413", shape)
    kw = dict(resampling=resampling, kernel_scale=scale)
    whole = _now(z, st, "EPSG:32633", dt, "EPSG:3413", shape, **kw)
    assert np.isfinite(whole).mean() > 0.5
    differs = False
    for rows in (64, 13, 1):
        parts, own = [], []
        for r0 in range(0, shape[0], rows):
            args = (z, st, "EPSG:32633", dt @ Affine.translation(0, r0), "EPSG:3413")
            n = min(rows, shape[0] - r0)
            parts.append(_now(*args, (n, shape[1]), **kw))
            own.append(_now(*args, (n, shape[1]), resampling=resampling))
        assert _same(np.vstack(parts), whole), rows
        differs |= not _same(np.vstack(own), whole)
    assert differs  # without it, blocks are not the whole grid (what the scale is for)


def test_grid_kernel_scale_is_none_within_one_crs():
    """The scale given to every piece of a warp: kernel_scales between two CRSs, None (GDAL's
    own, exact for an affine map) between grids of one horizontal CRS, a vertical part aside;
    as GDAL warp options, none for None."""
    st = Affine(30, 0, 500000, 0, -30, 8700000)
    coarse = Affine(90, 0, 500010, 0, -90, 8700000)
    assert warp.grid_kernel_scale(st, "EPSG:32633", coarse, "EPSG:32633+5773", (9, 9)) is None
    dt = _polar_grid(st, (600, 600), 30, (150, 160))
    scale = warp.grid_kernel_scale(st, "EPSG:32633", dt, "EPSG:3413", (150, 160))
    assert scale == warp.kernel_scales(st, "EPSG:32633", dt, "EPSG:3413", (150, 160))
    assert warp.kernel_scale_options(None) == {}
    opts = warp.kernel_scale_options(scale)
    assert opts.keys() == {"XSCALE", "YSCALE"} and float(opts["XSCALE"]) == scale[0]


def test_grid_kernel_scale_is_taken_where_the_source_lies_on_a_large_grid():
    """A 30 m UTM 33N DEM at 60 N on a 0.01 degree lon/lat grid of lon 0..40 E, lat 0..75 N:
    the cells are 0.55 km wide at the DEM, 0.91 km at the grid's centre (37.5 N); the scale
    given for the whole grid is the one at the DEM (its footprint's window of the grid), as
    a grid cut around the DEM gives, not the centre's (a kernel 1.6 times too wide)."""
    st, shape = Affine(30, 0, 500000, 0, -30, 6680000), (1000, 1000)
    big, big_shape = Affine(0.01, 0, 0, 0, -0.01, 75), (7500, 4000)
    at_centre = warp.kernel_scales(st, "EPSG:32633", big, "EPSG:4326", big_shape)
    scale = warp.grid_kernel_scale(st, "EPSG:32633", big, "EPSG:4326", big_shape, src_shape=shape)
    # the grid cut to the DEM's footprint (15.00..15.55 E, 59.98..60.26 N) plus a cell
    cut = big @ Affine.translation(1499, 1473)
    around = warp.kernel_scales(st, "EPSG:32633", cut, "EPSG:4326", (30, 57))
    assert scale == pytest.approx(around, rel=2e-3)
    assert scale[0] == pytest.approx(0.054, abs=1e-3) and at_centre[0] == pytest.approx(
        0.034, abs=1e-3
    )
    # the footprint given directly (the mosaic's, in the grid's CRS) is the same window
    fp = (15.0, 59.986, 15.542, 60.257)
    assert warp.grid_kernel_scale(
        st, "EPSG:32633", big, "EPSG:4326", big_shape, footprint=fp
    ) == pytest.approx(scale, rel=1e-4)


def test_a_grid_whose_centre_the_source_crs_cannot_take_gets_gdals_own_scale(caplog):
    """A lon/lat grid at 80 W..70 W for a UTM 33N source (15 E): PROJ refuses the point
    ("outside of projection domain", or an infinite position, depending on GDAL's state);
    the kernel scale is then GDAL's own (None, logged at debug), not an exception out of the
    warp (the mosaic caught a ValueError only, the assessment nothing)."""
    src, dst = Affine(30, 0, 500000, 0, -30, 6680000), Affine(1, 0, -80, 0, -1, 5)
    with pytest.raises(ValueError, match="no position in the source"):
        warp.kernel_scales(src, "EPSG:32633", dst, "EPSG:4326", (10, 10))
    with caplog.at_level("DEBUG", logger="stereodem.core.warp"):
        assert warp.grid_kernel_scale(src, "EPSG:32633", dst, "EPSG:4326", (10, 10)) is None
    assert "GDAL's own" in caplog.text
