"""What a person reads off the figures: colour maps that do not suggest what is not there,
clipped colour scales said, y axes from 0 where a ratio is read, the file in the title, and
legends off the data. Checked on the matplotlib Figure objects, not on pixels."""

from __future__ import annotations

import logging
import re

import matplotlib.colors as mcolors
import numpy as np
import pytest
from affine import Affine
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.post import assess, coreg_figures, error_analysis, figures
from stereodem.post.coreg import parse_chain
from stereodem.post.report import write_report
from stereodem.post.spatialstats import EmpiricalVariogram, VariogramModel
from stereodem.sensor.estimation import compare
from stereodem.sensor.estimation.adjust import report as adjust_report

T = Affine(30.0, 0.0, 600000.0, 0.0, -30.0, 4390000.0)


@pytest.fixture(scope="module")
def small_pair():
    b = DEM.bundled()
    ref = b.heights[:120, :120].astype(np.float32).copy()
    z = ref + np.random.default_rng(1).normal(0, 1.0, ref.shape).astype(np.float32) + 2.0
    return (
        DEM(z, T, "EPSG:32637", "geoid", "/data/aster_2004.tif"),
        DEM(ref, T, "EPSG:32637", "geoid", "/data/srtm.tif"),
    )


def _luminance(rgb):
    r, g, b = rgb[:3]
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def test_height_colours_start_neither_black_nor_sea_blue(tmp_path, captured):
    """The lowest heights of a relief were drawn black (gist_earth's start): read as voids."""
    cmap = figures.height_cmap()
    for x in (0.0, 0.05, 0.1):
        r, g, b, _ = cmap(x)
        assert _luminance((r, g, b)) > 0.35, x
        assert not (b > r and b > g), f"blue (sea) at {x}"
    z = np.linspace(1500, 3000, 60 * 60).reshape(60, 60)
    figures.hillshade_png(z, T, "EPSG:32637", tmp_path / "hs.png", title="Shaded relief of a.tif")
    fig = captured[0]
    ax, cax = fig.axes
    assert cax._colorbar.cmap.name == cmap.name
    assert "(m)" in cax.get_ylabel()
    assert "a.tif" in ax.get_title()
    assert any(isinstance(a, AnchoredSizeBar) for a in ax.artists)


def test_coreg_maps_name_the_files_say_their_clipping_and_centre_on_zero(
    small_pair, tmp_path, captured
):
    dem, ref = small_pair
    out = DEM(ref.heights + 0.1, T, "EPSG:32637", "geoid", None)
    mask = np.ones(dem.shape, bool)
    coreg_figures.dh_before_after_png(
        ref.heights, dem, out, mask, tmp_path / "dh.png", ref_name="srtm.tif"
    )
    fig = captured[0]
    sup = fig._suptitle.get_text()
    assert "aster_2004.tif" in sup and "srtm.tif" in sup and "clipped" in sup
    maps = [ax for ax in fig.axes if ax.get_images()]
    assert len(maps) == 2
    for ax in maps:
        im = ax.get_images()[0]
        assert im.norm.vmin == pytest.approx(-im.norm.vmax)
        assert isinstance(im.cmap, mcolors.Colormap) and im.cmap(0.5)[:3] == pytest.approx(
            (0.97, 0.97, 0.97), abs=0.04
        )  # white at 0
        assert "% of cells beyond" in ax.get_title()
        assert any(isinstance(a, AnchoredSizeBar) for a in ax.artists)
        assert "km" in ax.get_xlabel()
    # before: 2 m off (noise 1 m) against a ±0.2 m scale: nearly every cell beyond, said
    share = float(re.search(r"([0-9.]+) % of cells beyond", maps[0].get_title()).group(1))
    assert share > 90.0
    cbar = [ax for ax in fig.axes if not ax.get_images()][0]
    assert "(m)" in cbar.get_ylabel()


