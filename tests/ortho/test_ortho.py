"""DRM orthorectification: accuracy against known truth, GDAL's RPC ortho, the forward DRM,
layers and the command line."""

import argparse
import json
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.transform import RPCTransformer
from rasterio.warp import Resampling, reproject

import stereodem.ortho.drm as drm
from stereodem.cli import main
from stereodem.core import geodesy as g
from stereodem.core.dem import DEM
from stereodem.core.errors import CRSError as StereodemCRSError
from stereodem.core.errors import (
    DEMCoverageError,
    DEMError,
    InputError,
    OutputExistsError,
    SensorModelError,
)
from stereodem.core.grid import MapGrid, grid_from_bounds
from stereodem.core.raster import write_geotiff, write_text_atomic
from stereodem.ortho.concurrent import orthorectify_all
from stereodem.ortho.drm import build_backward_map, crop_dem, orthorectify
from stereodem.ortho.forward import forward_localize, forward_ortho
from stereodem.ortho.grid import footprint_height_range, grid_for_model
from stereodem.ortho.layers import incidence_angle, occlusion_mask
from stereodem.ortho_cli import add_parser
from stereodem.sensor.io.sidecar import save_model
from stereodem.sensor.models.frame import FrameCamera
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation import simulate as sim

LON0, LAT0 = 40.4, 39.6


def oblique_camera(size=384, pitch=4, dlon=1.0, dlat=-1.5, lon0=LON0, lat0=LAT0, h0=2000.0):
    """A BILSAT-like frame camera ~20 deg off nadir (distortion on), looking at (lon0, lat0)."""
    north = g.enu_basis(lon0, lat0)[1]
    pos = np.array(g.geodetic_to_ecef(lon0 + dlon, lat0 + dlat, 686e3))
    return FrameCamera.looking_at(
        pos,
        7500 * north,
        lon0,
        lat0,
        h0,
        width=size,
        height=size,
        focal_mm=184.0,
        pitch_mm=0.0074 * pitch,
        k1=3.6e-4,
        k2=-1e-6,
        p1=2e-5,
        p2=-1e-5,
        dx_mm=0.01,
        dy_mm=-0.02,
    )


def ls_shift(a, ref):
    """Sub-pixel shift d (grid cells, x right / y down) with a(p) = ref(p + d), by least squares
    on the reference gradients (one Lucas-Kanade step; unbiased for small shifts)."""
    gy, gx = np.gradient(np.asarray(ref, np.float64))
    m = np.isfinite(a) & np.isfinite(gx) & np.isfinite(gy)
    A = np.stack([gx[m], gy[m]], 1)
    d, *_ = np.linalg.lstsq(A, (a - ref)[m], rcond=None)
    return d


def albedo_field(res, seed=1, n=12):
    """A smooth ground albedo (sum of plane waves, wavelengths 16-40 cells) on map x, y."""
    rng = np.random.default_rng(seed)
    lam = rng.uniform(16, 40, n) * res
    th, ph, amp = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n), rng.uniform(0.5, 1, n)

    def f(x, y):
        out = np.zeros(np.shape(x))
        for a, l, t, p in zip(amp, lam, th, ph):
            out += a * np.cos(2 * np.pi * (x * np.cos(t) + y * np.sin(t)) / l + p)
        return out

    return f


@pytest.fixture(scope="module")
def rendered():
    """An oblique frame image rendered by the forward DRM from a known albedo over the real DEM."""
    cam = oblique_camera()
    dem = DEM.bundled()
    grid = grid_for_model(cam, dem)
    f = albedo_field(grid.res[0])
    cc, rr = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    loc = cam.localize_dem(cc, rr, dem, threshold=0.01)
    assert loc.converged.all()
    x, y = g.lonlat_to_crs(loc.lon, loc.lat, grid.crs)
    img = f(x, y).astype(np.float32)
    X, Y = grid.xy(*np.meshgrid(np.arange(grid.width), np.arange(grid.height)))
    return cam, dem, grid, img, f(X, Y).astype(np.float32)


# --------------------------------------------------------------------------- grid


def test_grid_defaults_utm_gsd_and_footprint(rendered):
    cam, dem, grid, *_ = rendered
    assert grid.crs.to_epsg() == g.utm_epsg(LON0, LAT0) == 32637
    assert grid.res[0] == pytest.approx(cam.gsd(2000.0), rel=0.02)

    lo, hi = footprint_height_range(cam, dem)
    z = dem.sample(*cam.footprint(2000.0))
    assert lo <= np.nanmin(z) and hi >= np.nanmax(z)
    w, s, e, n = grid.bounds
    for h in (lo, hi):
        x, y = g.lonlat_to_crs(*cam.footprint(h), grid.crs)
        assert (x >= w).all() and (x <= e).all() and (y >= s).all() and (y <= n).all()
    # snapped to the posting, north-up
    assert w % grid.res[0] == pytest.approx(0, abs=1e-6) and grid.transform.e < 0
    g2 = grid_for_model(cam, dem, res=250.0, crs="EPSG:32638")
    assert g2.res == (250.0, 250.0) and g2.crs.to_epsg() == 32638


