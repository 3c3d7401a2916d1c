"""Co-registration chains (issue 25): each step recovers what was injected into a real DEM
crop, chains compose, altimetry points work as reference, and bad inputs get one line."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import shapely
from affine import Affine
from pyproj import CRS
from rasterio.transform import from_origin

from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.core.errors import DEMError, InputError, NoOverlapError, VerticalReferenceError
from stereodem.core.stats import nmad
from stereodem.post import biascorr, terrain
from stereodem.post.altimetry import AltimetryPoints, read_points
from stereodem.post.biascorr import maximum_curvature
from stereodem.post.coreg import (
    ICP,
    AlongTrack,
    CoregChain,
    CrossTrack,
    Curvature,
    Deramp,
    NuthKaab,
    StableMask,
    VerticalShift,
    bilinear,
    local_metric_coords,
    parse_chain,
    shift_text,
    step_line,
    track_coords,
)
from stereodem.post.spatialstats import VariogramModel
from stereodem.post.synthetic import InjectedErrors, inject_errors

N = 200  # crop of the bundled SRTM tile (~14 x 18 km)


@pytest.fixture(scope="module")
def truth():
    full = DEM.bundled()
    return DEM(
        full.heights[100 : 100 + N, 300 : 300 + N].copy(),
        full.transform @ Affine.translation(300, 100),
        full.crs,
        "geoid",
    )


def _noise(s=0.5):
    return VariogramModel(np.array([150.0]), np.array([s * s]))


def test_nuth_kaab_recovers_an_integer_pixel_shift_and_offset(truth):
    px = abs(truth.transform.a) * 111320 * math.cos(math.radians(truth.transform.f))
    dem, _ = inject_errors(truth, InjectedErrors(dx=px, dz=4.0, seed=1))
    nk = NuthKaab().fit(truth, dem)
    assert nk.dx == pytest.approx(px, abs=0.5)
    assert nk.dy == pytest.approx(0.0, abs=0.5)
    assert nk.dz == pytest.approx(4.0, abs=0.05)
    assert nk.params["dx"]["sigma"] > 0


def _hills_on(epsg, shift=(0.0, 0.0)):
    """Smooth hills (wavelengths 4-7 km) evaluated exactly at the cell centres of a 40 km grid
    of 100 m cells in ``epsg`` around 15 E, 78 N, the DEM displaced by ``shift`` (metres along
    the grid's x, y)."""
    from pyproj import Transformer

    cx, cy = Transformer.from_crs(4326, epsg, always_xy=True).transform(15.0, 78.0)
    t = Affine(100.0, 0, cx - 20000, 0, -100.0, cy + 20000)
    r, c = np.mgrid[0:400, 0:400]
    x, y = t @ (c + 0.5, r + 0.5)
    lon, lat = Transformer.from_crs(epsg, 4326, always_xy=True).transform(
        x - shift[0], y - shift[1]
    )
    e, n = (lon - 15.0) * 111700.0 * np.cos(np.radians(lat)), (lat - 78.0) * 111600.0
    h = 300 + 100 * np.sin(e / 700 + 0.3) * np.cos(n / 900) + 60 * np.sin((e + 2 * n) / 1100)
    return DEM(h.astype(np.float32), t, f"EPSG:{epsg}", "ellipsoid", f"hills_{epsg}.tif")


@pytest.mark.parametrize("shift", [(0.0, 0.0), (30.0, -20.0)])
def test_nuth_kaab_against_a_reference_on_a_turned_grid_finds_the_true_shift(shift):
    """The same surface on UTM 33N and on EPSG:3413 (grids turned by 60 degrees at 78 N): the
    reference's warp onto the DEM grid interpolated the transformation between the CRSs along
    rows (rasterio's 0.125 px), a displacement of one sign fitted as a 2.4 m shift (xdem, which
    warps with the same call, finds as much); now within 5 cm with GDAL 3.10 (0.053 m left
    with the GDAL 3.6 of the lowest rasterio this package supports: within 0.1 m)."""
    nk = NuthKaab().fit(_hills_on(3413), _hills_on(32633, shift))
    assert nk.dx == pytest.approx(shift[0], abs=0.1)  # was +0.0 / +30.0
    assert nk.dy == pytest.approx(shift[1], abs=0.1)  # was +2.4 / -17.7


def test_vshift_and_deramp_recover_offset_and_ramp(truth):
    dem, _ = inject_errors(
        truth, InjectedErrors(dz=-2.5, ramp_e=1.5, ramp_n=-0.8, noise=_noise(), seed=2)
    )
    v = VerticalShift().fit(truth, dem)
    assert v.dz == pytest.approx(-2.5, abs=0.3)
    d = Deramp(1).fit(truth, dem)
    assert d.coef[1] == pytest.approx(1.5, abs=0.1)  # m per 10 km east
    assert d.coef[2] == pytest.approx(-0.8, abs=0.1)
    assert d.coef[0] == pytest.approx(-2.5, abs=0.15)
    out = d.apply(dem)
    assert nmad(out.heights - truth.heights) < 0.6


def test_deramp_reports_its_slopes_in_metres_per_metre(truth):
    """A plane's coefficients are m per m, not "m" (its slopes were labelled "m" while
    their values were metres per 10 km): values per metre of east/north with the unit
    m/m (m/m^2 for the second order), the constant in m, and which metres the coordinates
    are; the same in a chain's report (coregistration.json)."""
    dem, _ = inject_errors(truth, InjectedErrors(dz=-2.5, ramp_e=1.5, ramp_n=-0.8, seed=2))
    p = Deramp(1).fit(truth, dem).parameters()
    assert {k: v["unit"] for k, v in p.items() if isinstance(v, dict)} == {
        "c_e0n0": "m",
        "c_e1n0": "m/m",
        "c_e0n1": "m/m",
    }
    assert p["c_e1n0"]["value"] == pytest.approx(1.5e-4, abs=1e-5)  # 1.5 m per 10 km
    assert p["c_e0n1"]["value"] == pytest.approx(-0.8e-4, abs=1e-5)
    assert p["c_e0n0"]["value"] == pytest.approx(-2.5, abs=0.15)
    assert 0 < p["c_e1n0"]["sigma"] < 1e-5
    assert p["coordinates"].startswith("east/north: ground metres")  # a lon/lat grid
    assert "coordinate_unit_m" not in p
    chain = parse_chain("deramp:2").fit(truth, dem)
    units = {k: v["unit"] for k, v in chain.report()[0]["parameters"].items() if "unit" in v}
    assert units["c_e2n0"] == units["c_e1n1"] == units["c_e0n2"] == "m/m^2"
    assert units["c_e1n0"] == "m/m" and units["c_e0n0"] == "m"
    utm = DEM(dem.heights, Affine(30, 0, 5e5, 0, -30, 4.4e6), "EPSG:32637", "geoid")
    ref = DEM(truth.heights, utm.transform, utm.crs, "geoid")
    assert Deramp(1).fit(ref, utm).parameters()["coordinates"].startswith("east/north: grid")


def test_cross_track_and_curvature_coefficients_carry_their_units(truth):
    """The same for the other polynomials: cross-track ``c1`` in m per m of cross-track
    distance (its value was per 10 km, labelled "m"), curvature ``c1`` per unit of
    curvature (1/100 m)."""
    e, n = local_metric_coords(truth.transform, truth.crs, truth.shape)
    _, c = track_coords(e, n, 10.0)
    dem = DEM(truth.heights + (0.5 + 1.0 * c / 1e4).astype(np.float32), truth.transform, truth.crs)
    p = CrossTrack(1).fit(DEM(truth.heights, truth.transform, truth.crs), dem, track_angle_deg=10.0)
    p = p.parameters()
    assert (p["c0"]["unit"], p["c1"]["unit"]) == ("m", "m/m")
    assert p["c1"]["value"] == pytest.approx(1e-4, abs=2e-6)
    assert Curvature(2).fit(truth, truth).parameters()["c2"]["unit"] == "m/(1/100 m)^2"


def test_along_track_recovers_a_sine(truth):
    dem, _ = inject_errors(
        truth,
        InjectedErrors(heading_deg=200.0, along_sines=[(2.0, 4000.0, 0.7)], noise=_noise(), seed=3),
    )
    at = AlongTrack(2).fit(truth, dem, track_angle_deg=200.0)
    assert at.params["sine1_wavelength"]["value"] == pytest.approx(4000.0, rel=0.02)
    assert at.params["sine1_amplitude"]["value"] == pytest.approx(2.0, abs=0.15)
    assert nmad(at.apply(dem).heights - truth.heights) < 1.15 * 0.5 * 1.0 + 0.1


def test_along_track_needs_a_heading(truth):
    with pytest.raises(InputError, match="heading"):
        AlongTrack().fit(truth, truth)


def test_cross_track_recovers_a_quadratic(truth):
    e, n = local_metric_coords(truth.transform, truth.crs, truth.shape)
    _, c = track_coords(e, n, 10.0)
    bias = 0.5 + 1.0 * (c / 1e4) - 2.0 * (c / 1e4) ** 2
    dem = DEM(truth.heights + bias.astype(np.float32), truth.transform, truth.crs, "geoid")
    ct = CrossTrack(2).fit(truth, dem, track_angle_deg=10.0)
    np.testing.assert_allclose(ct.coef, [0.5, 1.0, -2.0], atol=0.02)


def test_curvature_bias_is_recovered(truth):
    curv = maximum_curvature(truth.heights, truth.transform, truth.crs)
    dem = DEM(
        truth.heights - np.nan_to_num(0.8 * curv).astype(np.float32),
        truth.transform,
        truth.crs,
        "geoid",
    )
    cv = Curvature(1).fit(truth, dem)
    # the DEM's own curvature differs slightly from the truth's: slope within 10 %
    assert cv.coef[1] == pytest.approx(-0.8, rel=0.1)


def test_icp_recovers_a_translation(truth):
    px = abs(truth.transform.a) * 111320 * math.cos(math.radians(truth.transform.f))
    dem, _ = inject_errors(truth, InjectedErrors(dx=px, dz=2.0, seed=4))
    icp = ICP().fit(truth, dem)
    assert icp.t[0] == pytest.approx(-px, abs=1.0)  # ICP moves the DEM onto the reference
    assert icp.t[2] == pytest.approx(-2.0, abs=0.3)
    assert nmad(icp.apply(dem).heights - truth.heights) < 1.0


def test_chain_composition_text_and_plus_agree(truth):
    dem, _ = inject_errors(truth, InjectedErrors(dz=2.0, ramp_e=1.0, noise=_noise(), seed=5))
    a = parse_chain("vshift,deramp:1")
    b = VerticalShift() + Deramp(1)
    assert isinstance(b, CoregChain) and len(b.steps) == 2
    a.fit(truth, dem)
    b.fit(truth, dem)
    np.testing.assert_allclose(a.apply(dem).heights, b.apply(dem).heights, atol=1e-5)
    rep = a.report()
    assert [r["step"] for r in rep] == ["vshift", "deramp:1"]
    assert rep[0]["before"]["nmad"] > rep[1]["after"]["nmad"]
    assert rep[1]["parameters"]["c_e1n0"]["sigma"] > 0
    # applying the chain equals applying its steps in turn
    one = a.steps[1].apply(a.steps[0].apply(dem))
    np.testing.assert_allclose(a.apply(dem).heights, one.heights)


def test_chain_fits_on_altimetry_points(truth):
    px = abs(truth.transform.a) * 111320 * math.cos(math.radians(truth.transform.f))
    dem, _ = inject_errors(truth, InjectedErrors(dx=px, dz=3.0, seed=6))
    rng = np.random.default_rng(0)
    r, c = rng.uniform(2, N - 3, 1500), rng.uniform(2, N - 3, 1500)
    x, y = truth.transform @ (c + 0.5, r + 0.5)
    pts = AltimetryPoints(x, y, bilinear(truth.heights, r, c), vertical="geoid")
    ch = (NuthKaab() + VerticalShift()).fit(pts, dem)
    assert ch.steps[0].dx == pytest.approx(px, abs=1.5)
    assert ch.report()[-1]["after"]["median"] == pytest.approx(0.0, abs=0.1)


def test_parse_chain_rejects_unknown_steps_and_orders():
    with pytest.raises(InputError, match="unknown co-registration step 'warp'"):
        parse_chain("nuth_kaab,warp")
    with pytest.raises(InputError, match="order"):
        parse_chain("deramp:5")
    with pytest.raises(InputError, match="integer"):
        parse_chain("deramp:x")


# ----------------------------------------------------------------------------- bad input


def _geojson(path, ring, crs=None):
    d = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {},
                "geometry": {"type": "Polygon", "coordinates": [ring]},
            }
        ],
    }
    if crs:
        d["crs"] = {"type": "name", "properties": {"name": crs}}
    path.write_text(json.dumps(d))