def _plots(ranges=(40.0, 20000.0)):
    centre = np.array([5.0, 15.0, 25.0])
    nmad = np.array([0.73, 0.74, 0.75])  # a 3 % variation
    hs = {
        "slope": {"centre": centre, "nmad": nmad, "quadratic_fit": [0.0, 0.001, 0.72]},
        "curvature": {"centre": centre / 10, "nmad": nmad, "quadratic_fit": None},
    }
    lag = np.geomspace(20, 5000, 12)
    emp = EmpiricalVariogram(np.r_[lag, 6000], lag, np.linspace(0.7, 1.0, 12), np.full(12, 50))
    model = VariogramModel(np.array(ranges), np.array([0.8, 0.2]))
    return {"hs": hs, "emp": emp, "model": model, "chain": None, "name": "aster_2004.tif"}


@pytest.mark.slow
def test_error_analysis_axes_start_at_zero_and_say_extrapolated_ranges(tmp_path, captured):
    error_analysis.write_figures(_plots(), tmp_path)
    terrain_fig, vario_fig = captured
    for ax in terrain_fig.axes:
        assert ax.get_ylim()[0] == 0.0  # a 3 % variation is not blown up to the whole axis
        assert "(m)" in ax.get_ylabel()
    assert "aster_2004.tif" in terrain_fig._suptitle.get_text()
    ax = vario_fig.axes[0]
    assert ax.get_ylim()[0] == 0.0 and ax.get_ylim()[1] >= 1.0
    assert any(np.allclose(ln.get_ydata(), 1.0) for ln in ax.get_lines())  # the sill of 1
    assert "extrapolated" in ax.get_title() and "aster_2004.tif" in ax.get_title()
    assert "(m)" in ax.get_xlabel()
    captured.clear()
    error_analysis.write_figures(_plots(ranges=(40.0, 2000.0)), tmp_path, overwrite=True)
    assert "extrapolated" not in captured[1].axes[0].get_title()


def test_compare_legend_beside_the_axes_and_one_style_per_model(tmp_path, captured):
    records = [
        {
            "model": f"m{k}",
            "family": ("generic", "physical", "orbital")[k % 3],
            "n_params": 4,
            "n_gcp": n,
            "icp_rmse_px": 0.1 * (k + 1) / n,
        }
        for k in range(27)
        for n in (6, 10, 20)
    ]
    compare.figure(records, tmp_path / "c.png", image="left.tif")
    fig = captured[0]
    ax = fig.axes[0]
    assert "left.tif" in ax.get_title()
    assert ax.get_xlabel() and "(pixels)" in ax.get_ylabel()
    fig.canvas.draw()
    leg = ax.get_legend().get_window_extent()
    assert leg.x0 >= ax.get_window_extent().x1  # off the lines
    styles = {
        (mcolors.to_hex(ln.get_color()), ln.get_marker(), ln.get_linestyle())
        for ln in ax.get_lines()
    }
    assert len(styles) == 27


@pytest.mark.slow
def test_report_figures_name_the_files_and_say_before_coregistration(
    small_pair, tmp_path, captured
):
    dem, ref = small_pair
    a = assess.assess_dem(dem, ref, coregister=True)
    write_report(a, tmp_path / "r")
    hs, diff, hist = captured[:3]
    assert "aster_2004.tif" in hs.axes[0].get_title()
    title = diff.axes[0].get_title()
    assert "aster_2004.tif − srtm.tif" in title and "before co-registration" in title
    assert "before co-registration" in hist.axes[0].get_title()
    assert diff.axes[0].get_images()[0].norm.vmin == pytest.approx(
        -diff.axes[0].get_images()[0].norm.vmax
    )


def test_check_points_are_read_and_logged_once_with_coregistration(small_pair, tmp_path, caplog):
    """The check points' line ('N check point(s); M GCP(s) left out') came twice: once per
    stage (before, after co-registration)."""
    dem, ref = small_pair
    lon, lat = (np.asarray(v) for v in _lonlat(dem, [(30, 30), (60, 60), (90, 40)]))
    csv = tmp_path / "pts.csv"
    rows = ["id,lon,lat,h,role"] + [
        f"P{k},{x:.8f},{y:.8f},2000,{'check' if k else 'gcp'}"
        for k, (x, y) in enumerate(zip(lon, lat))
    ]
    csv.write_text("\n".join(rows) + "\n")
    with caplog.at_level(logging.INFO, logger="stereodem"):
        r = assess.assess_dem(dem, ref, coregister=True, checkpoints=csv).report
    lines = [rec for rec in caplog.records if "check point(s)" in rec.getMessage()]
    assert len(lines) == 1
    ids = [p["id"] for p in r["checkpoints"]["points"]]
    assert ids == ["P1", "P2"]  # the ids kept, the GCP left out
    assert [p["id"] for p in r["after_coregistration"]["checkpoints"]["points"]] == ids


