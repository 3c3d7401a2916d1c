"""``stereodem coregister`` end to end on a small real-DEM crop; bad inputs: one line, exit 1,
nothing written."""

from __future__ import annotations

import base64
import json
import json as _json
import re
from html import escape as html_escape
from pathlib import Path

import numpy as np
import pytest
import rasterio
import shapely
from affine import Affine
from affine import Affine as A
from helpers.cli_scene import assert_clear_error, run_cli

from stereodem.cli import main
from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.core.raster import write_geotiff
from stereodem.post import terrain, warp
from stereodem.post.altimetry import read_points
from stereodem.post.coreg import StableMask, bilinear
from stereodem.post.coreg_run import TRACK_HEADING_TAG, track_heading, track_heading_of
from stereodem.post.report import FIGURE_CAPTIONS, figure_caption
from stereodem.post.spatialstats import VariogramModel, area_mean_sigma
from stereodem.post.synthetic import InjectedErrors, inject_errors
from stereodem.sensor.models.pushbroom import PushbroomModel


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("coreg")
    full = DEM.bundled()
    ref = DEM(full.heights[:150, :150].copy(), full.transform, full.crs, "geoid")
    dem, _ = inject_errors(
        ref,
        InjectedErrors(
            dz=2.0,
            heading_deg=190.0,
            along_sines=[(1.5, 3000.0, 0.0)],
            noise=VariogramModel(np.array([150.0]), np.array([0.25])),
            seed=1,
        ),
    )
    ref.write(d / "ref.tif")
    dem.write(d / "dem.tif")
    far = DEM(ref.heights, ref.transform @ Affine.translation(3000, 0), ref.crs, "geoid")
    far.write(d / "far.tif")
    DEM(ref.heights, ref.transform, ref.crs, None).write(d / "unknown.tif")
    return d


