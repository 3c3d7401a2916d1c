import dataclasses
import threading

import numpy as np
import pytest
import rasterio
from affine import Affine

import stereodem.core.dem as dem_module
from stereodem.core import geodesy
from stereodem.core.dem import DEM, OUTSIDE, VOID, geoid_name
from stereodem.core.errors import (
    CRSError,
    DEMCoverageError,
    DEMError,
    InputError,
    OutputExistsError,
    VerticalReferenceError,
)
from stereodem.core.raster import image_dtype, read_image
from stereodem.post.assess import reconcile_vertical
from stereodem.post.coreg_run import CoregJob, load_inputs
from stereodem.post.mosaic_coreg import check_reference
from stereodem.post.mosaic_sources import open_source
from stereodem.post.stack_build import header_bounds_lonlat


def test_bundled_dem_metadata():
    dem = DEM.bundled()
    assert dem.vertical == "geoid"
    assert dem.shape == (1000, 1000)
    w, s, e, n = dem.bounds_lonlat()
    assert (w, s, e, n) == pytest.approx((40.0, 39.1667, 40.8333, 40.0), abs=1e-3)


def test_bilinear_sampling_matches_pixel_centres_and_interpolates():
    dem = DEM.bundled()
    H = dem.heights
    # pixel centre (r, c) is at lon = 40 + (c + 0.5) dx, lat = 40 - (r + 0.5) dx
    dx = 1 / 1200
    r, c = 500, 321
    lon, lat = 40 + (c + 0.5) * dx, 40 - (r + 0.5) * dx
    assert dem.sample(lon, lat, reference=None) == pytest.approx(H[r, c], abs=1e-3)
    # midway between four centres: the mean of the four
    z = dem.sample(lon + dx / 2, lat - dx / 2, reference=None)
    assert z == pytest.approx(H[r : r + 2, c : c + 2].mean(), abs=1e-3)
    # ellipsoidal heights add the EGM96 undulation
    ze = dem.sample(lon, lat)
    assert ze - H[r, c] == pytest.approx(float(geodesy.geoid_undulation(lon, lat)), abs=1e-3)


def _dem_file(path, a, **profile):
    """Write ``a`` (rows, cols) or (bands, rows, cols) as a GeoTIFF on a UTM 37N grid of
    30 m cells; the path."""
    bands = a if a.ndim == 3 else a[None]
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=bands.shape[2],
        height=bands.shape[1],
        count=bands.shape[0],
        dtype=a.dtype,
        crs="EPSG:32637",
        transform=Affine(30, 0, 500000, 0, -30, 4400000),
        **profile,
    ) as ds:
        ds.write(bands)
        return ds.name


def test_outside_and_void_are_reported_not_invented(tmp_path):
    h = np.full((50, 60), 1000.0, np.float32)
    h[20:23, 30:33] = -9999
    dem = DEM.from_file(_dem_file(tmp_path / "dem.tif", h, nodata=-9999), vertical="ellipsoid")
    x = np.array([500000 + 31.5 * 30, 500000 + 10 * 30, 400000.0])
    y = np.array([4400000 - 21.5 * 30, 4400000 - 10 * 30, 4400000.0])
    lon, lat = geodesy.crs_to_lonlat(x, y, "EPSG:32637")
    z, st = dem.sample(lon, lat, return_status=True)
    assert np.isnan(z[0]) and st[0] == VOID
    assert z[1] == pytest.approx(1000.0) and st[1] == 0
    assert np.isnan(z[2]) and st[2] == OUTSIDE
    with pytest.raises(DEMCoverageError, match="outside the DEM"):
        dem.sample(lon, lat, strict=True)


def test_unknown_vertical_reference_is_an_error(tmp_path):
    path = _ones_tif(
        tmp_path / "dem.tif", crs="EPSG:4326", transform=Affine(0.01, 0, 40, 0, -0.01, 40)
    )
    dem = DEM.from_file(path)
    assert dem.vertical is None
    assert dem.sample(40.015, 39.985, reference=None) == pytest.approx(1.0)
    with pytest.raises(VerticalReferenceError, match="vertical reference unknown"):
        dem.sample(40.015, 39.985)