def _lonlat(dem, cells):
    xs, ys = zip(*[dem.transform @ (c + 0.5, r + 0.5) for r, c in cells])
    return geodesy.crs_to_lonlat(np.array(xs), np.array(ys), dem.crs)


def test_coreg_step_figure_names_the_files_the_step_and_the_fitted_values(
    small_pair, tmp_path, captured
):
    """``coreg_<k>_<step>.png`` said "nuth_kaab: bias and fit" and a legend "fit": the files,
    the step's place in the chain and its fitted values (σ, units) are said now."""
    dem, ref = small_pair
    shifted = DEM(dem.heights, T @ Affine.translation(0.4, 0.0), dem.crs, "geoid", dem.path)
    chain = parse_chain("nuth_kaab,vshift").fit(ref, shifted)
    out = chain.apply(shifted)
    files = coreg_figures.chain_figures(
        chain, ref, shifted, out, np.ones(dem.shape, bool), tmp_path
    )
    assert set(files) == {"dh_png", "nuth_kaab_png"}  # vshift has no curve
    ax = captured[1].axes[0]
    title = ax.get_title()
    assert "aster_2004.tif − srtm.tif" in title and "step 1 of 2: nuth_kaab" in title
    labels = [ln.get_label() for ln in ax.get_lines()]
    fit = next(t for t in labels if t.startswith("fit"))
    p = chain.steps[0].parameters()
    for name in ("dx", "dy", "dz"):
        value = re.search(rf"{name} = (-?[0-9.e-]+) ± [0-9.e-]+ m", fit)
        assert value and float(value.group(1)) == pytest.approx(p[name]["value"], rel=1e-3)
    assert "(m)" in ax.get_ylabel()


def test_bundle_residual_figures_give_the_image_rmse_and_the_arrow_scale(tmp_path, monkeypatch):
    """The bundle's ``adjust_residuals_left/right.png`` were titled "left: residuals (model −
    measured)": no RMSE and no arrow scale, which the one-image figure gives."""
    figs = []
    save = adjust_report.save_png
    monkeypatch.setattr(
        adjust_report, "save_png", lambda fig, *a, **k: (figs.append(fig), save(fig, *a, **k))[1]
    )
    pts = [
        {"id": "g1", "role": "gcp", "col": 10.0, "row": 10.0, "residual_px": [0.3, 0.4]},
        {"id": "g2", "role": "gcp", "col": 50.0, "row": 20.0, "residual_px": [0.0, 0.5]},
        {"id": "c1", "role": "check", "col": 30.0, "row": 60.0, "residual_px": [1.2, 0.0]},
        {"id": "t1", "role": "tie", "col": 70.0, "row": 70.0, "residual_px": [0.1, 0.0]},
        {"id": "x", "role": "gcp", "col": 80.0, "row": 5.0, "residual_px": [9.0, 9.0]},
    ]
    for p in pts:
        p["outlier"] = p["id"] == "x"
    rep = {"points": pts, "gcp_rmse_px": 2.0, "check_rmse_px": 3.0}
    adjust_report.residual_figure(rep, tmp_path / "l.png", width=100, height=80, image="left")
    title = figs[0].axes[0].get_title()
    assert title.startswith("left: residuals (model − measured), arrows ×")
    assert "(scale arrow: 1 px)" in title
    # this image's RMSE, the outlier left out (the report's 2.0 / 3.0 are the bundle's)
    assert "GCP 0.5 px (n=2), check 1.2 px (n=1), tie 0.1 px (n=1)" in title
    adjust_report.residual_figure(rep, tmp_path / "one.png", width=100, height=80)
    assert "GCP RMSE 2 px, check 3 px" in figs[1].axes[0].get_title()
