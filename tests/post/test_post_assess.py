import argparse
import io
import json
import subprocess
import sys
import warnings

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import CRS
from rasterio.errors import NotGeoreferencedWarning
from rasterio.warp import calculate_default_transform
from scipy import ndimage as ndi

from stereodem import assess_cli
from stereodem.cli import main
from stereodem.core import geodesy, jsonutil
from stereodem.core.dem import DEM
from stereodem.core.errors import (
    DEMError,
    InputError,
    NoOverlapError,
    OutputExistsError,
    VerticalReferenceError,
)
from stereodem.core.raster import write_geotiff
from stereodem.post import assess, figures
from stereodem.post.coreg import reference_on_grid
from stereodem.post.mosaic_coreg import crop_reference
from stereodem.post.report import write_report
from stereodem.post.warp import to_grid


@pytest.fixture(scope="module")
def ref():
    d = DEM.bundled()
    return DEM(d.heights[:400, :400].copy(), d.transform, d.crs, "geoid", "srtm_crop")


@pytest.fixture(scope="module")
def simulated(ref):
    """A DEM with a 0.4-px geolocation error (errors grow with slope) and 2 m noise."""
    z = ref.heights.astype(np.float64)
    sim = ndi.shift(z, (0.3, 0.4), order=3, mode="nearest")
    sim += np.random.default_rng(5).normal(0, 2.0, z.shape)
    return DEM(sim.astype(np.float32), ref.transform, ref.crs, "geoid", "sim")


def test_slope_classes_show_error_growing_with_slope(ref, simulated):
    res = assess.assess_dem(simulated, ref)
    rows = [r for r in res.report["by_slope"] if r["n"] > 200]
    assert len(rows) >= 4
    nm = [r["nmad"] for r in rows]
    assert all(b > a for a, b in zip(nm, nm[1:]))
    assert res.report["slope_fit"]["slope_m_per_deg"] > 0
    assert res.report["slope_class_trend"]["r"] > 0.9
    # whole-DEM statistics are those of the difference array
    dh = simulated.heights.astype(float) - ref.heights.astype(float)
    s = res.report["stats"]
    assert s["rmse"] == pytest.approx(np.sqrt(np.mean(dh[np.isfinite(dh)] ** 2)), rel=1e-4)
    assert sum(r["n"] for r in res.report["by_elevation"]) == s["n"]


def test_reference_in_another_crs_is_warped(ref):
    # the reference put on a UTM grid: the DEM (lon/lat) is warped onto it
    utm = CRS.from_epsg(32637)
    b = ref.bounds_lonlat()
    t, w, h = calculate_default_transform(
        "EPSG:4326", "EPSG:32637", ref.shape[1], ref.shape[0], *b, resolution=100.0
    )
    zu = to_grid(ref.heights, ref.transform, ref.crs, t, utm, (h, w), resampling="cubic")
    ref_utm = DEM(zu, t, utm, "geoid", "ref_utm")
    res = assess.assess_dem(ref, ref_utm)
    assert res.report["grid"]["crs"] == "EPSG:32637"
    assert res.report["grid"]["pixel_size_m"] == pytest.approx([100.0, 100.0])
    assert abs(res.report["stats"]["median"]) < 0.5 and res.report["stats"]["nmad"] < 5.0


def test_vertical_references_reconciled(ref):
    ell = ref.to_reference("ellipsoid")
    res = assess.assess_dem(ell, ref)
    assert abs(res.report["stats"]["mean"]) < 0.01
    assert "converted" in res.report["vertical"]["note"]
    unknown = DEM(ell.heights, ell.transform, ell.crs, None, "unknown.tif")
    with pytest.raises(VerticalReferenceError, match="unknown.tif"):
        assess.assess_dem(unknown, ref)
    ok = assess.assess_dem(unknown, ref, dem_vertical="ellipsoid")
    assert abs(ok.report["stats"]["mean"]) < 0.01