def test_outline_outside_the_dem_is_one_line(truth, tmp_path):
    p = tmp_path / "far.geojson"
    _geojson(p, [[10, 10], [10.1, 10], [10.1, 10.1], [10, 10]])
    with pytest.raises(NoOverlapError, match="far.geojson: no outline overlaps the DEM"):
        StableMask(exclude=[str(p)]).array(truth)


def test_outline_in_another_crs_is_reprojected(truth, tmp_path):
    w, s, e, n = truth.bounds_lonlat()
    x, y = geodesy.lonlat_to_crs(np.array([w, e]), np.array([s, n]), "EPSG:32637")
    xm, ym = (x[0] + x[1]) / 2, (y[0] + y[1]) / 2
    ring = [
        [xm - 2000, ym - 2000],
        [xm + 2000, ym - 2000],
        [xm + 2000, ym + 2000],
        [xm - 2000, ym + 2000],
        [xm - 2000, ym - 2000],
    ]
    p = tmp_path / "utm.geojson"
    _geojson(p, ring, "urn:ogc:def:crs:EPSG::32637")
    m = StableMask(exclude=[str(p)]).array(truth)
    assert not m[N // 2, N // 2] and m[0, 0]
    cells = (
        (~m).sum()
        * (truth.transform.a * 111320 * math.cos(math.radians(truth.transform.f)))
        * (abs(truth.transform.e) * 110950)
    )
    assert cells == pytest.approx(16e6, rel=0.1)  # 4 km x 4 km


def test_mask_leaving_under_5_percent_says_how_much(truth):
    mask = np.zeros(truth.shape, bool)
    mask[:5, :] = True
    with pytest.raises(InputError, match=r"only 2\.5 % of the overlapping cells"):
        VerticalShift().fit(truth, truth, stable=mask)


def test_points_with_nan_or_unsaid_datum(tmp_path):
    p = tmp_path / "pts.csv"
    p.write_text("lon,lat,h\n40.1,39.9,1000\n40.2,39.8,nan\n")
    with pytest.raises(InputError, match="pts.csv: 1 of 2 points have NaN"):
        read_points(p, vertical="ellipsoid")
    p.write_text("lon,lat,h\n40.1,39.9,1000\n40.2,39.8,1001\n")
    with pytest.raises(
        VerticalReferenceError, match="pts.csv: vertical reference of the point heights not said"
    ):
        read_points(p)
    assert read_points(p, vertical="ellipsoid").vertical == "ellipsoid"


def test_a_points_file_that_says_its_datum_wins_over_the_option(tmp_path, caplog):
    """A height column that says its reference (``h_ellipsoid``) contradicted by the option
    given (``--ref-vertical geoid``): the file wins, with a warning naming the file, as a DEM
    file's CRS wins (``core.dem.said_vertical``, one rule). It was an error for points
    ("column 'h_ellipsoid' says ellipsoid but geoid was given") and a warning for DEMs."""
    p = tmp_path / "pts.csv"
    p.write_text("lon,lat,h_ellipsoid\n40.1,39.9,1000\n40.2,39.8,1001\n")
    with caplog.at_level("WARNING", logger="stereodem.core.dem"):
        pts = read_points(p, vertical="geoid")
    assert pts.vertical == "ellipsoid" and pts.h.tolist() == [1000.0, 1001.0]
    assert (
        "pts.csv: the file says ellipsoid heights (column 'h_ellipsoid'): read as ellipsoid"
        in caplog.text
    )
    assert "renaming its height column" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="stereodem.core.dem"):
        assert read_points(p, vertical="ellipsoid").vertical == "ellipsoid"  # agrees: quiet
        assert read_points(p).vertical == "ellipsoid"
    assert not caplog.text


