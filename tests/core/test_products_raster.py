"""GeoTIFF products: Cloud-Optimised layout, predictor, vertical reference in the CRS, band
descriptions and units, umask permissions, lossless values (issue #19)."""

from __future__ import annotations

import os
import pickle
import re
import shutil
import stat
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import rasterio
import rasterio.shutil
from affine import Affine
from pyproj import CRS
from rasterio.rpc import RPC

import stereodem.core.raster as raster
from stereodem.cli import main
from stereodem.core.blockwrite import BlockWriter
from stereodem.core.grid import MapGrid
from stereodem.ortho.drm import orthorectify
from stereodem.sensor.simulation.simulate import simulate_scene

cog_validate = pytest.importorskip("rio_cogeo.cogeo").cog_validate

from stereodem.core.dem import DEM, ELLIPSOID, GEOID
from stereodem.core.errors import (
    CRSError,
    InputError,
    OutputExistsError,
    OutputWriteError,
    error_message,
)
from stereodem.core.raster import (
    DEFLATE_LEVEL,
    check_creation_options,
    cog_creation_options,
    parse_creation_options,
    write_geotiff,
    write_text_atomic,
)

T = Affine(30.0, 0.0, 500000.0, 0.0, -30.0, 4400000.0)


def _rng_data(dtype, shape=(600, 700)):
    rng = np.random.default_rng(1)
    if np.issubdtype(np.dtype(dtype), np.floating):
        a = (1500 + 40 * rng.standard_normal(shape)).astype(dtype)
        a[:40, :90] = np.nan
        return a
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, size=shape, endpoint=True).astype(dtype)


@pytest.mark.parametrize(
    "dtype,predictor",
    [("float32", 3), ("float64", 3), ("uint8", 2), ("int16", 2), ("uint16", 2), ("int32", 2)],
)
def test_cog_layout_predictor_overviews_and_lossless(tmp_path, dtype, predictor):
    a = _rng_data(dtype)
    p = write_geotiff(tmp_path / f"{dtype}.tif", a, T, "EPSG:32637")
    valid, errors, warnings = cog_validate(str(p))
    assert valid, (errors, warnings)
    with rasterio.open(p) as ds:
        assert ds.overviews(1), "a 600x700 raster with 256² tiles needs overviews"
        assert ds.block_shapes[0] == (256, 256)
        assert ds.tags(ns="IMAGE_STRUCTURE").get("PREDICTOR") == str(predictor)
        assert ds.compression.name.lower() == "deflate"
        b = ds.read(1)
    assert b.dtype == a.dtype
    assert np.array_equal(a, b, equal_nan=True)


def test_small_raster_and_unreferenced_image_with_rpcs_validate(tmp_path):
    small = write_geotiff(
        tmp_path / "small.tif", np.arange(12, dtype=np.int16).reshape(3, 4), T, "EPSG:32637", -1
    )
    assert cog_validate(str(small))[0]
    rpc = RPC(
        height_off=1000,
        height_scale=500,
        lat_off=39.5,
        lat_scale=0.1,
        line_den_coeff=[1] + [0] * 19,
        line_num_coeff=[0, 0, -1] + [0] * 17,
        line_off=300,
        line_scale=300,
        long_off=40.4,
        long_scale=0.1,
        samp_den_coeff=[1] + [0] * 19,
        samp_num_coeff=[0, 1] + [0] * 18,
        samp_off=300,
        samp_scale=300,
    )
    img = write_geotiff(tmp_path / "img.tif", _rng_data("uint8", (600, 600)), rpcs=rpc)
    assert cog_validate(str(img))[0]
    with rasterio.open(img) as ds:
        assert ds.rpcs is not None and abs(ds.rpcs.lat_off - 39.5) < 1e-9


def test_deflate_level_defaults_to_the_fastest_unless_given():
    assert cog_creation_options("float32")["LEVEL"] == DEFLATE_LEVEL == "1"
    assert cog_creation_options("float32", {"LEVEL": "9"})["LEVEL"] == "9"
    for other in ("LZW", "WEBP", "NONE"):  # LEVEL means something else or nothing there
        assert "LEVEL" not in cog_creation_options("uint8", compress=other)