@pytest.mark.slow
def test_coregister_writes_dem_json_and_figures(files, capsys, caplog):
    out = files / "out"
    caplog.set_level("INFO")  # what -v shows (under pytest the CLI adds no handler of its own)
    rc = main(
        [
            "-v",
            "coregister",
            str(files / "dem.tif"),
            "--ref",
            str(files / "ref.tif"),
            "--chain",
            "vshift,along_track",
            "--track-angle",
            "190",
            "-o",
            str(out),
        ]
    )
    assert rc == 0
    # each step's result line once, also with -v (the chain's log said it a second time)
    said = capsys.readouterr()
    for step in ("vshift", "along_track"):
        shown = said.out + said.err + caplog.text
        assert shown.count(f"{step}: stable NMAD ") == 1, shown
    rep = json.loads((out / "coregistration.json").read_text())
    assert [s["step"] for s in rep["steps"]] == ["vshift", "along_track"]
    assert rep["steps"][0]["parameters"]["dz"]["value"] == pytest.approx(2.0, abs=0.2)
    assert rep["steps"][1]["after"]["nmad"] < 0.7 * rep["steps"][0]["after"]["nmad"]
    assert (out / "coreg_dh.png").is_file() and (out / "coreg_1_along_track.png").is_file()
    d = DEM.from_file(out / "dem_coregistered.tif")
    assert d.vertical == "geoid" and d.shape == (150, 150)
    # a second run into the same folder is refused without --overwrite
    rc = main(
        ["coregister", str(files / "dem.tif"), "--ref", str(files / "ref.tif"), "-o", str(out)]
    )
    assert rc == 1


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--ref", "far.tif"], "does not overlap"),
        (["--ref", "unknown.tif"], "vertical reference unknown"),
        (["--ref", "ref.tif", "--chain", "along_track"], "heading"),
        (["--ref", "ref.tif", "--chain", "nuth_kaab,bogus"], "unknown co-registration step"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(files, capsys, extra, message):
    out = files / f"bad_{abs(hash(tuple(extra)))}"
    args = (
        ["coregister", str(files / "dem.tif")]
        + [str(files / a) if a.endswith(".tif") else a for a in extra]
        + ["-o", str(out)]
    )
    rc = main(args)
    err = capsys.readouterr().err.strip()
    assert rc == 1
    assert message in err and "Traceback" not in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_tiny_overlap_says_how_many_cells_not_a_share(files, tmp_path, capsys):
    """A 3 x 3 DEM on the reference: all 9 overlapping cells are stable (100 %), too few to fit;
    the error said "only 100.0 % ... stable terrain; at least 5 % needed"."""
    ref = DEM.from_file(files / "ref.tif")
    DEM(ref.heights[:3, :3] + 1, ref.transform, ref.crs, "geoid").write(tmp_path / "tiny.tif")
    out = tmp_path / "out"
    argv = ["coregister", tmp_path / "tiny.tif", "--ref", files / "ref.tif", "-o", out]
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(
        code, err, "coregister", r"ref\.tif: only 9 stable cells overlap .*tiny\.tif.* 20 needed"
    )
    assert not out.exists()


@pytest.mark.parametrize(
    "command, grid, words",
    [
        ("coregister", "rotated", "rotated DEM grids are not supported"),
        ("assess", "rotated", "rotated DEM grids are not supported"),
        ("change-b", "rotated", "rotated DEM grids are not supported"),
        ("change-a", "south_up", "the grid is not north-up"),
    ],
)
def test_a_grid_that_is_not_north_up_is_named(files, tmp_path, capsys, command, grid, words):
    """A rotated or south-up DEM grid was refused without naming the file ("rotated DEM grids
    are not supported", "MapGrid: the transform must be north-up"), assess after its work."""
    ref = DEM.from_file(files / "ref.tif")
    z, t = ref.heights[:40, :40], ref.transform
    if grid == "rotated":
        t, bad = t @ Affine.rotation(10), tmp_path / "rotated.tif"
    else:
        z, t = z[::-1], Affine(t.a, 0, t.c, 0, -t.e, t.f + 40 * t.e)
        bad = tmp_path / "south_up.tif"
    prof = dict(driver="GTiff", width=40, height=40, count=1, dtype="float32", crs=ref.crs)
    with rasterio.open(bad, "w", transform=t, nodata=np.nan, **prof) as ds:
        ds.write(z[None])
        ds.update_tags(STEREODEM_VERTICAL="geoid")
    good, out = files / "ref.tif", tmp_path / "out"
    argv = {
        "coregister": ["coregister", bad, "--ref", good],
        "assess": ["assess", bad, "--ref", good],
        "change-b": ["change", good, bad],
        "change-a": ["change", bad, good],
    }[command]
    code, _, err = run_cli(capsys, [*argv, "-o", out])
    assert_clear_error(code, err, argv[0], rf"{re.escape(str(bad))}: {words}")
    assert not out.exists()


def _assert_error_analysis_in_html(out):
    """report.html holds the error-analysis section (the variogram's fit and every Markdown
    item of the section) and embeds variogram.png and error_vs_terrain.png byte for byte,
    with their captions."""
    html = (out / "report.html").read_text()
    assert html.count("<h2>Error analysis (stable terrain)</h2>") == 1
    section = html.split("<h2>Error analysis (stable terrain)</h2>", 1)[1]
    md = (out / "report.md").read_text().split("## Error analysis (stable terrain)", 1)[1]
    items = [ln[2:] for ln in md.splitlines() if ln.startswith("* ")]
    assert any(i.startswith("variogram of standardised dh: range") for i in items)
    for item in items:
        assert f"<li>{html_escape(item)}</li>" in section
    for name in ("variogram", "error_vs_terrain"):
        m = re.search(rf'<img alt="{name}" src="data:image/png;base64,([^"]+)">', html)
        assert m, name
        assert base64.b64decode(m.group(1)) == (out / f"{name}.png").read_bytes()
        assert FIGURE_CAPTIONS[name] in html


@pytest.mark.slow
def test_assess_error_analysis_adds_section_and_figures(files):
    out = files / "assess"
    rc = main(
        [
            "assess",
            str(files / "dem.tif"),
            "--ref",
            str(files / "ref.tif"),
            "--error-analysis",
            "--chain",
            "vshift,along_track",
            "--track-angle",
            "190",
            "-o",
            str(out),
        ]
    )
    assert rc == 0
    rep = _json.loads((out / "report.json").read_text())
    ea = rep["error_analysis"]
    assert len(ea["variogram"]["model"]["ranges_m"]) == 2
    assert [s["step"] for s in ea["coregistration"]["steps"]] == ["vshift", "along_track"]
    assert (out / "variogram.png").is_file() and (out / "error_vs_terrain.png").is_file()
    assert "Error analysis" in (out / "report.md").read_text()
    _assert_error_analysis_in_html(out)
    # the chain's figures, as `stereodem coregister` draws them, in every form of the report
    assert rep["figures"]["coreg_dh"] == "coreg_dh.png"
    assert rep["figures"]["coreg_along_track"] == "coreg_1_along_track.png"
    html = (out / "report.html").read_text()
    for name, file in (
        ("coreg_dh", "coreg_dh.png"),
        ("coreg_along_track", "coreg_1_along_track.png"),
    ):
        m = re.search(rf'<img alt="{name}" src="data:image/png;base64,([^"]+)">', html)
        assert m, name
        assert base64.b64decode(m.group(1)) == (out / file).read_bytes()
        assert html_escape(figure_caption(name)) in html
    assert "coreg_dh.png" in (out / "report.md").read_text()


def test_assess_error_analysis_of_a_constant_difference_is_one_line(files, tmp_path, capsys):
    """A DEM that differs from its reference by a constant has no dispersion to analyse: one
    line naming both files, nothing written (it was "variogram: only 0 valid cells")."""
    ref = DEM.from_file(files / "ref.tif")
    DEM(ref.heights + 5.0, ref.transform, ref.crs, "geoid").write(tmp_path / "const.tif")
    out = tmp_path / "assess"
    rc = main(
        [
            "assess",
            str(tmp_path / "const.tif"),
            "--ref",
            str(files / "ref.tif"),
            "--error-analysis",
            "-o",
            str(out),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1
    assert len(err) == 1 and "no dispersion" in err[0] and "const.tif" in err[0], err
    assert "ref.tif" in err[0]
    assert not out.exists() or not any(out.iterdir())


def test_track_heading_of_a_pushbroom_model_and_tag_round_trip(tmp_path):
    left, _ = PushbroomModel.synthetic_pair(
        40.0,
        39.0,
        width=400,
        height=400,
        gsd=15.0,
        heading_deg=195.0,
        first_tilt_deg=0.0,
        backward_tilt_deg=-27.6,
    )
    hdg = track_heading(left, (400, 400))
    # the ground track turns from the orbit's 195° by the Earth's rotation under it:
    # ω_E·R·cos(39°)/v_ground ≈ 7.29e-5 · 6.371e6 · 0.777 / 6.8e3 rad ≈ 3.0° (descending: to the
    # west)
    assert hdg == pytest.approx(198.0, abs=1.0)
    full = DEM.bundled()
    d = DEM(full.heights[:50, :50].copy(), full.transform, full.crs, "geoid")
    d.write(tmp_path / "d.tif", tags={TRACK_HEADING_TAG: f"{hdg:.4f}"})
    assert track_heading_of(tmp_path / "d.tif") == pytest.approx(hdg, abs=1e-3)


@pytest.mark.slow
def test_assess_with_a_sensor_sigma_map_reports_the_explained_share(files):
    ref = DEM.from_file(files / "ref.tif")
    write_geotiff(
        files / "sigma.tif", np.full(ref.shape, 0.3, np.float32), ref.transform, ref.crs, np.nan
    )
    out = files / "assess_sigma"
    rc = main(
        [
            "assess",
            str(files / "dem.tif"),
            "--ref",
            str(files / "ref.tif"),
            "--chain",
            "vshift",
            "--sigma-map",
            str(files / "sigma.tif"),
            "-o",
            str(out),
        ]
    )
    assert rc == 0
    sm = _json.loads((out / "report.json").read_text())["error_analysis"]["heteroscedasticity"][
        "sensor_model"
    ]
    # injected noise σ 0.5 m plus a 1.5 m along-track sine left in: 0.3 m explains a small share
    assert 0.0 < sm["explained_variance_share"] < 0.3
    assert sm["rms_sigma"] == pytest.approx(0.3, rel=1e-3)


def test_reference_on_another_grid_crs_and_vertical_is_warped_and_converted(files, tmp_path):
    """An ellipsoidal UTM reference for a geoid lon/lat DEM: warped onto the DEM's grid and
    converted through EGM96 (the offset left is the warp's, not the ~-20 m geoid height)."""
    ref = DEM.from_file(files / "ref.tif")
    t = A(90.0, 0, 0, 0, -90.0, 0)

    w, s, e, n = ref.bounds_lonlat()
    x, y = geodesy.lonlat_to_crs(np.array([w, e]), np.array([s, n]), "EPSG:32637")
    t = A(90.0, 0, float(x.min()), 0, -90.0, float(y.max()))
    shape = (int((y.max() - y.min()) / 90), int((x.max() - x.min()) / 90))
    z = warp.to_grid(
        ref.heights, ref.transform, ref.crs, t, "EPSG:32637", shape, resampling="cubic"
    )
    utm = DEM(z, t, "EPSG:32637", "geoid").to_reference("ellipsoid")
    utm.write(tmp_path / "ref_utm_ell.tif")
    out = tmp_path / "o"
    rc = main(
        [
            "coregister",
            str(files / "ref.tif"),
            "--ref",
            str(tmp_path / "ref_utm_ell.tif"),
            "--chain",
            "vshift",
            "-o",
            str(out),
            "--no-figures",
        ]
    )
    assert rc == 0
    rep = json.loads((out / "coregistration.json").read_text())
    assert "converted from ellipsoid to geoid" in rep["vertical"]
    assert abs(rep["steps"][0]["parameters"]["dz"]["value"]) < 0.5


def test_stable_mask_raster_and_include(files, tmp_path):
    ref = DEM.from_file(files / "ref.tif")
    m = np.zeros(ref.shape, np.uint8)
    m[:, :75] = 1
    write_geotiff(tmp_path / "m.tif", m, ref.transform, ref.crs, None)
    got = StableMask(raster=str(tmp_path / "m.tif")).array(ref)
    assert got[:, :75].all() and not got[:, 76:].any()
    t = ref.transform
    ring = [
        [t.c, t.f],
        [t.c + 30 * t.a, t.f],
        [t.c + 30 * t.a, t.f + 30 * t.e],
        [t.c, t.f + 30 * t.e],
        [t.c, t.f],
    ]
    (tmp_path / "inc.geojson").write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {},
                        "geometry": {"type": "Polygon", "coordinates": [ring]},
                    }
                ],
            }
        )
    )
    inc = StableMask(include=[str(tmp_path / "inc.geojson")]).array(ref)
    assert inc.sum() == 900 and inc[:30, :30].all()