def test_a_dem_already_reconciled_is_not_converted_again(ref, monkeypatch):
    """``reconciled=`` (what ``assess_stage`` has already converted): the same report, no
    second conversion; something else than the DEM in the reference's vertical reference is
    refused, not compared."""
    ell = ref.to_reference("ellipsoid")
    reconciled = assess.reconcile_vertical(ell, ref)
    converted = []
    monkeypatch.setattr(DEM, "to_reference", lambda self, to: converted.append(to) or self)
    got = assess.assess_dem(ell, ref, reconciled=reconciled)
    assert converted == []
    monkeypatch.undo()
    same = assess.assess_dem(ell, ref).report
    assert jsonutil.dumps(got.report) == jsonutil.dumps(same)  # NaN (empty classes) as null
    with pytest.raises(InputError, match=r"reconciled= is not this DEM"):
        assess.assess_dem(ell, ref, reconciled=(ell, "not converted"))


def test_a_vertical_given_for_a_dem_that_says_its_own_is_not_applied(ref, tmp_path, caplog):
    """``assess_dem(ell, ref, dem_vertical="geoid")`` relabelled an ellipsoidal DEM object as
    geoid heights (a +29 m mean difference here) while the same DEM given as its file was read
    as ellipsoidal, with a warning: one rule for files and DEM objects. A DEM above EGM2008
    kept its geoid too (it was rebuilt without ``geoid_crs``)."""
    ell = DEM(ref.to_reference("ellipsoid").heights, ref.transform, ref.crs, "ellipsoid", "e.tif")
    path = ell.write(tmp_path / "e.tif")
    for dem in (ell, path):
        caplog.clear()
        res = assess.assess_dem(dem, ref, dem_vertical="geoid")
        assert res.report["vertical"]["dem"] == "ellipsoid"
        assert abs(res.report["stats"]["mean"]) < 0.01
        assert "e.tif: the file says ellipsoid heights" in caplog.text
    egm08 = DEM(ref.heights, ref.transform, ref.crs, "geoid", geoid_crs=CRS("EPSG:3855"))
    assert assess._with_vertical(egm08, "geoid") is egm08


def test_bad_inputs_are_clear_errors(ref):
    far = DEM(ref.heights, Affine.translation(20, 0) @ ref.transform, ref.crs, "geoid", "far.tif")
    with pytest.raises(NoOverlapError, match="far.tif"):
        assess.assess_dem(far, ref)
    with pytest.raises(DEMError, match="no valid height"):
        DEM(np.full((10, 10), np.nan, np.float32), ref.transform, ref.crs, "geoid")
    # footprints overlap but every overlapping DEM cell is void
    h = ref.heights.copy()
    h[:, :] = np.nan
    h[0, 0] = 1000.0
    half = DEM(h, ref.transform, ref.crs, "geoid", "void.tif")
    sub = DEM(
        ref.heights[200:, 200:].copy(),
        Affine.translation(200 * ref.transform.a, 200 * ref.transform.e) @ ref.transform,
        ref.crs,
        "geoid",
        "sub",
    )
    with pytest.raises(NoOverlapError):
        assess.assess_dem(half, sub)


def test_grids_either_side_of_the_antimeridian_are_compared(ref):
    """A lon/lat DEM at 179.97..180.03 E and a reference tile at -180..-179.9 E (both
    EPSG:4326) overlap by 0.03 degrees, but assess, coregister and change refused them as
    not overlapping (and GDAL, which does not wrap within one geographic CRS, warped no cell
    of one onto the other)."""

    def dem(west, res, shape, name):
        t = Affine(res, 0, west, 0, -res, 65.1)
        lon, lat = t @ np.meshgrid(np.arange(shape[1]) + 0.5, np.arange(shape[0]) + 0.5)
        z = 1000 + 50 * np.sin(np.radians((lon - 180.0) % 360.0) * 200) + 800 * (lat - 65)
        return DEM(z.astype(np.float32), t, "EPSG:4326", "geoid", name)

    a = dem(179.97, 0.0005, (100, 120), "a.tif")
    b = dem(-180.0, 0.0004, (125, 250), "b.tif")
    for d, r, n in ((a, b, 75 * 125), (b, a, 60 * 100)):
        rep = assess.assess_dem(d, r).report
        assert rep["stats"]["n"] == n and abs(rep["stats"]["mean"]) < 0.01, rep["stats"]
    z = reference_on_grid(b, a)
    assert np.isfinite(z[:, 62:-2]).all() and not np.isfinite(z[:, :58]).any()