@pytest.mark.slow
def test_a_cog_write_lets_the_other_threads_run(tmp_path):
    """The background writer overlaps the next stage only if GDAL compresses with the GIL
    released. Closing a dataset opened with ``driver="COG"`` copies it to the COG holding
    the GIL (rasterio 1.3-1.4): the thread below then stalls for most of the write.
    :func:`write_geotiff` copies a MEM dataset with ``rasterio.shutil.copy`` instead, during
    which another thread keeps running; the longest stall is compared with the write's own
    length, in the same run."""
    a = np.random.default_rng(5).random((2048, 2048)).astype(np.float32)
    done = threading.Event()

    def write():
        try:
            write_geotiff(tmp_path / "w.tif", a, Affine(30, 0, 0, 0, -30, 0), "EPSG:32633")
        finally:
            done.set()

    gaps, th = [], threading.Thread(target=write)
    last = time.perf_counter()
    th.start()
    while not done.is_set():
        time.sleep(0.001)
        now = time.perf_counter()
        gaps.append(now - last)
        last = now
    th.join()
    assert len(gaps) > 20 and max(gaps) < 0.5 * sum(gaps), (len(gaps), max(gaps), sum(gaps))
    with rasterio.open(tmp_path / "w.tif") as f:
        assert np.array_equal(f.read(1), a)


def test_creation_options_override_defaults(tmp_path):
    a = _rng_data("float32", (300, 300))
    p = write_geotiff(
        tmp_path / "z.tif",
        a,
        T,
        "EPSG:32637",
        creation_options=["COMPRESS=ZSTD", "BLOCKSIZE=512", "LEVEL=1"],
    )
    with rasterio.open(p) as ds:
        assert ds.compression.name.lower() == "zstd"
        assert ds.block_shapes[0] == (300, 300) or ds.block_shapes[0] == (512, 512)
        assert not ds.overviews(1)  # 300 < 512: no overview level needed
        assert np.array_equal(ds.read(1), a, equal_nan=True)
    assert parse_creation_options({"compress": "lzw"}) == {"COMPRESS": "lzw"}
    with pytest.raises(InputError, match="KEY=VALUE"):
        parse_creation_options(["COMPRESS"])


@pytest.mark.parametrize(
    "options, complaint",
    [
        (["COMPRESS=NOPE"], "'NOPE' is an unexpected value for COMPRESS"),
        (["FOO=1"], "does not support creation option FOO"),
        (["BLOCKSIZE=13"], "should be >= 128"),
        (["COMPRESS=ZSTD", "PREDICTOR=7"], "'7' is an unexpected value for PREDICTOR"),
    ],
)
def test_creation_options_gdal_would_ignore_are_an_error(options, complaint):
    # GDAL ignores an option it does not know, or a value it does not accept, with a warning
    # and writes the file without it: checked before any work instead
    for _ in range(2):  # again (a batch, a second job in one process): not a cached pass
        with pytest.raises(InputError, match=complaint) as e:
            check_creation_options(options, source="--co")
        assert str(e.value).startswith(f"--co {' '.join(options)}: GDAL's COG driver: ")


@pytest.mark.parametrize(
    "kwargs, complaint",
    [
        (dict(creation_options={"FOO": "1"}), "FOO=1: .*does not support creation option FOO"),
        (dict(creation_options=["COMPRESS=NOPE"]), "COMPRESS=NOPE: .*'NOPE' is an unexpected"),
        (dict(compress="nope"), "COMPRESS=NOPE: .*'NOPE' is an unexpected value"),
    ],
)
def test_library_writes_check_their_creation_options(tmp_path, kwargs, complaint):
    """``write_geotiff(..., creation_options=...)`` and ``BlockWriter`` wrote the file without
    an option GDAL did not know, with a warning only (only the command line and the
    configuration checked them): an InputError naming the file and the option, nothing
    written."""
    path = tmp_path / "z.tif"
    with pytest.raises(InputError, match=rf"^{re.escape(str(path))}: creation options {complaint}"):
        write_geotiff(path, _rng_data("float32", (40, 40)), T, "EPSG:32637", **kwargs)
    if "creation_options" in kwargs:
        with pytest.raises(InputError, match=rf"^{re.escape(str(path))}: creation options "):
            BlockWriter(path, MapGrid(T, 40, 40, "EPSG:32637"), ["a"], **kwargs)
    assert not list(tmp_path.iterdir())
    # accepted options still write, from any thread
    with ThreadPoolExecutor(2) as ex:
        done = ex.map(
            lambda k: write_geotiff(
                tmp_path / f"ok{k}.tif",
                _rng_data("float32", (40, 40)),
                T,
                "EPSG:32637",
                creation_options={"COMPRESS": "ZSTD"},
            ),
            range(2),
        )
        assert len(list(done)) == 2