# ----------------------------------------------------------------------------- altimetry points


@pytest.fixture(scope="module")
def points_case(tmp_path_factory):
    """A DEM shifted one cell east (~71 m) and raised 3 m, with 0.5 m correlated noise, and 800
    points of the unshifted truth (geoid heights) as CSV and GeoParquet."""
    d = tmp_path_factory.mktemp("points")
    full = DEM.bundled()
    truth = DEM(full.heights[:150, :150].copy(), full.transform, full.crs, "geoid")
    px = abs(truth.transform.a) * 111320 * np.cos(np.radians(truth.transform.f))
    dem, _ = inject_errors(
        truth,
        InjectedErrors(
            dx=px, dz=3.0, noise=VariogramModel(np.array([150.0]), np.array([0.25])), seed=6
        ),
    )
    dem.write(d / "dem.tif")
    rng = np.random.default_rng(0)
    r, c = rng.uniform(2, 147, 800), rng.uniform(2, 147, 800)
    lon, lat = truth.transform @ (c + 0.5, r + 0.5)
    h = bilinear(truth.heights, r, c)
    with open(d / "pts.csv", "w") as f:
        f.write("# ATL06-like points of the truth\nlon,lat,h\n")
        f.writelines(
            f"{a!r},{b!r},{z!r}\n" for a, b, z in zip(lon.tolist(), lat.tolist(), h.tolist())
        )
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    geom = shapely.to_wkb(shapely.points(lon, lat))
    pq.write_table(pa.table({"geometry": geom, "h": h}), d / "pts.parquet")
    return dict(dir=d, px=px, n=800)


