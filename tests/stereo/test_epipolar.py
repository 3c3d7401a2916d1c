"""Epipolar resampling: residual vertical parallax per tile, maps, resampling, disparity range."""

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from stereodem.core.errors import InputError
from stereodem.sensor.io.aster_xml import bundled_xml
from stereodem.sensor.models.corrected import ImageCorrectedModel
from stereodem.sensor.models.parameters import project_jacobian
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation.simulate import frame_pair, pushbroom_pair
from stereodem.stereo.epipolar import apply_map, rectify_tile, virtual_matches
from stereodem.stereo.tiling import Tile, tile_grid


def _aster_rpc(path):
    """ASP's RPC fit of the real ASTER 3N/3B geometry (tests/data/aster, uw-cryo/asp_plot)."""
    root = ET.parse(path).getroot()
    im = root.find("RPB/IMAGE")
    g = lambda t: float(im.find(t).text)  # noqa: E731
    co = lambda t: [float(x) for x in im.find(f"{t}List/{t}").text.split()]  # noqa: E731
    return RPCModel(
        line_num=co("LINENUMCOEF"),
        line_den=co("LINEDENCOEF"),
        samp_num=co("SAMPNUMCOEF"),
        samp_den=co("SAMPDENCOEF"),
        line_off=g("LINEOFFSET"),
        samp_off=g("SAMPOFFSET"),
        line_scale=g("LINESCALE"),
        samp_scale=g("SAMPSCALE"),
        lon_off=g("LONGOFFSET"),
        lat_off=g("LATOFFSET"),
        lon_scale=g("LONGSCALE"),
        lat_scale=g("LATSCALE"),
        height_off=g("HEIGHTOFFSET"),
        height_scale=g("HEIGHTSCALE"),
        width=int(root.find(".//IMAGE_COLS").text),
        height=int(root.find(".//IMAGE_ROWS").text),
    )


def _worst_tile(left, right, size, hr, tile=512, **kw):
    tiles = tile_grid(size[0], size[1], tile)
    ets = [rectify_tile(left, right, t, hr, **kw) for t in tiles]
    return ets, max(e.residual_rms for e in ets)


def test_tile_grid_covers_window_exactly():
    tiles = tile_grid(1031, 1102, 512, window=(10, 20, 1000, 1090))
    area = sum(t.cols * t.rows for t in tiles)
    assert area == (1000 - 10 + 1) * (1090 - 20 + 1)
    assert all(400 <= t.cols <= 600 and 400 <= t.rows <= 600 for t in tiles)
    assert min(t.col0 for t in tiles) == 10 and max(t.bounds[3] for t in tiles) == 1090


@pytest.mark.slow
def test_aster_like_pushbroom_pair_full_scene_parallax():
    """Synthetic ASTER 3N/3B (4100 x 4200 px, 15 m, 27.6 deg backward), 512 px tiles: <= 0.05 px."""
    left, right = pushbroom_pair(40.4, 39.6, 2000.0, (4100, 4200), (0.0, -27.6))
    ets, worst = _worst_tile(left, right, (4100, 4200), (500.0, 4000.0))
    assert worst <= 0.05, worst
    assert all(e.method == "affine" for e in ets)
    # B/H ~0.6 at 15 m: ~0.04 px of disparity per metre of height
    assert 0.03 < abs(ets[0].px_per_m) < 0.05


def test_real_aster_geometry_parallax():
    """ASP's RPCs of a real ASTER 3N/3B granule, 0-4400 m: every 512 px tile <= 0.05 px."""
    left = _aster_rpc(bundled_xml("3N"))
    right = _aster_rpc(bundled_xml("3B"))
    _, worst = _worst_tile(left, right, (left.width, left.height), (0.0, 4400.0))
    assert worst <= 0.05, worst


