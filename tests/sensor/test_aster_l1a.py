"""ASTER L1A granules: V004 (HDF-EOS2) and V003 (zip / folder) round trips through the
simulator's writers and the readers, radiometric correction, and bad input."""

import copy
import re
import shutil

import numpy as np
import pytest
import rasterio

from stereodem.batch import expand_inputs
from stereodem.cli import main
from stereodem.core import geodesy
from stereodem.core.errors import InputError, SensorModelError
from stereodem.core.stats import nmad
from stereodem.sensor.geo.rotations import orbital_frame
from stereodem.sensor.io.aster_l1a import (
    AsterGranule,
    is_aster_granule,
    open_aster_granule,
    read_granule_band,
)
from stereodem.sensor.io.odl import flatten_odl, format_odl, parse_odl
from stereodem.sensor.io.sidecar import load_image_model, load_model, save_model
from stereodem.sensor.simulation.aster_granule import (
    granule_from_scene,
    struct_metadata,
    write_v003,
    write_v004,
)
from stereodem.sensor.simulation.simulate import (
    SUN_AZIMUTH,
    SUN_ELEVATION,
    simulate_scene,
    write_scene,
)
from stereodem.stereo.pipeline import make_dem


@pytest.fixture(scope="module")
def scene():
    return simulate_scene("aster", size=(410, 400), right_size=(500, 540), seed=3)


@pytest.fixture(scope="module")
def granule(scene):
    return granule_from_scene(scene, seed=3)


@pytest.fixture(scope="module")
def files(granule, tmp_path_factory):
    d = tmp_path_factory.mktemp("granules")
    v3 = granule.granule_id.replace("_004", "_003", 1)
    return {
        "v004": write_v004(granule, d / f"{granule.granule_id}.hdf"),
        "v003_zip": write_v003(granule, d / f"{v3}.zip"),
        "v003_dir": write_v003(granule, d / v3),
        "v003_full": write_v003(granule, d / f"{v3}_full", decimals=None),
    }


def _geodetic(lat_geocentric):
    return np.degrees(np.arctan(np.tan(np.radians(lat_geocentric)) / (1.0 - geodesy.F) ** 2))


def _lattice_projection_error(band):
    """Max distance (px) from the lattice (col, row) to the model's projection of the
    product's lattice latitude/longitude (on the ellipsoid)."""
    f = band.fields
    lat = _geodetic(np.asarray(f.latitude, float))
    c, r = band.model.project(np.asarray(f.longitude, float), lat, np.zeros_like(lat))
    return float(np.max(np.hypot(c - f.lattice[..., 0], r - f.lattice[..., 1])))


def _sight_vector_error(band):
    """Max angle (rad) between the stored sight vectors and the model's lattice rays turned
    into the orbital frame of the stored position and (inertial) velocity."""
    f = band.fields
    _, d = band.model.rays(f.lattice[..., 0].astype(float), f.lattice[..., 1].astype(float))
    v = np.asarray(f.satellite_velocities, float)
    if band.velocity_convention == "earth_fixed":
        v = v + np.cross([0, 0, geodesy.OMEGA_EARTH], f.satellite_positions)
    m = orbital_frame(np.asarray(f.satellite_positions, float), v, inertial=False)
    s = np.einsum("nji,nkj->nki", m, d)
    ref = f.sight_vectors / np.linalg.norm(f.sight_vectors, axis=-1, keepdims=True)
    return float(np.max(np.linalg.norm(np.cross(s, ref), axis=-1)))


# ------------------------------------------------------------------------------ ODL