def _coregister_points(dem, ref, out, *extra):
    rc = main(
        ["coregister", str(dem), "--ref", str(ref), "--chain", "nuth_kaab,vshift"]
        + [*extra, "-o", str(out)]
    )
    assert rc == 0
    return json.loads((out / "coregistration.json").read_text())


def _residuals(rep):
    cols = rep["points"]["columns"]
    rows = np.array([[np.nan if v is None else v for v in r] for r in rep["points"]["rows"]])
    return {k: rows[:, i] for i, k in enumerate(cols)}


def test_coregister_to_altimetry_points_csv_and_geoparquet(points_case, tmp_path):
    """``--ref points.csv --ref-vertical geoid``: the shift and offset are recovered from the
    points, coregistration.json carries one residual per point (DEM - point, before and
    after), the residuals shrink to the noise; the GeoParquet file gives the same result."""
    d = points_case["dir"]
    rep = _coregister_points(
        d / "dem.tif", d / "pts.csv", tmp_path / "csv", "--ref-vertical", "geoid"
    )
    assert rep["reference_kind"] == "points"
    nk = rep["steps"][0]["parameters"]
    assert nk["dx"]["value"] == pytest.approx(points_case["px"], abs=0.5)
    assert nk["dy"]["value"] == pytest.approx(0.0, abs=0.5)
    assert nk["dz"]["value"] == pytest.approx(3.0, abs=0.1)
    pts = rep["points"]
    assert pts["n"] == pts["n_on_dem"] == points_case["n"] == len(pts["rows"])
    assert pts["columns"] == ["lon", "lat", "h", "dh_before", "dh_after", "stable"]
    r = _residuals(rep)
    rms_before = np.sqrt(np.mean(r["dh_before"] ** 2))
    rms_after = np.sqrt(np.mean(r["dh_after"] ** 2))
    # before: the 3 m offset and the shift on slopes; after: the 0.5 m noise alone
    assert rms_before > 5.0 and rms_after < 0.6
    assert abs(np.median(r["dh_after"])) < 0.05
    # no dh map for points; the Nuth & Kääb curve is drawn from them
    assert {"dem", "nuth_kaab_png"} <= set(rep["files"])
    assert all(Path(f).is_file() for f in rep["files"].values())

    rep_pq = _coregister_points(
        d / "dem.tif", d / "pts.parquet", tmp_path / "pq", "--ref-vertical", "geoid", "--no-figures"
    )
    for a, b in zip(rep["steps"], rep_pq["steps"]):
        for k, v in a["parameters"].items():
            if isinstance(v, dict):
                assert b["parameters"][k]["value"] == pytest.approx(v["value"], abs=1e-6)
    np.testing.assert_allclose(_residuals(rep_pq)["dh_after"], r["dh_after"], atol=1e-6)


