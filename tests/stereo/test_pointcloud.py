"""Point clouds of the stereo DEM (issue 26 item 5): tiles write their points, merged into one
LAS/LAZ in chunks (laspy), CRS in a WKT VLR, extra dimensions, the filters' classification."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import CRS
from scipy.ndimage import map_coordinates

from stereodem.cli import main
from stereodem.config import config_from_dict
from stereodem.core import geodesy
from stereodem.core.errors import InputError
from stereodem.core.grid import MapGrid
from stereodem.pipeline.job import run
from stereodem.sensor.simulation.simulate import simulate_scene, write_scene
from stereodem.stereo.pointcloud import FUSION_REJECTED, read_pairs, save_tile_points, write_las

laspy = pytest.importorskip("laspy")
pytest.importorskip("lazrs")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("pc_scene")
    write_scene(simulate_scene("aster", size=(300, 300), seed=2, n_points=10), d, overwrite=True)
    return d


def _bilinear(path, x, y):
    """The raster interpolated bilinearly at map points (NaN next to voids and outside)."""
    with rasterio.open(path) as ds:
        a = ds.read(1).astype(np.float64)
        col, row = ~ds.transform @ (np.asarray(x), np.asarray(y))
    return map_coordinates(a, [row - 0.5, col - 0.5], order=1, cval=np.nan)


def _cell_values(path, x, y, band=1):
    with rasterio.open(path) as ds:
        a = ds.read(band)
        col, row = ~ds.transform @ (np.asarray(x), np.asarray(y))
    c, r = np.floor(col).astype(int), np.floor(row).astype(int)
    ok = (c >= 0) & (r >= 0) & (c < a.shape[1]) & (r < a.shape[0])
    out = np.full(len(c), np.nan)
    out[ok] = a[r[ok], c[ok]]
    return out


@pytest.mark.slow
def test_dem_point_cloud_lies_on_the_dem(scene_dir, tmp_path):
    out = tmp_path / "dem"
    assert (
        main(
            [
                "-q",
                "dem",
                str(scene_dir / "left.tif"),
                str(scene_dir / "right.tif"),
                "-o",
                str(out),
                "--tile-size",
                "200",
                "--height-range",
                "1000",
                "3500",
                "--workers",
                "1",
                "--point-cloud",
                "laz",
            ]
        )
        == 0
    )
    rep = json.loads((out / "dem_report.json").read_text())
    las = laspy.read(out / "dem.laz")
    assert rep["point_cloud"]["n_points"] == rep["n_points"] == len(las.points) > 10000
    assert not (out / "tiles").exists()  # per-tile files removed after the merge
    # CRS: the DEM's (UTM 37N with ellipsoidal heights), from the WKT VLR
    with rasterio.open(out / "dem.tif") as ds:
        dem_crs = CRS.from_wkt(ds.crs.to_wkt())
    crs = las.header.parse_crs()
    assert crs is not None and las.header.global_encoding.wkt
    assert (
        crs.equals(dem_crs)
        or CRS.from_user_input(crs.sub_crs_list[0] if crs.is_compound else crs.to_2d()).to_epsg()
        == 32637
    )
    assert any("ellipsoidal height" in a.name.lower() for a in crs.axis_info)
    # points on the DEM: each point against the DEM interpolated at its position
    z = np.asarray(las.z)
    dem_z = _bilinear(out / "dem.tif", las.x, las.y)
    ok = np.isfinite(dem_z)
    assert ok.mean() > 0.97
    d = z[ok] - dem_z[ok]
    med, bias = float(np.median(np.abs(d))), float(np.median(d))
    print(f"median |z - dem| = {med:.3f} m, median z - dem {bias:+.3f} m over {ok.sum()} points")
    assert med < 1.5 and abs(bias) < 0.2, (med, bias)
    # extra dimensions, with values that mean what they say
    names = set(las.point_format.extra_dimension_names)
    assert {"ray_gap", "score", "source_pair", "edit_code"} <= names
    assert np.all(las.ray_gap >= 0) and np.all(las.ray_gap <= rep["info"]["max_ray_gap_m"] + 1e-3)
    np.testing.assert_allclose(
        np.median(las.ray_gap),
        np.nanmedian(_cell_values(out / "raygap.tif", las.x, las.y)),
        rtol=0.3,
    )
    score = np.asarray(las.score)
    fin = np.isfinite(score)  # NaN where the matcher kept a pixel without a score
    print(f"scores: {100 * fin.mean():.1f} % finite, median {np.median(score[fin]):.3f}")
    assert fin.mean() > 0.5 and np.all(score[fin] <= 1.0) and np.all(score[fin] >= -1.0)
    assert np.all(las.source_pair == 0) and np.all(las.classification == 1)
    assert las.header.mins[2] <= z.min() and las.header.maxs[2] >= z.max()


def test_write_las_in_chunks_with_classes_and_geoid_crs(tmp_path):
    grid = MapGrid(Affine(10.0, 0, 500_000.0, 0, -10.0, 4_400_000.0), 20, 10, "EPSG:32637")
    rng = np.random.default_rng(0)
    lon0, lat0 = 39.0, 39.74
    for index, n in ((0, 500), (2, 300), (3, 0)):
        x = rng.uniform(500_000, 500_200, n)
        y = rng.uniform(4_399_900, 4_400_000, n)

        lon, lat = geodesy.crs_to_lonlat(x, y, "EPSG:32637")
        save_tile_points(
            tmp_path / "pts",
            index,
            lon,
            lat,
            np.full(n, 1500.0),
            rng.uniform(0, 1, n),
            rng.uniform(0, 3, n),
            crs="EPSG:32637",
            geoid=True,
            pair=index,
        )
    codes = np.zeros((10, 20), np.uint8)
    codes[:, 10:] = 3  # a filter removed the east half
    info = write_las(
        tmp_path / "c.las", tmp_path / "pts", [0, 1, 2, 3], grid, vertical="geoid", edit_codes=codes
    )
    assert info["n_points"] == 800 and info["missing_tiles"] == [1]
    las = laspy.read(tmp_path / "c.las")
    assert len(las.points) == 800
    east = np.asarray(las.x) >= 500_100
    assert np.all(las.classification[east] == 7) and np.all(las.classification[~east] == 1)
    assert np.all(las.edit_code[east] == 3) and np.all(las.edit_code[~east] == 0)
    assert info["classes"]["noise (filtered)"] == int(east.sum())
    assert sorted(set(las.source_pair)) == [0, 2] and np.array_equal(
        las.point_source_id, las.source_pair
    )
    # geoid heights: z = h - N (N about +25 m here), and a compound CRS with EGM96 height

    n_geoid = geodesy.geoid_undulation(lon0, lat0)
    assert abs(float(np.median(las.z)) - (1500.0 - float(n_geoid))) < 1.0
    crs = las.header.parse_crs()
    assert crs.is_compound and "EGM96" in crs.sub_crs_list[1].name
    assert crs.sub_crs_list[0].to_epsg() == 32637
    # one mask per pair id (N-view: the fusion's rejections differ by pair), the pair list in
    # a VLR; a mask off the grid is refused in one line
    per_pair = np.zeros((3, 10, 20), np.uint8)
    per_pair[2, :, :10] = FUSION_REJECTED  # pair 2 rejected in the west half
    info = write_las(
        tmp_path / "n.las",
        tmp_path / "pts",
        [0, 2],
        grid,
        vertical="geoid",
        edit_codes=per_pair,
        pairs={0: ("a.tif", "b.tif"), 2: ("b.tif", "c.tif")},
    )
    las = laspy.read(tmp_path / "n.las")
    west2 = (np.asarray(las.x) < 500_100) & (np.asarray(las.source_pair) == 2)
    assert west2.any() and np.array_equal(np.asarray(las.edit_code) == FUSION_REJECTED, west2)
    assert np.array_equal(las.classification == 7, west2)
    assert info["classes"]["of which rejected by the N-view fusion"] == int(west2.sum())
    assert read_pairs(las) == {0: ["a.tif", "b.tif"], 2: ["b.tif", "c.tif"]}
    assert read_pairs(laspy.read(tmp_path / "c.las")) == {}
    with pytest.raises(InputError, match="do not match the grid"):
        write_las(tmp_path / "m.las", tmp_path / "pts", [0], grid, edit_codes=codes[:5])
    # never over an existing file without overwrite
    with pytest.raises(FileExistsError):
        write_las(tmp_path / "c.las", tmp_path / "pts", [0], grid, vertical="geoid")


def test_bad_point_cloud_settings_are_one_line_errors(tmp_path, capsys):
    raw = {
        "inputs": {"left": "a.tif", "right": "b.tif"},
        "output": {"dir": str(tmp_path / "o")},
        "dem": {"point_cloud": "ply"},
    }
    with pytest.raises(InputError, match=r"\[dem\] point_cloud must be 'las' or 'laz'"):
        config_from_dict(raw)
    with pytest.raises(SystemExit) as e:
        main(["dem", "a.tif", "b.tif", "-o", str(tmp_path / "o"), "--point-cloud", "xyz"])
    assert e.value.code == 2
    with pytest.raises(InputError):
        write_las(
            tmp_path / "c.xyz", tmp_path, [], MapGrid(Affine(1, 0, 0, 0, -1, 0), 2, 2, "EPSG:32637")
        )


@pytest.mark.slow
def test_run_classifies_the_points_of_filtered_cells(scene_dir, tmp_path):
    out = tmp_path / "run"
    raw = {
        "inputs": {"left": str(scene_dir / "left.tif"), "right": str(scene_dir / "right.tif")},
        "output": {"dir": str(out)},
        "rectification": {"tile_size": 200, "height_range": [1000, 3500]},
        "ortho": {"enabled": False},
        "run": {"workers": 1},
        "dem": {"point_cloud": "las"},
    }
    run(config_from_dict(raw))
    rj = json.loads((out / "run.json").read_text())
    pc = rj["stages"]["point_cloud"]
    las = laspy.read(out / "dem.las")
    assert pc["n_points"] == len(las.points) and (out / "tiles").exists()
    # the points stay with the tile cache, for a later --resume
    assert len(list((out / "tiles" / "points").glob("points_*.npz"))) == pc["tiles_with_points"]
    mask = _cell_values(out / "dem_edit_mask.tif", las.x, las.y)
    ok = np.isfinite(mask)
    assert ok.mean() > 0.99
    np.testing.assert_array_equal(np.asarray(las.edit_code)[ok], mask[ok].astype(np.uint8))
    removed = ok & (mask >= 1) & (mask <= 99)
    assert removed.any() and (~removed & ok).any()
    assert np.all(las.classification[removed] == 7) and np.all(
        las.classification[~removed & ok] == 1
    )


def _resume_cfg(scene_dir, out, **run_settings):
    return config_from_dict(
        {
            "inputs": {"left": str(scene_dir / "left.tif"), "right": str(scene_dir / "right.tif")},
            "output": {"dir": str(out)},
            "rectification": {"tile_size": 200, "height_range": [1000, 3500]},
            "ortho": {"enabled": False},
            "filters": {"erode": 2},
            "run": {"workers": 1, **run_settings},
            "dem": {"point_cloud": "las"},
        }
    )


@pytest.mark.slow
def test_resumed_run_keeps_every_point_in_the_cloud(scene_dir, tmp_path):
    """``run --resume`` on a finished point-cloud job (e.g. with another filter setting) wrote
    an EMPTY dem.las: the merge had removed the tiles' point files and the cached tiles were
    reused without them (real Pleiades pair: 973 908 points -> 0, one warning). The point
    files now stay with the tile cache; a cached tile whose point file is gone (a cache from
    before) is recomputed."""
    out = tmp_path / "run"
    run(_resume_cfg(scene_dir, out))
    n = len(laspy.read(out / "dem.las").points)
    assert n > 1000
    again = _resume_cfg(scene_dir, out, resume=True, overwrite=True)
    again.filters.erode = 1  # a post setting: the tiles are reused
    run(again)
    assert len(laspy.read(out / "dem.las").points) == n
    # a cache without the point files (as the merge left it before): those tiles are redone
    for f in (out / "tiles" / "points").glob("points_*.npz"):
        f.unlink()
    run(_resume_cfg(scene_dir, out, resume=True, overwrite=True))
    assert len(laspy.read(out / "dem.las").points) == n
    rj = json.loads((out / "run.json").read_text())
    assert rj["stages"]["point_cloud"]["tiles_with_points"] == rj["stages"]["stereo"]["tiles"]
    # --clean-tiles removes the points with the cache
    run(_resume_cfg(scene_dir, out, resume=True, overwrite=True, keep_tiles=False))
    assert len(laspy.read(out / "dem.las").points) == n
    assert not (out / "tiles").exists()