@pytest.mark.parametrize("width, height", [(1, 1), (1, 40), (40, 1)])
def test_grid_of_a_one_pixel_wide_image_has_a_cell(width, height):
    """An image of one pixel, row or column has a footprint of no width through its pixel
    centres: the grid was refused ("empty or invalid grid bounds"), so ``uncertainty`` and
    ``ortho`` failed on it."""
    one = replace(oblique_camera(), width=width, height=height)
    dem = DEM.bundled()
    grid = grid_for_model(one, dem, res=30.0)
    assert grid.width >= 1 and grid.height >= 1
    w, s, e, n = grid.bounds
    xy = [g.lonlat_to_crs(*one.footprint(h), grid.crs) for h in footprint_height_range(one, dem)]
    x, y = np.concatenate([p[0] for p in xy]), np.concatenate([p[1] for p in xy])
    assert (x >= w).all() and (x <= e).all() and (y >= s).all() and (y <= n).all()
    # no more than the footprint (at the DEM's lowest and highest heights) and a cell around
    assert e - w <= x.max() - x.min() + 3 * 30.0 and n - s <= y.max() - y.min() + 3 * 30.0


@pytest.mark.parametrize("res", [1e5, 1e300, 1e308])
def test_a_posting_beyond_the_footprint_is_refused(res):
    """``ortho --res 1e308`` was a traceback (OverflowError: the grid's snapped corners at
    ±1e308, their difference infinite), ``--res 1e300`` "the DEM does not cover lon
    -136..inf", a posting beyond the footprint (45 km here) a one-cell orthoimage."""
    cam, dem = oblique_camera(), DEM.bundled()
    with pytest.raises(InputError, match=r"posting .* exceeds the image footprint \(\d+ x \d+ m\)"):
        grid_for_model(cam, dem, res=res)
    assert grid_for_model(cam, dem, res=2e4).width >= 2  # a coarse posting within it


def test_grid_corners_that_overflow_are_an_input_error():
    with pytest.raises(InputError, match="snapped corners overflow"):
        grid_from_bounds((-5e307, -5e307, 5e307, 5e307), 1e308, "EPSG:32637")
    g1 = grid_from_bounds((100.0, 200.0, 350.0, 420.0), 100.0, "EPSG:32637")
    assert (g1.width, g1.height, g1.bounds) == (3, 3, (100.0, 200.0, 400.0, 500.0))


# --------------------------------------------------------------------------- accuracy


def test_ortho_matches_rendered_truth(rendered):
    """Own rendering (albedo at each pixel's DRM ground point): shift <= 0.05 px, residual at
    the noise level, interpolated map within its measured bound of the exact model."""
    cam, dem, grid, img, truth = rendered
    sigma = 0.05
    noisy = img + np.random.default_rng(3).normal(0, sigma, img.shape).astype(np.float32)
    o = orthorectify(noisy, cam, dem, grid=grid, resampling="bilinear", keep_maps=True)
    assert o.interpolation_error_px <= 0.01
    assert o.valid.mean() > 0.8
    a = np.where(o.valid, o.data, np.nan)
    d = ls_shift(a, truth)
    assert np.all(np.abs(d) <= 0.05), d
    resid = (a - truth)[o.valid]
    assert abs(resid.mean()) < 0.01 and resid.std() <= sigma  # at (below) the noise level
    # the reported bound holds on independent cells against the exact model
    rng = np.random.default_rng(7)
    iv, iu = np.nonzero(o.valid)
    k = rng.choice(iv.size, 3000, replace=False)
    lon, lat = grid.lonlat(iu[k], iv[k])
    ce, re = cam.project(lon, lat, o.heights[iv[k], iu[k]].astype(float))
    err = np.hypot(o.col[iv[k], iu[k]] - ce, o.row[iv[k], iu[k]] - re)
    assert err.max() <= 0.01 + 1e-3  # + float32 storage of the maps
    # the heights used are the DEM's (ellipsoidal)
    assert np.allclose(o.heights[iv[k], iu[k]], dem.sample(lon, lat), atol=0.05)


def test_an_orthoimage_given_as_a_dem_is_refused(rendered, tmp_path):
    """An orthoimage written by stereodem, given where a DEM is wanted (``stereodem assess
    ortho_left.tif --ref ...``), had its radiances read as heights in metres without a word;
    its band description says what it is, and the DEM reader refuses it in one line."""
    cam, dem, grid, img, _ = rendered
    o = orthorectify(img, cam, dem, grid=grid, resampling="bilinear")
    path = o.write(tmp_path / "ortho.tif")
    with pytest.raises(DEMError) as err:
        DEM.from_file(path)
    assert str(err.value) == (
        f"{path}: band 1 is stereodem's 'orthoimage (bilinear resampling)', not heights; "
        "give the DEM itself"
    )


def test_threads_give_the_same_ortho(rendered):
    cam, dem, grid, img, truth = rendered
    one = orthorectify(img, cam, dem, grid=grid, resampling="cubic", block_rows=37, threads=1)
    two = orthorectify(img, cam, dem, grid=grid, resampling="cubic", block_rows=37, threads=2)
    np.testing.assert_array_equal(one.data, two.data)
    np.testing.assert_array_equal(one.valid, two.valid)


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_concurrent_orthos_equal_the_serial_ones(rendered):
    # two orthoimages at once (and their blocks on the budget's threads): the serial rasters;
    # the second image is another oblique view over the same grid
    cam, dem, grid, img, truth = rendered
    cam2 = oblique_camera(dlon=-1.0, dlat=1.0)
    items = [("left", img, cam), ("right", img[::-1].copy(), cam2)]
    calls = []
    kw = dict(resampling="cubic", block_rows=37)
    serial = orthorectify_all(items, dem, threads=1, **kw)
    both = orthorectify_all(items, dem, threads=3, progress=lambda d, t: calls.append((d, t)), **kw)
    assert list(both) == ["left", "right"] and serial["left"].grid == both["right"].grid == grid
    for name in both:
        alone = orthorectify(
            items[0 if name == "left" else 1][1],
            items[0 if name == "left" else 1][2],
            dem,
            grid=grid,
            **kw,
        )
        assert alone.valid.mean() > 0.2
        for o in (serial[name], both[name]):
            np.testing.assert_array_equal(o.data, alone.data)
            np.testing.assert_array_equal(o.valid, alone.valid)
    assert calls[-1] == (2 * grid.height, 2 * grid.height)
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)