def test_pleiades_rpc_parallax(data_dir):
    """The real Pleiades pair's RPCs (s2p test data), 512 px tiles: <= 0.1 px per tile."""
    left = RPCModel.from_file(data_dir / "pleiades" / "img_01_rpc.tif")
    right = RPCModel.from_file(data_dir / "pleiades" / "img_02_rpc.tif")
    assert (left.width, left.height) == (1024, 1024)
    ets, worst = _worst_tile(left, right, (1024, 1024), (2100.0, 2600.0))
    assert worst <= 0.1, worst
    # the disparity range spans the heights: the virtual matches' disparities lie inside it
    et = ets[0]
    x1, x2, h = virtual_matches(left, right, et.tile.bounds, [2100.0, 2600.0], n=5)
    u1, _ = apply_map(et.H_left, x1[:, 0], x1[:, 1])
    u2, _ = apply_map(et.H_right, x2[:, 0], x2[:, 1])
    d = u1 - u2
    assert et.disparity_range[0] < d.min() and d.max() < et.disparity_range[1]
    assert et.disparity_range[1] - et.disparity_range[0] < d.max() - d.min() + 8.01


def test_frame_pair_projective_and_zero_disparity_at_mean_height():
    left, right = frame_pair(40.4, 39.6, 2000.0, (1024, 1024))
    ets, worst = _worst_tile(left, right, (1024, 1024), (1000.0, 3000.0))
    assert ets[0].method == "projective"
    assert worst <= 0.05, worst
    et = ets[0]
    x1, x2, _ = virtual_matches(left, right, et.tile.bounds, [2000.0], n=6)
    u1, v1 = apply_map(et.H_left, x1[:, 0], x1[:, 1])
    u2, v2 = apply_map(et.H_right, x2[:, 0], x2[:, 1])
    assert np.abs(u1 - u2).max() < 0.5  # shear registration: d ~ 0 at the mean height
    assert np.abs(v1 - v2).max() < 0.1


def test_affine_maps_keep_row_scale_and_resample_content():
    left, right = pushbroom_pair(40.4, 39.6, 2000.0, (600, 600), (0.0, -27.6))
    t = Tile(0, 10, 300, 280)
    et = rectify_tile(left, right, t, (1500.0, 3000.0))
    assert et.is_affine
    # rows are not stretched: the left map is a similarity (rotation x zoom), orthogonal axes
    A = et.H_left[:2, :2]
    assert abs(A[:, 0] @ A[:, 1]) < 1e-9 * np.abs(A).max() ** 2
    assert abs(np.linalg.norm(A[:, 0]) / np.linalg.norm(A[:, 1]) - 1) < 1e-9
    # resampling puts image content where the map says
    rr, cc = np.mgrid[0:600, 0:600].astype(np.float64)
    f = lambda c, r: 0.3 * c + 0.7 * r + 5e-4 * c * r  # noqa: E731
    img = f(cc, rr).astype(np.float32)
    L, R = et.rectify(img, img)
    assert L.shape == et.shape and L.dtype == np.float32
    v, u = np.mgrid[0 : L.shape[0] : 7, 0 : L.shape[1] : 7].astype(float)
    c, r = apply_map(np.linalg.inv(et.H_left), u, v)
    inside = (c > 2) & (c < 597) & (r > 2) & (r < 597)
    got = L[v.astype(int), u.astype(int)]
    assert np.isfinite(got[inside]).all()
    assert np.abs(got[inside] - f(c[inside], r[inside])).max() < 0.02
    outside = (c < -3) | (c > 602) | (r < -3) | (r > 602)
    assert outside.any() and np.isnan(got[outside]).all()
    # to_image inverts the maps
    (c1, r1), (c2, r2) = et.to_image(u, v, np.full(u.shape, 3.0))
    uu, vv = apply_map(et.H_right, c2, r2)
    assert np.allclose(uu, u - 3.0, atol=1e-9) and np.allclose(vv, v, atol=1e-9)


def test_shifted_model_translates_image_coordinates():
    left, _ = frame_pair(40.4, 39.6, 2000.0, (512, 512))
    sm = ImageCorrectedModel(left, col_shift=1.25, row_shift=-0.5)
    lon, lat = left.localize(100.0, 200.0, 1500.0)
    c, r = sm.project(lon, lat, 1500.0)
    assert c == pytest.approx(101.25, abs=1e-6) and r == pytest.approx(199.5, abs=1e-6)
    lon2, lat2 = sm.localize(101.25, 199.5, 1500.0)
    assert lon2 == pytest.approx(lon, abs=1e-10) and lat2 == pytest.approx(lat, abs=1e-10)
    o1, d1 = left.rays(100.0, 200.0)
    o2, d2 = sm.rays(101.25, 199.5)
    assert np.allclose(d1, d2, atol=1e-12)
    assert sm.height_bounds() == left.height_bounds()