def test_odl_round_trip_and_flat_keys():
    tree = {
        "INVENTORYMETADATA": {
            "GROUPTYPE": "MASTERGROUP",
            "SHORTNAME": {"NUM_VAL": 1, "VALUE": "ASTL1A"},
            "POINTINGANGLE": {"CLASS": "1", "NUM_VAL": 1, "VALUE": 8.5},
            "UPPERLEFT": {"NUM_VAL": 2, "VALUE": (47.38, -122.15)},
        }
    }
    back = parse_odl(format_odl(tree))
    assert back == tree
    flat = flatten_odl(back)
    assert flat == {"SHORTNAME": "ASTL1A", "POINTINGANGLE.1": 8.5, "UPPERLEFT": (47.38, -122.15)}
    with pytest.raises(InputError, match="never closed"):
        parse_odl("GROUP = A\n  X = 1\nEND\n")


# ------------------------------------------------------------------------------ V004


def test_v004_structure_follows_the_specification(files, granule):
    """Vgroup hierarchy, SDS names repeated per swath, dimension suffixes, ODL attributes."""
    # pyhdf where an HDF file is read (DESIGN.md, imports, reason (b))
    import pyhdf.V  # noqa: F401
    from pyhdf.HDF import HDF
    from pyhdf.SD import SD

    path = str(files["v004"])
    sd = SD(path)
    names = [sd.select(i).info()[0] for i in range(sd.info()[0])]
    assert names.count("ImageData") == 2 and names.count("SightVector") == 2
    assert {
        "HDFEOSVersion",
        "StructMetadata.0",
        "coremetadata.0",
        "productmetadata.0",
        "productmetadata.v",
    } <= set(sd.attributes())
    struct = parse_odl(sd.attributes()["StructMetadata.0"])
    assert struct["SwathStructure"]["SWATH_2"]["SwathName"] == "VNIR_Band3B"
    h = HDF(path)
    v = h.vgstart()
    top = v.attach(v.find("VNIR"))
    swaths = {v.attach(r)._name: r for t, r in top.tagrefs() if t == 1965}
    assert set(swaths) == {"VNIR_Band3N", "VNIR_Band3B"}
    sw = v.attach(swaths["VNIR_Band3B"])
    assert sw._class == "SWATH"
    children = {v.attach(r)._name: r for t, r in sw.tagrefs() if t == 1965}
    assert set(children) == {"Geolocation Fields", "Data Fields", "Swath Attributes"}
    geo = [
        sd.select(sd.reftoindex(r)) for t, r in v.attach(children["Geolocation Fields"]).tagrefs()
    ]
    assert {s.info()[0] for s in geo} == {"Latitude", "Longitude", "SceneLineNumber"}
    assert all(d.endswith(":VNIR_Band3B") for s in geo for d in s.dimensions())
    img = [
        s
        for s in (
            sd.select(sd.reftoindex(r)) for t, r in v.attach(children["Data Fields"]).tagrefs()
        )
        if s.info()[0] == "ImageData"
    ][0]
    assert img.info()[2] == [540, 500] and img.info()[3] == 21  # uint8 (rows, cols)
    assert struct_metadata(granule).count("\tGROUP=SWATH_") == 2


@pytest.mark.parametrize("kind", ["v004", "v003_full"])
def test_round_trip_lattice_and_sight_vectors(files, kind):
    g = open_aster_granule(files[kind])
    assert isinstance(g, AsterGranule) and set(g.bands) == {"3N", "3B"}
    for b in ("3N", "3B"):
        band = g[b]
        assert band.velocity_convention == "inertial"
        err_px = _lattice_projection_error(band)
        err_sv = _sight_vector_error(band)
        print(
            f"{kind} {b}: lattice projection {err_px:.2e} px, sight vectors {1e6 * err_sv:.3f} urad"
        )
        assert err_px < 0.01
        assert err_sv < 2e-6


