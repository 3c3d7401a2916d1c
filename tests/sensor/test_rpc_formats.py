"""RPC readers for every container (sensor.io.rpc_formats): each file in tests/data/rpc_formats
(the real Pleiades RPC written in that format's layout, see tests/data/SOURCES.md) must agree
with rpcm or GDAL, whichever reads it, to 1e-6 px on a grid of points."""

import json
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import RPCTransformer

from stereodem.core.errors import RPCError, SensorModelError
from stereodem.sensor.io.rpc_formats import read_rpc
from stereodem.sensor.io.sidecar import load_model, save_model
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.models.rpc_direct import DirectRPCModel, check_validity

DATA = Path(__file__).resolve().parents[1] / "data"
FILES = DATA / "rpc_formats"
TOL = 1e-6


def _rpcm():
    """rpcm's RPC model and file readers (its ``srtm4`` dependency, used only for DEM
    look-ups, is stubbed when it is not installed: it needs libtiff headers to build)."""
    if "srtm4" not in sys.modules:
        try:
            import srtm4  # noqa: F401
        except ImportError:
            sys.modules["srtm4"] = types.ModuleType("srtm4")
    rpc_model = pytest.importorskip("rpcm.rpc_model")
    readers = pytest.importorskip("rpcm.rpc_file_readers")
    return rpc_model, readers


@pytest.fixture(scope="module")
def truth():
    return RPCModel.from_file(DATA / "pleiades" / "img_01_rpc.tif")


def _grid(m):
    """Ground points of a 9 x 9 x 5 grid of image points and heights (exact localisation)."""
    c, r, h = (
        a.ravel()
        for a in np.meshgrid(
            np.linspace(0, m.width - 1, 9),
            np.linspace(0, m.height - 1, 9),
            np.linspace(*m.height_bounds(), 5),
            indexing="ij",
        )
    )
    lon, lat = m.localize(c, r, h)
    return lon, lat, h


def _agree_with_rpcm(ours, ref, truth):
    lon, lat, h = _grid(truth)
    c, r = ours.project(lon, lat, h)
    rc, rr = (np.asarray(v, float) for v in ref.projection(lon, lat, h))
    assert np.max(np.abs(c - rc)) <= TOL and np.max(np.abs(r - rr)) <= TOL
    # and the file is the real Pleiades RPC in our pixel convention
    tc, tr = truth.project(lon, lat, h)
    assert np.max(np.hypot(c - tc, r - tr)) <= TOL


def _agree_with_gdal(ours, truth):
    lon, lat, h = _grid(truth)
    with RPCTransformer(ours.to_rasterio(), RPC_PIXEL_ERROR_THRESHOLD=1e-10) as gdal:
        g_row, g_col = gdal.rowcol(lon.copy(), lat.copy(), zs=h.copy(), op=np.positive)
    c, r = ours.project(lon, lat, h)
    # GDAL pixel/line = ours + 0.5 (GDAL's origin is the pixel corner)
    assert np.max(np.abs(c - (np.asarray(g_col) - 0.5))) <= TOL
    assert np.max(np.abs(r - (np.asarray(g_row) - 0.5))) <= TOL
    tc, tr = truth.project(lon, lat, h)
    assert np.max(np.hypot(c - tc, r - tr)) <= TOL


# ----------------------------------------------------------------------------- one per format


def test_dimap_v2_agrees_with_rpcm(truth):
    rpc_model, _ = _rpcm()
    path = FILES / "RPC_PHR1A_P_pleiades-dimap2.XML"
    ours = read_rpc(path)
    assert (ours.width, ours.height) == (1024, 1024) and ours.loc_coeffs is not None
    _agree_with_rpcm(ours, rpc_model.rpc_from_rpc_file(str(path)), truth)


def test_dimap_v1_agrees_with_rpcm_reading_the_same_rpc_as_dimap_v2(truth):
    # neither rpcm nor GDAL reads DIMAP v1: the same coefficients in v2 are the reference
    rpc_model, _ = _rpcm()
    ours = read_rpc(FILES / "PHRDIMAP_pleiades-dimap1.XML")
    assert (ours.width, ours.height) == (1024, 1024)
    ref = rpc_model.rpc_from_rpc_file(str(FILES / "RPC_PHR1A_P_pleiades-dimap2.XML"))
    _agree_with_rpcm(ours, ref, truth)
    v2 = read_rpc(FILES / "RPC_PHR1A_P_pleiades-dimap2.XML")
    np.testing.assert_array_equal(ours.loc_coeffs, v2.loc_coeffs)