@pytest.mark.slow
def test_concurrent_orthos_share_one_pool_of_block_threads(rendered, monkeypatch):
    """With a budget of 2 threads for 2 orthoimages, each one's row blocks run on both
    threads of one shared pool (not on one thread each: the larger one then finished alone
    on one core), and no more than 2 block threads exist."""
    cam, dem, grid, img, truth = rendered
    ran, remap = {}, drm.remap_nan

    def record(image, *args, **kw):
        ran.setdefault(id(image), set()).add(threading.current_thread().name)
        time.sleep(0.005)  # a block's work: both threads take blocks
        return remap(image, *args, **kw)

    monkeypatch.setattr(drm, "remap_nan", record)
    items = [("left", img, cam), ("right", img[::-1].copy(), oblique_camera(dlon=-1.0, dlat=1.0))]
    orthorectify_all(items, dem, resampling="cubic", block_rows=8, threads=2)
    assert len(ran) == 2
    for names in ran.values():
        assert len(names) == 2 and all(n.startswith("stereodem-ortho-rows") for n in names)
    assert len(set.union(*ran.values())) == 2


def test_wrong_dem_is_detected(rendered):
    """Negative control: a DEM 150 m too high displaces the oblique ortho measurably."""
    cam, dem, grid, img, truth = rendered
    high = DEM(dem.heights + 150, dem.transform, dem.crs, dem.vertical)
    o = orthorectify(img, cam, high, grid=grid)
    d = ls_shift(np.where(o.valid, o.data, np.nan), truth)
    assert np.hypot(*d) > 0.3


def _sum_w2(frac, resampling):
    """Sum of the squared 1-D kernel weights at fractional offsets ``frac`` (OpenCV's bilinear
    and Lanczos-4 kernels): the factor by which resampling scales white-noise variance."""
    f = np.asarray(frac, np.float64)
    if resampling == "bilinear":
        return (1 - f) ** 2 + f**2
    x = (np.arange(8)[:, None] - 3) - f[None]  # the 8 taps' offsets
    w = np.sinc(x) * np.sinc(x / 4)
    w /= w.sum(0)
    return (w**2).sum(0)


@pytest.mark.slow
def test_simulated_scene_true_ortho():
    """Simulator truth: ortho - truth_ortho is the interpolator's error on the band-limited
    image (shrinking as the system MTF at Nyquist falls and the kernel improves) plus the image
    noise propagated through the kernel, sigma^2 * mean(sum of squared weights)."""
    sigma = 1.0  # the presets' noise (simulate_scene default)
    rms, expected_noise_var, shifts = {}, {}, []
    for mtf in (0.3, 0.01):
        for noise in (0.0, sigma):
            sc = sim.simulate_scene(
                preset="frame", size=(320, 320), noise=noise, seed=4, mtf_nyquist=mtf
            )
            d = sc.truth_dem
            grid = MapGrid(d.transform, d.shape[1], d.shape[0], d.crs)
            for rs in ("bilinear", "cubic", "lanczos"):
                o = orthorectify(
                    sc.left, sc.left_model, d, grid=grid, resampling=rs, keep_maps=True
                )
                assert o.interpolation_error_px <= 0.01
                a = np.where(o.valid, o.data, np.nan)
                shifts.append(float(np.max(np.abs(ls_shift(a, sc.truth_ortho)))))
                r = (a - sc.truth_ortho)[o.valid]
                rms[mtf, noise, rs] = float(np.sqrt(np.mean(r**2)))
                if rs != "cubic":
                    v = o.valid
                    expected_noise_var[mtf, rs] = (
                        float(np.mean(_sum_w2(o.col[v] % 1, rs) * _sum_w2(o.row[v] % 1, rs)))
                        * sigma**2
                    )
    print(
        {k: round(v, 3) for k, v in rms.items()},
        f"largest shift vs truth_ortho {max(shifts):.4f} px",
    )
    # geometry: every ortho sits on the true orthoimage to a few thousandths of a pixel (the
    # README's figure is this printed maximum)
    assert max(shifts) <= 0.005
    # the floor (noise off) is interpolation error: better kernels and a more band-limited
    # image (lower MTF at Nyquist) both shrink it
    assert rms[0.3, 0.0, "bilinear"] > rms[0.3, 0.0, "cubic"] > rms[0.3, 0.0, "lanczos"]
    for rs in ("bilinear", "cubic", "lanczos"):
        assert rms[0.01, 0.0, rs] < 0.6 * rms[0.3, 0.0, rs]
    # on a band-limited scene a good kernel reproduces truth_ortho well below the noise
    # (what is left is mostly the 8-bit quantisation, 0.29 DN before resampling)
    assert rms[0.01, 0.0, "lanczos"] <= 0.4 * sigma
    # with noise on, the residual is the floor plus the propagated noise, within 3 %
    for (mtf, rs), nv in expected_noise_var.items():
        expected = np.sqrt(rms[mtf, 0.0, rs] ** 2 + nv)
        assert rms[mtf, sigma, rs] == pytest.approx(expected, rel=0.03), (mtf, rs)
    assert (
        0.4 < expected_noise_var[0.3, "bilinear"] / sigma**2 < 0.5
    )  # bilinear averages noise down


