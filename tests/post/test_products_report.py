"""Figures people can read and the HTML report (issue #19): map coordinates, scale bars,
colour bars with units, legends on every line, class counts, stated clipping, transparent
nodata; report.html parsed (and screenshotted in a headless browser when one is installed);
valid % on the DEM's own footprint."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
from html.parser import HTMLParser

import numpy as np
import pytest
from affine import Affine
from matplotlib.image import imread
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from stereodem.core.dem import DEM
from stereodem.post import assess, figures
from stereodem.post.report import write_report
from stereodem.post.stats import binned_stats
from stereodem.provenance import provenance

T = Affine(30.0, 0.0, 600000.0, 0.0, -30.0, 4390000.0)


@pytest.fixture(scope="module")
def pair():
    """A reference (400x400 UTM cells) and a noisy DEM covering rows 50:350, cols 100:300
    with a 20x20 void inside."""
    b = DEM.bundled()
    ref_h = b.heights[:400, :400].astype(np.float32).copy()
    z = ref_h + np.random.default_rng(3).normal(0, 2.0, ref_h.shape).astype(np.float32)
    z[:50], z[350:], z[:, :100], z[:, 300:] = np.nan, np.nan, np.nan, np.nan
    z[150:170, 150:170] = np.nan
    z[200, 200] += 400.0  # one blunder: a long histogram tail
    return DEM(z, T, "EPSG:32637", "geoid", "dem"), DEM(ref_h, T, "EPSG:32637", "geoid", "ref")


@pytest.fixture
def captured(monkeypatch):
    """Figures as drawn (the matplotlib Figure just before it is saved)."""
    figs = []
    orig = figures._save

    def keep(fig, path, overwrite):
        figs.append(fig)
        return orig(fig, path, overwrite)

    monkeypatch.setattr(figures, "_save", keep)
    return figs


def test_valid_pct_is_measured_on_the_dem_footprint(pair):
    dem, ref = pair
    s = assess.assess_dem(dem, ref).report["stats"]
    expected = 100.0 * (300 * 200 - 20 * 20) / (300 * 200)  # the hole, not the frame
    assert s["n_total"] == 300 * 200
    assert s["valid_pct"] == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("blockwise", [True, False], ids=["blocks", "whole"])
def test_valid_pct_per_class_is_measured_on_the_dem_footprint_too(pair, blockwise):
    """Per slope, elevation and land-cover class, valid_pct is the share of the class's cells
    inside the DEM's footprint that have a height: the reference's cells beyond the DEM no
    longer dilute it (a DEM without voids on steep slopes read 30-55 % valid per class)."""
    dem, ref = pair
    lc = (np.arange(400)[None, :] // 100 + np.zeros((400, 1), int)).astype(float)
    if blockwise:
        s, _, _ = assess.blockwise_comparison(
            dem, ref, block_rows=64, landcover=(lc, ref.transform, ref.crs)
        )
    else:
        cmp = assess.compare_on_reference_grid(dem, ref)
        cmp.landcover = lc
        s = assess.comparison_stats(cmp)
    n_total = s["stats"]["n_total"]
    assert n_total == 300 * 200
    # every finite reference cell is in one elevation band: the bands share out the footprint
    assert sum(c["n_total"] for c in s["by_elevation"]) == n_total
    assert sum(c["n_total"] for c in s["by_landcover"]) == n_total
    assert 0.99 * n_total <= sum(c["n_total"] for c in s["by_slope"]) <= n_total
    # land-cover columns 100-199 and 200-299 lie inside the DEM (one holds the 20 x 20 void);
    # 0-99 and 300-399 outside it: those classes have no cell in the footprint, left out
    by_lc = {c["value"]: c for c in s["by_landcover"]}
    assert sorted(by_lc) == [1, 2]
    assert by_lc[1]["n_total"] == by_lc[2]["n_total"] == 300 * 100
    assert by_lc[1]["valid_pct"] == pytest.approx(100.0 * (300 * 100 - 400) / (300 * 100))
    assert by_lc[2]["valid_pct"] == pytest.approx(100.0)


def _legend_ok(ax):
    """Every labelled line of ``ax`` is in its legend."""
    leg = ax.get_legend()
    labels = [t.get_text() for t in leg.get_texts()] if leg else []
    lines = [ln.get_label() for ln in ax.get_lines() if not ln.get_label().startswith("_")]
    return leg is not None and all(lab in labels for lab in lines)


@pytest.mark.slow
def test_maps_have_coordinates_scale_bar_colour_bar_and_transparent_voids(pair, tmp_path, captured):
    dem, ref = pair
    p = figures.hillshade_png(
        dem.heights,
        dem.transform,
        dem.crs,
        tmp_path / "hs.png",
        height_label="height above the EGM96 geoid (m)",
    )
    dh = dem.heights.astype(float) - ref.heights
    figures.difference_map_png(dh, tmp_path / "dm.png", transform=T, crs=dem.crs)
    for fig in captured:
        ax, cax = fig.axes[0], fig.axes[1]
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("easting (km)", "northing (km)")
        assert any(isinstance(a, AnchoredSizeBar) for a in ax.artists)
        assert "(m)" in cax.get_ylabel()
        # view cropped to the data: the DEM's 200 columns fill the x range (3 % margin)
        x0, x1 = ax.get_xlim()
        assert abs(x1 - x0) == pytest.approx(30.0 * (200 + 2 * 12), rel=0.02)
    assert "EGM96" in captured[0].axes[1].get_ylabel()
    assert "clipped at ±" in captured[1].axes[0].get_title()
    rgba = imread(p)  # no solid red (or any) void fill
    red = (rgba[..., 0] > 0.9) & (rgba[..., 1] < 0.1) & (rgba[..., 2] < 0.1)
    assert red.sum() == 0


def test_histogram_states_its_clipping_and_labels_every_line(pair, tmp_path, captured):
    dem, ref = pair
    dh = (dem.heights.astype(float) - ref.heights).ravel()
    figures.histogram_png(dh, tmp_path / "h.png")
    ax = captured[0].axes[0]
    assert _legend_ok(ax)
    fin = dh[np.isfinite(dh)]
    lo, hi = np.percentile(fin, [0.5, 99.5])
    note = " ".join(t.get_text() for t in ax.texts)
    assert f"{int((fin < lo).sum()):,} cells below" in note
    assert f"{int((fin > hi).sum()):,} above (max {fin.max():.1f} m)" in note


def test_error_vs_slope_counts_greys_sparse_classes_and_stays_in_axes(tmp_path, captured):
    rng = np.random.default_rng(0)
    slope = np.concatenate([rng.uniform(0, 40, 5000), [46.0, 47.0, 48.0, 49.0]])
    dh = rng.normal(0, 1 + slope / 20)
    dh[-4:] = [30.0, -40.0, 55.0, 60.0]  # a 4-cell class far off the others

    by = binned_stats(dh, slope, [0, 10, 20, 30, 45, 90], unit="deg", name="slope")
    figures.error_vs_slope_png(dh, slope, by, tmp_path / "s.png")
    ax = captured[0].axes[0]
    assert _legend_ok(ax)
    top = ax.get_ylim()[1]
    for ln in ax.get_lines():  # every drawn point is inside the axes
        y = np.asarray(ln.get_ydata(), float)
        if ln.get_label().endswith("per slope class"):
            assert len(y) == 4 and np.all(y <= top)  # the sparse class is not joined
    counts = [t.get_text() for t in ax.child_axes[0].get_xticklabels()]
    assert counts == [f"n={e['n']:,}" for e in by]
    assert ax.child_axes[0].get_xticklabels()[-1].get_color() != "k"
    assert any("↑" in t.get_text() for t in ax.texts)  # off-scale sparse values are stated


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.imgs, self.tags, self.text, self.dt = [], [], [], []
        self._in_dt = False

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        if tag == "img":
            self.imgs.append(dict(attrs))
        self._in_dt = tag == "dt"

    def handle_data(self, data):
        self.text.append(data)
        if self._in_dt:
            self.dt.append(data)
            self._in_dt = False


def _report(pair, out):
    dem, ref = pair
    res = assess.assess_dem(dem, ref)
    return write_report(res, out, provenance=provenance(argv=["stereodem", "assess", "x"]))


@pytest.mark.slow
def test_html_report_is_self_contained_with_figures_tables_provenance(pair, tmp_path):
    files = _report(pair, tmp_path / "rep")
    page = _Page()
    page.feed(files["html"].read_text(encoding="utf-8"))
    pngs = {
        k: files[k].read_bytes() for k in ("hillshade", "difference", "histogram", "error_vs_slope")
    }
    srcs = [i["src"] for i in page.imgs]
    assert len(srcs) == 4 and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert sorted(base64.b64decode(s.split(",", 1)[1]) for s in srcs) == sorted(pngs.values())
    assert page.tags.count("table") == 3  # whole DEM, slope classes, elevation bands
    assert {"started_utc", "command_line", "stereodem_version"} <= set(page.dt)
    text = " ".join(page.text)
    rep = json.loads(files["json"].read_text())
    assert f"NMAD {rep['stats']['nmad']:.2f} m" in text
    assert rep["provenance"]["command_line"] == "stereodem assess x"
    assert "## Provenance" in files["markdown"].read_text()


@pytest.mark.slow
@pytest.mark.skipif(
    not (shutil.which("chromium") or shutil.which("chromium-browser")),
    reason="no headless browser (apt-get install chromium)",
)
def test_html_report_renders_in_a_headless_browser(pair, tmp_path):
    files = _report(pair, tmp_path / "rep")
    shot = tmp_path / "shot.png"
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    subprocess.run(
        [
            exe,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            f"--screenshot={shot}",
            "--window-size=1000,2400",
            files["html"].resolve().as_uri(),
        ],
        capture_output=True,
        timeout=120,
    )
    img = imread(shot)
    assert img.shape[:2] == (2400, 1000)
    # figures rendered: many distinct colours (a page of text alone is grey on white)
    colours = np.unique((img[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 2000