def test_digitalglobe_xml_agrees_with_rpcm(truth):
    rpc_model, _ = _rpcm()
    path = FILES / "pleiades_worldview.XML"
    ours = read_rpc(path)
    assert (ours.width, ours.height) == (1024, 1024)
    _agree_with_rpcm(ours, rpc_model.rpc_from_rpc_file(str(path)), truth)


def test_ikonos_txt_agrees_with_rpcm(truth):
    rpc_model, _ = _rpcm()
    path = FILES / "pleiades_ikonos_rpc.txt"
    ours = read_rpc(path)
    _agree_with_rpcm(ours, rpc_model.rpc_from_rpc_file(str(path)), truth)
    assert ours.loc_coeffs is not None  # extended IKONOS: direct model kept
    assert ours.err_bias == pytest.approx(3.31)  # "0003.31 meters"


def test_rpcm_json_agrees_with_rpcm(truth):
    rpc_model, _ = _rpcm()

    path = FILES / "pleiades_rpcm.json"
    ours = read_rpc(path)
    assert (ours.width, ours.height) == (1024, 1024)
    ref = rpc_model.RPCModel(json.loads(path.read_text())["rpc"], dict_format="rpcm")
    _agree_with_rpcm(ours, ref, truth)


def test_ossim_geom_agrees_with_gdal(truth):
    ours = read_rpc(FILES / "pleiades.geom")
    assert (ours.width, ours.height) == (1024, 1024)
    _agree_with_gdal(ours, truth)


def test_vrt_agrees_with_gdal(truth):
    path = FILES / "pleiades_rpc.vrt"
    ours = read_rpc(path)
    with rasterio.open(path) as ds:
        assert ds.rpcs is not None  # GDAL itself reads the VRT's RPCs
    assert (ours.width, ours.height) == (1024, 1024)
    _agree_with_gdal(ours, truth)


def test_rpc_txt_with_units_through_gdal_tags(truth):
    # GDAL picks up dg_scene_RPC.TXT and hands the values up raw ("+19403.5 pixels")
    with rasterio.open(FILES / "dg_scene.tif") as ds:
        assert "pixels" in ds.tags(ns="RPC")["LINE_OFF"]
    ours = read_rpc(FILES / "dg_scene.tif")
    assert (ours.width, ours.height) == (1024, 1024)
    _agree_with_gdal(ours, truth)
    rpc_model, _ = _rpcm()
    _agree_with_rpcm(
        read_rpc(FILES / "dg_scene_RPC.TXT"),
        rpc_model.rpc_from_rpc_file(str(FILES / "dg_scene_RPC.TXT")),
        truth,
    )


# ----------------------------------------------------------------------------- direct models


@pytest.mark.parametrize(
    "name", ["RPC_PHR1A_P_pleiades-dimap2.XML", "pleiades_rpcm.json", "pleiades_ikonos_rpc.txt"]
)
def test_direct_model_localisation_agrees_with_rpcm(name, truth):
    rpc_model, _ = _rpcm()

    path = FILES / name
    ours = read_rpc(path, direct=True)
    assert isinstance(ours, DirectRPCModel)
    if name.endswith(".json"):
        ref = rpc_model.RPCModel(json.loads(path.read_text())["rpc"], dict_format="rpcm")
    else:
        ref = rpc_model.rpc_from_rpc_file(str(path))
    assert hasattr(ref, "lon_num")  # rpcm localises with the direct model too
    c, r, h = (
        a.ravel()
        for a in np.meshgrid(
            np.linspace(0, 1023, 9),
            np.linspace(0, 1023, 9),
            np.linspace(*truth.height_bounds(), 5),
            indexing="ij",
        )
    )
    lon, lat = ours.localize(c, r, h)
    rlon, rlat = (np.asarray(v, float) for v in ref.localization(c, r, h))
    # compared in pixels through the projection
    c1, r1 = truth.project(lon, lat, h)
    c2, r2 = truth.project(rlon, rlat, h)
    assert np.max(np.hypot(c1 - c2, r1 - r2)) <= TOL
    # the direct model is a separate fit: close to, not equal to, the exact inverse
    exact = read_rpc(path)
    c3, r3 = exact.project(lon, lat, h)
    gap = np.hypot(c3 - c, r3 - r)
    assert np.max(gap) < 1e-2 and np.max(gap) > 0


