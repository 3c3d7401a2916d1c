"""RPC00B model (sensor.rpc) and RPC fitting (sensor.rpcfit).

Reference implementation: GDAL's RPC transformer through ``rasterio.transform.RPCTransformer``.

Pixel convention (stated and tested here): RPC00B and stereodem put the centre of the
top-left pixel at (0, 0), so ``col = samp``, ``row = line``. GDAL's transformer puts (0, 0) at
the top-left pixel *corner*: GDAL pixel/line = ours + 0.5. Hence, empirically (rasterio 1.4,
GDAL 3.10):

* ``RPCTransformer.rowcol(lon, lat, zs=h, op=np.positive)`` returns unrounded GDAL
  (line, pixel) = (row + 0.5, col + 0.5);
* ``RPCTransformer.xy(row, col, zs=h, offset="center")`` adds 0.5 itself and so localises our
  (col, row) exactly; GDAL iterates its inverse only to RPC_PIXEL_ERROR_THRESHOLD (default
  0.1 px), so the comparison passes 1e-8 px (at 1e-10 GDAL gives up on most points and
  returns inf).
"""

import warnings

import numpy as np
import pytest
import rasterio
from rasterio.transform import RPCTransformer

from stereodem.core import geodesy
from stereodem.core.errors import RPCError
from stereodem.sensor.estimation.rpcfit import fit_rational, fit_rpc
from stereodem.sensor.models.base import SensorModel
from stereodem.sensor.models.rpc import COEFF_KEYS, SCALAR_KEYS, RPCModel

PLEIADES = ("img_01_rpc.tif", "img_02_rpc.tif")
M_PER_DEG = 111_320.0

# rasterio 1.3 (the declared minimum) multiplies an Affine with ``*`` inside its RPC
# transformer, once per point with affine >= 3: 80 000 warnings from the reference library
# alone, recorded one by one (0.9 s of this file)
pytestmark = pytest.mark.filterwarnings(
    "ignore:Use `@` matmul instead of `\\*` mul operator:PendingDeprecationWarning"
)


@pytest.fixture(scope="module", params=PLEIADES)
def pleiades(request, data_dir):
    return RPCModel.from_file(data_dir / "pleiades" / request.param)


@pytest.fixture(scope="module")
def pleiades1(data_dir):
    return RPCModel.from_file(data_dir / "pleiades" / "img_01_rpc.tif")


def _image_points(model, n, hlo, hhi, seed=0):
    rng = np.random.default_rng(seed)
    return (
        rng.uniform(0, model.width - 1, n),
        rng.uniform(0, model.height - 1, n),
        rng.uniform(hlo, hhi, n),
    )


def _ground_m(lon1, lat1, lon2, lat2):
    """Approximate ground distance (m) between nearby points."""
    return np.hypot((lon1 - lon2) * M_PER_DEG * np.cos(np.radians(lat1)), (lat1 - lat2) * M_PER_DEG)


def _same_coefficients(a, b):
    for attr in ("line_num", "line_den", "samp_num", "samp_den"):
        np.testing.assert_array_equal(getattr(a, attr), getattr(b, attr))
    for attr in (
        "line_off",
        "samp_off",
        "line_scale",
        "samp_scale",
        "lon_off",
        "lat_off",
        "lon_scale",
        "lat_scale",
        "height_off",
        "height_scale",
    ):
        assert getattr(a, attr) == getattr(b, attr), attr


# ---------------------------------------------------------------------- (a) reading, GDAL agreement
def test_reads_real_pleiades_metadata(pleiades, data_dir):
    with rasterio.open(pleiades.source) as ds:
        ref = ds.rpcs
        size = int(ds.tags()["SOURCE_WIDTH"]), int(ds.tags()["SOURCE_HEIGHT"])
    assert (pleiades.width, pleiades.height) == size
    np.testing.assert_array_equal(pleiades.line_num, ref.line_num_coeff)
    np.testing.assert_array_equal(pleiades.samp_den, ref.samp_den_coeff)
    assert pleiades.samp_off == ref.samp_off and pleiades.lon_scale == ref.long_scale
    assert pleiades.height_bounds() == (
        ref.height_off - ref.height_scale,
        ref.height_off + ref.height_scale,
    )