def test_creation_options_gdal_knows_pass_their_check():
    assert check_creation_options(None) == {}
    assert check_creation_options(["compress=zstd", "LEVEL=9"]) == {
        "COMPRESS": "zstd",
        "LEVEL": "9",
    }
    # valid for 8-bit orthoimages, not for float heights: a matter of each product's write
    assert check_creation_options(["COMPRESS=JPEG"]) == {"COMPRESS": "JPEG"}


def test_a_write_onto_a_full_disk_says_so(tmp_path, monkeypatch):
    """A full disk made GDAL fail to read back a block it had not written ('IReadBlock
    failed ... TIFFReadEncodedTile() failed'), and the error blamed the creation options."""

    def failing_copy(*args, **kwargs):
        raise rasterio.errors.RasterioIOError("IReadBlock failed: TIFFReadEncodedTile() failed.")

    monkeypatch.setattr(raster.rasterio.shutil, "copy", failing_copy)
    usage = shutil.disk_usage(tmp_path)
    for free, words in (
        (
            1000,
            r"z\.tif: cannot be written: the disk holding .* is full: "
            r"1 kB free for a raster of 6 kB",
        ),
        (usage.free, r"z\.tif: cannot be written with the creation options"),
    ):
        monkeypatch.setattr(raster.shutil, "disk_usage", lambda p, f=free: usage._replace(free=f))
        with pytest.raises(OutputWriteError, match=words) as err:
            write_geotiff(tmp_path / "z.tif", _rng_data("float32", (40, 40)), T)
        assert "TIFFReadEncodedTile() failed" in str(err.value)
        assert not list(tmp_path.iterdir())
    # a raster written in blocks (mosaics, orthoimages): its size is the grid's, float32 bands
    monkeypatch.setattr(raster.shutil, "disk_usage", lambda p: usage._replace(free=1000))
    with pytest.raises(OutputWriteError, match="1 kB free for a raster of 19 kB before"):
        with BlockWriter(tmp_path / "b.tif", MapGrid(T, 40, 40, "EPSG:32637"), list("abc")) as w:
            w.write(0, 0, np.zeros((3, 40, 40), np.float32))
    assert not list(tmp_path.iterdir())


def test_a_write_gdal_refuses_is_an_error_naming_the_file(tmp_path):
    # JPEG cannot hold float32 heights, WEBP needs 3 or 4 bands: a one-line error naming the
    # product and its options (a rasterio CPLE_AppDefinedError traceback before), no file
    for co in (["COMPRESS=JPEG"], ["COMPRESS=WEBP"]):
        with pytest.raises(OutputWriteError, match=r"z\.tif: cannot be written with the creation"):
            write_geotiff(
                tmp_path / "z.tif", _rng_data("float32", (40, 40)), T, creation_options=co
            )
        assert not list(tmp_path.iterdir())
    # compressed on GDAL's own threads, a refusal was printed, not raised: the copy wrote
    # blank tiles and succeeded (a single-band WEBP orthoimage of zeros, exit status 0)
    with pytest.raises(OutputWriteError, match="WEBP driver doesn't support 1 bands"):
        write_geotiff(
            tmp_path / "w.tif",
            _rng_data("uint8", (600, 700)),
            T,
            creation_options=["COMPRESS=WEBP", "NUM_THREADS=2"],
        )
    assert not list(tmp_path.iterdir())
    # the same options on what they suit are written
    p = write_geotiff(
        tmp_path / "u8.tif", _rng_data("uint8", (40, 40)), T, creation_options=["COMPRESS=JPEG"]
    )
    with rasterio.open(p) as ds:
        assert ds.compression.name.lower() == "jpeg"