def test_altimetry_points_in_another_datum_are_converted(points_case, tmp_path, caplog):
    """The same points as WGS84 ellipsoidal heights (column ``h_ellipsoid``, datum said by the
    column): converted to the DEM's geoid through EGM96, the same offset is found."""
    d = points_case["dir"]
    g = read_points(d / "pts.csv", vertical="geoid")
    p = g.to_reference("ellipsoid")
    assert abs(np.mean(p.h - g.h)) > 5.0  # the geoid height here: a wrong datum would show
    with open(tmp_path / "ell.csv", "w") as f:
        f.write("lon,lat,h_ellipsoid\n")
        f.writelines(
            f"{a!r},{b!r},{z!r}\n" for a, b, z in zip(*(v.tolist() for v in (p.lon, p.lat, p.h)))
        )
    rep = _coregister_points(d / "dem.tif", tmp_path / "ell.csv", tmp_path / "o", "--no-figures")
    assert "converted from ellipsoid to geoid" in rep["vertical"]
    assert rep["steps"][0]["parameters"]["dz"]["value"] == pytest.approx(3.0, abs=0.1)
    # --ref-vertical contradicting the column: the column wins, with a warning (the rule of
    # DEM files), where the command stopped on an error
    with caplog.at_level("WARNING", logger="stereodem.core.dem"):
        said = _coregister_points(
            d / "dem.tif",
            tmp_path / "ell.csv",
            tmp_path / "g",
            "--ref-vertical",
            "geoid",
            "--no-figures",
        )
    assert "ell.csv: the file says ellipsoid heights (column 'h_ellipsoid')" in caplog.text
    assert said["steps"][0]["parameters"]["dz"] == rep["steps"][0]["parameters"]["dz"]


