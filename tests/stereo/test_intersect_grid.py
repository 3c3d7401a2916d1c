"""Space intersection (closed form, exact models) and gridding to a DEM."""

import cv2
import numpy as np
import pytest
import rasterio
from rasterio.windows import Window
from rasterio.windows import transform as window_transform

from stereodem.core import geodesy
from stereodem.core.dem import DEM, horizontal_crs
from stereodem.core.errors import OutputExistsError
from stereodem.sensor.geo.intersect import intersect_matches, intersect_rays
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation.simulate import frame_pair, pushbroom_pair
from stereodem.stereo import grid as grid_module
from stereodem.stereo.epipolar import apply_map, rectify_tile
from stereodem.stereo.grid import SUM_LAYERS, GridSpec, accumulate, finish, grid_points
from stereodem.stereo.tiling import Tile


def _ground(n, seed=0, lon0=40.4, lat0=39.6, spread=0.05):
    rng = np.random.default_rng(seed)
    return (
        lon0 + rng.uniform(-spread, spread, n),
        lat0 + rng.uniform(-spread, spread, n),
        rng.uniform(1000, 3000, n),
    )


@pytest.mark.parametrize("pair", ["frame", "pushbroom"])
def test_recovers_projected_ground_points_to_mm(pair):
    if pair == "frame":
        L, R = frame_pair(40.4, 39.6, 2000.0, (2048, 2048))
    else:
        L, R = pushbroom_pair(40.4, 39.6, 2000.0, (1200, 1200), (0.0, -27.6))
    lon, lat, h = _ground(2000, spread=0.03)
    c1, r1 = L.project(lon, lat, h)
    c2, r2 = R.project(lon, lat, h)
    p = intersect_matches(L, R, c1, r1, c2, r2)
    truth = np.stack(geodesy.geodetic_to_ecef(lon, lat, h), -1)
    assert np.linalg.norm(p.ecef - truth, axis=1).max() < 1e-3
    assert np.abs(p.h - h).max() < 1e-3
    assert p.ray_gap.max() < 1e-3


def test_rpc_pair_generic_rays(data_dir):
    L = RPCModel.from_file(data_dir / "pleiades" / "img_01_rpc.tif")
    R = RPCModel.from_file(data_dir / "pleiades" / "img_02_rpc.tif")
    lon0, lat0 = L.center_lonlat(2300.0)
    lon, lat, h = _ground(500, lon0=lon0, lat0=lat0, spread=0.002)
    h = 2200 + (h - 1000) / 10
    p = intersect_matches(L, R, *L.project(lon, lat, h), *R.project(lon, lat, h))
    assert np.abs(p.h - h).max() < 1e-3 and p.ray_gap.max() < 1e-3


def test_one_pixel_error_matches_the_geometry():
    """1 px along the epipolar line -> height error 1/(px per m), no gap; across it -> a gap."""
    L, R = pushbroom_pair(40.4, 39.6, 2000.0, (1200, 1200), (0.0, -27.6))
    et = rectify_tile(L, R, Tile(400, 400, 400, 400), (1500.0, 2500.0))
    rng = np.random.default_rng(1)
    c1, r1 = rng.uniform(450, 750, 200), rng.uniform(450, 750, 200)
    lon, lat = L.localize(c1, r1, 2000.0)
    c2, r2 = R.project(lon, lat, 2000.0)
    Hi = np.linalg.inv(et.H_right)
    along = Hi[:2, 0] / np.linalg.norm(Hi[:2, 0])  # right-image direction of the rectified rows
    across = np.array([-along[1], along[0]])
    u2, v2 = apply_map(et.H_right, c2, r2)
    p = intersect_matches(L, R, c1, r1, *apply_map(Hi, u2 - 1.0, v2))  # one rectified pixel
    dh = p.h - 2000.0
    assert np.abs(np.abs(dh) - 1 / abs(et.px_per_m)).max() < 0.05 / abs(et.px_per_m)
    assert p.ray_gap.max() < 0.5
    q = intersect_matches(L, R, c1, r1, c2 + across[0], r2 + across[1])
    gsd = R.gsd(2000.0)
    assert np.all(q.ray_gap > 0.5 * gsd) and np.all(q.ray_gap < 2.0 * gsd)
    assert np.abs(q.h - 2000.0).max() < 0.3 / abs(et.px_per_m)