def test_the_option_gives_the_datum_of_a_points_file_that_does_not_say(tmp_path, caplog):
    """The other side of the rule: a column that says nothing (``h``) takes the option given,
    without a warning; a value that is no vertical reference is refused naming the file,
    whatever the file says (as ``DEM.from_file``)."""
    p = tmp_path / "pts.csv"
    p.write_text("lon,lat,h\n40.1,39.9,1000\n40.2,39.8,1001\n")
    with caplog.at_level("WARNING", logger="stereodem.core.dem"):
        assert read_points(p, vertical="geoid").vertical == "geoid"
        assert read_points(p, vertical="ellipsoid").vertical == "ellipsoid"
    assert not caplog.text
    q = tmp_path / "said.csv"
    q.write_text("lon,lat,h_geoid\n40.1,39.9,1000\n")
    for path in (p, q):
        with pytest.raises(DEMError, match=rf"{path.name}: vertical reference must be 'geoid'"):
            read_points(path, vertical="EGM96")


def test_reference_that_does_not_overlap(truth):
    far = DEM(
        truth.heights, truth.transform @ Affine.translation(5000, 0), truth.crs, "geoid", "far.tif"
    )
    with pytest.raises(NoOverlapError, match="does not overlap"):
        VerticalShift().fit(far, truth)
    pts = AltimetryPoints([10.0, 10.1], [10.0, 10.1], [1.0, 2.0], vertical="geoid", path="far.csv")
    with pytest.raises(NoOverlapError, match="far.csv: no point falls on the DEM"):
        VerticalShift().fit(pts, truth)