@pytest.mark.parametrize(
    "vertical,axis", [(GEOID, "Gravity-related height"), (ELLIPSOID, "Ellipsoidal height")]
)
@pytest.mark.parametrize("horizontal", ["EPSG:32637", "EPSG:4326"])
def test_vertical_reference_in_the_crs(tmp_path, vertical, axis, horizontal):
    t = T if horizontal != "EPSG:4326" else Affine(0.001, 0, 40.0, 0, -0.001, 39.6)
    dem = DEM(_rng_data("float32", (300, 300)), t, horizontal, vertical)
    p = dem.write(tmp_path / "dem.tif")
    assert cog_validate(str(p))[0]
    with rasterio.open(p) as ds:  # what GDAL reports (incl. a PAM side-car)
        crs = CRS.from_wkt(ds.crs.to_wkt())
        assert ds.descriptions[0].startswith("height above the")
        assert ds.units[0] == "metre"
    assert [a.name for a in crs.axis_info][-1] == axis
    if vertical == GEOID:  # in the GeoTIFF keys: compound with EPSG:5773
        assert crs.is_compound and crs.sub_crs_list[1].to_epsg() == 5773
        assert not (tmp_path / "dem.tif.aux.xml").exists()
    back = DEM.from_file(p)
    assert back.vertical == vertical
    assert back.crs.equals(CRS(horizontal)) and len(back.crs.axis_info) == 2
    assert np.array_equal(back.heights, dem.heights, equal_nan=True)


def _write_with_block_writer(path, data, transform, crs, vertical):
    grid = MapGrid(transform, data.shape[1], data.shape[0], crs)
    with BlockWriter(path, grid, ["height"], vertical=vertical) as w:
        w.write(0, 0, data[None])
    return path


def _write_dem(path, data, transform, crs, vertical):
    return DEM(data, transform, crs, vertical).write(path)


@pytest.mark.parametrize("writer", [_write_dem, _write_with_block_writer], ids=["DEM", "blocks"])
@pytest.mark.parametrize("horizontal", ["EPSG:32637", "EPSG:2193", "EPSG:4326"])
def test_file_alone_keeps_its_crs_when_the_side_car_is_lost(tmp_path, writer, horizontal):
    """A projected CRS with ellipsoidal heights has no GeoTIFF encoding: GDAL put it, with the
    geotransform, in the .aux.xml side-car only, and a DEM copied without it had no CRS
    (DEM.from_file refused it). The file now holds the horizontal CRS in its keys and the
    vertical reference in its tag; the side-car adds the 3-D CRS for GDAL readers."""
    t = T if horizontal != "EPSG:4326" else Affine(0.001, 0, 40.0, 0, -0.001, 39.6)
    if horizontal == "EPSG:2193":  # a projected CRS whose EPSG axis order is north, east
        t = Affine(30.0, 0.0, 1600000.0, 0.0, -30.0, 5400000.0)
    data = _rng_data("float32", (300, 300))
    p = writer(tmp_path / "dem.tif", data, t, horizontal, ELLIPSOID)
    side_car = tmp_path / "dem.tif.aux.xml"
    assert side_car.exists() == (horizontal != "EPSG:4326")  # geographic 3-D: in the keys
    with rasterio.open(p) as ds:  # with the side-car: the 3-D CRS, as GDAL writes it
        crs = CRS.from_wkt(ds.crs.to_wkt())
        assert [a.name for a in crs.axis_info][-1] == "Ellipsoidal height"
        assert ds.transform == t
    alone = tmp_path / "copy" / "dem.tif"
    alone.parent.mkdir()
    shutil.copy(p, alone)
    with rasterio.open(alone) as ds:
        assert ds.crs is not None and ds.transform == t
        epsg = CRS(horizontal).to_3d().to_epsg() if horizontal == "EPSG:4326" else None
        # GDAL reads NZTM's keys with easting first and an unnamed conversion: the same CRS,
        # identified with less confidence (GDAL 3.6 below 70 %)
        got = CRS.from_wkt(ds.crs.to_wkt()).to_epsg(min_confidence=20)
        assert got == (epsg or CRS(horizontal).to_epsg())
    back = DEM.from_file(alone)
    assert back.vertical == ELLIPSOID
    assert back.crs.to_epsg(min_confidence=20) == CRS(horizontal).to_epsg()
    assert np.array_equal(back.heights, data, equal_nan=True)