def _box_geojson(path, dem: DEM, boxes):
    """A GeoJSON of rectangles ``(row0, row1, col0, col1)`` (cell edges) on ``dem``'s grid."""
    t = dem.transform

    def ring(r0, r1, c0, c1):
        xy = [(c0, r0), (c1, r0), (c1, r1), (c0, r1), (c0, r0)]
        return [list(t @ (c, r)) for c, r in xy]

    feats = [
        {
            "type": "Feature",
            "properties": {},
            "geometry": {"type": "Polygon", "coordinates": [ring(*b)]},
        }
        for b in boxes
    ]
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    return path


@pytest.mark.slow
def test_assess_outlines_give_the_area_mean_sigma_from_the_variogram(files, tmp_path):
    """``assess --outlines``: per polygon, the σ of the mean dh from the fitted variogram. With
    the offset and the along-track sine removed, what is left is the injected noise (spherical,
    150 m range, σ 0.5 m), whose σ of an area mean is known: the reported σ agrees with it
    within 15 % and is well above the naive σ/√N (correlated cells)."""
    ref = DEM.from_file(files / "ref.tif")
    boxes = [(40, 100, 40, 100), (10, 20, 120, 130)]
    outlines = _box_geojson(tmp_path / "outlines.geojson", ref, boxes)
    out = tmp_path / "assess"
    rc = main(
        ["assess", str(files / "dem.tif"), "--ref", str(files / "ref.tif")]
        + ["--chain", "vshift,along_track", "--track-angle", "190"]
        + ["--outlines", str(outlines), "-o", str(out)]
    )
    assert rc == 0
    areas = _json.loads((out / "report.json").read_text())["error_analysis"]["area_means"]
    assert [(a["file"], a["polygon"]) for a in areas] == [(str(outlines), 1), (str(outlines), 2)]
    noise = VariogramModel(np.array([150.0]), np.array([0.25]))
    for a, (r0, r1, c0, c1) in zip(areas, boxes):
        m = np.zeros(ref.shape, bool)
        m[r0:r1, c0:c1] = True
        truth = area_mean_sigma(noise, m, ref.transform, ref.crs)
        assert a["n_cells"] == m.sum()
        assert np.isfinite(a["sigma_mean"]) and a["sigma_mean"] > 1.3 * a["sigma_naive"]
        assert a["sigma_mean"] == pytest.approx(truth["sigma_mean"], rel=0.15)
        assert abs(a["mean_dh"]) < 4 * a["sigma_mean"]
    md = (out / "report.md").read_text()
    assert "outlines.geojson #1: mean dh" in md and "outlines.geojson #2: mean dh" in md
    _assert_error_analysis_in_html(out)  # the area means are items of the HTML section too
    assert "outlines.geojson #2: mean dh" in (out / "report.html").read_text()


# ------------------------------------------------------------------------ stable-terrain limits


@pytest.fixture(scope="module")
def cloudy(tmp_path_factory):
    """The reference crop and a DEM of it raised 2 m, 0.5 m noise, and a 20 x 20 cell cloud
    (+100 m) in rows/columns 20..39."""
    d = tmp_path_factory.mktemp("cloudy")
    full = DEM.bundled()
    ref = DEM(full.heights[:150, :150].copy(), full.transform, full.crs, "geoid")
    dem, _ = inject_errors(
        ref,
        InjectedErrors(dz=2.0, noise=VariogramModel(np.array([150.0]), np.array([0.25])), seed=1),
    )
    h = dem.heights.copy()
    h[20:40, 20:40] += 100.0
    ref.write(d / "ref.tif")
    DEM(h, dem.transform, dem.crs, "geoid").write(d / "dem.tif")
    return d


