import json

import numpy as np
import pytest
import rasterio
from affine import Affine

from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError, OutputExistsError
from stereodem.sensor.estimation.rpcfit import fit_rpc
from stereodem.sensor.io.sidecar import load_image_model
from stereodem.sensor.simulation.simulate import (
    aster_geometry_parameters,
    psf_sigma,
    simulate_scene,
    write_scene,
)


def _parallax_per_km(left, right, col, row):
    """Relative image displacement (right minus left, px) of a ground column from 1 to 2 km."""
    lon, lat = left.localize(col, row, 2000.0)
    d = []
    for m in (left, right):
        c1, r1 = m.project(lon, lat, 1000.0)
        c2, r2 = m.project(lon, lat, 2000.0)
        d.append(np.array([c2 - c1, r2 - r1]))
    return d[1] - d[0]


@pytest.fixture(scope="module")
def frame_scene():
    return simulate_scene("frame", size=(256, 240), seed=3, noise=1.0)


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_reproducible_from_seed(frame_scene):
    again = simulate_scene("frame", size=(256, 240), seed=3, noise=1.0)
    assert np.array_equal(again.left, frame_scene.left) and np.array_equal(
        again.right, frame_scene.right
    )
    other = simulate_scene("frame", size=(256, 240), seed=4, noise=1.0)
    assert not np.array_equal(other.left, frame_scene.left)


def test_images_are_textured_and_quantised(frame_scene):
    for img in (frame_scene.left, frame_scene.right):
        assert img.dtype == np.uint8 and img.shape == (240, 256)
        assert img.std() > 10  # real texture and shading
        assert (img == 0).mean() < 0.01  # no black (nodata) areas inside the scene
    sc16 = simulate_scene("frame", size=(64, 64), seed=3, bits=16)
    assert sc16.left.dtype == np.uint16 and sc16.left.max() > 255


def test_rendering_follows_the_exact_models(frame_scene):
    # the coarse-grid renderer agrees with the exact models (reported, and small)
    d = frame_scene.diagnostics
    assert d["left_render_error_px"] < 0.01 and d["right_render_error_px"] < 0.01
    # check points: exact DEM localisation of the left pixel projects into the right image
    # where the right image shows the same ground (texture correlation around the point)
    p = frame_scene.points[0]
    col, row = frame_scene.right_model.project(p["lon"], p["lat"], p["h"])
    assert col == pytest.approx(p["col_right"], abs=1e-6) and row == pytest.approx(
        p["row_right"], abs=1e-6
    )
    # truth DEM height at the point matches the point's height (DEM is the surface)
    assert frame_scene.truth_dem.sample(p["lon"], p["lat"]) == pytest.approx(p["h"], abs=0.05)


def test_truth_grid_is_utm_and_ellipsoidal(frame_scene):
    dem = frame_scene.truth_dem
    assert dem.vertical == "ellipsoid"
    assert dem.crs.to_epsg() == geodesy.utm_epsg(40.42, 39.58)
    assert frame_scene.truth_ortho.shape == dem.shape
    # ellipsoidal = SRTM (geoid) + ~29.6 m here
    lo, hi = dem.height_range()
    assert 1100 < lo < hi < 3400


def test_stereo_parallax_is_along_track(frame_scene):
    """The two views see the same ground point at rows differing with height (B/H ~ 0.6)."""
    par = _parallax_per_km(frame_scene.left_model, frame_scene.right_model, 128.0, 120.0)
    # 1000 m of height gives B/H * 1000 m of parallax, B/H = 0.6 by construction
    assert np.hypot(*par) * frame_scene.settings["gsd"] == pytest.approx(600.0, rel=0.1)
    assert abs(par[1]) > 5 * abs(par[0])  # along the rows (flight)


def test_aster_preset_geometry():
    sc = simulate_scene("aster", size=(200, 180), seed=0, n_points=10)
    assert sc.settings["gsd"] == pytest.approx(15.0, rel=0.02)
    par = _parallax_per_km(sc.left_model, sc.right_model, 100.0, 90.0)
    # 3N near nadir, 3B 27.7 deg backward: B/H ~ 0.53-0.6, i.e. that many metres of parallax
    # per metre of height, along the rows (both views share the ~8.6 deg cross-track pointing)
    assert 0.5 < np.hypot(*par) * 15.0 / 1000.0 < 0.65
    assert abs(par[1]) > 5 * abs(par[0])
    assert sc.diagnostics["right_render_error_px"] < 0.01