def test_intersect_rays_closed_form():
    o1, d1 = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]])
    o2, d2 = np.array([[0.0, 1, 2]]), np.array([[0.0, 0, 1]])
    p, gap = intersect_rays(o1, d1, o2, d2)
    assert np.allclose(p, [[0, 0.5, 0]]) and gap[0] == pytest.approx(1.0)
    p, gap = intersect_rays(o1, d1, o1 + [0, 1, 0], d1)  # parallel lines
    assert np.isnan(p).all()


def test_grid_mean_count_layers_and_utm():
    crs = geodesy.utm_crs(40.4, 39.6)
    x0, y0 = geodesy.lonlat_to_crs(40.4, 39.6, crs)
    x0, y0 = np.floor(x0 / 30) * 30, np.floor(y0 / 30) * 30
    # 3 points in cell (0, 0), 1 in cell (1, 2), none elsewhere
    xs = x0 + np.array([5.0, 15.0, 25.0, 75.0])
    ys = y0 - np.array([5.0, 20.0, 25.0, 45.0])
    lon, lat = geodesy.crs_to_lonlat(xs, ys, crs)
    h = np.array([100.0, 110.0, 120.0, 500.0])
    g = grid_points(
        lon,
        lat,
        h,
        posting=30.0,
        bounds=(x0, y0 - 90, x0 + 90, y0),
        score=np.array([0.9, 0.8, 0.7, 0.5]),
        ray_gap=np.array([1.0, 2.0, 3.0, 4.0]),
    )
    assert g.crs.to_epsg() == 32637 and g.heights.shape == (3, 3)
    assert g.heights[0, 0] == pytest.approx(110.0) and g.count[0, 0] == 3
    assert g.heights[1, 2] == pytest.approx(500.0) and g.count[1, 2] == 1
    assert g.score[0, 0] == pytest.approx(0.8, abs=1e-6) and g.ray_gap[0, 0] == pytest.approx(2.0)
    assert np.isnan(g.heights).sum() == 7 and g.count.sum() == 4
    gg = grid_points(lon, lat, h, posting=30.0, bounds=(x0, y0 - 90, x0 + 90, y0), geoid=True)
    n = geodesy.geoid_undulation(lon[3], lat[3])
    assert gg.heights[1, 2] == pytest.approx(500.0 - n, abs=1e-3) and gg.vertical == "geoid"


def test_grid_gaussian_reproduces_a_plane_and_fills_cells():
    crs = geodesy.utm_crs(40.4, 39.6)
    x0, y0 = geodesy.lonlat_to_crs(40.4, 39.6, crs)
    xs, ys = np.meshgrid(x0 + np.arange(1.5, 600, 3.0), y0 + np.arange(1.5, 600, 3.0))
    xs, ys = xs.ravel(), ys.ravel()
    plane = lambda x, y: 1000 + 0.2 * (x - x0) - 0.1 * (y - y0)  # noqa: E731
    lon, lat = geodesy.crs_to_lonlat(xs, ys, crs)
    b = (x0, y0, x0 + 600, y0 + 600)
    g = grid_points(lon, lat, plane(xs, ys), posting=30.0, bounds=b, method="gaussian", crs=crs)
    cx, cy = g.grid.cell_centres()
    inner = np.s_[1:-1, 1:-1]
    assert np.abs(g.heights[inner] - plane(cx, cy)[inner]).max() < 0.01
    assert np.isfinite(g.heights).all()