def test_v003_six_decimals_within_its_rounding(files, granule):
    """Real V003 tables carry 6 decimals: sight vectors are rounded by up to
    0.5e-6 per component; the lattice must still be reproduced within what that allows."""
    for kind in ("v003_zip", "v003_dir"):
        g = open_aster_granule(files[kind])
        for b in ("3N", "3B"):
            band = g[b]
            f = band.fields
            rng_m = np.linalg.norm(
                geodesy.intersect_height(
                    *band.model.rays(
                        f.lattice[..., 0].astype(float), f.lattice[..., 1].astype(float)
                    ),
                    np.zeros(f.lattice.shape[:2]),
                )
                - f.satellite_positions[:, None, :],
                axis=-1,
            ).max()
            gsd = band.model.gsd(0.0)
            bound_px = np.sqrt(3) * 0.5e-6 * rng_m / gsd + np.hypot(0.5e-6, 0.5e-6) * 111e3 / gsd
            err_px = _lattice_projection_error(band)
            print(f"{kind} {b}: lattice projection {err_px:.4f} px (rounding bound {bound_px:.4f})")
            assert err_px < bound_px
            assert _sight_vector_error(band) < 2e-6


def test_v003_and_v004_give_the_same_band(files):
    a, c = open_aster_granule(files["v004"]), open_aster_granule(files["v003_zip"])
    for b in ("3N", "3B"):
        np.testing.assert_array_equal(a[b].dn(), c[b].dn())
        np.testing.assert_array_equal(a[b].fields.lattice, c[b].fields.lattice)
        np.testing.assert_allclose(
            a[b].fields.satellite_positions, c[b].fields.satellite_positions, atol=1e-6
        )
    assert (
        a.metadata["acquisition_time"] == c.metadata["acquisition_time"] == "2017-07-31T19:07:28Z"
    )


def test_metadata_from_odl(files, scene):
    g = open_aster_granule(files["v004"])
    md = g.metadata

    assert md["granule_id"] == files["v004"].stem
    assert (md["sun_azimuth_deg"], md["sun_elevation_deg"]) == (SUN_AZIMUTH, SUN_ELEVATION)
    assert md["cloud_cover_pct"] == 0.0
    lon, lat = scene.left_model.localize(np.array([0.0]), np.array([0.0]), np.array([0.0]))
    assert md["corners"]["UPPERLEFT"] == pytest.approx((lat[0], lon[0]), abs=1e-5)
    assert g.tags()["ASTER_ACQUISITION_TIME"] == "2017-07-31T19:07:28Z"


def test_earth_fixed_velocity_is_detected(scene, tmp_path):
    g = granule_from_scene(scene, seed=3, velocity="earth_fixed")
    band = open_aster_granule(write_v004(g, tmp_path / "ef.hdf"))["3B"]
    assert band.velocity_convention == "earth_fixed"
    assert _lattice_projection_error(band) < 0.01


def test_model_sidecar_keeps_product_velocity(files, tmp_path):
    m = open_aster_granule(files["v004"]).model("3B")
    save_model(m, tmp_path / "m.json")
    back = load_model(tmp_path / "m.json")
    assert back.geometry.velocity_convention == "inertial"
    np.testing.assert_allclose(back.geometry.satellite_velocities, m.geometry.satellite_velocities)
    c, r = np.array([10.0, 250.0]), np.array([5.0, 300.0])
    np.testing.assert_allclose(back.localize(c, r, 1000.0), m.localize(c, r, 1000.0), atol=1e-12)


# ------------------------------------------------------------------------------ radiometry


def _column_profile_variation(image, truth):
    """(max - min) / mean of the ratio of column means of ``image`` to those of ``truth``."""
    ok = np.isfinite(image) & np.isfinite(truth)
    num = np.where(ok, image, 0).sum(0) / ok.sum(0)
    den = np.where(ok, truth, 0).sum(0) / ok.sum(0)
    p = num / den
    return float((p.max() - p.min()) / p.mean())


def test_radiometric_correction_removes_striping(files, granule):
    g = open_aster_granule(files["v004"])
    for b in ("3N", "3B"):
        truth = granule.bands[b].radiance
        before = _column_profile_variation(g[b].image(radiometric=False), truth)
        after = _column_profile_variation(g[b].image(), truth)
        print(f"{b}: column-mean variation before {100 * before:.2f} %, after {100 * after:.3f} %")
        assert before > 0.02  # the injected striping is visible in the DN
        assert after <= 0.005


