"""Orthorectification onto a DEM with holes or partial coverage: nodata there, the share of
the footprint reported, and a second DEM (``fill_dem``) filling them."""

import argparse
import logging
from importlib import resources

import numpy as np
import pytest
import rasterio
from affine import Affine
from test_ortho import _rpc_setup, albedo_field, oblique_camera  # the shared scene builders

from stereodem.core import geodesy as g
from stereodem.core.dem import DEM
from stereodem.core.errors import RPCError
from stereodem.core.raster import write_geotiff
from stereodem.ortho.concurrent import orthorectify_all
from stereodem.ortho.drm import orthorectify
from stereodem.ortho.grid import grid_for_model
from stereodem.ortho_cli import add_parser


@pytest.fixture(scope="module")
def scene():
    cam = oblique_camera(size=256)
    dem = DEM.bundled()
    grid = grid_for_model(cam, dem)
    f = albedo_field(grid.res[0])
    cc, rr = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    loc = cam.localize_dem(cc, rr, dem, threshold=0.01)
    x, y = g.lonlat_to_crs(loc.lon, loc.lat, grid.crs)
    return cam, dem, grid, f(x, y).astype(np.float32)


def _holed(dem, cam, name):
    """``dem`` with a 40 x 40-cell void under the image centre."""
    lon, lat = cam.localize(np.array([cam.width / 2]), np.array([cam.height / 2]), 2000.0)
    c, r = ~dem.transform @ (lon, lat)
    h = dem.heights.copy()
    h[int(r[0]) - 20 : int(r[0]) + 20, int(c[0]) - 20 : int(c[0]) + 20] = np.nan
    return DEM(h, dem.transform, dem.crs, dem.vertical, name)


def test_holes_give_nodata_and_a_warning_with_the_share(scene, caplog):
    cam, dem, grid, img = scene
    full = orthorectify(img, cam, dem, grid=grid)
    holed = _holed(dem, cam, "holed.tif")
    with caplog.at_level(logging.WARNING):
        o = orthorectify(img, cam, holed, grid=grid, strict_dem=True)  # holes are not an error
    lost = full.valid & ~o.valid
    assert lost.sum() > 100
    share = o.dem_missing["footprint_share"]
    assert share == pytest.approx(o.dem_missing["n_no_height"] / full.valid.sum(), rel=0.05)
    assert share == pytest.approx(lost.sum() / full.valid.sum(), rel=0.1)
    msg = [r.getMessage() for r in caplog.records if "no DEM height" in r.getMessage()]
    assert len(msg) == 1 and "holed.tif" in msg[0] and f"{100 * share:.1f}%" in msg[0]
    assert o.report()["dem_no_height_share"] == share


def test_several_images_warnings_say_which_image(scene, caplog):
    """``stereodem run`` orthorectifies the left and right images: their two "no DEM height"
    warnings both read "of the image footprint", naming the DEM only. Each now says which
    image; one image alone keeps the plain wording."""
    cam, dem, grid, img = scene
    holed = _holed(dem, cam, "holed.tif")
    with caplog.at_level(logging.WARNING, logger="stereodem.ortho.drm"):
        orthorectify_all([("left", img, cam), ("right", img, cam)], holed, grid=grid)
    msgs = [r.getMessage() for r in caplog.records if "no DEM height" in r.getMessage()]
    assert sorted(m.split(" footprint")[0].split("% of ")[1] for m in msgs) == [
        "the left image's",
        "the right image's",
    ]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="stereodem.ortho.drm"):
        orthorectify_all([("image", img, cam)], holed, grid=grid)
    assert "% of the image footprint" in caplog.text


def test_fill_dem_fills_holes_and_missing_coverage(scene):
    cam, dem, grid, img = scene
    full = orthorectify(img, cam, dem, grid=grid)
    holed = _holed(dem, cam, "holed.tif")
    # a primary DEM with a hole that also stops short of the footprint's western part
    west_cut = DEM(
        holed.heights[:, 470:],
        holed.transform @ Affine.translation(470, 0),
        holed.crs,
        holed.vertical,
        "partial.tif",
    )
    alone = orthorectify(img, cam, west_cut, grid=grid)
    assert alone.dem_missing["n_cells"] > 100  # part of the footprint is off the DEM
    assert alone.dem_missing["n_no_height"] > alone.dem_missing["n_cells"]  # and the hole
    o = orthorectify(img, cam, west_cut, grid=grid, fill_dem=dem)
    assert o.dem_missing["n_no_height"] == 0 and o.dem_missing["filled_cells"] > 100
    assert np.array_equal(o.valid, full.valid)
    d = o.data[full.valid] - full.data[full.valid]
    assert np.max(np.abs(d)) < 1e-3


def test_bundled_srtm_declares_its_vertical_reference():
    path = resources.files("stereodem.core") / "data" / "srtm_ref.tif"
    assert DEM.from_file(path).vertical == "geoid"  # no --ref-vertical / --dem-vertical needed


@pytest.mark.slow
def test_cli_dem_with_holes_and_fill_dem(tmp_path, data_dir, caplog):
    model, rpcs, dem_path, img = _rpc_setup(tmp_path, data_dir)
    image = tmp_path / "img.tif"
    write_geotiff(image, img, rpcs=rpcs)
    full = DEM.from_file(dem_path)
    h = full.heights.copy()
    r0, c0 = h.shape[0] // 2, h.shape[1] // 2
    h[r0 - 30 : r0 + 30, c0 - 30 : c0 + 30] = np.nan  # a hole under the image
    holed = tmp_path / "holed.tif"
    DEM(h, full.transform, full.crs, "ellipsoid").write(holed)
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())

    def ortho(*extra, out):
        args = parser.parse_args(
            ["ortho", str(image), "--dem", str(holed), "-o", str(out), "--res", "1", *extra]
        )
        assert args.run(args) == 0
        with rasterio.open(out) as ds:
            return ds.read(1)

    ref = parser.parse_args(
        ["ortho", str(image), "--dem", str(dem_path), "-o", str(tmp_path / "ref.tif"), "--res", "1"]
    )
    assert ref.run(ref) == 0
    with rasterio.open(tmp_path / "ref.tif") as ds:
        a_ref = ds.read(1)
    with caplog.at_level(logging.WARNING):
        a_holed = ortho(out=tmp_path / "holed_ortho.tif")  # holes: exit 0, nodata there
    assert any(
        "no DEM height under" in r.getMessage() and "--fill-dem" in r.getMessage()
        for r in caplog.records
    )
    lost = np.isfinite(a_ref) & ~np.isfinite(a_holed)
    assert lost.sum() > 1000
    a_fill = ortho("--fill-dem", str(dem_path), out=tmp_path / "filled_ortho.tif")
    assert np.array_equal(np.isfinite(a_fill), np.isfinite(a_ref))
    assert np.nanmax(np.abs(a_fill - a_ref)) < 1e-3


def test_rpc_ortho_on_heights_outside_its_validity_range(tmp_path, data_dir):
    model, rpcs, dem_path, img = _rpc_setup(tmp_path, data_dir)
    dem = DEM.from_file(dem_path)
    feet = DEM(dem.heights * 3.28084, dem.transform, dem.crs, "ellipsoid", "dem_in_feet.tif")
    with pytest.raises(RPCError) as e:
        orthorectify(img, model, feet)
    msg = str(e.value)
    assert "\n" not in msg and "outside the RPC validity range" in msg