def _coreg_stable(d, out, *extra):
    rc = main(
        ["coregister", str(d / "dem.tif"), "--ref", str(d / "ref.tif"), "--chain", "vshift"]
        + ["--no-figures", *extra, "-o", str(out)]
    )
    assert rc == 0
    rep = json.loads((out / "coregistration.json").read_text())
    return rep["stable"], rep["steps"][0]


def test_outlier_nmad_is_honoured(cloudy, tmp_path):
    """Default 5 NMAD: the cloud's 400 cells (and nothing else at 0.5 m noise) leave the stable
    terrain; 3 NMAD removes a few noise cells more; 0 turns the test off."""
    s5, step5 = _coreg_stable(cloudy, tmp_path / "n5")
    s3, _ = _coreg_stable(cloudy, tmp_path / "n3", "--outlier-nmad", "3")
    s0, step0 = _coreg_stable(cloudy, tmp_path / "n0", "--outlier-nmad", "0")
    assert s5["valid_cells"] == s0["valid_cells"] == 150 * 150
    assert (s0["outlier_nmad"], s0["outlier_cells"], s0["stable_cells"]) == (None, 0, 150 * 150)
    assert s5["outlier_nmad"] == 5.0 and s5["outlier_cells"] == 400
    assert s5["stable_cells"] == 150 * 150 - 400
    assert s3["outlier_nmad"] == 3.0 and 400 < s3["outlier_cells"] < 600
    assert s3["stable_cells"] == 150 * 150 - s3["outlier_cells"]
    for s, step in ((s5, step5), (s0, step0)):  # the fit used exactly the stable terrain said
        assert s["samples_used"] == step["before"]["n"] == s["stable_cells"]
    # the cloud out, the 0.5 m noise alone is left on stable terrain; in, it dominates the std
    assert step5["after"]["std"] < 0.7 and step0["after"]["std"] > 10.0


@pytest.mark.parametrize(
    "option, keep",
    [
        (["--max-slope", "10"], lambda s: s <= 10),
        (["--min-slope", "10"], lambda s: s >= 10),
        (["--min-slope", "5", "--max-slope", "15"], lambda s: (s >= 5) & (s <= 15)),
    ],
)
def test_slope_limits_are_honoured(cloudy, tmp_path, option, keep):
    """The stable terrain is exactly the cells whose slope (of the DEM, degrees) is within the
    limits (outlier test off, so that nothing else changes it)."""
    dem = DEM.from_file(cloudy / "dem.tif")
    slope = terrain.slope_deg(dem.heights, dem.transform, dem.crs)
    with np.errstate(invalid="ignore"):
        want = int(keep(slope).sum())
    assert 0.2 * slope.size < want < 0.8 * slope.size  # the limits do cut
    s, step = _coreg_stable(cloudy, tmp_path / "o", "--outlier-nmad", "0", *option)
    assert s["stable_cells"] == want == step["before"]["n"]


@pytest.mark.parametrize(
    "option, message",
    [
        (["--max-slope", "100"], r"--max-slope must be a slope in degrees, 0 to 90, got 100"),
        (["--min-slope", "-1"], r"--min-slope must be a slope in degrees, 0 to 90, got -1"),
        (["--max-slope", "nan"], r"--max-slope must be .*got nan"),
        (
            ["--min-slope", "20", "--max-slope", "10"],
            r"--min-slope 20 must be below --max-slope 10",
        ),
        (["--outlier-nmad", "-1"], r"--outlier-nmad must be a number >= 0 .*got -1"),
        (["--outlier-nmad", "nan"], r"--outlier-nmad must be .*got nan"),
        (
            ["--min-slope", "60"],
            r"dem\.tif: --min-slope 60: only 0\.0 % of the DEM's valid cells \(0 of 22500\) are "
            r"left as stable terrain",
        ),
    ],
)
def test_bad_stable_terrain_limits_are_one_line(cloudy, tmp_path, capsys, option, message):
    out = tmp_path / "o"
    code, _, err = run_cli(
        capsys,
        ["coregister", cloudy / "dem.tif", "--ref", cloudy / "ref.tif", *option, "-o", out],
    )
    assert_clear_error(code, err, "coregister", message)
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