def test_project_matches_gdal_with_half_pixel_shift(pleiades):
    col, row, h = _image_points(pleiades, 20000, 0.0, 2600.0)
    with RPCTransformer(pleiades.to_rasterio(), RPC_PIXEL_ERROR_THRESHOLD=1e-8) as gdal:
        lon, lat = (np.asarray(v) for v in gdal.xy(row, col, zs=h, offset="center"))
        g_row, g_col = (
            np.asarray(v) for v in gdal.rowcol(lon.copy(), lat.copy(), zs=h.copy(), op=np.positive)
        )
    c, r = pleiades.project(lon, lat, h)
    # GDAL pixel/line = ours + 0.5 (GDAL's origin is the pixel corner)
    assert np.max(np.abs(c - (g_col - 0.5))) < 1e-3
    assert np.max(np.abs(r - (g_row - 0.5))) < 1e-3
    # and xy(offset="center") localised our pixel centre (col, row)
    assert np.max(np.abs(c - col)) < 1e-3 and np.max(np.abs(r - row)) < 1e-3


def test_localize_matches_gdal(pleiades):
    col, row, h = _image_points(pleiades, 20000, 0.0, 2600.0, seed=1)
    with RPCTransformer(pleiades.to_rasterio(), RPC_PIXEL_ERROR_THRESHOLD=1e-8) as gdal:
        g_lon, g_lat = (np.asarray(v) for v in gdal.xy(row, col, zs=h, offset="center"))
    lon, lat = pleiades.localize(col, row, h)
    # difference expressed in pixels: both ground points through the (GDAL-verified) projection
    c1, r1 = pleiades.project(lon, lat, h)
    c2, r2 = pleiades.project(g_lon, g_lat, h)
    assert np.max(np.hypot(c1 - c2, r1 - r2)) < 1e-3
    assert np.max(_ground_m(lon, lat, g_lon, g_lat)) < 1e-3 * 0.7  # Pleiades GSD ~0.7 m


# ---------------------------------------------------------------------- (b) exact inverse
@pytest.mark.slow
def test_round_trips_over_image_and_heights(pleiades):
    col, row, h = _image_points(pleiades, 200000, -500.0, 9000.0, seed=2)
    # the corners and the extreme heights explicitly
    col = np.concatenate([col, [0, pleiades.width - 1, 0, pleiades.width - 1] * 2])
    row = np.concatenate([row, [0, 0, pleiades.height - 1, pleiades.height - 1] * 2])
    h = np.concatenate([h, [-500.0] * 4 + [9000.0] * 4])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a non-converged point would warn
        lon, lat = pleiades.localize(col, row, h)
        c, r = pleiades.project(lon, lat, h)
        assert np.all(np.isfinite(lon)) and np.all(np.isfinite(lat))
        assert np.max(np.abs(c - col)) < 1e-6 and np.max(np.abs(r - row)) < 1e-6
        lon2, lat2 = pleiades.localize(c, r, h)
    assert np.max(_ground_m(lon, lat, lon2, lat2)) < 1e-3


def test_broadcasting_shapes_and_nan(pleiades1):
    col = np.array([[10.0, 500.0], [900.0, np.nan]])
    lon, lat = pleiades1.localize(col, 300.0, 1000.0)
    assert lon.shape == (2, 2) and np.isnan(lon[1, 1]) and np.all(np.isfinite(lon.ravel()[:3]))
    c, r = pleiades1.project(lon, lat, 1000.0)
    assert c.shape == (2, 2)
    np.testing.assert_allclose(c.ravel()[:3], col.ravel()[:3], atol=1e-6)


def test_non_convergence_gives_nan_and_warning(pleiades1):
    col, row, h = _image_points(pleiades1, 100, 0.0, 2000.0, seed=3)
    with pytest.warns(RuntimeWarning, match="did not converge"):
        lon, _ = pleiades1.localize(col, row, h, tol=1e-6, max_iterations=0)
    assert np.isnan(lon).any()