def test_nodata_image_holes_footprint_and_dem_voids(rendered):
    cam, dem, grid, img, truth = rendered
    im = img.copy()
    im[100:110, 200:210] = np.nan
    holed = DEM(dem.heights.copy(), dem.transform, dem.crs, dem.vertical)
    o0 = orthorectify(im, cam, dem, grid=grid, keep_maps=True)
    # cells whose bilinear kernel touches the hole are nodata; others next to it are valid
    c, r = o0.col, o0.row
    touches = (c > 199 - 1e-3) & (c < 210) & (r > 99 - 1e-3) & (r < 110)
    assert touches.sum() > 20 and not o0.valid[touches].any()
    # outside the image footprint: nodata
    out = ~((c >= 0) & (r >= 0) & (c <= cam.width - 1) & (r <= cam.height - 1))
    assert out.sum() > 100 and not o0.valid[out].any()
    # a void in the DEM -> nodata there
    lon, lat = cam.localize(np.array([190.0]), np.array([190.0]), 2000.0)
    cc, rr = ~dem.transform @ (lon, lat)
    holed.heights[int(rr[0]) - 5 : int(rr[0]) + 5, int(cc[0]) - 5 : int(cc[0]) + 5] = np.nan
    o1 = orthorectify(img, cam, holed, grid=grid)
    assert np.isnan(o1.heights).sum() > 20
    assert not o1.valid[np.isnan(o1.heights)].any()


def test_dem_coverage_errors(rendered):
    cam, dem, grid, img, _ = rendered
    # a DEM that covers only the western part of the footprint
    half = DEM(dem.heights[:, :480], dem.transform, dem.crs, dem.vertical, "west.tif")
    with pytest.raises(DEMCoverageError, match="west.tif.*does not cover"):
        orthorectify(img, cam, half, grid=grid, strict_dem=True)
    o = orthorectify(img, cam, half, grid=grid)
    assert o.dem_missing["n_cells"] > 100
    far = DEM(
        dem.heights, dem.transform @ Affine.translation(5000, 0), dem.crs, dem.vertical, "far.tif"
    )
    with pytest.raises(DEMCoverageError, match="far.tif"):
        orthorectify(img, cam, far, grid=grid)


# --------------------------------------------------------------------------- RPC vs GDAL


def _rpc_setup(tmp_path, data_dir):
    src = data_dir / "pleiades" / "img_01_rpc.tif"
    model = RPCModel.from_file(src)
    with rasterio.open(src) as ds:
        rpcs = ds.rpcs
    lon, lat = model.footprint(2300.0)
    w, s, e, n = lon.min() - 0.002, lat.min() - 0.002, lon.max() + 0.002, lat.max() + 0.002
    step = 5e-5
    tr = Affine(step, 0, w, 0, -step, n)
    nx, ny = int((e - w) / step), int((n - s) / step)
    X, Y = tr @ np.meshgrid(np.arange(nx) + 0.5, np.arange(ny) + 0.5)
    Z = 2300 + 60 * np.sin((X - w) / 0.0015) * np.cos((Y - s) / 0.002) + 30 * (X - w) / (e - w)
    dem_path = tmp_path / "dem_ellipsoid.tif"
    DEM(Z.astype(np.float32), tr, "EPSG:4326", "ellipsoid").write(dem_path)
    rng = np.random.default_rng(0)
    cc, rr = np.meshgrid(np.arange(model.width, dtype=float), np.arange(model.height, dtype=float))
    img = np.zeros(cc.shape)
    for _ in range(10):
        l, t = rng.uniform(8, 30), rng.uniform(0, 2 * np.pi)
        img += np.cos(2 * np.pi * (cc * np.cos(t) + rr * np.sin(t)) / l + rng.uniform(0, 2 * np.pi))
    return model, rpcs, dem_path, (1000 + 100 * img).astype(np.float32)


def test_gdal_rpc_dem_heights_are_ellipsoidal(tmp_path, data_dir):
    """GDAL's RPC_DEM without a vertical CRS uses the values as they are (ellipsoidal here):
    a flat DEM at 2300 m gives the same pixels as RPC_HEIGHT=2300, and both match our model."""
    model, rpcs, _, _ = _rpc_setup(tmp_path, data_dir)
    lon, lat = model.footprint(2300.0)
    tr = Affine(1e-4, 0, lon.min() - 0.01, 0, -1e-4, lat.max() + 0.01)
    flat = tmp_path / "flat.tif"
    DEM(np.full((250, 250), 2300, np.float32), tr, "EPSG:4326", "ellipsoid").write(flat)
    lo, la = model.localize(np.array([100.0, 500, 900]), np.array([200.0, 500, 800]), 2300.0)
    with RPCTransformer(rpcs, RPC_DEM=str(flat)) as t1, RPCTransformer(rpcs, RPC_HEIGHT=2300) as t2:
        r1, c1 = t1.rowcol(lo, la, op=lambda v: v)
        r2, c2 = t2.rowcol(lo, la, op=lambda v: v)
    assert np.allclose(r1, r2, atol=1e-6) and np.allclose(c1, c2, atol=1e-6)
    # GDAL counts from the pixel corner: ours + 0.5
    assert np.allclose(np.array(c1) - 0.5, [100, 500, 900], atol=1e-3)
    assert np.allclose(np.array(r1) - 0.5, [200, 500, 800], atol=1e-3)