def test_grid_write(tmp_path):
    lon, lat, h = _ground(1000)
    g = grid_points(lon, lat, h, posting=500.0)
    assert g.write(tmp_path / "dem.tif") == tmp_path / "dem.tif"
    paths = {k: tmp_path / f"{k}.tif" for k in ("dem", "count", "score", "raygap")}
    with rasterio.open(paths["dem"]) as ds:
        assert ds.dtypes[0] == "float32" and np.isnan(ds.nodata)
        assert horizontal_crs(ds.crs.to_wkt()).to_epsg() == 32637
        assert ds.transform.a == 500.0
        assert np.allclose(ds.read(1), g.heights, equal_nan=True)
    for k in ("count", "score", "raygap"):
        assert paths[k].exists()
    with rasterio.open(paths["count"]) as ds:
        assert ds.dtypes[0] == "int32" and ds.nodata == 0
        assert np.array_equal(ds.read(1), g.count)
    back = DEM.from_file(paths["dem"], layers=True)  # the one reader: layers beside it
    assert np.array_equal(back.count, g.count) and back.count.dtype == np.int32
    assert np.allclose(back.score, g.score, equal_nan=True)
    assert back.edit_mask is None and back.vertical == "ellipsoid"
    with pytest.raises(OutputExistsError):
        g.write(tmp_path / "dem.tif")


@pytest.mark.parametrize("spacing, n_per_cell", [(15.0, 4), (30.0, 1)])
def test_grid_gaussian_default_width_follows_point_density(spacing, n_per_cell):
    """Default sigma = max(posting / 2, point spacing): averages of white noise shrink alike."""
    crs = geodesy.utm_crs(40.4, 39.6)
    x0, y0 = geodesy.lonlat_to_crs(40.4, 39.6, crs)
    xs, ys = np.meshgrid(
        x0 + np.arange(spacing / 2, 1200, spacing), y0 + np.arange(spacing / 2, 1200, spacing)
    )
    xs, ys = xs.ravel(), ys.ravel()
    lon, lat = geodesy.crs_to_lonlat(xs, ys, crs)
    noise = np.random.default_rng(1).normal(0, 1.0, xs.size)
    b = (x0, y0, x0 + 1200, y0 + 1200)
    g = grid_points(lon, lat, 1000 + noise, posting=30.0, bounds=b, method="gaussian", crs=crs)
    sig = max(15.0, spacing)
    g_explicit = grid_points(
        lon,
        lat,
        1000 + noise,
        posting=30.0,
        bounds=b,
        method="gaussian",
        crs=crs,
        sigma=sig,
        radius=max(1, int(np.ceil(2 * sig / 30.0))),
    )
    assert np.array_equal(g.heights, g_explicit.heights, equal_nan=True)
    inner = g.heights[2:-2, 2:-2]
    # about 6 points or more per estimate in both cases: std well below 1 / sqrt(3)
    assert np.std(inner) < 0.45, np.std(inner)
    radius = 1 if n_per_cell == 4 else 2  # ceil(2 sigma / posting)
    assert (g.count[2:-2, 2:-2] == (2 * radius + 1) ** 2 * n_per_cell).all()