def test_fill_pixels_are_masked(granule, tmp_path):
    g = copy.deepcopy(granule)
    g.bands["3N"].dn[:7, :] = 0
    band = open_aster_granule(write_v004(g, tmp_path / "fill.hdf"))["3N"]
    img = band.image()
    assert band.fill_mask()[:7].all() and not band.fill_mask()[7:].any()
    assert np.isnan(img[:7]).all() and np.isfinite(img[7:]).all()
    assert np.isnan(band.image(radiometric=False)[:7]).all()
    # the radiance is L = A V / G + D per detector (column), float32, in that order
    v = band.dn().astype(np.float32)
    d, a, gain = (band.fields.rc_table[:, k].astype(np.float32) for k in range(3))
    want = np.where(band.dn() == 0, np.float32(np.nan), a * v / gain + d)
    assert img.dtype == np.float32 and np.array_equal(img, want, equal_nan=True)


# ------------------------------------------------------------------------------ bad input


def test_non_aster_hdf(tmp_path):
    from pyhdf.SD import SD, SDC  # DESIGN.md, imports, reason (b)

    p = tmp_path / "MOD021KM.hdf"
    sd = SD(str(p), SDC.WRITE | SDC.CREATE)
    s = sd.create("EV_1KM_RefSB", SDC.UINT16, (4, 5))
    s[:] = np.ones((4, 5), np.uint16)
    s.endaccess()
    sd.end()
    with pytest.raises(InputError, match=r"MOD021KM\.hdf: not an ASTER L1A granule"):
        open_aster_granule(p)
    q = tmp_path / "notes.hdf"
    q.write_text("hello")
    with pytest.raises(InputError, match=r"notes\.hdf: not an ASTER L1A granule \(neither an HDF4"):
        open_aster_granule(q)


@pytest.mark.parametrize("level,short", [("L1B", "ASTL1B"), ("L1T", "AST_L1T")])
def test_l1b_and_l1t_are_refused(granule, tmp_path, level, short):
    g = copy.deepcopy(granule)
    g.attributes["coremetadata.0"] = (
        g.attributes["coremetadata.0"]
        .replace('"ASTL1A"', f'"{short}"')
        .replace('"1A"', f'"{level[1:]}"')
    )
    p = write_v004(g, tmp_path / f"AST_{level}_00407312017190728.hdf")
    with pytest.raises(
        InputError,
        match=rf"{p.name}: this is an ASTER {level} product; "
        r"stereodem needs AST_L1A .*no sensor geometry",
    ):
        open_aster_granule(p)


def test_granule_without_3b(granule, tmp_path):
    g = copy.deepcopy(granule)
    del g.bands["3B"]
    g.attributes["StructMetadata.0"] = struct_metadata(g)
    p = write_v004(g, tmp_path / "night.hdf")
    with pytest.raises(InputError, match=r"night\.hdf: no band 3B \(VNIR_Band3B swath\)"):
        open_aster_granule(p)
    assert set(open_aster_granule(p, bands=("3N",)).bands) == {"3N"}


def test_truncated_files(files, tmp_path):
    data = files["v004"].read_bytes()
    p = tmp_path / "cut.hdf"
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.hdf: HDF4 file cannot be opened - truncated"):
        open_aster_granule(p)
    z = tmp_path / "cut.zip"
    z.write_bytes(files["v003_zip"].read_bytes()[:5000])
    with pytest.raises(InputError, match=r"cut\.zip: not a readable zip file - truncated"):
        open_aster_granule(z)


@pytest.mark.parametrize("table", ["SightVector", "RadiometricCorrTable", "Latitude"])
def test_v003_folder_missing_a_table(files, tmp_path, table):
    d = tmp_path / "granule"
    shutil.copytree(files["v003_dir"], d)
    victim = next(d.glob(f"*.VNIR_Band3B.{table}.txt"))
    victim.unlink()
    with pytest.raises(
        InputError, match=rf"granule: V003 granule has no .*VNIR_Band3B\.{table}\.txt"
    ):
        open_aster_granule(d)