@pytest.mark.slow
def test_rpc_ortho_agrees_with_gdal(tmp_path, data_dir):
    model, rpcs, dem_path, img = _rpc_setup(tmp_path, data_dir)
    dem = DEM.from_file(dem_path)
    assert dem.vertical == "ellipsoid"
    grid = grid_for_model(model, dem, res=0.5)
    o = orthorectify(img, model, dem, grid=grid, keep_maps=True)
    ref = np.full(grid.shape, np.nan, np.float32)
    reproject(
        img,
        ref,
        rpcs=rpcs,
        src_crs="EPSG:4326",
        dst_crs=grid.crs,
        dst_transform=grid.transform,
        resampling=Resampling.bilinear,
        dst_nodata=np.nan,
        RPC_DEM=str(dem_path),
    )
    both = o.valid & np.isfinite(ref)
    assert both.sum() > 0.9 * o.valid.sum() > 0.8 * grid.width * grid.height
    d = ls_shift(np.where(both, o.data, np.nan), ref)
    assert np.all(np.abs(d) <= 0.05), d
    # projected positions: GDAL's RPC transformer with the same DEM, at sampled cells
    vv, uu = np.mgrid[0 : grid.height : 37, 0 : grid.width : 41]
    lon, lat = grid.lonlat(uu, vv)
    with RPCTransformer(rpcs, RPC_DEM=str(dem_path)) as t:
        r, c = t.rowcol(lon.ravel(), lat.ravel(), op=lambda v: v)
    dc = np.array(c) - 0.5 - o.col[vv, uu].ravel()
    dr = np.array(r) - 0.5 - o.row[vv, uu].ravel()
    ok = np.isfinite(dc) & np.isfinite(dr)
    assert ok.mean() > 0.8 and np.abs(dc[ok]).max() <= 0.05 and np.abs(dr[ok]).max() <= 0.05


def test_real_pleiades_against_gdal(shared_data, tmp_path):
    """Real Pleiades image and RPC over s2p's DSM (ellipsoidal heights), both orthos compared."""
    img_path = shared_data / "s2p_pleiades" / "pair" / "img_01.tif"
    dsm_path = shared_data / "s2p_pleiades" / "pair" / "expected_dsm.tif"
    if not img_path.exists() or not dsm_path.exists():
        pytest.skip("Pleiades pair not present")
    model = RPCModel.from_file(img_path)
    with rasterio.open(img_path) as ds:
        img, rpcs = ds.read(1).astype(np.float32), ds.rpcs
    dem = DEM.from_file(dsm_path, vertical="ellipsoid")
    w, s, e, n = rasterio.open(dsm_path).bounds
    grid = grid_from_bounds((w + 20, s + 20, e - 20, n - 20), 0.5, dem.crs)
    o = orthorectify(img, model, dem, grid=grid)
    ref = np.full(grid.shape, np.nan, np.float32)
    reproject(
        img,
        ref,
        rpcs=rpcs,
        src_crs="EPSG:4326",
        dst_crs=grid.crs,
        dst_transform=grid.transform,
        resampling=Resampling.bilinear,
        dst_nodata=np.nan,
        RPC_DEM=str(dsm_path),
    )
    both = o.valid & np.isfinite(ref)
    assert both.mean() > 0.5
    d = ls_shift(np.where(both, o.data, np.nan), np.where(both, ref, np.nan))
    assert np.all(np.abs(d) <= 0.05), d
    rel = np.abs(o.data[both] - ref[both]) / np.maximum(np.abs(ref[both]), 1)
    assert np.median(rel) < 1e-3


# --------------------------------------------------------------------------- forward DRM


def test_forward_and_backward_mappings_agree(rendered):
    cam, dem, grid, img, _ = rendered

    pts = forward_localize(cam, dem, step=7, crs=grid.crs, threshold=0.01)
    assert pts.converged.mean() > 0.99
    bm = build_backward_map(cam, grid, crop_dem(dem, grid), tolerance=1e-3)
    assert bm.error_px <= 1e-3
    ok = pts.converged
    c, r = bm.image_coords(pts.x[ok], pts.y[ok], pts.h[ok])
    err = np.hypot(c - pts.col[ok], r - pts.row[ok])
    assert err.max() <= 1e-3, err.max()


@pytest.mark.slow
def test_forward_nearest_ortho_matches_backward_nearest(rendered):
    """On a grid three times finer than the pixels, each forward-filled cell holds the pixel
    the backward nearest-neighbour ortho picks there (white-noise image: equal value = same
    pixel)."""
    cam, dem, grid, _, _ = rendered
    fine = grid_from_bounds(grid.bounds, grid.res[0] / 3, grid.crs)
    noise = np.random.default_rng(2).random((cam.height, cam.width)).astype(np.float32)
    pts = forward_localize(cam, dem, crs=grid.crs)
    fwd, src = forward_ortho(noise, pts, fine)
    bwd = orthorectify(noise, cam, dem, grid=fine, resampling="nearest")
    filled = (src >= 0) & bwd.valid
    assert filled.sum() > 0.9 * cam.width * cam.height
    same = fwd[filled] == bwd.data[filled]
    assert same.mean() >= 0.999, same.mean()


# --------------------------------------------------------------------------- layers


def _ridge_dem(width=0.006, lon0=LON0, lat0=LAT0):
    """Ellipsoidal lon/lat DEM: plain at 1000 m with a 900 m north-south Gaussian ridge."""
    st = 0.0005
    tr = Affine(st, 0, lon0 - 0.25, 0, -st, lat0 + 0.25)
    lon, lat = tr @ np.meshgrid(np.arange(1000) + 0.5, np.arange(1000) + 0.5)
    z = 1000 + 900 * np.exp(-(((lon - lon0) / width) ** 2))
    return DEM(z.astype(np.float32), tr, "EPSG:4326", "ellipsoid")