def _global_reference(res=0.05, lat0=66.0, rows=40):
    """A -180..180 lon/lat reference, heights periodic in longitude (smooth across 180)."""
    t = Affine(res, 0, -180.0, 0, -res, lat0)
    lon, lat = t @ np.meshgrid(np.arange(round(360 / res)) + 0.5, np.arange(rows) + 0.5)
    return t, _height(lon, lat).astype(np.float32)


def _height(lon, lat):
    return 1000 + 50 * np.sin(np.radians(lon) * 20) + 800 * (lat - 65)


def test_a_global_reference_wraps_across_the_antimeridian(tmp_path):
    """A DEM at 179.9..180.1 E (lon/lat, or a projected CRS) against a global -180..180
    reference: its part beyond 180 got no reference (assess compared half of it, a mosaic's
    reference crop stopped at 180) and cells within a cell of 180 took the edge column's
    height; the reference now goes on across 180 from its west edge."""
    t, z = _global_reference()
    glob = DEM(z, t, "EPSG:4326", "geoid", "global.tif")
    dt = Affine(0.002, 0, 179.9, 0, -0.002, 65.5)  # 100 x 50 cells, half beyond 180
    lon, lat = dt @ np.meshgrid(np.arange(100) + 0.5, np.arange(50) + 0.5)
    dem = DEM(_height(lon, lat).astype(np.float32), dt, "EPSG:4326", "geoid", "a.tif")
    # the reference on the DEM's grid: every cell, interpolated across 180
    on_dem = reference_on_grid(glob, dem)
    assert np.isfinite(on_dem).all()
    assert np.abs(on_dem - dem.heights).max() < 0.05
    # the DEM on the reference's grid: the reference cells either side of 180
    rep = assess.assess_dem(dem, glob).report
    assert rep["stats"]["n"] == 4 * 2 and abs(rep["stats"]["mean"]) < 0.05, rep["stats"]
    # a projected DEM across 180 (EPSG:3832, Pacific Mercator), both ways
    to_merc = geodesy.transformer("EPSG:4326", "EPSG:3832").transform
    x0, y0 = to_merc(179.9, 65.5)
    x1, _ = to_merc(180.1, 65.5)
    pt = Affine((x1 - x0) / 100, 0, x0, 0, -(x1 - x0) / 100, y0)
    plon, plat = geodesy.transformer("EPSG:3832", "EPSG:4326").transform(
        *(pt @ np.meshgrid(np.arange(100) + 0.5, np.arange(50) + 0.5))
    )
    pdem = DEM(_height(plon, plat).astype(np.float32), pt, "EPSG:3832", "geoid", "p.tif")
    on_p = reference_on_grid(glob, pdem)
    assert np.isfinite(on_p).all() and np.abs(on_p - pdem.heights).max() < 0.05
    assert assess.assess_dem(pdem, glob).report["stats"]["n"] == 4  # 4 cols x 1 row
    # a mosaic's crop of the reference file reads on across 180 from its west edge
    write_geotiff(tmp_path / "global.tif", z, t, "EPSG:4326")
    for crs, bounds in (
        ("EPSG:4326", (179.9, 65.4, 180.1, 65.5)),
        ("EPSG:3832", (x0, y0 - (x1 - x0) / 2, x1, y0)),
    ):
        crop = crop_reference(tmp_path / "global.tif", bounds, crs, margin_cells=2)
        w = crop.transform.c
        e = w + crop.transform.a * crop.shape[1]
        assert w < 179.9 and e > 180.1, (crs, w, e)
        clon, clat = crop.transform @ np.meshgrid(
            np.arange(crop.shape[1]) + 0.5, np.arange(crop.shape[0]) + 0.5
        )
        assert np.abs(crop.heights - _height(clon, clat)).max() < 1e-3


def test_an_assessment_on_a_few_cells_warns(ref, caplog):
    # a 2 x 2 DEM on the reference: NMAD 0 m from 4 cells was reported without a word
    tiny = DEM(
        ref.heights[100:102, 100:102].copy(),
        Affine.translation(100 * ref.transform.a, 100 * ref.transform.e) @ ref.transform,
        ref.crs,
        "geoid",
        "tiny.tif",
    )
    with caplog.at_level("WARNING", logger="stereodem.post.assess"):
        res = assess.assess_dem(tiny, ref)
    assert 0 < res.report["stats"]["n"] < assess.MIN_RELIABLE_CELLS
    assert "tiny.tif: only" in caplog.text and "rest on them alone" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="stereodem.post.assess"):
        assess.assess_dem(ref, ref)
    assert "rest on them alone" not in caplog.text