def test_old_dem_without_its_side_car_says_where_its_crs_went(tmp_path, capsys):
    """A DEM written as older versions did (the 3-D CRS in the side-car only), copied without
    the side-car: a one-line error that names the missing side-car, not just "no CRS"."""
    p = tmp_path / "dem.tif"
    profile = dict(driver="MEM", width=64, height=64, count=1, dtype="float32")
    crs3d = rasterio.crs.CRS.from_wkt(CRS("EPSG:32637").to_3d().to_wkt())
    with rasterio.open("", "w", crs=crs3d, transform=T, **profile) as ds:
        ds.write(_rng_data("float32", (64, 64))[None])
        ds.update_tags(STEREODEM_VERTICAL="ellipsoid")
        rasterio.shutil.copy(ds, p, driver="COG")
    assert DEM.from_file(p).vertical == ELLIPSOID  # with its side-car: as before
    (tmp_path / "dem.tif.aux.xml").unlink()
    for read in (DEM.from_file, DEM.check_file):
        with pytest.raises(CRSError, match=r"has no CRS \(.*dem\.tif\.aux\.xml only"):
            read(p)
    assert main(["assess", str(p), "--ref", str(p), "-o", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dem.tif.aux.xml" in err[0] and "Traceback" not in err[0]


def test_old_private_tag_still_read(tmp_path):
    p = tmp_path / "old.tif"
    with rasterio.open(
        p,
        "w",
        driver="GTiff",
        width=8,
        height=8,
        count=1,
        dtype="float32",
        crs="EPSG:32637",
        transform=T,
    ) as ds:
        ds.write(np.ones((1, 8, 8), np.float32))
        ds.update_tags(STEREODEM_VERTICAL="geoid")
    assert DEM.from_file(p).vertical == GEOID


def test_overwrite_removes_stale_sidecar(tmp_path):
    p = tmp_path / "dem.tif"
    DEM(_rng_data("float32", (64, 64)), T, "EPSG:32637", ELLIPSOID).write(p)
    assert (tmp_path / "dem.tif.aux.xml").exists()  # projected + ellipsoidal: PAM
    DEM(_rng_data("float32", (64, 64)), T, "EPSG:32637", GEOID).write(p, overwrite=True)
    assert not (tmp_path / "dem.tif.aux.xml").exists()
    assert DEM.from_file(p).vertical == GEOID
    assert sorted(f.name for f in tmp_path.iterdir()) == ["dem.tif"]  # no temporary left


@pytest.mark.parametrize("umask,mode", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_permissions_follow_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        r = write_geotiff(
            tmp_path / "a.tif", _rng_data("float32", (32, 32)), T, "EPSG:32637", vertical=ELLIPSOID
        )
        t = write_text_atomic(tmp_path / "a.json", "{}")
    finally:
        os.umask(old)
    for f in (r, t, tmp_path / "a.tif.aux.xml"):
        assert stat.S_IMODE(f.stat().st_mode) == mode, f


def test_band_descriptions_units_and_count_check(tmp_path):
    a = np.stack([_rng_data("float32", (40, 50))] * 2)
    p = write_geotiff(
        tmp_path / "two.tif",
        a,
        T,
        "EPSG:32637",
        descriptions=["height", "score"],
        units=["metre", "1"],
    )
    with rasterio.open(p) as ds:
        assert ds.descriptions == ("height", "score") and ds.units == ("metre", "1")
    with pytest.raises(InputError, match="3 given for 2"):
        write_geotiff(tmp_path / "bad.tif", a, T, "EPSG:32637", units=["m", "m", "m"])


@pytest.fixture(scope="module")
def small_scene():
    return simulate_scene("aster", size=(200, 200), seed=0)


@pytest.mark.parametrize("resampling", ["bilinear", "cubic"])
def test_ortho_keeps_the_input_data_type(tmp_path, small_scene, resampling):
    img = small_scene.left
    assert img.dtype == np.uint8
    o = orthorectify(img, small_scene.left_model, small_scene.truth_dem, resampling=resampling)
    p = o.write(tmp_path / "o.tif", dtype=img.dtype)
    assert cog_validate(str(p))[0]
    with rasterio.open(p) as ds:
        assert ds.dtypes[0] == "uint8"
        b = ds.read(1, masked=True)
        assert ds.descriptions[0].startswith("orthoimage")
    valid = np.asarray(o.valid)
    assert np.array_equal(~np.ma.getmaskarray(b), valid)  # nodata only off the data
    want = np.clip(np.rint(o.data[valid]), 0, 255).astype(np.uint8)
    assert np.array_equal(b.data[valid], want)
    # float32 when asked (and by default), values unchanged
    f = o.write(tmp_path / "f.tif")
    with rasterio.open(f) as ds:
        assert ds.dtypes[0] == "float32"
        assert np.array_equal(ds.read(1), o.data, equal_nan=True)


def test_ortho_integer_mask_when_no_value_is_free(tmp_path, small_scene):
    img = small_scene.left.copy()
    img[:5, :5], img[-5:, -5:] = 0, 255  # 0 and 255 both taken, uint8 full
    o = orthorectify(img, small_scene.left_model, small_scene.truth_dem, resampling="nearest")
    vals = np.rint(o.data[o.valid])
    if not ((vals == 0).any() and (vals == 255).any()):
        pytest.skip("the saturated corners fell outside the ortho grid")
    p = o.write(tmp_path / "m.tif", dtype=np.uint8)
    with rasterio.open(p) as ds:
        assert ds.nodata is None
        assert np.array_equal(ds.read_masks(1) > 0, o.valid)


def test_georeferenced_writes_leave_the_warning_filters_alone(tmp_path, monkeypatch):
    """``warnings.catch_warnings`` saves and restores the whole process's filters (not
    thread-safe before Python 3.14), and products are written on a background thread: a
    georeferenced write does not enter it; one in sensor geometry (no transform, no RPCs)
    still silences rasterio's NotGeoreferencedWarning."""
    a = np.ones((4, 5), np.float32)
    real = warnings.catch_warnings

    def refused(*args, **kw):
        raise AssertionError("catch_warnings entered for a georeferenced write")

    monkeypatch.setattr(warnings, "catch_warnings", refused)
    write_geotiff(
        tmp_path / "map.tif", a, crs=CRS.from_epsg(32633), transform=Affine(30, 0, 5e5, 0, -30, 4e6)
    )
    monkeypatch.setattr(warnings, "catch_warnings", real)
    with warnings.catch_warnings(record=True) as log:
        warnings.simplefilter("always")
        write_geotiff(tmp_path / "sensor.tif", a)
    assert not [w for w in log if issubclass(w.category, rasterio.errors.NotGeoreferencedWarning)]
    with rasterio.open(tmp_path / "map.tif") as d:
        assert d.transform == Affine(30, 0, 5e5, 0, -30, 4e6)


def test_write_geotiff_refuses_bad_data_and_crs_naming_them(tmp_path):
    """Before, 1-D or None ``data`` raised a bare IndexError from the profile's shape, and an
    unknown CRS pyproj's own CRSError (not stereodem's); now InputError / CRSError naming
    the file, and nothing is written."""
    path = tmp_path / "x.tif"
    for data in (np.zeros(5), None, np.zeros((0, 4))):
        with pytest.raises(InputError, match=r"x.tif: data must be a non-empty 2-D"):
            write_geotiff(path, data, T, "EPSG:32633")
    with pytest.raises(CRSError, match=r"x.tif: unknown or unusable CRS 'foo'"):
        write_geotiff(path, np.ones((4, 4), np.float32), T, "foo")
    assert not path.exists()


def test_overwrite_advice_in_the_callers_words(tmp_path, capsys):
    """An existing output: the library said "pass overwrite=True (--overwrite)" to both its
    callers; now the library's message says overwrite=True and the command line's --overwrite
    (core.errors.OutputExistsError.needs_overwrite, worded by error_message), also after a trip
    through pickle (batch's and dask's workers)."""
    p = tmp_path / "dem.tif"
    DEM(_rng_data("float32", (64, 64)), T, "EPSG:32637", GEOID).write(p)
    with pytest.raises(OutputExistsError) as info:
        DEM(_rng_data("float32", (64, 64)), T, "EPSG:32637", GEOID).write(p)
    for exc in (info.value, pickle.loads(pickle.dumps(info.value))):
        lib, cli = str(exc), error_message(exc, "command line")
        assert lib == f"{p}: exists; pass overwrite=True to replace it", lib
        assert cli == f"{p}: exists; pass --overwrite to replace it", cli
        assert type(exc) is OutputExistsError and error_message(exc) == lib
    capsys.readouterr()
    assert main(["mosaic", str(p), "-o", str(p.with_name("m.tif"))]) == 0
    capsys.readouterr()
    assert main(["mosaic", str(p), "-o", str(p.with_name("m.tif"))]) == 1
    err = capsys.readouterr().err
    assert "pass --overwrite" in err and "overwrite=True" not in err, err
    # a non-empty output folder (the command line's folder policy, stereodem.outlock)
    (tmp_path / "sim").mkdir()
    (tmp_path / "sim" / "mine.txt").write_text("x")
    assert main(["simulate", "--size", "60", "60", "-o", str(tmp_path / "sim")]) == 1
    err = capsys.readouterr().err
    assert "pass --overwrite to write the products beside" in err and "=True" not in err, err