def test_direct_model_sidecar_round_trip(tmp_path):
    m = read_rpc(FILES / "PHRDIMAP_pleiades-dimap1.XML", direct=True)
    save_model(m, tmp_path / "m.model.json")
    back = load_model(tmp_path / "m.model.json")
    assert isinstance(back, DirectRPCModel) and (back.width, back.height) == (m.width, m.height)
    np.testing.assert_array_equal(back.loc_coeffs, m.loc_coeffs)
    assert back.localize(10.0, 20.0, 500.0) == m.localize(10.0, 20.0, 500.0)


# ----------------------------------------------------------------------------- bad input


def test_no_reader_accepts_names_the_formats_tried(tmp_path):
    p = tmp_path / "mystery.dat"
    p.write_text("GRID 1 2 3\nsomething else\n")
    with pytest.raises(RPCError) as e:
        read_rpc(p)
    msg = str(e.value)
    assert "\n" not in msg and "mystery.dat" in msg
    for fmt in ("GDAL", "DIMAP", "DigitalGlobe", "OSSIM", ".RPB", "_RPC.TXT", "rpcm JSON"):
        assert fmt in msg


def test_direct_requested_but_absent():
    with pytest.raises(RPCError, match=r"pleiades\.geom.*no direct"):
        read_rpc(FILES / "pleiades.geom", direct=True)


def test_units_tolerated_but_garbage_refused(tmp_path):
    text = (FILES / "dg_scene_RPC.TXT").read_text()
    ok = tmp_path / "ok_RPC.TXT"
    ok.write_text(text.replace("+1295 meters", "1295 metres").replace("LAT_OFF: ", "LAT_OFF:  "))
    assert read_rpc(ok).height_off == 1295.0
    bad = tmp_path / "bad_RPC.TXT"
    bad.write_text(text.replace("pixels", "furlongs", 1))
    with pytest.raises(RPCError, match=r"bad_RPC\.TXT.*LINE_OFF.*not a number"):
        read_rpc(bad)


def test_other_bad_files(tmp_path):
    vrt = tmp_path / "broken.vrt"
    vrt.write_text((FILES / "pleiades_rpc.vrt").read_text().replace(' rasterXSize="8"', ""))
    with pytest.raises(RPCError, match=r"broken\.vrt.*GDAL cannot open this VRT") as e:
        read_rpc(vrt)
    assert "\n" not in str(e.value)
    geom = tmp_path / "a.geom"
    geom.write_text(
        (FILES / "pleiades.geom")
        .read_text()
        .replace("polynomial_format:  B", "polynomial_format:  A")
    )
    with pytest.raises(RPCError, match=r"a\.geom.*polynomial_format 'A'"):
        read_rpc(geom)
    v1 = tmp_path / "PHRDIMAP_cut.XML"
    text = (FILES / "PHRDIMAP_pleiades-dimap1.XML").read_text()
    v1.write_text(text.replace("<F_COL>", "<F_COL>1 2 ", 1))
    with pytest.raises(RPCError, match=r"PHRDIMAP_cut\.XML.*F_COL: 42 coefficient"):
        read_rpc(v1)
    js = tmp_path / "r.json"
    js.write_text('{"rpc": {"row_offset": 1}}')
    with pytest.raises(RPCError, match=r"r\.json.*col_offset missing"):
        read_rpc(js)


def test_outside_the_validity_range(truth):
    lon, lat, h = _grid(truth)
    assert check_validity(truth, lon[:5], lat[:5], np.full(5, 1000.0)).all()
    with pytest.raises(RPCError) as e:
        check_validity(truth, lon[:5], lat[:5], np.full(5, 9000.0))
    msg = str(e.value)
    assert "\n" not in msg and "img_01_rpc.tif" in msg and "5 of 5 point(s) outside" in msg


def test_model_files_of_any_rpc_format(tmp_path):
    # --left-model / --right-model: a stereodem JSON sidecar, or any RPC file
    m = load_model(FILES / "PHRDIMAP_pleiades-dimap1.XML")
    assert type(m) is RPCModel and (m.width, m.height) == (1024, 1024)
    d = load_model(FILES / "pleiades_rpcm.json", rpc_direct=True)
    assert isinstance(d, DirectRPCModel)
    bad = tmp_path / "notes.json"
    bad.write_text('{"hello": 1}')

    with pytest.raises(SensorModelError) as e:
        load_model(bad)
    assert "notes.json" in str(e.value) and "\n" not in str(e.value)