def test_checkpoints_role_column_keeps_check_points_only(ref, tmp_path):
    """The GCP CSV of ``stereodem adjust`` (role gcp/check, as ``simulate`` and ``demo`` write
    it) given as check points: the GCPs, used in the estimation, are no independent check
    (they were all counted, an optimistic figure)."""
    w, s, e, n = ref.bounds_lonlat()
    lon = np.linspace(w + 0.01, e - 0.01, 6)
    lat = np.linspace(s + 0.01, n - 0.01, 6)
    hz = ref.sample(lon, lat, reference="ellipsoid")
    hz[:3] += 100.0  # the GCPs: wrong heights, that a check-point figure must not see
    roles = ["gcp", "", "GCP", "check", " Check", "check"]
    csv = tmp_path / "points.csv"
    csv.write_text(
        "id,lon,lat,h,col,row,role\n"
        + "".join(
            f"P{i},{a},{b},{c},0,0,{r}\n" for i, (a, b, c, r) in enumerate(zip(lon, lat, hz, roles))
        )
    )
    lon2, lat2, z2, ids = assess.read_checkpoints(csv)
    assert ids == ["P3", "P4", "P5"] and z2.size == lon2.size == lat2.size == 3
    cp = assess.assess_checkpoints(ref, csv, vertical="ellipsoid")
    assert cp["stats"]["n"] == 3 and abs(cp["stats"]["max"]) < 1e-6
    csv.write_text("id,lon,lat,h,role\nP0,40.1,39.5,1000,gcp\n")
    with pytest.raises(InputError, match=r"points.csv: no check point.*role gcp"):
        assess.read_checkpoints(csv)
    csv.write_text("id,lon,lat,h,role\nP0,40.1,39.5,1000,ground\n")
    with pytest.raises(InputError, match=r"points.csv: unknown role\(s\) ground"):
        assess.read_checkpoints(csv)


@pytest.mark.slow
def test_assess_logs_the_check_points_line_once(ref, simulated, tmp_path, caplog):
    """``assess --checkpoints`` reads the file to check it before any work and again to use
    it: the line saying how many GCPs are left out is logged once (``check_checkpoints`` is
    quiet), as ``run``'s input check does."""
    w, s, e, n = ref.bounds_lonlat()
    lon = np.linspace(w + 0.01, e - 0.01, 6)
    lat = np.linspace(s + 0.01, n - 0.01, 6)
    hz = ref.sample(lon, lat)
    csv = tmp_path / "points.csv"
    csv.write_text(
        "id,lon,lat,h,role\n"
        + "".join(
            f"P{i},{a},{b},{c},{'check' if i % 2 else 'gcp'}\n"
            for i, (a, b, c) in enumerate(zip(lon, lat, hz))
        )
    )
    ref.write(tmp_path / "ref.tif")
    simulated.write(tmp_path / "dem.tif")
    argv = ["assess", str(tmp_path / "dem.tif"), "--ref", str(tmp_path / "ref.tif")]
    with caplog.at_level("INFO", logger="stereodem.post.assess"):
        rc = main([*argv, "--checkpoints", str(csv), "-o", str(tmp_path / "o")])
    assert rc == 0
    lines = [r.getMessage() for r in caplog.records if "GCP(s) (role gcp) left out" in r.message]
    assert lines == [f"{csv}: 3 check point(s); 3 GCP(s) (role gcp) left out"]