def _ones_tif(path, **georeferencing):
    """A 4 x 4 float32 GeoTIFF of ones at ``path`` with the ``crs`` and ``transform`` given."""
    with rasterio.open(
        path, "w", driver="GTiff", width=4, height=4, count=1, dtype="float32", **georeferencing
    ) as d:
        d.write(np.ones((4, 4), np.float32), 1)
    return path


def _no_crs_tif(tmp_path):
    """A 4 x 4 float32 GeoTIFF without a CRS."""
    return _ones_tif(tmp_path / "nocrs.tif")


def test_bad_dems(tmp_path):
    with pytest.raises(CRSError, match="nocrs.tif: the DEM has no CRS"):
        DEM.from_file(_no_crs_tif(tmp_path))
    with pytest.raises(DEMError, match="all nodata"):
        DEM(np.full((3, 3), np.nan), Affine.identity(), "EPSG:4326")
    with pytest.raises(DEMError, match="cannot read"):
        DEM.from_file(tmp_path / "missing.tif")


def test_a_dem_with_a_crs_but_no_geotransform_is_refused(tmp_path):
    """Without a geotransform rasterio gives the identity (with a warning only): the heights
    would be placed at CRS coordinates 0..width, so reading and checking both refuse it."""
    with pytest.warns(rasterio.errors.NotGeoreferencedWarning):
        path = _ones_tif(tmp_path / "nogt.tif", crs="EPSG:32633")
    for read in (DEM.from_file, DEM.check_file):
        with pytest.warns(rasterio.errors.NotGeoreferencedWarning):
            with pytest.raises(DEMError, match="nogt.tif: the DEM has no geotransform"):
                read(path)


def test_check_file_refuses_what_from_file_refuses(tmp_path):
    """The input checks' cheap look (header, first block) gives from_file's errors."""
    with pytest.raises(CRSError, match="nocrs.tif: the DEM has no CRS"):
        DEM.check_file(_no_crs_tif(tmp_path))
    csv = tmp_path / "points.csv"
    csv.write_text("lon,lat,h\n40,39,1000\n")
    for bad in (tmp_path / "missing.tif", csv):
        with pytest.raises(DEMError, match="cannot read the DEM"):
            DEM.check_file(bad)
    DEM.bundled().write(tmp_path / "whole.tif")  # tiled and compressed
    with rasterio.open(tmp_path / "whole.tif") as ds:
        offset = int(ds.get_tag_item("BLOCK_OFFSET_0_0", "TIFF", bidx=1))
    data = bytearray((tmp_path / "whole.tif").read_bytes())
    data[offset : offset + 64] = b"\xff" * 64  # the first block does not decode any more
    broken = tmp_path / "broken.tif"
    broken.write_bytes(bytes(data))
    with pytest.raises(DEMError, match="broken.tif: cannot read the DEM"):
        DEM.check_file(broken)
    DEM.check_file(tmp_path / "whole.tif", vertical="geoid")  # a good one passes
    with pytest.raises(DEMError, match="vertical reference must be"):
        DEM.check_file(tmp_path / "whole.tif", vertical="msl")
    with pytest.raises(DEMError, match="no band 2"):
        DEM.check_file(tmp_path / "whole.tif", band=2)


@pytest.mark.slow
def test_write_round_trip_keeps_vertical_reference(tmp_path):
    dem = DEM.bundled()
    out = dem.to_reference("ellipsoid").write(tmp_path / "e.tif")
    back = DEM.from_file(out)
    assert back.vertical == "ellipsoid"
    assert np.nanmax(np.abs(back.heights - dem.to_reference("ellipsoid").heights)) == 0

    with pytest.raises(OutputExistsError):
        dem.write(out)