def test_points_from_csv_and_geoparquet_agree(tmp_path):
    p = tmp_path / "pts.csv"
    p.write_text(
        "# ATL06-like\nlongitude,latitude,h_ellipsoid,time\n40.1,39.9,1000.5,2020-01-01\n"
        "40.2,39.8,1001.25,2020-01-02\n"
    )
    a = read_points(p)
    assert a.vertical == "ellipsoid" and a.h.tolist() == [1000.5, 1001.25] and len(a.time) == 2
    pq = pytest.importorskip("pyarrow.parquet")
    import pyarrow as pa  # optional (the altimetry extra): there past the importorskip

    geom = shapely.to_wkb(shapely.points([40.1, 40.2], [39.9, 39.8]))
    pq.write_table(pa.table({"geometry": geom, "h": [1000.5, 1001.25]}), tmp_path / "pts.parquet")
    b = read_points(tmp_path / "pts.parquet", vertical="ellipsoid")
    np.testing.assert_allclose(b.lon, a.lon)
    np.testing.assert_allclose(b.lat, a.lat)
    np.testing.assert_allclose(b.h, a.h)


def test_points_file_with_a_bad_value_names_the_row(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("# a comment\nlon,lat,h\n40.1,39.9,1000\n\n40.2,39.8,abc\n")
    with pytest.raises(InputError, match=r"bad.csv: column 'h', line 5: 'abc' is not a number"):
        read_points(p, vertical="geoid")
    p.write_text("# a comment\nlon,lat,h\n40.1,39.9,1000\n40.2,39.8,nan\n")
    with pytest.raises(InputError, match=r"bad.csv: 1 of 2 points .*NaN.* \(first at line 4\)"):
        read_points(p, vertical="geoid")


@pytest.mark.parametrize("crs", ["EPSG:32637", "EPSG:4326"])
def test_gradient_at_cells_equals_the_whole_grids_gradient(crs):
    """Nuth & Kääb differences only its stable samples: terrain.gradient_at must give the
    whole grid's gradient there to the bit (edges, voids and geographic rows included)."""
    rng = np.random.default_rng(3)
    z = rng.normal(1000.0, 50.0, (40, 57))
    z[10:13, 20:22] = np.nan
    t = (
        from_origin(500000, 4400000, 30, 30)
        if crs != "EPSG:4326"
        else from_origin(40, 39, 1e-3, 1e-3)
    )
    ge, gn = terrain.gradient(z, t, crs)
    rows, cols = np.meshgrid(np.arange(40), np.arange(57), indexing="ij")
    se, sn = terrain.gradient_at(z, t, crs, rows.ravel(), cols.ravel())
    np.testing.assert_array_equal(se, ge.ravel())
    np.testing.assert_array_equal(sn, gn.ravel())


@pytest.mark.parametrize("crs", ["EPSG:32637", "EPSG:4326"])
def test_maximum_curvature_in_bands_is_the_whole_grids_on_any_number_of_threads(monkeypatch, crs):
    """The curvature in row bands on threads: the numbers of the whole grid's gradients taken
    twice, to the bit, on a projected and a geographic grid (row-dependent cell size), voids
    and the grid's edges included (issue 28)."""
    rng = np.random.default_rng(3)
    rows, cols = np.mgrid[0:61, 0:47]
    z = 1500 + 40 * np.sin(rows / 9.0) * np.cos(cols / 7.0) + rng.normal(0, 0.5, rows.shape)
    z = z.astype(np.float32)
    z[20:24, 10:13] = np.nan
    if crs == "EPSG:4326":
        t = Affine(0.0008, 0, 40.0, 0, -0.0008, 39.5)
    else:
        t = Affine(30.0, 0, 500000, 0, -30.0, 4400000)

    def whole(z):
        ge, gn = terrain.gradient(np.asarray(z, np.float64), t, crs)
        gee, gen = terrain.gradient(ge, t, crs)
        gne, gnn = terrain.gradient(gn, t, crs)
        gx = 0.5 * (gen + gne)
        m = 0.5 * (gee + gnn)
        r = np.sqrt(0.25 * (gee - gnn) ** 2 + gx**2)
        l1, l2 = m + r, m - r
        return 100.0 * np.where(np.abs(l1) >= np.abs(l2), l1, l2)

    monkeypatch.setattr(biascorr, "CURVATURE_BAND_ROWS", 7)  # 9 bands, the last one of 5 rows
    for part in (z, z[:2], z[:8], z[:1]):
        ref = whole(part)
        for threads in (1, 2, 3):
            got = maximum_curvature(part, t, crs, threads=threads)
            assert got.dtype == ref.dtype and got.tobytes() == ref.tobytes()


def test_the_reports_and_result_lines_give_each_shifts_sign(truth):
    """``nuth_kaab`` gives the DEM's displacement from the reference, ``icp`` the motion that
    brings the DEM onto it: for one offset their signs are opposite (Pleiades DSM shifted by
    +1.3 m E, -0.7 m N, +2 m up: nuth_kaab dx +1.30 dy -0.70 dz +2.00, icp tx -1.30 ty +0.70
    tz -2.00), and ``coregister`` said neither in its report nor on its result lines (which
    gave no shift at all). Each shift step's parameters now carry ``sign``, and the result
    line (``shift_text``, in every command's ``step_line``) states the shift with its
    meaning."""
    px = abs(truth.transform.a) * 111320 * math.cos(math.radians(truth.transform.f))
    dem, _ = inject_errors(truth, InjectedErrors(dx=px, dz=2.0, seed=4))
    nk, icp, vs = NuthKaab().fit(truth, dem), ICP().fit(truth, dem), VerticalShift().fit(truth, dem)
    assert nk.params["dx"]["value"] == pytest.approx(px, abs=1.0)
    assert icp.params["tx"]["value"] == pytest.approx(-px, abs=1.0)
    assert nk.params["sign"] == vs.params["sign"] == biascorr.DISPLACEMENT
    assert icp.params["sign"] == biascorr.MOTION
    line, said = shift_text(nk.params)
    assert line.startswith("DEM displaced from the reference by dx = +")
    assert "m along x (grid east)" in line and "dz = +2.0" in line
    assert said == ("dx", "dy", "dz")
    line, said = shift_text(icp.params)
    assert line.startswith("DEM moved onto the reference by tx = -") and said[0] == "tx"
    assert shift_text(vs.params) == (
        f"DEM displaced from the reference by dz = {vs.params['dz']['value']:+.3f} ± "
        f"{vs.params['dz']['sigma']:.3f} m (up)",
        ("dz",),
    )
    assert shift_text(Deramp(1).fit(truth, dem).params) is None


def test_the_chains_log_line_of_a_step_is_its_result_line(truth, caplog):
    """A fitted step is logged (``-vv``: ``coregister`` and ``assess`` print it at any
    verbosity, and ``-v`` showed it twice) in the one format of its result line,
    :func:`~stereodem.post.coreg.step_line`, as ``coregister`` and ``assess`` print it; the
    chain logged a third format, "nuth_kaab: NMAD a -> b m (n=N)" (no median, no shift)."""
    px = abs(truth.transform.a) * 111320 * math.cos(math.radians(truth.transform.f))
    dem, _ = inject_errors(truth, InjectedErrors(dx=px, dz=2.0, ramp_e=1.0, seed=5))
    with caplog.at_level("DEBUG", logger="stereodem.post.coreg"):
        chain = parse_chain("nuth_kaab,deramp").fit(truth, dem)
    logged = [r.getMessage() for r in caplog.records if r.name == "stereodem.post.coreg"]
    lines = [step_line(r) for r in chain.report()]
    assert len(lines) == 2 and lines[0].startswith("nuth_kaab: stable NMAD ")
    assert logged == lines


def test_apply_keeps_the_dems_geoid_and_takes_a_path(truth, tmp_path):
    """A DEM above EGM2008 corrected by a step kept its vertical reference ``"geoid"`` but
    lost ``geoid_crs``: written back, its heights were labelled EGM96 (the separation of the
    two geoids, metres, unsaid); and ``fit``/``apply`` given a file path raised an
    AttributeError from inside."""
    egm08 = CRS("EPSG:3855")
    dem = DEM(truth.heights + 3.0, truth.transform, truth.crs, "geoid", geoid_crs=egm08)
    step = VerticalShift().fit(truth, dem)
    out = step.apply(dem)
    assert out.geoid_crs == egm08
    chained = (VerticalShift() + Deramp(1)).fit(truth, dem).apply(dem)
    assert chained.geoid_crs == egm08
    path = truth.write(tmp_path / "ref.tif")
    by_path = VerticalShift().fit(path, dem).apply(path)
    assert by_path.path == str(path)
    assert step.parameters()["dz"]["value"] == pytest.approx(3.0, abs=0.01)
    with pytest.raises(DEMError, match="expected a DEM or a path, got ndarray"):
        step.apply(dem.heights)


def test_fit_brings_the_reference_to_the_dems_vertical_reference(truth):
    """``NuthKaab().fit(geoid_ref, ellipsoidal_dem)`` compared the two as they were: the
    geoid undulation (~30 m here) came out as ``dz`` and ``apply`` moved the ellipsoidal
    heights onto the geoid's, still labelled ellipsoidal. ``coregister`` converted the
    reference first; ``fit`` now does. One side unknown is refused."""
    dem = truth.to_reference("ellipsoid")
    dem = DEM(dem.heights + 2.0, dem.transform, dem.crs, "ellipsoid")
    step = VerticalShift().fit(truth, dem)
    assert step.parameters()["dz"]["value"] == pytest.approx(2.0, abs=0.01)
    out = step.apply(dem)
    assert out.vertical == "ellipsoid"
    assert np.nanmedian(out.heights - truth.to_reference("ellipsoid").heights) == pytest.approx(
        0.0, abs=0.01
    )
    unknown = DEM(truth.heights, truth.transform, truth.crs, None)
    with pytest.raises(VerticalReferenceError, match="vertical reference unknown"):
        VerticalShift().fit(truth, unknown)