def test_checkpoints_and_landcover(ref, simulated, tmp_path):
    rng = np.random.default_rng(2)
    w, s, e, n = ref.bounds_lonlat()
    lon, lat = rng.uniform(w + 0.01, e - 0.01, 30), rng.uniform(s + 0.01, n - 0.01, 30)
    hz = ref.sample(lon, lat, reference="ellipsoid")
    csv = tmp_path / "cp.csv"
    csv.write_text(
        "id,lon,lat,height\n"
        + "".join(f"p{i},{a},{b},{c}\n" for i, (a, b, c) in enumerate(zip(lon, lat, hz)))
    )
    cp = assess.assess_checkpoints(ref, csv, vertical="ellipsoid")
    assert (
        cp["stats"]["n"] == 30 and abs(cp["stats"]["max"]) < 1e-6 and cp["points"][0]["id"] == "p0"
    )
    cp2 = assess.assess_checkpoints(simulated, (lon, lat, hz), vertical="ellipsoid")
    dh = simulated.sample(lon, lat, reference="ellipsoid") - hz
    assert cp2["stats"]["rmse"] == pytest.approx(np.sqrt(np.mean(dh**2)))
    lc = (ref.heights > np.nanmedian(ref.heights)).astype(np.int16) + 1
    res = assess.assess_dem(
        simulated,
        ref,
        landcover=(lc, ref.transform, ref.crs),
        landcover_names={1: "low", 2: "high"},
    )
    names = [c["class"] for c in res.report["by_landcover"]]
    assert names == ["low", "high"]
    assert sum(c["n"] for c in res.report["by_landcover"]) == res.report["stats"]["n"]


def _parser():
    p = argparse.ArgumentParser(prog="stereodem")
    assess_cli.add_parser(p.add_subparsers(dest="command"))
    return p


@pytest.mark.slow
def test_cli_writes_report_and_figures(tmp_path, ref):
    z = ref.heights.astype(np.float64)
    sh = ndi.shift(z, (-1.5, 1.0), order=3, mode="nearest") + 4.0
    DEM(sh.astype(np.float32), ref.transform, ref.crs, "geoid").write(tmp_path / "dem.tif")
    DEM(ref.heights, ref.transform, ref.crs, None).write(tmp_path / "ref.tif")  # vertical unknown
    lc = np.where(np.arange(400)[None, :] < 200, 1, 2).repeat(400, 0).astype(np.uint8)

    write_geotiff(tmp_path / "lc.tif", lc, ref.transform, ref.crs, 0)
    out = tmp_path / "out"

    assert (
        main(
            [
                "assess",
                str(tmp_path / "dem.tif"),
                "--ref",
                str(tmp_path / "ref.tif"),
                "--landcover",
                str(tmp_path / "lc.tif"),
                "--coregister",
                "-o",
                str(out),
            ]
        )
        == 1
    )
    assert not out.exists()  # geoid vs unknown: a clear error, no output
    args = _parser().parse_args(
        [
            "assess",
            str(tmp_path / "dem.tif"),
            "--ref",
            str(tmp_path / "ref.tif"),
            "--ref-vertical",
            "geoid",
            "--landcover",
            str(tmp_path / "lc.tif"),
            "--slope-bins",
            "0,10,20,90",
            "--coregister",
            "-o",
            str(out),
        ]
    )
    assert args.run(args) == 0
    rep = json.loads((out / "report.json").read_text())
    for key in (
        "n",
        "valid_pct",
        "mean",
        "median",
        "std",
        "rmse",
        "nmad",
        "le90",
        "le95",
        "p16",
        "p84",
        "min",
        "max",
    ):
        assert key in rep["stats"]
    assert len(rep["by_slope"]) == 3 and len(rep["by_landcover"]) == 2
    co = rep["coregistration"]
    px = abs(ref.transform.a) * 111320 * np.cos(np.radians(39.9))
    assert abs(co["dx_px"] - 1.0) < 0.1 and abs(co["dy_px"] - 1.5) < 0.1 and abs(co["dz"] - 4) < 0.5
    assert co["dx"] == pytest.approx(co["dx_px"] * px, rel=0.02)
    assert rep["after_coregistration"]["stats"]["nmad"] < 0.2 * rep["stats"]["nmad"]
    assert "Nuth" in (out / "report.md").read_text()
    # matplotlib where a figure is drawn or read (DESIGN.md, imports, reason (b))
    import matplotlib.image as mpimg

    for name in ("hillshade.png", "difference_map.png", "histogram.png", "error_vs_slope.png"):
        img = mpimg.imread(out / name)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100 and img.std() > 0.01
    # refuses a non-empty folder without --overwrite
    with pytest.raises(OutputExistsError):
        args.run(args)
    args.overwrite = True
    assert args.run(args) == 0


