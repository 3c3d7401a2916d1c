"""Hostile inputs, tenth round (session 33): the job TOML's numeric keys and the ``[matching]
options`` / ``[rectification] sparse_options`` tables swept with NaN, infinity, -1, 0, 1e308,
99999999999 and text on the 300 x 300 simulated scene.

* ``sparse_options = {n_features = 99999999999}`` was OpenCV's traceback (SIFT's C int); SGBM's
  ``sgm_speckle_range``, ``sgm_uniqueness`` and an ``lr_tolerance`` of 1e30 failed every tile
  with "integer won't fit into a C int", reported as "no point was matched in any tile (no
  texture, or a wrong height range?)". Whole numbers handed to OpenCV are now bounded by its
  int, the uniqueness margin is a percentage, and a run whose every tile failed says the
  tiles' error.
* ``[refinement] sigma = 1e6`` took 10 GB and minutes in one Gaussian kernel, ``[fill]
  smooth_sigma = 1e308`` and ``[filters] erode = 99999999999`` were ValueError tracebacks,
  ``[rectification] halo = [1000, 1000]`` and ``disparity_margin = 1e6`` ran for minutes,
  ``[gridding] gaussian_sigma = 1e6`` failed every tile, a ``window`` wider than OpenCV's 255
  matched nothing, ``sparse_options n_heights`` 99999999999 was "out of memory", and
  ``[jitter] max_frequency = 1e308`` a LinAlgError after the first DEM.
* ``[run] tile_timeout = 1e-300`` fired before the tile's ``try`` (a TileTimeout traceback);
  ``[uncertainty] sigma = {roll_bias = 1e308}`` overflowed squaring it (a traceback), and
  ``samples = 99999999999`` ended "out of memory" (the command line took 3 samples, the
  TOML 10: one rule now, 10..100000).
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from helpers.cli_scene import HR, assert_clear_error, job_toml, run_cli, write_sim_scene

from stereodem.core.errors import InputError
from stereodem.post.filters import border_rim
from stereodem.sensor.estimation.jitter import SineSeries, fit_sum_of_sines, with_attitude_sines
from stereodem.sensor.io.sidecar import load_model
from stereodem.stereo.grid import MAX_SIGMA_POSTINGS, GridSpec
from stereodem.stereo.pipeline import no_point_matched
from stereodem.stereo.refine import _smooth_fill
from stereodem.stereo.runner import TileFailure
from stereodem.stereo.settings import StereoSettings
from stereodem.stereo.tiling import Tile

BIG = 99999999999


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return write_sim_scene(tmp_path_factory.mktemp("sim"))


def test_the_bounds_keep_what_a_user_would_set(sim, tmp_path, capsys):
    """The largest values still allowed run (not refused at the edge of the rule)."""
    cfg = job_toml(
        tmp_path / "job.toml",
        sim,
        tmp_path / "out",
        rect="tile_size = 300\nheight_range = [1000, 3500]\nhalo = [300, 40]\n"
        "disparity_margin = 20\nheight_margin = 10000",
        extra="[matching]\nmatcher = 'sgm'\noptions = {sgm_uniqueness = 15, "
        "sgm_speckle_range = 1000000}\n[refinement]\nsigma = 100\n[fill]\nsmooth_sigma = 2\n"
        "[ortho]\nenabled = false\n[assess]\nenabled = false",
    )
    code, _, err = run_cli(capsys, ["run", cfg])
    assert code == 0, err
    assert (tmp_path / "out" / "dem.tif").exists()


def test_a_jitter_band_beyond_the_line_rate_is_refused_before_the_first_dem(sim, tmp_path, capsys):
    cfg = job_toml(
        tmp_path / "job.toml",
        sim,
        tmp_path / "out",
        extra="[jitter]\nenabled = true\naxes = 'roll'\nmax_frequency = 1e308",
    )
    code, _, err = run_cli(capsys, ["run", cfg])
    assert_clear_error(code, err, "run", r"max_frequency\) of 1e\+308 Hz.*half the line rate")
    assert not list((tmp_path / "out").glob("*.tif"))


def test_an_erosion_wider_than_the_dem_removes_it_all_with_a_clear_error(sim, tmp_path, capsys):
    cfg = job_toml(tmp_path / "job.toml", sim, tmp_path / "out", extra=f"[filters]\nerode = {BIG}")
    code, _, err = run_cli(capsys, ["run", cfg])
    assert_clear_error(code, err, "run", r"border rim .* removed all .* smaller --erode")


@pytest.mark.parametrize("cells", [0, 1, 2, 5, 64, 65, 100, BIG])
def test_the_border_rim_is_the_erosion_by_a_square_at_any_width(cells):
    """Up to 64 cells OpenCV's erosion, wider the chessboard distance: the same cells (and
    no kernel of 2 x 99999999999 + 1 cells)."""
    rng = np.random.default_rng(cells % 1000)
    z = rng.normal(size=(150, 260))
    z[rng.random(z.shape) < 0.002] = np.nan
    z[40:60, 100:190] = np.nan
    valid = np.isfinite(z).astype(np.uint8)
    k = 2 * min(cells, 300) + 1  # wider than the grid: the same as the grid's width
    expected = (valid == 1) & (cv2.erode(valid, np.ones((k, k), np.uint8), borderValue=0) == 0)
    got = border_rim(z, cells)
    assert np.array_equal(got, expected)
    assert (cells == 0) != got.any() and (cells < 75 or got.sum() == valid.sum())


def test_the_refinement_warp_wider_than_the_map_is_its_widest_smoothing():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(64, 80)).astype(np.float32)
    d[10:20, 10:30] = np.nan
    t0 = time.process_time()
    wide = _smooth_fill(d, 1e6)
    assert time.process_time() - t0 < 60  # (was 10 GB and minutes: no kernel 8e6 px wide)
    assert np.array_equal(wide, _smooth_fill(d, max(d.shape)))
    assert np.isfinite(wide).all()


def test_the_gridding_gaussian_is_bounded_in_postings():
    spec = GridSpec.from_bounds((0, 0, 300, 300), 30.0, 32633, sigma=MAX_SIGMA_POSTINGS * 30.0)
    assert spec.sigma == 300.0
    assert GridSpec.from_bounds((0, 0, 300, 300), 30.0, 32633, sigma=3.0).sigma == 3.0
    for sigma in (MAX_SIGMA_POSTINGS * 30.0 + 1, 1e6, 0.0, 1e-300, 2.9, -1.0, float("nan")):
        with pytest.raises(InputError, match="gaussian_sigma"):
            GridSpec.from_bounds((0, 0, 300, 300), 30.0, 32633, sigma=sigma)


def test_a_pair_whose_every_tile_failed_says_the_tiles_error():
    tiles = [Tile(0, 0, 100, 100, index=0), Tile(100, 0, 100, 100, index=1)]
    failures = [TileFailure(t, "ValueError: integer won't fit into a C int") for t in tiles]
    err = no_point_matched(tiles, StereoSettings(), failures)
    assert "every tile failed (2)" in str(err) and "C int" in str(err)
    # some tiles ran: the likely causes, with the matching options given
    settings = StereoSettings()
    settings.matching.options = {"min_std": 1e30}
    err = no_point_matched(tiles, settings, failures[:1])
    assert "no point was matched" in str(err) and "min_std = 1e+30" in str(err)
    assert "[matching] options" not in str(no_point_matched(tiles, StereoSettings()))


def test_a_tile_timeout_that_fires_at_once_is_each_tiles_timeout(sim, tmp_path, capsys):
    """1e-300 s: the timer fired before the tile's try block (a TileTimeout traceback); now
    every tile times out and the run says so."""
    cfg = job_toml(
        tmp_path / "job.toml", sim, tmp_path / "out", extra="[run]\ntile_timeout = 1e-300"
    )
    code, _, err = run_cli(capsys, ["run", cfg])
    assert_clear_error(code, err, "run", r"every tile failed .*timed out after 1e-300 s")


@pytest.mark.parametrize("res", ["1e-300", "5e-324"])
def test_a_posting_too_fine_for_any_number_is_refused(res, sim, tmp_path, capsys):
    """5e-324 made the lattice's bounds NaN, which passed the memory check (a ValueError
    traceback converting its size); 1e-300 warned of an overflow before its refusal."""
    left, right = sim / "left.tif", sim / "right.tif"
    code, _, err = run_cli(capsys, ["dem", left, right, "-o", tmp_path / "d", "--res", res, *HR])
    assert_clear_error(code, err, "dem", r"DEM lattice .*choose a coarser --res")
    assert "Warning" not in err
    code, _, err = run_cli(
        capsys,
        ["ortho", left, "--dem", sim / "truth_dem.tif", "-o", tmp_path / "o.tif", "--res", res],
    )
    assert_clear_error(code, err, "ortho", r"orthoimage grid .*choose a coarser --res")
    assert "Warning" not in err


@pytest.mark.parametrize("res", ["1e-30", "5e-324"])
def test_a_mosaic_posting_beyond_gdals_largest_raster_is_refused(res, sim, tmp_path, capsys):
    """1e-30 streamed its blocks for ever, 5e-324 was a ValueError."""
    dem = sim / "truth_dem.tif"
    argv = ["mosaic", dem, "-o", tmp_path / "m.tif", "--res", res]
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(code, err, "mosaic", r"beyond GDAL's largest raster.*coarser --res")
    assert not (tmp_path / "m.tif").exists()


@pytest.mark.parametrize(
    "body, pattern",
    [
        # a ZeroDivisionError in every tile
        ("[gridding]\ngaussian_sigma = 1e-300", r"gaussian_sigma must be 0\.1 to 10 postings"),
        # every point dropped by the ray-gap limit: it read "no point was matched"
        ("[gridding]\nmax_ray_gap = 1e-300", r"matched \d+ point\(s\) but kept none.*max_ray_gap"),
        # sines flat over the image, fitted with amplitudes of radians: the corrected model
        # pointed elsewhere and the run ended "the two images do not overlap" (and SciPy
        # 1.10's Lomb-Scargle aborted the process)
        (
            "[jitter]\nenabled = true\naxes = 'roll'\nmin_frequency = 5e-324\n"
            "max_frequency = 1e-300",
            r"min_frequency\) of 4\.9\d*e-324 Hz is slower than .* not an oscillation",
        ),
    ],
)
def test_tiny_values_are_refused_for_what_they_are(body, pattern, sim, tmp_path, capsys):
    cfg = job_toml(tmp_path / "job.toml", sim, tmp_path / "out", extra=body)
    code, _, err = run_cli(capsys, ["run", cfg])
    assert_clear_error(code, err, "run", pattern)


def test_an_attitude_oscillation_beyond_10_mrad_is_no_oscillation(sim):
    """The rule of every model with attitude sines (the simulator's and a jitter fit's)."""
    model = load_model(sim / "right.model.json")
    series = SineSeries(np.array([0.02]), np.array([1.0]), np.array([0.0]))
    with pytest.raises(InputError, match=r"0\.02 rad \(roll\) is beyond 0\.01 rad"):
        with_attitude_sines(model, series, axis="roll")
    ok = SineSeries(np.array([0.01]), np.array([1.0]), np.array([0.0]))
    assert with_attitude_sines(model, ok, axis="roll") is not None
    with pytest.raises(InputError, match=r"slower than .* not an oscillation"):
        fit_sum_of_sines(np.linspace(0, 1, 50), np.zeros(50), f_range=(1e-4, 1.0))
