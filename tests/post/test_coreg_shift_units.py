"""Co-registration shifts on a projected grid are grid metres (the CRS's units, as xdem's): the
reports give the projection's scale factor at the grid centre and, where it differs from 1 by
over 0.1 %, the shift in ground metres (grid metres / k); a polar stereographic grid at 80° N
(k ≈ 0.977) warns, UTM (k ≈ 0.9996) does not, a lon/lat grid has k = 1."""

from __future__ import annotations

import logging

import pytest
from affine import Affine
from pyproj import Geod, Transformer

from stereodem.core.dem import DEM
from stereodem.post import shift_units, warp
from stereodem.post.assess import assess_dem
from stereodem.post.biascorr import NuthKaab
from stereodem.post.coreg import step_line
from stereodem.post.report import html_report, markdown
from stereodem.post.synthetic import InjectedErrors, inject_errors

N = 200
PX = 90.0  # the bundled SRTM tile's cells are ~90 m: its slopes kept on the projected grids
SHIFT = (40.0, -25.0)  # grid metres, x/east and y/north


@pytest.fixture(autouse=True)
def fresh_warnings(monkeypatch):
    """The grid-metres warning is once per CRS per process: each test starts with none said."""
    monkeypatch.setattr(shift_units, "_GROUND_SHIFT_WARNED_CRS", set())


@pytest.fixture(scope="module")
def heights():
    full = DEM.bundled()
    return full, full.heights[100 : 100 + N, 300 : 300 + N].copy()


def _on(crs, lon, lat, heights):
    """The heights on a ``PX`` m grid of ``crs`` centred on ``lon, lat``."""
    x, y = Transformer.from_crs(4326, crs, always_xy=True).transform(lon, lat)
    t = Affine(PX, 0.0, x - PX * N / 2, 0.0, -PX, y + PX * N / 2)
    return DEM(heights, t, crs, "geoid")


def _pair(truth):
    dem, _ = inject_errors(truth, InjectedErrors(dx=SHIFT[0], dy=SHIFT[1], dz=3.0, seed=2))
    return dem


def _fit(truth, caplog):
    with caplog.at_level(logging.WARNING, logger="stereodem.post.warp"):
        nk = NuthKaab().fit(truth, _pair(truth))
    warned = [r for r in caplog.records if "shifts are in CRS units" in r.getMessage()]
    return nk, warned


def test_polar_stereographic_reports_the_scale_factor_and_ground_metres(heights, caplog):
    truth = _on("EPSG:3413", 0.0, 80.0, heights[1])
    h, k = warp.scale_factors(truth.transform, truth.crs, truth.shape)
    # independently: a grid length near the centre over its geodesic length on the ellipsoid
    x0, y0 = truth.transform @ (N / 2, N / 2)
    inv = Transformer.from_crs("EPSG:3413", 4326, always_xy=True)
    for (dx, dy), scale in (((500.0, 0.0), h), ((0.0, 500.0), k)):
        lon, lat = inv.transform([x0 - dx, x0 + dx], [y0 - dy, y0 + dy])
        ground = Geod(ellps="WGS84").inv(lon[0], lat[0], lon[1], lat[1])[2]
        assert 1000.0 / ground == pytest.approx(scale, rel=1e-6)
    assert 0.97 < k < 0.985 and h == pytest.approx(k, rel=1e-9)  # true scale at 70° N

    nk, warned = _fit(truth, caplog)
    p = nk.params
    # the arithmetic is unchanged: the shift is recovered in grid metres (as xdem's)
    assert p["dx"]["value"] == pytest.approx(SHIFT[0], abs=1.0)
    assert p["dy"]["value"] == pytest.approx(SHIFT[1], abs=1.0)
    assert p["scale_factor"] == pytest.approx([h, k], rel=1e-12)
    for name, scale in (("dx", h), ("dy", k)):
        g = p[f"{name}_ground"]
        assert g["value"] == pytest.approx(p[name]["value"] / scale, rel=1e-6)
        assert g["sigma"] == pytest.approx(p[name]["sigma"] / scale, rel=1e-6)
    assert p["horizontal_unit"].startswith("grid metres")
    assert len(warned) == 1 and f"k = {k:.6g}" in warned[0].getMessage()

    # the assessment's summary and its markdown say it too
    a = assess_dem(_pair(truth), truth, coregister=True)
    co = a.report["coregistration"]
    assert co["scale_factor"] == pytest.approx([h, k], rel=1e-12)
    assert co["dx_ground"] == pytest.approx(co["dx"] / h, rel=1e-6)
    assert co["dy_ground"] == pytest.approx(co["dy"] / k, rel=1e-6)
    text = markdown(a.report, {})
    assert f"k = {k:.6g}" in text and f"dx = {co['dx_ground']:.2f} m" in text
    assert "grid metres" in text
    # dx/dy are along the grid's axes, turned from true east/north on a polar grid: the
    # markdown (and HTML) say so, not "m east"/"m north"; the JSON keeps dx/dy
    said = f"dx = {co['dx']:.2f} m along x (grid east), dy = {co['dy']:.2f} m along y (grid north)"
    assert said in text and "m east" not in text and "m north" not in text
    assert said in html_report(a.report, {})