@pytest.mark.parametrize("how", ["int16_nodata", "mask_band", "nan"])
def test_dem_voids_from_nodata_mask_band_or_nan(tmp_path, how):
    """Every way a GeoTIFF says 'no height' reads as NaN (float32), and nothing else does."""
    h = np.arange(48 * 40, dtype=np.float32).reshape(48, 40) % 900 + 100
    void = np.zeros(h.shape, bool)
    void[5:9, 11:20] = True
    path = tmp_path / "dem.tif"
    kw = dict(
        driver="GTiff",
        width=40,
        height=48,
        count=1,
        crs="EPSG:32637",
        transform=Affine(30, 0, 500000, 0, -30, 4400000),
    )
    data = h.copy()
    if how == "int16_nodata":
        data[void] = -32768
        with rasterio.open(path, "w", dtype="int16", nodata=-32768, **kw) as d:
            d.write(data.astype(np.int16), 1)
    elif how == "mask_band":
        data[void] = -1.0  # a plausible-looking value, masked out
        with (
            rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True),
            rasterio.open(path, "w", dtype="float32", **kw) as d,
        ):
            d.write(data, 1)
            d.write_mask(np.where(void, 0, 255).astype(np.uint8))
    else:
        data[void] = np.nan
        with rasterio.open(path, "w", dtype="float32", **kw) as d:
            d.write(data, 1)
    dem = DEM.from_file(path, vertical="ellipsoid")
    assert dem.heights.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(dem.heights), void)
    np.testing.assert_array_equal(dem.heights[~void], h[~void])


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_files_written_side_by_side_have_the_same_bytes_and_one_gdal_thread_each(
    tmp_path, monkeypatch
):
    """``threads`` > 1 writes a DEM's files concurrently, each compressed on one GDAL thread
    (unless the creation options say otherwise): the bytes are those of the plain write, and
    an error in one file reaches the caller."""
    base = DEM.bundled()
    rng = np.random.default_rng(0)
    dem = dataclasses.replace(
        base,
        count=rng.integers(0, 9, base.shape).astype(np.int32),
        score=rng.random(base.shape).astype(np.float32),
        ray_gap=rng.random(base.shape).astype(np.float32),
    )
    files = {}
    for threads in (1, 3):
        out = tmp_path / f"t{threads}"
        out.mkdir()
        files[threads] = dem.prepare_write(out / "dem.tif", threads=threads)()
    assert set(files[1]) == {"dem", "count", "score", "ray_gap"}
    for name, path in files[1].items():
        assert path.read_bytes() == files[3][name].read_bytes(), name

    seen = []
    real = dem_module.write_layer

    def recording(*args, creation_options=None, **kw):
        seen.append((threading.current_thread().name, dict(creation_options or {})))
        if args[1] == "score":
            raise OSError("disk full")
        return real(*args, creation_options=creation_options, **kw)

    monkeypatch.setattr(dem_module, "write_layer", recording)
    (tmp_path / "err").mkdir()
    with pytest.raises(OSError, match="disk full"):
        dem.prepare_write(tmp_path / "err" / "dem.tif", threads=2)()
    assert all(name.startswith("stereodem-dem-write") for name, _ in seen)
    assert all(co["NUM_THREADS"] == "1" for _, co in seen)
    seen.clear()
    (tmp_path / "user").mkdir()
    with pytest.raises(OSError):
        dem.prepare_write(
            tmp_path / "user" / "dem.tif", threads=2, creation_options=["NUM_THREADS=4"]
        )()
    assert all(co["NUM_THREADS"] == "4" for _, co in seen)


def test_a_vertical_contradicting_the_file_is_not_applied(tmp_path, caplog):
    """``vertical=`` (``--dem-vertical``, ``--ref-vertical``, a configuration's
    ``*_vertical``) is the reference of files that do not say: it relabelled a file that says
    the other one without a word (``filter``'s help example turned a stereodem DEM's
    ellipsoidal heights into a clean DEM tagged EGM96). The file's own is kept, with a
    warning naming the file; the same rule in the mosaic's header-only reader."""
    a = np.full((6, 6), 1500.0, np.float32)
    path = _dem_file(tmp_path / "e.tif", a)
    with rasterio.open(path, "r+") as ds:
        ds.update_tags(STEREODEM_VERTICAL="ellipsoid")
    with caplog.at_level("WARNING", logger="stereodem.core.dem"):
        d = DEM.from_file(path, vertical="geoid")
        src = open_source(path, vertical="geoid")
    assert d.vertical == "ellipsoid" and src.vertical == "ellipsoid"
    assert caplog.text.count("e.tif: the file says ellipsoid heights: read as ellipsoid") == 2
    caplog.clear()
    with caplog.at_level("WARNING", logger="stereodem.core.dem"):
        assert DEM.from_file(path, vertical="ellipsoid").vertical == "ellipsoid"
        # a file that does not say: the given reference, quietly
        assert DEM.from_file(_dem_file(tmp_path / "n.tif", a), vertical="geoid").vertical == "geoid"
        assert DEM.from_file(tmp_path / "n.tif").vertical is None
    assert not caplog.text