def test_write_scene_outputs(tmp_path, frame_scene):
    out = write_scene(frame_scene, tmp_path / "sim")
    for name in (
        "left.tif",
        "right.tif",
        "left.model.json",
        "right.model.json",
        "truth_dem.tif",
        "truth_ortho.tif",
        "points.csv",
        "scene.json",
    ):
        assert (out / name).exists(), name
    with rasterio.open(out / "left.tif") as ds:
        assert ds.rpcs is not None and ds.width == 256
    meta = json.loads((out / "scene.json").read_text())
    assert meta["rpc_fit"]["left"]["check_rms"] < 0.01

    m = load_image_model(out / "left.tif")
    c, r = m.project(*frame_scene.left_model.localize(10.0, 20.0, 1500.0), 1500.0)
    assert (float(c), float(r)) == pytest.approx((10.0, 20.0), abs=1e-6)
    with pytest.raises(OutputExistsError):
        write_scene(frame_scene, out)


def test_bad_input():
    with pytest.raises(InputError, match="unknown preset"):
        simulate_scene("spot")
    with pytest.raises(InputError, match="too small"):
        simulate_scene("frame", size=(8, 8))


def test_dem_across_the_antimeridian():
    """``simulate --dem`` with a lon/lat DEM across 180 (179.68..180.28 E at 65 N, Kamchatka or
    Alaska): the footprint check compared the footprint's longitudes (-180..180, so
    -179.99..179.99: the whole world) with the DEM's and refused ("the DEM does not cover the
    simulated scene"), and the DEM's cells east of 180 were outside for the truth's warp.
    The truth DEM is in zone 60 and holds the DEM's heights where they are."""

    def height(lon, lat):  # smooth relief, longitudes beside 180
        lon = geodesy.lon_beside(lon, 180.0)
        return 800.0 + 150.0 * np.sin((lon - 180.0) * 60.0) * np.cos((lat - 65.0) * 40.0)

    res_lon, res_lat = 0.0012, 0.0005
    cols, rows = 500, 400
    t = Affine(res_lon, 0.0, 179.68, 0.0, -res_lat, 65.1)
    lon, lat = t @ np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    dem = DEM(height(lon, lat).astype(np.float32), t, "EPSG:4326", "ellipsoid")
    sc = simulate_scene("aster", size=(100, 100), seed=0, n_points=4, dem=dem)
    truth = sc.truth_dem
    assert truth.crs.to_epsg() == 32660
    tlon, tlat = truth.grid.lonlat(
        *np.meshgrid(np.arange(truth.shape[1]), np.arange(truth.shape[0]))
    )
    assert tlon.min() < -179.9 and tlon.max() > 179.9  # the scene crosses 180
    assert np.isfinite(truth.heights).all()
    assert np.abs(truth.heights - height(tlon, tlat)).max() < 0.5


def test_dem_that_just_covers_the_scene(tmp_path):
    """``simulate --dem`` with a DEM that just covers the scene (here the truth DEM of a
    larger scene): some of the check points' candidate pixels localise off the DEM (NaN), and
    projecting them into the right image raised "PushbroomModel: non-finite ground
    coordinates given"; they are skipped. A texture that is not an image names the file."""
    big = simulate_scene("aster", size=(200, 200), seed=0, n_points=1)
    sc = simulate_scene("aster", size=(100, 100), seed=0, n_points=20, dem=big.truth_dem)
    assert len(sc.points) == 20
    bad = tmp_path / "texture.tif"
    bad.write_text("not an image\n")
    with pytest.raises(InputError, match="texture.tif: cannot read the texture image"):
        simulate_scene("frame", size=(64, 64), texture=bad)