def test_tile_by_tile_gridding_equals_gridding_all_points():
    """Cell sums of separate batches, added, give the grid of all points at once."""
    rng = np.random.default_rng(5)
    crs = geodesy.utm_crs(40.0, 39.5)
    x0, y0 = geodesy.lonlat_to_crs(40.0, 39.5, crs)
    xs, ys = x0 + rng.uniform(0, 3000, 20000), y0 + rng.uniform(0, 2000, 20000)
    lon, lat = geodesy.crs_to_lonlat(xs, ys, crs)
    h = 1500 + 0.02 * (xs - x0) + rng.normal(0, 2, xs.size)
    score, gap = rng.uniform(0.5, 1, xs.size), rng.uniform(0, 3, xs.size)
    b = (
        np.floor(x0 / 30) * 30 - 60,
        np.floor(y0 / 30) * 30 - 60,
        np.ceil((x0 + 3000) / 30) * 30 + 60,
        np.ceil((y0 + 2000) / 30) * 30 + 60,
    )
    spec = GridSpec.from_bounds(b, 30.0, crs, method="gaussian", sigma=15.0)
    whole = grid_points(
        lon,
        lat,
        h,
        posting=30.0,
        crs=crs,
        bounds=b,
        score=score,
        ray_gap=gap,
        method="gaussian",
        sigma=15.0,
    )
    total = np.zeros((len(SUM_LAYERS),) + spec.shape)
    parts = np.array_split(np.argsort(xs), 4)  # four vertical strips, like tiles
    cells = [accumulate(spec, lon[p], lat[p], h[p], score=score[p], ray_gap=gap[p]) for p in parts]
    for c in cells:
        assert c.sums.shape[2] < spec.shape[1]  # each batch touches only its window
        c.add_to(total)
    tiled = finish(spec, total)
    np.testing.assert_array_equal(np.isfinite(tiled.heights), np.isfinite(whole.heights))
    np.testing.assert_allclose(tiled.heights, whole.heights, atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(tiled.score, whole.score, atol=1e-9, equal_nan=True)
    np.testing.assert_array_equal(tiled.count, whole.count)
    assert sum(c.n_points for c in cells) == xs.size
    cropped = finish(spec, total, crop=True)
    assert (
        cropped.heights.shape[0] < spec.shape[0] and np.isfinite(cropped.heights[[0, -1], :]).any()
    )
    x_c, y_c = cropped.transform.c, cropped.transform.f  # the corner of pixel (0, 0)
    assert (x_c - b[0]) % 30 == 0 and (b[3] - y_c) % 30 == 0  # same lattice


def _reference_sums(spec, x, y, h, score, gap, sigma, radius):
    """Gaussian cell sums the plain way (every offset masked, every layer weighted)."""
    rows, cols = spec.shape
    p = spec.posting
    fj = (x - spec.transform.c) / p - 0.5
    fi = (spec.transform.f - y) / p - 0.5
    i0, j0 = np.rint(fi).astype(np.int64), np.rint(fj).astype(np.int64)
    r0, r1 = max(int(i0.min()) - radius, 0), min(int(i0.max()) + radius + 1, rows)
    c0, c1 = max(int(j0.min()) - radius, 0), min(int(j0.max()) + radius + 1, cols)
    wc, ncell = c1 - c0, (r1 - r0) * (c1 - c0)
    out = np.zeros((7, ncell))
    sok, gok = np.isfinite(score), np.isfinite(gap)
    score, gap = np.where(sok, score, 0.0), np.where(gok, gap, 0.0)
    for di in range(-radius, radius + 1):
        for dj in range(-radius, radius + 1):
            i, j = i0 + di, j0 + dj
            m = (i >= r0) & (i < r1) & (j >= c0) & (j < c1)
            w = np.exp(-0.5 * (((i - fi) ** 2 + (j - fj) ** 2)[m] * p**2) / sigma**2)
            idx = ((i - r0) * wc + (j - c0))[m]
            ws, wg = w * sok[m], w * gok[m]
            for k, v in enumerate((w, w * h[m], None, ws, ws * score[m], wg, wg * gap[m])):
                out[k] += (
                    np.bincount(idx, v, ncell)
                    if v is not None
                    else np.bincount(idx, minlength=ncell)
                )
    return r0, c0, out.reshape(7, r1 - r0, c1 - c0)


@pytest.mark.parametrize("where", ["interior", "border", "outside"])
def test_gaussian_cell_sums_equal_the_plain_computation(where):
    """The gridding's shortcuts (separable weights, one sparse product for all layers in
    blocks of points, shared weights of all-finite layers, points beyond the support dropped)
    give the plain sums up to the order of the floating-point additions: every term is
    positive, so the relative difference stays within a few hundred ulps; the window and the
    counts are exact."""
    spec = GridSpec.from_bounds(
        (500000.0, 4000000.0, 503000.0, 4003000.0), 30.0, "EPSG:32637", sigma=21.0
    )
    rng = np.random.default_rng(3)
    n = 20000
    lo, hi = (500600.0, 502400.0) if where == "interior" else (499990.0, 500700.0)
    x = rng.uniform(lo, hi, n)
    y = rng.uniform(4000600.0, 4002400.0, n)
    if where == "outside":  # a few points far off the lattice, a few just off its edge
        x[:50] = rng.uniform(400000.0, 450000.0, 50)
        x[50:100] = rng.uniform(499940.0, 500000.0, 50)
    h = rng.normal(2000, 50, n)
    score = rng.uniform(0.5, 1, n)
    gap = rng.uniform(0, 3, n)
    if where != "interior":
        score[::7] = np.nan  # the weighted score layer differs from w
    lon, lat = geodesy.crs_to_lonlat(x, y, spec.crs)
    saved = grid_module.SPREAD_BLOCK
    try:
        grid_module.SPREAD_BLOCK = 4096  # several blocks of points
        got = accumulate(spec, lon, lat, h, score=score, ray_gap=gap, xy=(x, y))
    finally:
        grid_module.SPREAD_BLOCK = saved
    r0, c0, want = _reference_sums(spec, x, y, h, score, gap, 21.0, 2)
    rows = np.flatnonzero(want[0].any(axis=1))
    cols = np.flatnonzero(want[0].any(axis=0))
    assert (got.row0, got.col0) == (r0 + rows[0], c0 + cols[0])  # the smallest window
    want = want[:, rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    assert got.sums.shape == want.shape
    np.testing.assert_array_equal(got.sums[2], want[2])
    np.testing.assert_allclose(got.sums, want, rtol=1e-13, atol=0)
    assert got.n_points == int(((x >= 500000) & (x < 503000)).sum())


def test_finish_in_row_bands_gives_the_cell_by_cell_layers():
    """finish() computes its layers in row bands on the thread budget: the same values as
    the whole-grid formulas (sums / weights, NaN without weight), at 1 or 3 threads."""
    spec = GridSpec.from_bounds((0, 0, 300 * 30.0, 420 * 30.0), 30.0, "EPSG:32637")
    rng = np.random.default_rng(5)
    t = np.zeros((len(SUM_LAYERS),) + spec.shape)
    w = rng.random(spec.shape) + 0.1
    w[rng.random(spec.shape) < 0.2] = 0.0  # cells without any point
    w[:7], w[:, -5:] = 0.0, 0.0  # rows and columns cropped away
    t[0], t[1], t[2] = w, w * rng.normal(2000, 300, w.shape), np.rint(w * 8)
    t[3], t[4], t[5], t[6] = w, w * rng.random(w.shape), w, w * rng.random(w.shape) * 3
    with np.errstate(invalid="ignore", divide="ignore"):
        expect = {
            "heights": np.where(t[0] > 0, t[1] / t[0], np.nan)[7:, :-5].astype(np.float32),
            "score": np.where(t[3] > 0, t[4] / t[3], np.nan)[7:, :-5].astype(np.float32),
            "ray_gap": np.where(t[5] > 0, t[6] / t[5], np.nan)[7:, :-5].astype(np.float32),
        }
    saved = cv2.getNumThreads()
    try:
        for threads in (1, 3):
            cv2.setNumThreads(threads)
            dem = finish(spec, t, crop=True)
            for name, want in expect.items():
                got = getattr(dem, name)
                assert got.dtype == np.float32 and np.array_equal(got, want, equal_nan=True)
            assert np.array_equal(dem.count, t[2][7:, :-5].astype(np.int32))
            # the grid's transform with its origin moved down 7 rows
            assert dem.transform == window_transform(Window(0, 7, 1, 1), spec.transform)
    finally:
        cv2.setNumThreads(saved)