# ----------------------------------------------------------------------------- bad input, CLI


@pytest.fixture(scope="module")
def bad_inputs(files):
    """Hostile inputs beside ``files``: an outline far from the DEM, a stable mask of its first
    5 rows (3.3 %), points with a NaN height (CSV and GeoParquet), points with no datum."""
    d = files / "bad_inputs"
    d.mkdir()
    ring = [[10, 10], [10.1, 10], [10.1, 10.1], [10, 10]]
    (d / "far.geojson").write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {},
                        "geometry": {"type": "Polygon", "coordinates": [ring]},
                    }
                ],
            }
        )
    )
    ref = DEM.from_file(files / "ref.tif")
    m = np.zeros(ref.shape, np.uint8)
    m[:5, :] = 1
    write_geotiff(d / "mask.tif", m, ref.transform, ref.crs, None)
    (d / "nan.csv").write_text(
        "# two points on the DEM, one height missing\nlon,lat,h\n"
        "40.05,39.95,1000\n40.06,39.94,nan\n"
    )
    (d / "nodatum.csv").write_text("lon,lat,h\n40.05,39.95,1000\n40.06,39.94,1001\n")
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    pq.write_table(
        pa.table({"lon": [40.05, 40.06], "lat": [39.95, 39.94], "h": [1000.0, float("nan")]}),
        d / "nan.parquet",
    )
    return d


def _bad_cases(f, b):
    far = r"far\.geojson: no outline overlaps the DEM"
    cor = ["coregister", f / "dem.tif"]
    return {
        "coregister-exclude": (cor + ["--ref", f / "ref.tif", "--exclude", b / "far.geojson"], far),
        "coregister-include": (cor + ["--ref", f / "ref.tif", "--include", b / "far.geojson"], far),
        "assess-outlines": (
            ["assess", f / "dem.tif", "--ref", f / "ref.tif", "--outlines", b / "far.geojson"],
            far,
        ),
        "assess-exclude": (
            ["assess", f / "dem.tif", "--ref", f / "ref.tif", "--error-analysis"]
            + ["--exclude", b / "far.geojson"],
            far,
        ),
        "change-exclude": (
            ["change", f / "ref.tif", f / "dem.tif", "--exclude", b / "far.geojson"],
            far,
        ),
        "coregister-mask-3pct": (
            cor + ["--ref", f / "ref.tif", "--stable-mask", b / "mask.tif"],
            r"mask\.tif: only 3\.3 % of the DEM's valid cells \(750 of 22500\) are left as "
            r"stable terrain \(need at least 5 %\)",
        ),
        "coregister-points-nan-csv": (
            cor + ["--ref", b / "nan.csv", "--ref-vertical", "geoid"],
            r"nan\.csv: 1 of 2 points have NaN/inf lon, lat or h \(first at line 4\)",
        ),
        "coregister-points-nan-parquet": (
            cor + ["--ref", b / "nan.parquet", "--ref-vertical", "geoid"],
            r"nan\.parquet: 1 of 2 points have NaN/inf lon, lat or h \(first at row 2\)",
        ),
        "coregister-points-no-datum": (
            cor + ["--ref", b / "nodatum.csv"],
            r"nodatum\.csv: vertical reference of the point heights not said; give --ref-vertical",
        ),
    }


@pytest.mark.parametrize(
    "case",
    [
        "coregister-exclude",
        "coregister-include",
        "assess-outlines",
        "assess-exclude",
        "change-exclude",
        "coregister-mask-3pct",
        "coregister-points-nan-csv",
        "coregister-points-nan-parquet",
        "coregister-points-no-datum",
    ],
)
def test_bad_outlines_masks_and_points_through_the_cli(files, bad_inputs, tmp_path, capsys, case):
    """Exit 1, one ``stereodem CMD: error:`` line naming the file and the problem (how much
    stable terrain is left, where the NaN is), nothing else on stderr, nothing in -o."""
    argv, message = _bad_cases(files, bad_inputs)[case]
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, [*argv, "-o", out])
    assert_clear_error(code, err, argv[0], message)
    assert len(err.strip().splitlines()) == 1, err
    assert not out.exists()