def test_aster_preset_uses_real_granule_geometry():
    p = aster_geometry_parameters()
    assert p["bands"]["3B"]["along_deg"] == pytest.approx(-27.7, abs=0.2)  # backward band
    assert abs(p["bands"]["3N"]["along_deg"]) < 0.1  # nadir band
    assert 8 < p["cross_track_right_deg"] < 9  # real pointing
    assert 700e3 < p["altitude_m"] < 715e3 and 14.5 < p["gsd_m"] < 15.5


@pytest.mark.parametrize("which", ["left", "right"])
@pytest.mark.slow
def test_rpc_fitted_to_aster_preset_reproduces_it(which):
    sc = simulate_scene("aster", size=(600, 600), seed=0, n_points=4)
    model = getattr(sc, f"{which}_model")
    rpc, rep = fit_rpc(model, height_range=(500.0, 4000.0))
    assert rep.check_max < 0.01  # px, on the independent check grid
    # and independently of the report: random points
    rng = np.random.default_rng(0)
    c, r, h = rng.uniform(0, 599, 500), rng.uniform(0, 599, 500), rng.uniform(500, 4000, 500)
    lon, lat = model.localize(c, r, h)
    pc, pr = rpc.project(lon, lat, h)
    assert np.hypot(pc - c, pr - r).max() < 0.01


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_system_psf_mtf_and_band_limit():
    """The Gaussian system PSF has the stated MTF at Nyquist, and a lower MTF removes the
    image's high-frequency content (power near Nyquist falls, the low band stays)."""
    for mtf in (0.3, 0.1):
        s = psf_sigma(mtf)
        assert np.exp(-2 * np.pi**2 * s**2 * 0.25) == pytest.approx(mtf, rel=1e-9)
    assert 0.45 < psf_sigma(0.3) < 0.55  # ~0.5 GSD for ASTER-like 0.3
    with pytest.raises(InputError):
        simulate_scene("frame", size=(64, 64), mtf_nyquist=1.5)

    def band_power(img):
        a = img.astype(np.float64)[16:-16, 16:-16]
        win = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1]))
        f = np.abs(np.fft.fft2((a - a.mean()) * win)) ** 2
        fr = np.fft.fftfreq(a.shape[0])[:, None], np.fft.fftfreq(a.shape[1])[None, :]
        r = np.maximum(np.abs(fr[0]), np.abs(fr[1]))
        return f[(r > 0.02) & (r < 0.1)].sum(), f[r > 0.35].sum()

    lo3, hi3 = band_power(simulate_scene("frame", size=(160, 160), seed=3, bits=16, noise=0.0).left)
    lo1, hi1 = band_power(
        simulate_scene("frame", size=(160, 160), seed=3, bits=16, noise=0.0, mtf_nyquist=0.1).left
    )
    # Gaussian MTF ratio squared at 0.35 cycle/px (the weakest attenuation in the band)
    bound = np.exp(-4 * np.pi**2 * 0.35**2 * (psf_sigma(0.1) ** 2 - psf_sigma(0.3) ** 2))
    print(hi1 / hi3, bound, lo1 / lo3)
    assert hi1 < bound * hi3 and lo1 > 0.7 * lo3


def test_second_image_may_be_larger_like_aster_3b():
    """ASTER's 3B image is wider and longer than 3N; the preset renders it whole."""
    sc = simulate_scene("aster", size=(200, 180), right_size=(240, 210), seed=3, n_points=10)
    assert sc.left.shape == (180, 200) and sc.right.shape == (210, 240)
    assert (sc.right_model.width, sc.right_model.height) == (240, 210)
    assert np.isfinite(sc.right).all() and sc.right.std() > 5
    assert sc.settings["right_size"] == [240, 210]
    # the larger image sees more ground: its footprint contains the left one's centre area
    h = float(np.nanmean(sc.truth_dem.heights))
    lon, lat = sc.left_model.localize(np.array([100.0]), np.array([90.0]), np.array([h]))
    c, r = sc.right_model.project(lon, lat, np.array([h]))
    assert 20 < c[0] < 220 and 15 < r[0] < 195
    with pytest.raises(InputError, match="frame preset"):
        simulate_scene("frame", size=(64, 64), right_size=(80, 64))