def test_the_warning_is_once_per_crs(heights, caplog):
    """Two fits on one polar grid (a mosaic's DEMs) warn once; another CRS warns again."""
    first = _on("EPSG:3413", 0.0, 80.0, heights[1])
    second = _on("EPSG:3413", 60.0, 79.0, heights[1])  # same CRS, another grid centre
    nk1, warned1 = _fit(first, caplog)
    caplog.clear()
    nk2, warned2 = _fit(second, caplog)
    assert len(warned1) == 1 and not warned2
    # each fit's record still has its own grid's scale factor and ground metres
    assert nk1.params["scale_factor"] != nk2.params["scale_factor"]
    assert "dx_ground" in nk1.params and "dx_ground" in nk2.params
    caplog.clear()
    _, warned3 = _fit(_on("EPSG:3031", 0.0, -80.0, heights[1]), caplog)
    assert len(warned3) == 1 and "said once per CRS" in warned3[0].getMessage()


def test_utm_scale_factor_is_near_one_without_warning(heights, caplog):
    truth = _on("EPSG:32637", 39.3, 40.0, heights[1])
    nk, warned = _fit(truth, caplog)
    h, k = nk.params["scale_factor"]
    assert 0.9996 <= h <= 1.0004 and 0.9996 <= k <= 1.0004
    assert not warned
    assert "dx_ground" not in nk.params and "dy_ground" not in nk.params
    assert nk.params["dx"]["value"] == pytest.approx(SHIFT[0], abs=1.0)


def test_geographic_scale_factor_is_one(heights, caplog):
    full, z = heights
    truth = DEM(z, full.transform @ Affine.translation(300, 100), full.crs, "geoid")
    assert warp.scale_factors(truth.transform, truth.crs, truth.shape) == (1.0, 1.0)
    nk, warned = _fit(truth, caplog)
    assert nk.params["scale_factor"] == [1.0, 1.0] and not warned
    assert nk.params["horizontal_unit"].startswith("ground metres")
    assert "dx_ground" not in nk.params


def test_a_steps_result_line_says_its_metres_on_a_projected_grid(heights, caplog):
    """``step_line`` (the line ``coregister`` and ``assess`` print for a step) gives the shift
    along the grid's axes with σ, then the grid-metres note with the ground metres, which are
    not listed a second time among the parameters."""
    truth = _on("EPSG:3413", 0.0, 80.0, heights[1])
    nk, _ = _fit(truth, caplog)
    stats = {"nmad": 1.0, "median": 0.5, "n": 10}
    line = step_line(
        {"step": "nuth_kaab", "parameters": nk.params, "before": stats, "after": stats}
    )
    p = nk.params
    assert line.startswith("nuth_kaab: stable NMAD 1.000 -> 1.000 m (median +0.500 m, n=10); ")
    assert f"dx = {p['dx']['value']:+.3f} ± {p['dx']['sigma']:.3f} m along x (grid east)" in line
    assert line.endswith(shift_units.shift_units(p))
    assert f"dx = {p['dx_ground']['value']:.2f} m" in line  # in the note
    assert "dx_ground" not in line and "scale_factor" not in line