def test_undeclared_nodata_is_no_data_with_a_warning(tmp_path, caplog):
    # read as heights, -9999 without a nodata value put a mean of -1455 m into an assessment
    # and 1e30 a mean of 1.6e28 m; int16 -32768 (SRTM voids) lies below any height on Earth
    a = np.full((20, 20), 1500.0, np.float32)
    a[:3, :3] = -9999.0
    a[5, 5] = 1e30
    a[6, 6] = -11_000.0  # the deepest ocean floor: a height
    with caplog.at_level("WARNING", logger="stereodem.core.dem"):
        d = DEM.from_file(_dem_file(tmp_path / "a.tif", a))
    assert np.isnan(d.heights).sum() == 10 and d.heights[6, 6] == -11_000.0
    assert "a.tif: 10 cell(s)" in caplog.text and "-9999, 1e+30" in caplog.text
    b = np.full((20, 20), -32768, np.int16)
    b[5:, 5:] = 300
    assert np.isnan(DEM.from_file(_dem_file(tmp_path / "b.tif", b)).heights).sum() == 175
    # a file that declares another nodata value keeps -9999 (its producer said what is void)
    c = DEM.from_file(_dem_file(tmp_path / "c.tif", a.clip(None, 5000), nodata=-32768))
    assert np.isnan(c.heights).sum() == 0 and c.heights[0, 0] == -9999.0
    caplog.clear()
    with caplog.at_level("WARNING", logger="stereodem.core.dem"):
        DEM.from_file(_dem_file(tmp_path / "d.tif", np.full((9, 9), 1500.0, np.float32)))
    assert not caplog.text


def test_scaled_heights_are_read_in_metres(tmp_path):
    # stored as decimetres plus an offset (GDAL's scale and offset): read as metres
    a = np.full((8, 8), 15000, np.int16)
    with rasterio.open(_dem_file(tmp_path / "s.tif", a), "r+") as ds:
        ds.scales, ds.offsets = (0.1,), (100.0,)
    assert np.all(DEM.from_file(tmp_path / "s.tif").heights == 1600.0)


def test_a_multi_band_file_read_as_a_dem_says_which_band(tmp_path, caplog):
    a = np.full((2, 6, 6), 1500.0, np.float32)
    a[1] = 10.0
    path = _dem_file(tmp_path / "two.tif", a)
    with caplog.at_level("WARNING", logger="stereodem.core.dem"):
        assert np.all(DEM.from_file(path).heights == 1500.0)
    assert "two.tif: 2 bands; the heights are read from band 1" in caplog.text
    with pytest.raises(DEMError, match="two.tif: no band 3"):
        DEM.from_file(path, band=3)
    # a band described as heights (stereodem's mosaic: height, sigma): said at info level
    with rasterio.open(path, "r+") as ds:
        ds.descriptions = ("height above the WGS84 ellipsoid", "sigma (1-sigma, propagated)")
    caplog.clear()
    with caplog.at_level("INFO", logger="stereodem.core.dem"):
        DEM.from_file(path)
    assert [r.levelname for r in caplog.records if "2 bands" in r.getMessage()] == ["INFO"]