def test_incidence_angle_against_analytic_normals():
    cam = oblique_camera(size=160, pitch=4, dlon=-2.5, dlat=0.0, h0=1000.0)
    width = 0.02
    dem = _ridge_dem(width)
    o = orthorectify(np.ones((160, 160), np.float32), cam, dem, res=50.0)
    inc = incidence_angle(o, cam)
    vv, uu = np.nonzero(np.isfinite(inc))
    k = np.random.default_rng(0).choice(vv.size, 400, replace=False)
    vv, uu = vv[k], uu[k]
    lon, lat = o.grid.lonlat(uu, vv)
    h = o.heights[vv, uu].astype(float)
    # exact line of sight (to the perspective centre) and the analytic surface normal, in ENU
    x, y, z = g.geodetic_to_ecef(lon, lat, h)
    basis = g.enu_basis(lon, lat)
    los = np.einsum("nij,nj->ni", basis, cam.position - np.stack([x, y, z], -1))
    los /= np.linalg.norm(los, axis=1, keepdims=True)
    m_per_deg = (
        np.radians(1)
        * g.A
        / np.sqrt(1 - g.E2 * np.sin(np.radians(lat)) ** 2)
        * np.cos(np.radians(lat))
    )
    dzdx = 900 * np.exp(-(((lon - LON0) / width) ** 2)) * (-2 * (lon - LON0) / width**2) / m_per_deg
    nrm = np.stack([-dzdx, np.zeros_like(dzdx), np.ones_like(dzdx)], 1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    expected = np.degrees(np.arccos(np.sum(los * nrm, 1)))
    assert np.abs(inc[vv, uu] - expected).max() < 1.0
    assert expected.max() - expected.min() > 20  # flanks facing toward and away


def test_occlusion_against_exact_rays():
    """Ray-marching mask vs a brute-force check with the exact model (localise the cell's
    pixel at many heights above it and compare with the DEM)."""
    cam = oblique_camera(size=160, pitch=4, dlon=-6.0, dlat=0.0, h0=1000.0)
    dem = _ridge_dem()
    o = orthorectify(np.ones((160, 160), np.float32), cam, dem, res=60.0)
    occ = occlusion_mask(o, cam)
    finite = np.isfinite(o.heights)
    assert 0.003 < occ[finite].mean() < 0.2
    rng = np.random.default_rng(1)
    # sample occluded cells and cells near the ridge (the hard ones)
    near = finite & (o.heights > 1005)
    cand = np.concatenate(
        [rng.choice(np.flatnonzero(occ), 150), rng.choice(np.flatnonzero(near & ~occ), 150)]
    )
    vv, uu = np.unravel_index(cand, occ.shape)
    lon, lat = o.grid.lonlat(uu, vv)
    h0 = o.heights[vv, uu].astype(float)
    col, row = cam.project(lon, lat, h0)
    hs = h0[:, None] + np.linspace(1.0, 1000.0, 400)[None]
    lo2, la2 = cam.localize(np.repeat(col[:, None], 400, 1), np.repeat(row[:, None], 400, 1), hs)
    zt = dem.sample(lo2, la2)
    exact = np.nanmax(zt - hs, axis=1) > 0.1 * 60
    agree = (exact == occ[vv, uu]).mean()
    assert agree >= 0.97, agree


def test_second_image_on_shared_grid(rendered):
    cam, dem, grid, img, _ = rendered
    cam2 = oblique_camera(dlon=-1.0, dlat=1.5)
    o2 = orthorectify(img, cam2, dem, grid=grid)
    assert o2.grid == grid and o2.data.shape == grid.shape


# --------------------------------------------------------------------------- CLI


@pytest.mark.slow
def test_cli_rpc_ortho_layers_and_errors(tmp_path, data_dir, capsys):
    model, rpcs, dem_path, img = _rpc_setup(tmp_path, data_dir)
    image = tmp_path / "img.tif"
    write_geotiff(image, img, rpcs=rpcs)
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    out = tmp_path / "ortho.tif"
    args = parser.parse_args(
        [
            "ortho",
            str(image),
            "--dem",
            str(dem_path),
            "-o",
            str(out),
            "--res",
            "1",
            "--layers",
            "incidence,occlusion",
        ]
    )
    assert args.run(args) == 0
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 32740 and ds.res == (1.0, 1.0)
        a = ds.read(1)
        assert np.isfinite(a).mean() > 0.8
    assert (tmp_path / "ortho_incidence.tif").exists() and (
        tmp_path / "ortho_occlusion.tif"
    ).exists()
    assert "interpolation error" in capsys.readouterr().out
    # existing output without --overwrite

    with pytest.raises(OutputExistsError):
        args.run(args)
    # DEM far from the image
    far = tmp_path / "far.tif"
    DEM(
        np.full((50, 50), 100, np.float32),
        Affine(1e-3, 0, 10, 0, -1e-3, 10),
        "EPSG:4326",
        "ellipsoid",
    ).write(far)
    args = parser.parse_args(
        ["ortho", str(image), "--dem", str(far), "-o", str(tmp_path / "o2.tif")]
    )
    with pytest.raises(DEMCoverageError, match="far.tif"):
        args.run(args)
    # no model in the image
    bare = tmp_path / "bare.tif"
    write_geotiff(bare, img)
    args = parser.parse_args(
        ["ortho", str(bare), "--dem", str(dem_path), "-o", str(tmp_path / "o3.tif")]
    )
    with pytest.raises(SensorModelError, match="bare.tif"):
        args.run(args)
    # a generic model without GCPs
    args = parser.parse_args(
        [
            "ortho",
            str(image),
            "--dem",
            str(dem_path),
            "-o",
            str(tmp_path / "o4.tif"),
            "--model",
            "poly2d-1",
        ]
    )
    with pytest.raises(InputError, match="--gcps"):
        args.run(args)


@pytest.mark.slow  # over 0.5 s: out of the fast subset (CI runs it)
def test_cli_gcp_model(tmp_path, data_dir, capsys):
    model, rpcs, dem_path, img = _rpc_setup(tmp_path, data_dir)
    image = tmp_path / "img.tif"
    write_geotiff(image, img)
    dem = DEM.from_file(dem_path)
    rng = np.random.default_rng(0)
    c, r = rng.uniform(10, 1010, 40), rng.uniform(10, 1010, 40)
    loc = model.localize_dem(c, r, dem, threshold=0.001, h0=2300.0)
    rows = ["id,lon,lat,h,col,row,role"] + [
        f"p{i},{loc.lon[i]:.9f},{loc.lat[i]:.9f},{loc.h[i]:.3f},{c[i]:.3f},{r[i]:.3f},"
        f"{'gcp' if i < 30 else 'check'}"
        for i in range(40)
    ]
    csv = tmp_path / "gcps.csv"
    write_text_atomic(csv, "\n".join(rows) + "\n")
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    args = parser.parse_args(
        [
            "ortho",
            str(image),
            "--dem",
            str(dem_path),
            "-o",
            str(tmp_path / "o.tif"),
            "--model",
            "rational-1",
            "--gcps",
            str(csv),
            "--res",
            "1",
        ]
    )
    assert args.run(args) == 0
    out = capsys.readouterr().out
    assert "rational-1: 30 GCPs, 10 check points" in out
    few = tmp_path / "few.csv"
    write_text_atomic(few, "\n".join(rows[:4]) + "\n")
    args = parser.parse_args(
        [
            "ortho",
            str(image),
            "--dem",
            str(dem_path),
            "-o",
            str(tmp_path / "o5.tif"),
            "--model",
            "rational-3",
            "--gcps",
            str(few),
        ]
    )
    with pytest.raises(InputError):
        args.run(args)


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    """A 100 x 100 simulated ASTER-like left image with its model sidecar, the truth DEM and
    16 points (as ``points``)."""
    d = tmp_path_factory.mktemp("small_scene")
    sc = sim.simulate_scene("aster", size=(100, 100), seed=0, n_points=16)
    write_geotiff(d / "left.tif", sc.left)
    save_model(sc.left_model, d / "left.model.json")
    sc.truth_dem.write(d / "truth_dem.tif")
    return d, sc.points


def _points_with_roles(scene, path, role):
    _, pts = scene
    rows = ["id,lon,lat,h,col,row,role"] + [
        f"{p['id']},{p['lon']:.9f},{p['lat']:.9f},{p['h']:.3f},{p['col']:.4f},{p['row']:.4f},{role}"
        for p in pts
    ]
    path.write_text("\n".join(rows) + "\n")
    return path


def _ortho_gcp_args(scene, csv, out):
    d, _ = scene
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    return parser.parse_args(
        ["ortho", str(d / "left.tif"), "--dem", str(d / "truth_dem.tif"), "-o", str(out)]
        + ["--model", "poly2d-1", "--gcps", str(csv), "--workers", "1"]
    )


def test_cli_gcp_model_without_check_points_prints_no_nan(small_scene, tmp_path, capsys):
    """Every point a GCP: the summary said "check RMSE nan px"."""
    args = _ortho_gcp_args(
        small_scene, _points_with_roles(small_scene, tmp_path / "g.csv", "gcp"), tmp_path / "o.tif"
    )
    assert args.run(args) == 0
    out = capsys.readouterr().out
    assert "16 GCPs, 0 check points" in out and "nan" not in out, out
    assert "check RMSE n/a (no check point)" in out


def test_cli_gcp_model_with_only_check_points_is_refused(small_scene, tmp_path):
    """Every point a check point: ortho fitted the model to the check points and reported them
    as check points too (its "check RMSE" was the GCP RMSE); refused now, as adjust does."""
    csv = _points_with_roles(small_scene, tmp_path / "c.csv", "check")
    args = _ortho_gcp_args(small_scene, csv, tmp_path / "o.tif")
    with pytest.raises(InputError, match=r"c.csv: no GCP to fit --model poly2d-1.*role 'check'"):
        args.run(args)
    assert not (tmp_path / "o.tif").exists()


def test_cli_gcp_model_covers_the_whole_image(small_scene, tmp_path):
    """The generic model takes the image's size, not the GCPs' extent: the orthoimage covers
    the rows and columns beyond the outermost GCPs. Its grid is within 4 % of the physical
    model's (an affine model is not the physical one at the image's corners: 110 x 127 cells
    against 113 x 129); it was 15 % smaller (96 x 118)."""
    d, _ = small_scene
    csv = _points_with_roles(small_scene, tmp_path / "g.csv", "gcp")
    args = _ortho_gcp_args(small_scene, csv, tmp_path / "generic.tif")
    assert args.run(args) == 0
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    phys = parser.parse_args(
        ["ortho", str(d / "left.tif"), "--dem", str(d / "truth_dem.tif")]
        + ["-o", str(tmp_path / "physical.tif"), "--workers", "1"]
    )
    assert phys.run(phys) == 0
    with (
        rasterio.open(tmp_path / "generic.tif") as g,
        rasterio.open(tmp_path / "physical.tif") as p,
    ):
        for a, b in ((g.width, p.width), (g.height, p.height)):
            assert abs(a - b) <= 0.04 * b, (g.shape, p.shape)


def test_a_model_that_sees_no_ground_is_blamed_not_the_dem(small_scene, tmp_path):
    """A sidecar with an absurd tilt (89.9 degrees across track) localises no pixel on the
    Earth: the error was "DEM: no valid height under the image footprint lon nan..nan"."""
    d, _ = small_scene
    model = json.loads((d / "left.model.json").read_text())
    model["cross_track_tilt_deg"] = 89.9
    (tmp_path / "left.tif").write_bytes((d / "left.tif").read_bytes())
    (tmp_path / "left.model.json").write_text(json.dumps(model))
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    args = parser.parse_args(
        ["ortho", str(tmp_path / "left.tif"), "--dem", str(d / "truth_dem.tif")]
        + ["-o", str(tmp_path / "o.tif"), "--workers", "1"]
    )
    with pytest.raises(SensorModelError, match="localises no point of the image's border"):
        args.run(args)
    assert not (tmp_path / "o.tif").exists()


def test_ortho_overwrite_removes_the_layers_of_the_earlier_orthoimage(small_scene, tmp_path):
    """``ortho -o o.tif --overwrite`` without ``--layers`` kept an earlier run's
    o_incidence.tif / o_occlusion.tif beside the new orthoimage, which they no longer belong
    to (another DEM, grid or image). They are removed, as ``dem --overwrite`` removes the
    earlier job's companions; a layer asked for again is rewritten, and a file of the user's
    by a layer's name is left."""
    d, _ = small_scene
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    base = ["ortho", str(d / "left.tif"), "--dem", str(d / "truth_dem.tif")]
    base += ["-o", str(tmp_path / "o.tif"), "--workers", "1"]
    args = parser.parse_args([*base, "--layers", "incidence,occlusion"])
    assert args.run(args) == 0
    inc, occ = tmp_path / "o_incidence.tif", tmp_path / "o_occlusion.tif"
    assert inc.exists() and occ.exists()
    args = parser.parse_args([*base, "--overwrite", "--layers", "occlusion"])
    assert args.run(args) == 0
    assert not inc.exists() and occ.exists()
    args = parser.parse_args([*base, "--overwrite"])
    assert args.run(args) == 0
    assert not occ.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.tif"]
    inc.write_text("the user's own notes\n")
    assert args.run(args) == 0
    assert inc.read_text() == "the user's own notes\n"


def test_orthorectify_given_no_model_or_an_unknown_crs_says_so(rendered):
    """``model=None`` raised an AttributeError from inside the DRM, and ``crs="foo"`` pyproj's
    own CRSError, not stereodem's."""
    cam, dem, grid, img, _ = rendered
    with pytest.raises(InputError, match="model must be a sensor model"):
        orthorectify(img, None, dem, grid=grid)
    with pytest.raises(
        StereodemCRSError, match="the orthoimage CRS: unknown or unusable CRS 'foo'"
    ):
        orthorectify(img, cam, dem, crs="foo")


@pytest.mark.slow
def test_result_line_and_tags_give_the_posting_in_the_crs_unit(tmp_path, capsys):
    """`ortho` said "cells of 15.2 in EPSG:32637" from a field named res_m, which is in the
    CRS's units: now "cells of 15.2 m" (options.posting), and the report/tags carry res and
    res_unit, with res_m only on a metre grid (on a feet grid it was feet)."""
    sc = sim.simulate_scene("aster", size=(80, 80), seed=0, n_points=1)
    write_geotiff(tmp_path / "img.tif", sc.left)
    save_model(sc.left_model, tmp_path / "img.model.json")
    sc.truth_dem.write(tmp_path / "dem.tif")
    img, dem = str(tmp_path / "img.tif"), str(tmp_path / "dem.tif")
    assert main(["ortho", img, "--dem", dem, "--res", "15", "-o", str(tmp_path / "m.tif")]) == 0
    assert "cells of 15 m in EPSG:32637" in capsys.readouterr().out
    with rasterio.open(tmp_path / "m.tif") as ds:
        tags = ds.tags()
    assert (tags["STEREODEM_RES"], tags["STEREODEM_RES_UNIT"], tags["STEREODEM_RES_M"]) == (
        "15.0",
        "metre",
        "15.0",
    )
    feet = "+proj=utm +zone=37 +datum=WGS84 +units=us-ft +type=crs"
    argv = ["ortho", img, "--dem", dem, "--crs", feet, "--res", "50", "-o", str(tmp_path / "f.tif")]
    assert main(argv) == 0
    assert "cells of 50 US survey foot in " in capsys.readouterr().out
    with rasterio.open(tmp_path / "f.tif") as ds:
        tags = ds.tags()
    assert tags["STEREODEM_RES_UNIT"] == "US survey foot" and "STEREODEM_RES_M" not in tags
    # the uncertainty maps' sensitivity.json: the same fields
    u = tmp_path / "u"
    assert main(["uncertainty", img, "--dem", dem, "--sigma", "dem_height=4", "-o", str(u)]) == 0
    grid = json.loads((u / "sensitivity.json").read_text())["grid"]
    assert grid["res_unit"] == "metre" and grid["res"] == grid["res_m"]


def test_an_image_that_is_not_its_models_is_refused(tmp_path):
    """``orthorectify(image[:50], model, dem)`` (an image of another size than its model
    describes) only logged a warning and returned an orthoimage of the wrong pixels (NaN
    where the crop ends; a decimated image's pixels taken for the model's); ``make_dem``
    refuses the same. A path given as the image was "expected a 2-D
    image, got shape ()"."""
    sc = sim.simulate_scene("aster", size=(80, 80), seed=0, n_points=1)
    with pytest.raises(InputError, match=r"image shape \(50, 80\) differs from its model's"):
        orthorectify(sc.left[:50], sc.left_model, sc.truth_dem, res=30.0)
    with pytest.raises(InputError, match=r"left.tif is a path: read it first"):
        orthorectify(str(tmp_path / "left.tif"), sc.left_model, sc.truth_dem, res=30.0)