def test_inconsistent_geometry_is_refused(granule, tmp_path):
    g = copy.deepcopy(granule)
    g.bands["3N"].latitude = g.bands["3N"].latitude + 0.01  # ~1 km off
    p = write_v004(g, tmp_path / "bad_geo.hdf")
    with pytest.raises(
        SensorModelError,
        match=r"bad_geo\.hdf:VNIR_Band3N: SightVector/"
        r"SatellitePosition do not reproduce",
    ):
        open_aster_granule(p)


def test_v003_l1b_folder_is_refused(tmp_path):
    d = tmp_path / "l1b"
    d.mkdir()
    (d / "AST_L1B_00307312017190728_20160404141337_1.VNIR_Swath.ImageData3N.tif").write_bytes(
        b"II*\0"
    )
    with pytest.raises(
        InputError, match=r"l1b: this is an ASTER L1B product; stereodem needs AST_L1A"
    ):
        open_aster_granule(d)


def test_band_names_and_single_band_reader(files):
    g = open_aster_granule(files["v004"])
    assert g.band("3b") is g.band("Band3B") is g.band("VNIR_Band3B") is g["3B"]
    with pytest.raises(InputError, match=r"no band '2' in this granule \(has 3N, 3B\)"):
        g.band("2")
    img, model, tags = read_granule_band(files["v003_zip"], "3B", radiometric=False)
    assert img.shape == (model.height, model.width) == g["3B"].shape
    np.testing.assert_array_equal(img, g["3B"].image(radiometric=False))
    assert tags["ASTER_BAND"] == "3B" and tags["ASTER_GRANULE_ID"] == g.granule_id


def test_is_aster_granule(files, tmp_path):
    assert all(is_aster_granule(files[k]) for k in ("v004", "v003_zip", "v003_dir"))
    plain = tmp_path / "left.tif"
    plain.write_bytes(b"II*\0" + bytes(100))
    assert not is_aster_granule(plain) and not is_aster_granule(tmp_path / "missing.hdf")
    assert not is_aster_granule(tmp_path)


# ------------------------------------------------------------------------------ command line