def test_rasters_that_hold_no_heights_are_refused_as_dems(tmp_path):
    """A colour photograph (3 bands of uint8, band 1 its red), stereodem's own score, count,
    ray-gap and edit layers, and a band in a unit that is no length were read as heights:
    ``mosaic good.tif photo.tif`` wrote a mosaic with the photo's red values as metres (a
    warning only), ``coregister photo.tif`` said "only 0 stable samples". Each is now one
    DEMError naming the file and what it holds, from the full read, the header checks
    before long work, the mosaic's and the stack's headers and the mosaic's reference alike."""
    photo = tmp_path / "photo.tif"
    _dem_file(photo, np.zeros((3, 8, 8), np.uint8), photometric="RGB")
    sums = np.full((8, 8), 3.0, np.float32)
    dem = DEM(
        np.full((8, 8), 1500.0, np.float32),
        Affine(30, 0, 500000, 0, -30, 4400000),
        "EPSG:32637",
        "ellipsoid",
        count=np.ones((8, 8), np.int32),
        score=sums,
        ray_gap=sums,
        edit_mask=np.zeros((8, 8), np.uint8),
    )
    dem.write(tmp_path / "dem.tif", layers=True)
    slope = tmp_path / "slope.tif"
    with rasterio.open(_dem_file(slope, np.full((8, 8), 12.0, np.float32)), "r+") as ds:
        ds.units = ("degree",)
    cases = {
        photo: "band 1 is the red channel of a colour image (3 band(s) of uint8), not heights",
        slope: "band 1 is in unit 'degree', not a length: not heights",
    }
    for name in ("count", "score", "ray_gap", "edit_mask"):
        spec = dem_module.LAYERS[name]
        path = dem_module.layer_path(tmp_path / "dem.tif", name)
        assert path.is_file(), name
        cases[path] = f"band 1 is stereodem's {spec.description!r}, not heights"
    for path, said in cases.items():
        for read in (
            DEM.from_file,
            DEM.check_file,
            open_source,
            header_bounds_lonlat,
            check_reference,
        ):
            with pytest.raises(DEMError) as err:
                read(path)
            assert str(err.value) == f"{path}: {said}; give " + (
                "the DEM itself" if "stereodem's" in said else "a DEM"
            ), read
    # the DEM beside them, and a DEM whose band says nothing, read as before
    assert np.all(DEM.from_file(tmp_path / "dem.tif").heights == 1500.0)
    assert DEM.from_file(_dem_file(tmp_path / "plain.tif", np.ones((8, 8), np.int16))).shape


def test_heights_in_feet_are_read_in_metres(tmp_path):
    """A DEM whose vertical CRS is in US survey feet (NAVD88 height (ftUS), EPSG:6360) or
    whose band unit says feet was read as metres: an assessment against a metre reference
    reported a mean difference of +2616 m for 3762 ft of terrain."""
    ft_us = 1200 / 3937
    a = np.full((6, 6), 3000.0, np.float32)
    for name, crs in (("us.tif", "EPSG:32637+6360"), ("m.tif", "EPSG:32637+5773")):
        with rasterio.open(_dem_file(tmp_path / name, a), "r+") as ds:
            ds.crs = rasterio.crs.CRS.from_user_input(crs)
    d = DEM.from_file(tmp_path / "us.tif")
    assert d.heights == pytest.approx(3000.0 * ft_us) and d.vertical == "geoid"
    assert d.crs.to_epsg() == 32637
    with rasterio.open(_dem_file(tmp_path / "ft.tif", a), "r+") as ds:
        ds.units = ("ft",)
        ds.scales, ds.offsets = (0.5,), (100.0,)  # GDAL's scaling first, in the band's unit
    assert DEM.from_file(tmp_path / "ft.tif").heights == pytest.approx(1600.0 * 0.3048)
    # metres stay as they are (an EGM96 compound CRS, or a band unit of metre)
    assert np.all(DEM.from_file(tmp_path / "m.tif").heights == 3000.0)


@pytest.mark.parametrize(
    "crs, name, factor",
    [
        ("EPSG:32637+3855", "EGM2008 height", 1.0),
        ("EPSG:32637+6360", "North American Vertical Datum 1988 height", 1200 / 3937),
    ],
)
def test_a_geoid_other_than_egm96_is_kept_and_its_conversion_warns(
    tmp_path, caplog, crs, name, factor
):
    """Heights above EGM2008 (the Copernicus DEM's geoid) or NAVD88 were taken for EGM96
    heights: written back as EGM96 (EPSG:5773), converted to the ellipsoid with EGM96 and
    compared with EGM96 heights without a word (an error up to a few metres)."""
    a = np.full((6, 6), 1000.0, np.float32)
    with rasterio.open(_dem_file(tmp_path / "g.tif", a), "r+") as ds:
        ds.crs = rasterio.crs.CRS.from_user_input(crs)
    d = DEM.from_file(tmp_path / "g.tif")
    assert d.vertical == "geoid" and geoid_name(d) == name
    assert d.heights == pytest.approx(1000.0 * factor)
    # written back above its own geoid (in metres), not EGM96's
    back = DEM.from_file(d.write(tmp_path / "back.tif"))
    assert geoid_name(back) == name and back.heights == pytest.approx(d.heights)
    # converted with EGM96: said
    caplog.clear()
    e = back.to_reference("ellipsoid")
    assert e.geoid_crs is None and f"heights above {name} converted to the ellipsoid" in (
        caplog.text
    )
    # compared with EGM96 heights: said, and in the note
    egm96 = DEM(a, d.transform, d.crs, "geoid", "egm96.tif")
    assert geoid_name(egm96) == "EGM96 height"
    caplog.clear()
    _, note = reconcile_vertical(back, egm96)
    assert f"{name} and EGM96 height" in note and "as if one geoid" in caplog.text
    caplog.clear()
    assert reconcile_vertical(back, back)[1] == "both geoid" and not caplog.text