@pytest.mark.slow
def test_assess_at_1_and_2_workers_writes_the_same_bytes(tmp_path):
    """`stereodem assess --workers N` (the comparison's blocks of 512 rows on N threads,
    GDAL's reads on N threads): the report and the figures of 1 and 2 workers are the same
    files, byte for byte; a worker count below 1 is refused before any work."""
    b = DEM.bundled()  # 1000 x 1000 cells: two blocks
    z = ndi.shift(b.heights.astype(np.float64), (0.3, -0.4), order=3, mode="nearest")
    z += np.random.default_rng(11).normal(0, 2.0, z.shape)
    DEM(z.astype(np.float32), b.transform, b.crs, "geoid").write(tmp_path / "dem.tif")
    b.write(tmp_path / "ref.tif")
    argv = ["assess", str(tmp_path / "dem.tif"), "--ref", str(tmp_path / "ref.tif")]
    for w in (1, 2):
        assert main([*argv, "--workers", str(w), "-o", str(tmp_path / f"w{w}")]) == 0
    files = [{p.name: p.read_bytes() for p in (tmp_path / f"w{w}").iterdir()} for w in (1, 2)]
    assert sorted(files[0]) == sorted(files[1]) and "hillshade.png" in files[0]
    assert all(files[0][name] == files[1][name] for name in files[0])
    assert main([*argv, "--workers", "0", "-o", str(tmp_path / "w0")]) == 1
    assert not (tmp_path / "w0").exists()


def test_write_report_refuses_nonempty_dir(tmp_path, ref, simulated):
    (tmp_path / "x.txt").write_text("x")
    res = assess.assess_dem(simulated, ref)
    with pytest.raises(OutputExistsError):
        write_report(res, tmp_path)


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_large_rasters_are_decimated_for_figures(tmp_path, monkeypatch):
    """Figures draw at most DISPLAY_CELLS per side: a big raster costs no more than a small one."""
    # matplotlib where a figure is drawn or read (DESIGN.md, imports, reason (b))
    import matplotlib.pyplot as plt

    monkeypatch.setattr(figures, "DISPLAY_CELLS", 100)
    drawn = []
    real = plt.Axes.imshow
    monkeypatch.setattr(
        plt.Axes, "imshow", lambda self, a, **k: drawn.append(np.shape(a)) or real(self, a, **k)
    )
    z = np.add.outer(np.arange(450.0), np.arange(300.0))
    figures.hillshade_png(
        z, Affine(30, 0, 500000, 0, -30, 4400000), geodesy.utm_crs(39, 39.7), tmp_path / "hs.png"
    )
    figures.difference_map_png(z - z.mean(), tmp_path / "dh.png")
    assert [s[:2] for s in drawn] == [
        (90, 60),
        (90, 60),
    ]  # every 5th cell of 450 x 300 (RGBA or values)
    assert (tmp_path / "hs.png").stat().st_size > 1000 and (tmp_path / "dh.png").exists()