@pytest.mark.slow  # over 0.5 s: out of the fast subset (CI runs it)
def test_cli_simulate_granule_and_info(tmp_path, capsys):
    out = tmp_path / "sim"
    assert (
        main(
            [
                "simulate",
                "--preset",
                "aster",
                "--format",
                "l1a-v004",
                "--size",
                "200",
                "200",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    hdf = next(out.glob("AST_L1A_004*.hdf"))
    assert (out / "truth_dem.tif").exists() and not (out / "left.tif").exists()
    g = open_aster_granule(hdf)
    assert g["3N"].shape == (200, 200) and g["3B"].shape == (257, 240)  # real 3N:3B ratio
    capsys.readouterr()
    assert main(["info", str(hdf)]) == 0
    text = capsys.readouterr().out
    assert "band 3N: 200 x 200 px, lattice" in text and "band 3B: 240 x 257 px" in text
    assert "acquired 2017-07-31T19:07:28Z" in text and "upperleft" in text
    assert main(["info", str(out / "truth_dem.tif")]) == 1
    assert "stereodem info: error:" in capsys.readouterr().err
    assert (
        main(["simulate", "--preset", "frame", "--format", "l1a-v003", "-o", str(tmp_path / "x")])
        == 1
    )


# ---------------------------------------------------------------------------- DEM through a granule


@pytest.mark.slow
def test_dem_from_granule_matches_dem_from_geotiff_and_sidecar(tmp_path):
    """The same simulated scene given as a V004 granule (radiance images, AsterModel from the
    lattice) and as GeoTIFFs with exact model sidecars gives the same DEM: the difference is
    a small fraction of either DEM's error against the truth."""
    sc = simulate_scene("aster", size=(410, 400), right_size=(500, 520), seed=2)
    out = write_scene(sc, tmp_path / "tif")
    gr = open_aster_granule(write_v004(granule_from_scene(sc, seed=2), tmp_path / "g.hdf"))
    with rasterio.open(out / "left.tif") as a, rasterio.open(out / "right.tif") as b:
        left, right = a.read(1), b.read(1)
    tif = make_dem(
        left,
        right,
        load_image_model(out / "left.tif"),
        load_image_model(out / "right.tif"),
        seed_dem=sc.truth_dem,
    ).dem
    gran = make_dem(
        gr.read_image("3N"),
        gr.read_image("3B"),
        gr.model("3N"),
        gr.model("3B"),
        seed_dem=sc.truth_dem,
    ).dem
    assert gran.heights.shape == tif.heights.shape and gran.transform == tif.transform
    cc, rr = np.meshgrid(
        np.arange(tif.heights.shape[1]) + 0.5, np.arange(tif.heights.shape[0]) + 0.5
    )
    x, y = tif.transform @ (cc, rr)
    truth = sc.truth_dem.sample(*geodesy.crs_to_lonlat(x, y, tif.crs))

    diff = gran.heights - tif.heights
    print(
        f"granule vs GeoTIFF DEM: median {np.nanmedian(diff):.4f} m, NMAD {nmad(diff):.3f} m; "
        f"vs truth NMAD {nmad(tif.heights - truth):.2f} / {nmad(gran.heights - truth):.2f} m"
    )
    assert abs(np.nanmedian(diff)) < 0.05
    assert nmad(diff) < 0.15 * nmad(tif.heights - truth)
    assert abs(np.isfinite(gran.heights).mean() - np.isfinite(tif.heights).mean()) < 0.005


@pytest.mark.slow
def test_simulated_granules_of_different_seeds_share_a_folder(tmp_path):
    """`simulate --seed N`: the granule's id (file name) carries a production stamp from the
    seed, in the real AST_L1A_004<acquired>_<produced> pattern, so granules of two seeds copied
    into one folder do not overwrite each other and `batch` sees two scenes."""
    both = tmp_path / "both"
    both.mkdir()
    for seed in (1, 2):
        out = tmp_path / f"s{seed}"
        args = ["simulate", "--preset", "aster", "--format", "l1a-v004", "--size", "120", "120"]
        assert main([*args, "--seed", str(seed), "-o", str(out)]) == 0
        (hdf,) = out.glob("AST_L1A_004*.hdf")
        assert re.fullmatch(r"AST_L1A_004\d{14}_\d{14}\.hdf", hdf.name), hdf.name
        assert not (both / hdf.name).exists(), f"seed {seed}: {hdf.name} is already there"
        shutil.copy(hdf, both / hdf.name)
    granules = sorted(both.glob("*.hdf"))
    assert len(granules) == 2
    for p in granules:
        g = open_aster_granule(p)
        assert g["3N"].shape == (120, 120)
        md = g.metadata
        assert md["granule_id"] == p.stem and md["acquisition_time"] == "2017-07-31T19:07:28Z"
    scenes = expand_inputs([str(p) for p in granules])
    assert len({s.name for s in scenes}) == 2 and {s.kind for s in scenes} == {"granule"}


def test_tile_cache_key_does_not_depend_on_how_the_granule_is_named(files, monkeypatch):
    """The same granule by a relative and by an absolute path is the same model for the tile
    cache: ``stereodem demo -o /abs/out`` then ``stereodem run out/demo.toml --resume`` refused
    the demo's tiles ("belong to a run with other inputs or settings": the model's description
    holds the path it was read from)."""
    from stereodem.stereo.execution import _model_fingerprint

    path = files["v004"]
    monkeypatch.chdir(path.parent)
    absolute = open_aster_granule(str(path))["3N"].model
    relative = open_aster_granule(path.name)["3N"].model
    assert absolute.to_dict()["geometry"]["path"] != relative.to_dict()["geometry"]["path"]
    assert _model_fingerprint(absolute) == _model_fingerprint(relative)