@pytest.mark.parametrize(
    "crs, name", [("EPSG:32637+3855", "EGM2008 height"), ("EPSG:32637+5703", "NAVD88 height")]
)
def test_coregister_warns_of_a_geoid_other_than_egm96_as_assess_does(tmp_path, caplog, crs, name):
    """``coregister DEM --ref REF`` with DEM above EGM2008 (or NAVD88) and REF ellipsoidal
    converts REF to EGM96 geoid heights and fitted them to the DEM's without a word, while
    ``assess`` said the result is off by the separation of the two geoids: one rule
    (``core.dem.to_vertical_of``) for both, whichever side is converted."""
    a = np.full((6, 6), 1000.0, np.float32)
    with rasterio.open(_dem_file(tmp_path / "g.tif", a), "r+") as ds:
        ds.crs = rasterio.crs.CRS.from_user_input(crs)
    g = DEM.from_file(tmp_path / "g.tif")
    e = DEM(a, g.transform, g.crs, "ellipsoid", None)
    e.write(tmp_path / "e.tif")
    # coregister: the reference is brought to the DEM's vertical reference
    caplog.clear()
    with caplog.at_level("WARNING"):
        _, ref, note, _ = load_inputs(CoregJob(str(tmp_path / "g.tif"), str(tmp_path / "e.tif")))
    assert ref.vertical == "geoid"
    assert note == (
        f"reference converted from ellipsoid to geoid (EGM96); compared with {name} as if one geoid"
    )
    said = (
        "e.tif: heights above EGM96 height (converted from the ellipsoid with EGM96) compared "
        f"with {tmp_path / 'g.tif'}'s above {name} as if one geoid"
    )
    assert said in caplog.text
    # assess: the DEM brought to the reference's, either way round: said too
    for dem, ref in (
        (g, DEM.from_file(tmp_path / "e.tif")),
        (DEM.from_file(tmp_path / "e.tif"), g),
    ):
        caplog.clear()
        with caplog.at_level("WARNING"):
            reconcile_vertical(dem, ref)
        assert name in caplog.text and "EGM96" in caplog.text and "separation" in caplog.text
    caplog.clear()
    assert reconcile_vertical(e, e)[1] == "both ellipsoid" and not caplog.text


def test_a_lon_lat_dem_is_sampled_across_the_antimeridian():
    """A lon/lat DEM stored at 179.97..180.03 E reported the point -179.99 E on it as outside
    (and one stored at 0..360 E every point west of Greenwich): longitudes were compared
    without wrapping."""
    t = Affine(0.01, 0, 179.97, 0, -0.01, 65.1)
    d = DEM(np.arange(60, dtype=np.float32).reshape(10, 6), t, "EPSG:4326", "geoid")
    z, status = d.sample(
        [-179.985, 179.975 + 360], [65.095, 65.005], return_status=True, reference=None
    )
    assert list(status) == [0, 0] and list(z) == pytest.approx([4.0, 54.0])
    g = DEM(np.arange(36, dtype=np.float32)[None].repeat(3, 0), Affine(10, 0, 0, 0, -10, 30), 4326)
    assert g.sample(-5.0, 15.0, reference=None) == pytest.approx(35.0)


