"""The track of a stereodem DEM, end to end: ``stereodem dem`` and ``stereodem run`` write the
left sensor model's along/cross-track frame (and heading) in the DEM's tags (the ``tags=`` path
of ``pipeline/job.py`` included); ``stereodem coregister`` fits ``along_track`` on it without
``--track-angle``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from helpers.cli_scene import HR, job_toml, write_sim_scene
from pyproj import Geod

from stereodem import cli
from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.post import warp
from stereodem.post.coreg_run import TRACK_HEADING_TAG, CoregJob, load_inputs, track_heading
from stereodem.post.track import TRACK_FRAME_TAG, TrackFrame, track_frame_of
from stereodem.sensor.io.sidecar import load_model


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return write_sim_scene(tmp_path_factory.mktemp("sim"))


@pytest.fixture(scope="module")
def dem_dir(sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("dem") / "out"
    assert (
        cli.main(
            [
                "-q",
                "dem",
                str(sim / "left.tif"),
                str(sim / "right.tif"),
                "-o",
                str(out),
                "--workers",
                "1",
                *HR,
            ]
        )
        == 0
    )
    return out


def _model_rows_cols(sim, dem: DEM, heights):
    """Row and column of the left image that see each cell of ``dem`` at ``heights`` (m)."""
    model = load_model(sim / "left.model.json")
    rr, cc = np.indices(dem.shape)
    x, y = dem.transform @ (cc + 0.5, rr + 0.5)
    lon, lat = geodesy.crs_to_lonlat(x, y, dem.crs)
    col, row = model.project(lon, lat, heights)
    return x, y, np.asarray(row), np.asarray(col)


@pytest.mark.slow
def test_dem_writes_the_sensor_model_track_frame(sim, dem_dir):
    with rasterio.open(dem_dir / "dem.tif") as ds:
        tags = ds.tags()
    assert 0.0 <= float(tags[TRACK_HEADING_TAG]) < 360.0
    frame = TrackFrame.from_tag(tags[TRACK_FRAME_TAG])
    dem = DEM.from_file(dem_dir / "dem.tif")
    assert frame is not None and frame.matches(dem.crs)
    # the frame gives the left model's own row/column of every cell, at the cell's height,
    # to well under a pixel (the polynomial fit over the ~1 km of relief)
    h = np.where(np.isfinite(dem.heights), dem.heights, np.nanmedian(dem.heights))
    x, y, row, col = _model_rows_cols(sim, dem, h)
    along, cross = frame.coords(x, y, h)
    assert np.max(np.abs(along / frame.m_per_row - row)) < 0.01
    assert np.max(np.abs(cross / frame.m_per_col - col)) < 0.05
    # metres per row: the ground distance between the image's first and last rows, per row
    model = load_model(sim / "left.model.json")
    lon, lat = model.localize(
        np.array([149.5, 149.5]), np.array([0.0, 299.0]), np.full(2, frame.height_m)
    )
    per_row = Geod(ellps="WGS84").inv(lon[0], lat[0], lon[1], lat[1])[2] / 299.0
    assert frame.m_per_row == pytest.approx(per_row, rel=0.01)


@pytest.mark.slow
def test_coregister_fits_along_track_on_the_frame_without_track_angle(sim, dem_dir, tmp_path):
    """A 3 m oscillation of 100 image rows injected along the left model's rows (the truth on
    the stereodem DEM's grid, with that DEM's tags, plus 1 m of noise) is found on the frame."""
    dem = DEM.from_file(dem_dir / "dem.tif")
    truth = DEM.from_file(sim / "truth_dem.tif")
    zt = warp.to_grid(
        truth.heights,
        truth.transform,
        truth.crs,
        dem.transform,
        dem.crs,
        dem.shape,
        resampling="cubic",
    )
    _, _, row, _ = _model_rows_cols(sim, dem, zt)
    noise = np.random.default_rng(1).normal(0.0, 1.0, dem.shape)
    z = zt + 3.0 * np.sin(2 * np.pi * row / 100.0) + noise
    with rasterio.open(dem_dir / "dem.tif") as ds:
        tags = ds.tags()
    DEM(z.astype(np.float32), dem.transform, dem.crs, dem.vertical).write(
        tmp_path / "osc.tif", tags=tags
    )
    out = tmp_path / "co"
    assert (
        cli.main(
            [
                "-q",
                "coregister",
                str(tmp_path / "osc.tif"),
                "--ref",
                str(sim / "truth_dem.tif"),
                "--chain",
                "along_track",
                "-o",
                str(out),
                "--no-figures",
            ]
        )
        == 0
    )
    rep = json.loads((out / "coregistration.json").read_text())
    frame = track_frame_of(tmp_path / "osc.tif")
    assert rep["track_frame"]["m_per_row"] == pytest.approx(frame.m_per_row)
    step = rep["steps"][0]
    p = step["parameters"]
    assert p["track"]["source"].startswith("left sensor model")
    assert p["n_sines"] == 1
    assert p["sine1_wavelength"]["value"] == pytest.approx(100.0 * frame.m_per_row, rel=0.005)
    assert p["sine1_amplitude"]["value"] == pytest.approx(3.0, abs=0.1)
    # what is left is the injected noise (NMAD of N(0, 1) = 1)
    assert step["after"]["nmad"] < 1.1 < 2.0 < step["before"]["nmad"]
    # assess --error-analysis --chain reads the same frame from the DEM's tags
    out_a = tmp_path / "assess"
    assert (
        cli.main(
            [
                "-q",
                "assess",
                str(tmp_path / "osc.tif"),
                "--ref",
                str(sim / "truth_dem.tif"),
                "--error-analysis",
                "--chain",
                "along_track",
                "-o",
                str(out_a),
            ]
        )
        == 0
    )
    ea = json.loads((out_a / "report.json").read_text())["error_analysis"]["coregistration"][
        "steps"
    ][0]
    assert ea["parameters"]["track"]["source"].startswith("left sensor model")
    assert ea["parameters"]["sine1_wavelength"]["value"] == pytest.approx(
        100.0 * frame.m_per_row, rel=0.005
    )
    # the same DEM without the tags: along_track needs --track-angle, one line, nothing written
    DEM(z.astype(np.float32), dem.transform, dem.crs, dem.vertical).write(tmp_path / "bare.tif")
    assert (
        cli.main(
            [
                "-q",
                "coregister",
                str(tmp_path / "bare.tif"),
                "--ref",
                str(sim / "truth_dem.tif"),
                "--chain",
                "along_track",
                "-o",
                str(tmp_path / "co2"),
                "--no-figures",
            ]
        )
        == 1
    )
    assert not (tmp_path / "co2").exists()


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_run_writes_the_track_tags_through_the_background_writer(sim, tmp_path):
    """``stereodem run``: ``pipeline/job.py`` passes the track tags to ``DEM.prepare_write``
    (``tags=``), which the background writer puts in ``dem.tif``."""
    out = tmp_path / "run"
    cfg = tmp_path / "job.toml"
    job_toml(cfg, sim, out, extra="[ortho]\nenabled = false\n[run]\nworkers = 1")
    assert cli.main(["-q", "run", str(cfg)]) == 0
    with rasterio.open(out / "dem.tif") as ds:
        tags = ds.tags()
    dem = DEM.from_file(out / "dem.tif")
    frame = TrackFrame.from_tag(tags.get(TRACK_FRAME_TAG))
    assert frame is not None and frame.matches(dem.crs)
    assert 0.0 <= float(tags[TRACK_HEADING_TAG]) < 360.0
    h = np.where(np.isfinite(dem.heights), dem.heights, np.nanmedian(dem.heights))
    x, y, row, _ = _model_rows_cols(sim, dem, h)
    along, _ = frame.coords(x, y, h)
    assert np.max(np.abs(along / frame.m_per_row - row)) < 0.01
    # the heading the tag carries is the left model's (not a default)

    model = load_model(sim / "left.model.json")
    assert float(tags[TRACK_HEADING_TAG]) == pytest.approx(
        track_heading(model, (300, 300)), abs=1e-3
    )


def test_a_frame_for_another_crs_is_not_used(dem_dir, tmp_path):
    """A frame tag that does not match the DEM's CRS (a reprojected file keeps its tags) is
    ignored: the heading is used instead."""
    with rasterio.open(dem_dir / "dem.tif") as ds:
        tags = ds.tags()
    d = DEM.from_file(dem_dir / "dem.tif")
    t = dict(tags)
    f = json.loads(t[TRACK_FRAME_TAG])
    f["crs"] = "EPSG:32636"
    t[TRACK_FRAME_TAG] = json.dumps(f)
    d.write(tmp_path / "moved.tif", tags=t)
    _, _, _, (heading, frame) = load_inputs(
        CoregJob(dem=str(tmp_path / "moved.tif"), ref=str(dem_dir / "dem.tif"))
    )
    assert frame is None and heading == pytest.approx(float(tags[TRACK_HEADING_TAG]), abs=1e-3)
    assert TrackFrame.from_tag("{not json") is None and TrackFrame.from_tag(None) is None


def test_frame_in_a_geographic_crs(sim):
    """The frame works in any map CRS: in lon/lat degrees it still gives the model's rows."""
    model = load_model(sim / "left.model.json")
    frame = TrackFrame.from_model(model, (300, 300), "EPSG:4326", height=2300.0)
    rng = np.random.default_rng(3)
    c, r = rng.uniform(20, 280, 200), rng.uniform(20, 280, 200)
    h = rng.uniform(1800, 2800, 200)
    lon, lat = model.localize(c, r, h)
    along, cross = frame.coords(lon, lat, h)
    assert np.max(np.abs(along / frame.m_per_row - r)) < 0.01
    assert np.max(np.abs(cross / frame.m_per_col - c)) < 0.05