def test_unusable_height_range_raises():
    left, right = frame_pair(40.4, 39.6, 2000.0, (256, 256))
    with pytest.raises(InputError):
        rectify_tile(left, right, Tile(0, 0, 256, 256), (3000.0, 1000.0))
    with pytest.raises(InputError):
        rectify_tile(left, right, Tile(0, 0, 256, 256), (np.nan, 1000.0))


def test_image_correction_affine_inverse_and_partials():
    left, _ = frame_pair(40.4, 39.6, 2000.0, (512, 512))
    cm = ImageCorrectedModel(
        left, col_shift=2.0, row_shift=-1.0, col_drift_row=1e-3, row_drift_col=-2e-3
    )
    c0 = np.array([10.0, 250.0, 500.0])
    r0 = np.array([20.0, 260.0, 490.0])
    lon, lat = cm.localize(c0, r0, 1500.0)
    c, r = cm.project(lon, lat, np.full(3, 1500.0))
    assert np.allclose(c, c0, atol=1e-6) and np.allclose(r, r0, atol=1e-6)
    # analytic partials agree with central differences through with_parameters
    names = list(cm.parameters())
    _, _, J = project_jacobian(cm, lon, lat, np.full(3, 1500.0), names)
    for k, n in enumerate(names):
        p = cm.parameters()[n]
        step = 1e-3
        cp, rp = cm.with_parameters(**{n: p + step}).project(lon, lat, 1500.0)
        cq, rq = cm.with_parameters(**{n: p - step}).project(lon, lat, 1500.0)
        assert np.allclose(J[:, 0, k], (cp - cq) / (2 * step), atol=1e-6)
        assert np.allclose(J[:, 1, k], (rp - rq) / (2 * step), atol=1e-6)
    with pytest.raises(Exception, match="unknown parameter"):
        cm.with_parameters(focal=1.0)


def test_numeric_jacobian_of_pushbroom_parameters():
    left, _ = pushbroom_pair(40.4, 39.6, 2000.0, (400, 400), (0.0, -27.6))
    lon, lat = left.localize(np.array([50.0, 200.0]), np.array([60.0, 300.0]), 2000.0)
    h = np.full(2, 2000.0)
    _, _, J = project_jacobian(left, lon, lat, h, ["pitch_bias", "roll_bias"])
    # a pitch bias moves the image along track (rows), a roll bias across track (columns)
    assert np.all(np.abs(J[:, 1, 0]) > 10 * np.abs(J[:, 0, 0]))
    assert np.all(np.abs(J[:, 0, 1]) > 10 * np.abs(J[:, 1, 1]))


@pytest.mark.parametrize("order", [1, 3])
def test_affine_warp_is_the_general_warp(order):
    """An affine map (pushbroom tiles) is warped by ``ndimage.affine_transform``, the general
    (projective) one by ``map_coordinates`` on coordinate arrays: for the same map, written as
    a homography whose last row is (0, 0, 2) (the same map, not detected as affine), the two
    give the same pixels, NaN alike (outside the image, at its cropped edges, around no-data),
    the values within float32 rounding."""
    from stereodem.stereo.epipolar import _warp

    rng = np.random.default_rng(7)
    img = rng.normal(100, 20, (900, 1000)).astype(np.float32)
    img[400:404, 200:700] = np.nan
    for _ in range(6):
        th, s = rng.uniform(-0.3, 0.3), rng.uniform(0.8, 1.2)
        H = np.array(
            [
                [s * np.cos(th), -s * np.sin(th) + rng.uniform(-0.1, 0.1), rng.uniform(-300, 50)],
                [s * np.sin(th), s * np.cos(th), rng.uniform(-300, 50)],
                [0.0, 0.0, 1.0],
            ]
        )
        shape = (int(rng.integers(200, 600)), int(rng.integers(200, 700)))
        fast, general = _warp(img, H, shape, order), _warp(img, 2.0 * H, shape, order)
        assert np.array_equal(np.isfinite(fast), np.isfinite(general))
        ok = np.isfinite(fast)
        assert ok.mean() > 0.2 and (~ok).any()
        np.testing.assert_allclose(fast[ok], general[ok], rtol=2e-7, atol=1e-4)