@pytest.mark.slow
def test_figures_crop_as_bbox_inches_tight(ref, simulated, monkeypatch):
    """figures._save crops in one draw (core.png._tight_rgba): the PNG of every figure has the
    size of savefig(bbox_inches="tight")'s and its content in the same place, to the nearest
    pixel (the placement's fraction of a pixel aside: shifting by 2 pixels matches worse)."""
    # matplotlib where a figure is drawn or read (DESIGN.md, imports, reason (b))
    import matplotlib.pyplot as plt

    from stereodem.core import png
    from stereodem.post import coreg_figures  # before _save is replaced: it imports _save

    cmp = assess.compare_on_reference_grid(simulated, ref)
    figs = []
    monkeypatch.setattr(figures, "_save", lambda fig, path, overwrite: figs.append(fig))
    figures.hillshade_png(ref.heights, ref.transform, ref.crs, "h.png")
    figures.difference_map_png(cmp.dh, "d.png", transform=cmp.transform, crs=cmp.crs)
    figures.difference_map_png(cmp.dh, "d.png")
    figures.histogram_png(cmp.dh, "hist.png")
    stats = assess.comparison_stats(cmp)
    figures.error_vs_slope_png(cmp.dh, cmp.slope, stats["by_slope"], "e.png")
    monkeypatch.setattr(coreg_figures, "_save", lambda fig, path, overwrite: figs.append(fig))
    mask = np.isfinite(cmp.dh)
    coreg_figures.dh_before_after_png(ref.heights, simulated, simulated, mask, "c.png")

    def error(a, b, dy, dx):  # mean |a - b| (8-bit levels) with b shifted by dy, dx
        h, w = a.shape[:2]
        a = a[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)].astype(int)
        b = b[max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)].astype(int)
        return np.abs(a - b).mean()

    for fig in figs:
        buf = io.BytesIO()
        fig.savefig(buf, dpi=figures.DPI, bbox_inches="tight", format="png")
        tight = np.round(plt.imread(io.BytesIO(buf.getvalue())) * 255).astype(np.uint8)
        once = png._tight_rgba(fig, figures.DPI)
        assert once is not None and once.shape == tight.shape
        near = min(error(tight, once, dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        far = min(error(tight, once, dy, dx) for dy, dx in ((2, 0), (-2, 0), (0, 2), (0, -2)))
        assert error(tight, once, 0, 0) < far and near < far
        plt.close(fig)


@pytest.mark.slow
def test_colours_as_bytes_draw_as_float_colours_with_nearest_cells():
    """hillshade_png hands matplotlib its colours as bytes, (rgba · 255) cast as matplotlib
    casts float colours after resampling to the nearest cell: the PNG is the same."""
    # matplotlib where a figure is drawn or read (DESIGN.md, imports, reason (b))
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(4)
    for shape in ((900, 700), (60, 40)):  # fewer cells than pixels, more
        rgba = rng.random((*shape, 4))
        rgba[..., 3] = rng.random(shape) > 0.3  # transparent cells
        pngs = []
        for image in (rgba, (rgba * 255).astype(np.uint8)):
            fig, ax = plt.subplots(figsize=(6.5, 6))
            ax.imshow(image, extent=(0, 7000, 0, 9000), interpolation="nearest")
            buf = io.BytesIO()
            fig.savefig(buf, dpi=figures.DPI, format="png")
            plt.close(fig)
            pngs.append(plt.imread(io.BytesIO(buf.getvalue())))
        np.testing.assert_array_equal(pngs[0], pngs[1])


@pytest.mark.slow
def test_blocks_warped_on_threads_do_not_warn_not_georeferenced():
    """rasterio's reproject of arrays warns "no geotransform" from its in-memory datasets when
    threads race on its ``warnings.catch_warnings`` (about 1 in 2000 calls on 4 threads
    measured): the filter :mod:`stereodem.post.warp` sets when imported ignores that warning
    from ``rasterio.warp`` only, for every thread. In a fresh interpreter, as a command runs
    (pytest restores the filters of before each test module's import)."""
    code = """
import json, warnings
from concurrent.futures import ThreadPoolExecutor
import numpy as np
from affine import Affine
from pyproj import CRS
from rasterio.errors import NotGeoreferencedWarning
from stereodem.post.warp import to_grid
shown = []
warnings.showwarning = lambda m, c, f, *a, **k: shown.append([c.__name__, f.split("/")[-1]])
crs = CRS.from_epsg(32633)
src = np.random.default_rng(0).random((40, 40), np.float32)
t0, t1 = Affine(30, 0, 500000, 0, -30, 4000000), Affine(10, 0, 500000, 0, -10, 4000000)
msg = "Dataset has no geotransform, gcps, or rpcs."
for module, name in (("rasterio.warp", "warp.py"), ("rasterio", "__init__.py")):
    warnings.warn_explicit(msg, NotGeoreferencedWarning, name, 1, module=module)
with ThreadPoolExecutor(4) as ex:
    out = list(ex.map(lambda _: to_grid(src, t0, crs, t1, crs, (60, 60)), range(400)))
same = all(np.array_equal(o, out[0], equal_nan=True) for o in out)
print(json.dumps([shown, same]))
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    shown, same = json.loads(res.stdout.strip().splitlines()[-1])
    # the one from rasterio.warp (as reproject raises it) filtered, from elsewhere still
    # shown (before the threads: rasterio's racing blocks can also leave an ignore behind);
    # none from the warps on threads
    assert shown == [["NotGeoreferencedWarning", "__init__.py"]] and same


def test_a_warp_sets_the_in_memory_warp_filter_again_when_it_is_gone():
    """A ``catch_warnings`` block around the module's import (pytest's, a notebook's) restores
    the filters of before and drops the module's; the next warp sets it again, so blocks
    warped on threads afterwards do not warn either."""

    def ours():
        return [
            f
            for f in warnings.filters
            if f[0] == "ignore" and f[2] is NotGeoreferencedWarning and f[3] is not None
        ]

    crs = CRS.from_epsg(32633)
    t = Affine(30, 0, 500000, 0, -30, 4000000)
    with warnings.catch_warnings():
        warnings.resetwarnings()
        assert not ours()
        to_grid(np.ones((4, 4), np.float32), t, crs, t, crs, (4, 4))
        assert [f[3].pattern for f in ours()] == [r"rasterio\.warp$"]
        to_grid(np.ones((4, 4), np.float32), t, crs, t, crs, (4, 4))
        assert len(ours()) == 1  # once


def test_coreg_dh_maps_have_km_axes_a_scale_bar_and_a_labelled_colour_bar(monkeypatch):
    """coreg_dh.png: before, the two dh maps had no axes at all (ticks removed, no scale bar:
    no idea of the size of a pattern) and a colour bar labelled "dh (m)"; now easting/northing
    in km with a scale bar, as the assessment's maps, and "DEM − reference (m)"."""
    # matplotlib where a figure is drawn or read (DESIGN.md, imports, reason (b))
    from matplotlib.offsetbox import AnchoredOffsetbox

    from stereodem.post import coreg_figures

    figs = []
    monkeypatch.setattr(coreg_figures, "_save", lambda fig, path, overwrite: figs.append(fig))
    t = Affine(30, 0, 500000, 0, -30, 4000000)
    z = np.random.default_rng(0).normal(1000, 5, (40, 50)).astype(np.float32)
    dem = DEM(z, t, "EPSG:32633", "ellipsoid")
    coreg_figures.dh_before_after_png(z - 1, dem, dem, np.ones(z.shape, bool), "c.png")
    (fig,) = figs
    maps, bar = fig.axes[:2], fig.axes[2]
    for ax in maps:
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("easting (km)", "northing (km)")
        assert ax.get_xlim() == (500000, 500000 + 50 * 30)
        assert any(isinstance(a, AnchoredOffsetbox) for a in ax.artists)  # the scale bar
    assert bar.get_ylabel() == "DEM − reference (m)"


def test_a_landcover_raster_without_geotransform_is_refused(tmp_path):
    """A land-cover GeoTIFF with a CRS but no geotransform: rasterio gives the identity
    transform with a warning only, so before the classes were placed at CRS coordinates
    0..width, overlapped nothing and ``by_landcover`` came out empty without an error."""
    t = Affine(30, 0, 500000, 0, -30, 4000000)
    z = np.random.default_rng(0).normal(1000, 5, (30, 30)).astype(np.float32)
    dem = DEM(z, t, "EPSG:32633", "ellipsoid")
    lc = tmp_path / "lc.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(
            lc, "w", driver="GTiff", width=30, height=30, count=1, dtype="uint8", crs="EPSG:32633"
        ) as ds:
            ds.write(np.ones((1, 30, 30), np.uint8))
        with pytest.raises(InputError, match="lc.tif: the land-cover raster has no geotransform"):
            assess.assess_dem(dem, dem, landcover=lc)


@pytest.mark.parametrize("bad", [None, np.zeros((3, 3), np.float32), 5])
def test_assess_dem_given_no_dem_says_what_it_takes(bad, ref):
    """An array, None or a number for the DEM raised an AttributeError ('NoneType' object has
    no attribute 'transform') from inside the assessment."""
    with pytest.raises(DEMError, match="expected a DEM or a path"):
        assess.assess_dem(bad, ref)
    with pytest.raises(DEMError, match="expected a DEM or a path"):
        assess.assess_dem(ref, bad, dem_vertical="geoid")