# ---------------------------------------------------------------------- (c) writers and readers
def test_rpb_round_trip_and_gdal_reads_it(pleiades1, tmp_path):
    rpb = tmp_path / "scene.RPB"
    pleiades1.write_rpb(rpb)
    back = RPCModel.from_file(rpb)
    _same_coefficients(back, pleiades1)
    # GDAL picks the .RPB up as the sidecar of scene.tif and reads the same coefficients
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(
            tmp_path / "scene.tif", "w", driver="GTiff", width=16, height=16, count=1, dtype="uint8"
        ) as ds:
            ds.write(np.zeros((1, 16, 16), np.uint8))
        with rasterio.open(tmp_path / "scene.tif") as ds:
            gdal_rpc = ds.rpcs
    _same_coefficients(RPCModel.from_rasterio(gdal_rpc), pleiades1)
    sidecar = RPCModel.from_file(tmp_path / "scene.tif")
    _same_coefficients(sidecar, pleiades1)
    assert (sidecar.width, sidecar.height) == (16, 16)
    with pytest.raises(FileExistsError):
        pleiades1.write_rpb(rpb)


def _bare_tiff(path, rpc_tags=None):
    """An 8 x 8 uint8 GeoTIFF of zeros without georeferencing (and with ``rpc_tags`` in its
    RPC domain); the path."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(
            path, "w", driver="GTiff", width=8, height=8, count=1, dtype="uint8"
        ) as ds:
            ds.write(np.zeros((1, 8, 8), np.uint8))
            if rpc_tags:
                ds.update_tags(ns="RPC", **rpc_tags)
    return path


def test_geotiff_tags_round_trip(pleiades1, tmp_path):
    new = tmp_path / "new.tif"
    pleiades1.write_geotiff_tags(new, data=np.zeros((8, 8), np.uint8))
    _same_coefficients(RPCModel.from_file(new), pleiades1)
    # into an existing GeoTIFF, in place
    old = _bare_tiff(tmp_path / "old.tif")
    with pytest.raises(RPCError, match="old.tif"):
        RPCModel.from_file(old)
    pleiades1.write_geotiff_tags(old)
    _same_coefficients(RPCModel.from_file(old), pleiades1)
    # dict and rasterio conversions are exact
    _same_coefficients(RPCModel.from_dict(pleiades1.to_dict()), pleiades1)
    _same_coefficients(RPCModel.from_rasterio(pleiades1.to_rasterio()), pleiades1)


def _write_rpc_txt(model, path, drop=None, garble=None):
    d = model.to_dict()
    lines = []
    for k in (
        "LINE_OFF",
        "SAMP_OFF",
        "LAT_OFF",
        "LONG_OFF",
        "HEIGHT_OFF",
        "LINE_SCALE",
        "SAMP_SCALE",
        "LAT_SCALE",
        "LONG_SCALE",
        "HEIGHT_SCALE",
    ):
        unit = {"LAT": "degrees", "LON": "degrees", "HEI": "meters"}.get(k[:3], "pixels")
        lines.append(f"{k}: {float(d[k]):+.17g} {unit}")
    for k in COEFF_KEYS:
        for i, v in enumerate(d[k].split(), start=1):
            lines.append(f"{k}_{i}: {float(v):+.17E}")
    text = "\n".join(ln for ln in lines if not (drop and ln.startswith(drop + ":"))) + "\n"
    if garble:
        text = text.replace(f"{garble}: ", f"{garble}: 1.2.3x ", 1)
    path.write_text(text)
    return path


def test_rpc_txt_reader(pleiades1, tmp_path):
    back = RPCModel.from_file(_write_rpc_txt(pleiades1, tmp_path / "scene_RPC.TXT"))
    _same_coefficients(back, pleiades1)
    c, r = back.project(55.65, -21.233, 300.0)
    c0, r0 = pleiades1.project(55.65, -21.233, 300.0)
    assert (c, r) == (c0, r0)


def _dimap(model, loc=None):
    """A DIMAP v2 RPC file with ``model`` as Inverse_Model (pixel offsets counted from 1)."""
    d = model.to_dict()
    inv = "".join(
        f"<{k}_{i}>{v}</{k}_{i}>"
        for k in ("SAMP_NUM_COEFF", "SAMP_DEN_COEFF", "LINE_NUM_COEFF", "LINE_DEN_COEFF")
        for i, v in enumerate(d[k].split(), start=1)
    )
    direct = ""
    if loc is not None:
        direct = (
            "<Direct_Model>"
            + "".join(
                f"<{k}_{i}>{v!r}</{k}_{i}>"
                for k, row in zip(
                    ("SAMP_NUM_COEFF", "SAMP_DEN_COEFF", "LINE_NUM_COEFF", "LINE_DEN_COEFF"), loc
                )
                for i, v in enumerate(row.tolist(), start=1)
            )
            + "</Direct_Model>"
        )
    val = "".join(
        f"<{k}>{float(d[k]) + (1.0 if k in ('LINE_OFF', 'SAMP_OFF') else 0.0)!r}</{k}>"
        for k in SCALAR_KEYS
    )
    return (
        "<?xml version='1.0' encoding='UTF-8'?>\n<Dimap_Document><Metadata_Identification>"
        "<METADATA_FORMAT version='2.0'>DIMAP</METADATA_FORMAT><METADATA_PROFILE>PHR_SENSOR"
        "</METADATA_PROFILE></Metadata_Identification><Rational_Function_Model><Global_RFM>"
        f"{direct}<Inverse_Model>{inv}</Inverse_Model><RFM_Validity>"
        "<Direct_Model_Validity_Domain><FIRST_ROW>1</FIRST_ROW><FIRST_COL>1</FIRST_COL>"
        f"<LAST_ROW>{model.height}</LAST_ROW><LAST_COL>{model.width}</LAST_COL>"
        f"</Direct_Model_Validity_Domain>{val}</RFM_Validity></Global_RFM>"
        "</Rational_Function_Model></Dimap_Document>\n"
    )


def test_dimap_reader_inverse_is_projection_and_direct_seeds_localize(pleiades1, tmp_path):
    m = pleiades1
    # an image -> ground "Direct_Model" in the DIMAP layout: SAMP_* -> lon, LINE_* -> lat of
    # normalised (col, row, H) in the (L, P, H) slots
    col, row, h = (
        a.ravel()
        for a in np.meshgrid(
            np.linspace(0, m.width - 1, 12),
            np.linspace(0, m.height - 1, 12),
            np.linspace(-20, 2610, 6),
            indexing="ij",
        )
    )
    lon, lat = m.localize(col, row, h)
    cn, rn = (col - m.samp_off) / m.samp_scale, (row - m.line_off) / m.line_scale
    hn = (h - m.height_off) / m.height_scale
    # (unregularised: this crop lies far outside its RPC's normalisation box, cn ~ -38, so
    # the monomials are badly scaled and even a tiny Tikhonov weight would bias the fit)
    lon_n, lon_d, _ = fit_rational(cn, rn, hn, (lon - m.lon_off) / m.lon_scale, regularization=0.0)
    lat_n, lat_d, _ = fit_rational(cn, rn, hn, (lat - m.lat_off) / m.lat_scale, regularization=0.0)
    loc = np.stack([lon_n, lon_d, lat_n, lat_d])
    path = tmp_path / "RPC_PHR1A_P_201301010000000_SEN_0000000101-001.XML"
    path.write_text(_dimap(m, loc))
    back = RPCModel.from_file(path)
    _same_coefficients(back, m)  # LINE_OFF/SAMP_OFF: DIMAP value - 1
    assert (back.width, back.height) == (m.width, m.height)
    np.testing.assert_array_equal(back.loc_coeffs, loc)
    # the direct model alone lands within 1e-4 px; Newton then makes it exact
    v = back.loc_coeffs @ np.stack(
        [
            np.ones_like(cn),
            cn,
            rn,
            hn,
            cn * rn,
            cn * hn,
            rn * hn,
            cn**2,
            rn**2,
            hn**2,
            cn * rn * hn,
            cn**3,
            cn * rn**2,
            cn * hn**2,
            cn**2 * rn,
            rn**3,
            rn * hn**2,
            cn**2 * hn,
            rn**2 * hn,
            hn**3,
        ]
    )
    c_g, r_g = m.project(
        m.lon_off + m.lon_scale * v[0] / v[1], m.lat_off + m.lat_scale * v[2] / v[3], h
    )
    assert np.max(np.hypot(c_g - col, r_g - row)) < 1e-4
    lon2, lat2 = back.localize(col, row, h)
    c2, r2 = back.project(lon2, lat2, h)
    assert np.max(np.abs(c2 - col)) < 1e-6 and np.max(np.abs(r2 - row)) < 1e-6
    # without a Direct_Model the reader still works (affine initial guess)
    path2 = tmp_path / "RPC_nodirect.XML"
    path2.write_text(_dimap(m))
    assert RPCModel.from_file(path2).loc_coeffs is None


# ---------------------------------------------------------------------- (d) bad input
def test_missing_key(pleiades1, tmp_path):
    p = _write_rpc_txt(pleiades1, tmp_path / "bad_RPC.TXT", drop="HEIGHT_SCALE")
    with pytest.raises(RPCError, match=r"bad_RPC\.TXT.*HEIGHT_SCALE.*missing"):
        RPCModel.from_file(p)
    p = _write_rpc_txt(pleiades1, tmp_path / "bad2_RPC.TXT", drop="LINE_NUM_COEFF_7")
    with pytest.raises(RPCError, match=r"bad2_RPC\.TXT.*LINE_NUM_COEFF_7"):
        RPCModel.from_file(p)
    with pytest.raises(RPCError, match="LONG_OFF missing"):
        RPCModel.from_dict({k: v for k, v in pleiades1.to_dict().items() if k != "LONG_OFF"})


def test_garbled_number(pleiades1, tmp_path):
    p = _write_rpc_txt(pleiades1, tmp_path / "garbled_RPC.TXT", garble="LAT_SCALE")
    with pytest.raises(RPCError, match=r"garbled_RPC\.TXT.*LAT_SCALE.*not a number"):
        RPCModel.from_file(p)
    rpb = tmp_path / "g.RPB"
    pleiades1.write_rpb(rpb)
    rpb.write_text(rpb.read_text().replace("sampScale = ", "sampScale = nan", 1))
    with pytest.raises(RPCError, match=r"g\.RPB.*SAMP_SCALE"):
        RPCModel.from_file(rpb)
    d = pleiades1.to_dict()
    d["LINE_DEN_COEFF"] = " ".join(d["LINE_DEN_COEFF"].split()[:19])
    with pytest.raises(RPCError, match="LINE_DEN_COEFF: 19 coefficient"):
        RPCModel.from_dict(d, path="x.tif")
    x = tmp_path / "RPC_bad.XML"
    x.write_text(_dimap(pleiades1).replace("<LINE_NUM_COEFF_3>", "<LINE_NUM_COEFF_3>zz", 1))
    with pytest.raises(RPCError, match=r"RPC_bad\.XML.*LINE_NUM_COEFF\[3\]"):
        RPCModel.from_file(x)


@pytest.mark.parametrize(
    "key, coeffs, match",
    [
        ("LINE_DEN_COEFF", [0.0] * 20, "all 20 coefficients are zero"),
        ("SAMP_NUM_COEFF", [0.0] * 20, "all 20 coefficients are zero"),
        ("LINE_NUM_COEFF", [0.3] + [0.0] * 19, r"\(only the constant term\)"),
    ],
)
def test_blank_rpc_polynomial_names_the_file_and_key(pleiades1, tmp_path, key, coeffs, match):
    """A GeoTIFF whose RPC tags hold a blank polynomial (zeros, as some tools write for "no
    RPC"): refused when read, naming the file and key. It was accepted; ortho and uncertainty
    then blamed the DEM ("no valid height under the image footprint lon nan..nan") and adjust
    wrote an "adjusted" model of it."""
    d = pleiades1.to_dict()
    d[key] = " ".join(str(c) for c in coeffs)
    with pytest.raises(RPCError, match=f"blank.tif: RPC {key}: .*{match}"):
        RPCModel.from_dict(d, path=tmp_path / "blank.tif")
    tif = _bare_tiff(tmp_path / "blank.tif", rpc_tags=d)
    with pytest.raises(RPCError, match=f"blank.tif: RPC {key}: .*{match}"):
        RPCModel.from_file(tif)


def test_files_without_rpc(tmp_path):
    txt = tmp_path / "notes.txt"
    txt.write_text("hello\n")
    with pytest.raises(RPCError, match="notes.txt"):
        RPCModel.from_file(txt)
    xml = tmp_path / "other.XML"
    xml.write_text("<Dimap_Document><Other/></Dimap_Document>")
    with pytest.raises(RPCError, match="other.XML.*no RPC"):
        RPCModel.from_file(xml)
    with pytest.raises(RPCError, match="absent.tif"):
        RPCModel.from_file(tmp_path / "absent.tif")


# ---------------------------------------------------------------------- (e) fitting
@pytest.mark.slow
def test_fit_rpc_reproduces_an_rpc(pleiades):
    rpc, rep = fit_rpc(pleiades, height_range=(0.0, 2600.0))
    assert rep.check_rms < 1e-5 and rep.check_max < 1e-4  # << 0.01 px
    assert rep.n_check > 1000 and rep.n_train > 1000
    # independent random points over the image agree as well
    col, row, h = _image_points(pleiades, 5000, 0.0, 2600.0, seed=4)
    lon, lat = pleiades.localize(col, row, h)
    c, r = rpc.project(lon, lat, h)
    assert np.max(np.hypot(c - col, r - row)) < 1e-4
    d = rep.to_dict()
    assert d["check_max"] == rep.check_max and d["grid"] == [15, 15, 7]


class _Pushbroom(SensorModel):
    """A smooth analytic pushbroom: circular 705 km orbit through (lon0, lat0), one scan line
    per time step, 27.6 deg backward look (like ASTER 3B), 15 m pixels, with a slow roll
    oscillation of the attitude. Only ``localize`` is needed by ``fit_rpc``."""

    def __init__(self, lon0=7.0, lat0=46.0, width=1000, height=1000):
        self.width, self.height = width, height
        gm = 3.986004418e14
        self.radius = 6378137.0 + 705e3
        self.omega = np.sqrt(gm / self.radius**3)
        x, y, z = geodesy.geodetic_to_ecef(lon0, lat0 + 1.9, 0.0)  # back-looking: satellite north
        u = np.array([x, y, z], float)
        self.u = u / np.linalg.norm(u)
        north = np.array(
            [
                -np.sin(np.radians(lat0)) * np.cos(np.radians(lon0)),
                -np.sin(np.radians(lat0)) * np.sin(np.radians(lon0)),
                np.cos(np.radians(lat0)),
            ]
        )
        v = -north - (-north @ self.u) * self.u  # descending, southward track
        self.v = v / np.linalg.norm(v)
        self.dt = 15.0 / (self.omega * 6371e3)  # one line per 15 m of ground track
        self.ifov = 15.0 / 705e3 * 0.95
        self.tilt = np.radians(27.6)

    def localize(self, col, row, h):
        col, row, h = np.broadcast_arrays(
            np.asarray(col, float), np.asarray(row, float), np.asarray(h, float)
        )
        t = (row - self.height / 2) * self.dt
        wt = self.omega * t
        pos = self.radius * (np.cos(wt)[..., None] * self.u + np.sin(wt)[..., None] * self.v)
        vel = -np.sin(wt)[..., None] * self.u + np.cos(wt)[..., None] * self.v
        nadir = -pos / np.linalg.norm(pos, axis=-1, keepdims=True)
        cross = np.cross(vel, nadir)
        psi = (col - self.width / 2) * self.ifov + 2e-5 * np.sin(t / 3.0)
        d0 = np.cos(psi)[..., None] * nadir + np.sin(psi)[..., None] * cross
        d = np.cos(self.tilt) * d0 - np.sin(self.tilt) * vel  # looking backwards
        p = geodesy.intersect_height(pos, d, h)
        lon, lat, _ = geodesy.ecef_to_geodetic(p[..., 0], p[..., 1], p[..., 2])
        return np.asarray(lon), np.asarray(lat)


@pytest.mark.slow
def test_fit_rpc_to_a_pushbroom_model():
    model = _Pushbroom()
    rpc, rep = fit_rpc(model, height_range=(0.0, 4000.0), grid=(12, 12, 6))
    assert (rpc.width, rpc.height) == (model.width, model.height)
    # measured: check RMS 2.5e-6 px, max 4.0e-6 px (15 m pixels, 0-4000 m)
    assert rep.check_rms < 1e-5 and rep.check_max < 2e-5
    assert rep.train_rms < 1e-5
    col, row, h = _image_points(model, 2000, 0.0, 4000.0, seed=5)
    lon, lat = model.localize(col, row, h)
    c, r = rpc.project(lon, lat, h)
    assert np.max(np.hypot(c - col, r - row)) < 2e-5  # measured 5.0e-6 px
    # and the fitted RPC's own localisation inverts it (measured 7e-5 m)
    lon2, lat2 = rpc.localize(col, row, h)
    assert np.max(_ground_m(lon, lat, lon2, lat2)) < 1e-3