def test_a_dem_built_from_bad_arguments_is_refused_naming_the_argument():
    """Before, an unknown CRS escaped as pyproj's CRSError (not stereodem's), a transform that
    was no Affine (None, a GDAL geotransform tuple) made a DEM that failed later or placed the
    heights wrongly, and text heights gave numpy's bare ValueError."""
    h, t = np.ones((4, 4), np.float32), Affine(30, 0, 500000, 0, -30, 4000000)
    for crs in ("EPSG:999999", "foo"):
        with pytest.raises(CRSError, match=f"DEM: crs: unknown or unusable CRS '{crs}'"):
            DEM(h, t, crs)
    for transform in (None, (500000, 30, 0, 4000000, 0, -30)):
        with pytest.raises(DEMError, match="transform must be an affine.Affine"):
            DEM(h, transform, "EPSG:32633")
    with pytest.raises(DEMError, match="heights are not numbers"):
        DEM(np.array([["a", "b"]]), t, "EPSG:32633")


def test_sample_refuses_mismatched_or_missing_coordinates():
    """Before, lon and lat of different shapes raised numpy's broadcasting ValueError, and
    None gave a NaN height with status "outside" instead of an error."""
    dem = DEM(np.ones((4, 4), np.float32), Affine(0.01, 0, 10, 0, -0.01, 45), "EPSG:4326")
    with pytest.raises(InputError, match=r"DEM.sample: lon \(3,\) and lat \(2,\)"):
        dem.sample(np.zeros(3), np.zeros(2), reference=None)
    with pytest.raises(InputError, match="lon and lat are required"):
        dem.sample(None, None, reference=None)


def test_a_directory_given_for_a_dem_or_an_image_says_so(tmp_path):
    """Every reader of DEM files and images (``core.raster.unreadable``): a folder is "is a
    directory, not a DEM file", not GDAL's "not recognized as being in a supported file
    format"."""
    folder = tmp_path / "scene"
    folder.mkdir()
    for read in (DEM.from_file, DEM.check_file, open_source, header_bounds_lonlat):
        with pytest.raises(DEMError) as e:
            read(folder)
        assert str(e.value) == f"{folder}: is a directory, not a DEM file"
    with pytest.raises(DEMError, match="is a directory, not a reference DEM file$"):
        check_reference(folder)
    for read in (read_image, image_dtype):
        with pytest.raises(InputError) as e:
            read(folder)
        assert str(e.value) == f"{folder}: is a directory, not an image file"
    with pytest.raises(
        DEMError, match=r"missing.tif: cannot read the DEM \(No such file or directory\)$"
    ):
        DEM.from_file(tmp_path / "missing.tif")


def test_edit_mask_description_names_every_code_written():
    """The edit mask's band description is its legend: it said '1-8 filter reason' after the
    cloud mask added reason 9 (``filter --cloud-max-dev``, ``stack``)."""
    from stereodem.post.filters import EditCode, Reason

    text = dem_module.LAYERS["edit_mask"].description
    assert f"1-{max(Reason)} filter reason" in text
    for code in EditCode:
        assert str(int(code)) in text, code


@pytest.mark.parametrize("given", ["EGM96", "wgs84", "geoïd"])
def test_from_file_refuses_a_vertical_that_is_none_whatever_the_file_says(tmp_path, given):
    """``DEM.from_file(path, vertical="EGM96")`` raised a DEMError for a file that says
    nothing, but for a file that says its reference the bad value was dropped without a word
    (and so was ``assess_dem(..., dem_vertical="egm96")``): one rule, one error."""
    said = DEM(
        np.full((4, 4), 100.0), Affine(30, 0, 500000, 0, -30, 4e6), "EPSG:32637", "ellipsoid"
    )
    path = said.write(tmp_path / "said.tif")
    with pytest.raises(DEMError, match="vertical reference must be 'geoid' or 'ellipsoid'"):
        DEM.from_file(path, vertical=given)
    assert DEM.from_file(path, vertical="geoid").vertical == "ellipsoid"  # the file's wins


def test_repr_is_one_line_with_the_grid_reference_and_heights():
    """The dataclass repr printed the arrays and the CRS's whole description (about 30
    lines); one line says what a DEM is, as xdem's and rasterio's objects do."""
    d = DEM.bundled()
    text = repr(d)
    assert "\n" not in text and len(text) < 200
    assert text.startswith("DEM(") and "srtm_ref.tif" in text
    assert "1000 x 1000 cells of 0.000833333°, EPSG:4326, vertical geoid" in text
    assert "heights 1111..3270 m, 100.0 % valid" in text
