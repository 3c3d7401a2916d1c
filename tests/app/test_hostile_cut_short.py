"""Hostile inputs, fifth round (session 26): a user's mistakes that still gave a wrong or
misleading message, or a wrong product.

* a GeoTIFF cut short (a partial download or copy: its first 1000 bytes, or 60 % of it)
  given as a DEM, an image, a land-cover raster or a texture: it said "the DEM has no CRS"
  (its GeoTIFF keys were cut off with its pixels) or "Read failed. See previous exception for
  details.", and a reference DEM cut short in the middle stopped ``stereodem run`` only at the
  assessment, after the DEM and the orthoimages had been made;
* an existing output folder that cannot be written was named as ``FOLDER/x``, a file the user
  never gave;
* ``adjust --alpha 2`` (a significance level outside 0..1) turned data snooping off without a
  word ("outliers: none"); ``simulate --noise nan`` or ``-5`` rendered noiseless images while
  ``scene.json`` recorded the value asked for.

Each error case asserts exit status 1, exactly one ``stereodem CMD: error:`` line naming the
culprit, no traceback, and nothing written.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import rasterio
from helpers.cli_scene import HR, assert_clear_error, job_toml, run_cli, write_sim_scene

from stereodem.core import raster
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.post.biascorr import AlongTrack
from stereodem.post.clouds import CloudSettings
from stereodem.sensor.estimation.adjust import gauss_markov, reliability
from stereodem.sensor.estimation.adjust.bundle import bundle_adjust
from stereodem.sensor.estimation.adjust.bundle_multi import bundle_adjust_images

CUT = r"cut short or damaged"


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return write_sim_scene(tmp_path_factory.mktemp("sim"))


@pytest.fixture(scope="module")
def srtm(tmp_path_factory):
    """``ref.tif``: 300 x 300 cells of the bundled SRTM tile (4 blocks), and ``head.tif`` /
    ``part.tif``, its first 1000 bytes and its first 60 %: for the DEM-only commands, without
    the simulated scene."""
    d = tmp_path_factory.mktemp("srtm")
    full = DEM.bundled()
    DEM(full.heights[:300, :300].copy(), full.transform, full.crs, "geoid").write(d / "ref.tif")
    b = (d / "ref.tif").read_bytes()
    (d / "head.tif").write_bytes(b[:1000])
    (d / "part.tif").write_bytes(b[: len(b) * 6 // 10])
    return d


@pytest.fixture(scope="module")
def cut(sim, tmp_path_factory):
    """``head.tif``: the first 1000 bytes of the scene's true DEM (475 x 423 cells, 4 blocks);
    ``part.tif``: its first 60 % (header and georeferencing intact, pixels cut);
    ``left_part.tif``: the left image cut the same way (with its model side-car)."""
    d = tmp_path_factory.mktemp("cut")
    dem = (sim / "truth_dem.tif").read_bytes()
    (d / "head.tif").write_bytes(dem[:1000])
    (d / "part.tif").write_bytes(dem[: len(dem) * 6 // 10])
    shutil.copy(sim / "truth_dem.tif.aux.xml", d / "part.tif.aux.xml")
    img = (sim / "left.tif").read_bytes()
    (d / "left_part.tif").write_bytes(img[: len(img) * 6 // 10])
    shutil.copy(sim / "left.model.json", d / "left_part.model.json")
    return d


def _argv(command, s, bad, t):
    """``command`` given ``bad`` where a DEM (or raster) is read, writing under ``t/out``;
    ``s`` the folder of ``ref.tif`` (or of the simulated scene)."""
    ref, out = s / "ref.tif", t / "out"
    return {
        "filter": ["filter", bad, "-o", out / "f.tif"],
        "assess_dem": ["assess", bad, "--ref", ref, "-o", out],
        "assess_ref": ["assess", ref, "--ref", bad, "-o", out],
        "assess_landcover": ["assess", ref, "--ref", ref, "--landcover", bad, "-o", out],
        "coregister": ["coregister", ref, "--ref", bad, "-o", out],
        "change": ["change", ref, bad, "-o", out],
        "mosaic": ["mosaic", ref, bad, "-o", out / "m.tif"],
        "stack": ["stack", ref, bad, "--ref", ref, "--dates", "2020-01-01,2021-01-01", "-o", out],
        "simulate_dem": ["simulate", "--dem", bad, "--size", "64", "64", "-o", out],
        "simulate_texture": ["simulate", "--texture", bad, "--size", "64", "64", "-o", out],
        "ortho": ["ortho", s / "left.tif", "--dem", bad, "-o", out / "o.tif"],
        "uncertainty": [
            *("uncertainty", s / "left.tif", "--dem", bad, "--sigma", "dem_height=5", "-o", out)
        ],
        "dem_seed": ["dem", s / "left.tif", s / "right.tif", "--seed-dem", bad, "-o", out],
    }[command]


#: the commands that read a DEM (or a raster onto a map grid) alone, and those that also
#: need the simulated pair's images
DEM_ONLY = [
    "filter",
    "assess_dem",
    "assess_ref",
    "assess_landcover",
    "coregister",
    "change",
    "mosaic",
    "stack",
    "simulate_dem",
    "simulate_texture",
]
WITH_IMAGES = ["ortho", "uncertainty", "dem_seed"]


def _check_cut(command, argv, which, tmp_path, capsys):
    code, _, err = run_cli(capsys, [*argv, "--workers", "1"])
    assert_clear_error(code, err, command.split("_")[0], rf"{which}: cannot read .*{CUT}")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("which", ["head.tif", "part.tif"])
@pytest.mark.parametrize("command", DEM_ONLY)
def test_a_raster_cut_short_is_one_line_naming_it(command, which, srtm, tmp_path, capsys):
    # before: "head.tif: the DEM has no CRS"; "part.tif: cannot read the DEM (Read failed. See
    # previous exception for details.)", and stack left a partial stack.zarr and stack.json
    _check_cut(command, _argv(command, srtm, srtm / which, tmp_path), which, tmp_path, capsys)


@pytest.mark.slow
@pytest.mark.parametrize("which", ["head.tif", "part.tif"])
@pytest.mark.parametrize("command", WITH_IMAGES)
def test_a_dem_cut_short_beside_images_is_one_line(command, which, sim, cut, tmp_path, capsys):
    _check_cut(command, _argv(command, sim, cut / which, tmp_path), which, tmp_path, capsys)


@pytest.mark.slow
@pytest.mark.parametrize("command", ["dem", "ortho"])
def test_an_image_cut_short_is_one_line_naming_it(command, sim, cut, tmp_path, capsys):
    bad = cut / "left_part.tif"
    argv = {
        "dem": ["dem", bad, sim / "right.tif", "-o", tmp_path / "out", *HR],
        "ortho": ["ortho", bad, "--dem", sim / "truth_dem.tif", "-o", tmp_path / "out" / "o.tif"],
    }[command]
    code, _, err = run_cli(capsys, [*argv, "--workers", "1"])
    assert_clear_error(code, err, command, rf"left_part.tif: cannot read the image: .*{CUT}")
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_run_refuses_a_reference_dem_cut_short_before_any_work(sim, cut, tmp_path, capsys):
    # before: the stereo, filter and orthoimage stages ran, and the job failed at the
    # assessment with "Read failed. See previous exception for details."
    toml = job_toml(
        tmp_path / "job.toml", sim, tmp_path / "out", inputs=f'reference_dem = "{cut}/part.tif"'
    )
    code, _, err = run_cli(capsys, ["run", toml, "--workers", "1"])
    assert_clear_error(code, err, "run", rf"part.tif: cannot read the DEM: .*{CUT}")
    assert not (tmp_path / "out").exists()


def test_probe_blocks_reads_two_blocks_only(srtm, monkeypatch):
    """The check costs two block reads whatever the raster's size."""
    reads = []
    with rasterio.open(srtm / "ref.tif") as ds:
        real = ds.read
        monkeypatch.setattr(ds, "read", lambda *a, **k: reads.append(k["window"]) or real(*a, **k))
        raster.probe_blocks(ds)
        assert len(reads) == 2
        (r0, r1), (c0, c1) = reads[1]
        assert (r1, c1) == (ds.height, ds.width)  # the last block


@pytest.mark.parametrize("command", ["change", "assess", "simulate"])
def test_an_output_folder_that_cannot_be_written_is_named_itself(
    command, srtm, tmp_path, capsys, monkeypatch
):
    # before: "OUT/x: cannot be created (OUT is not a writable folder: ...)"; a read-only
    # folder is simulated (the tests may run as root, which may write anywhere)
    out = tmp_path / "out"
    out.mkdir()

    def read_only(*a, **k):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(raster.tempfile, "mkstemp", read_only)
    ref = srtm / "ref.tif"
    argv = {
        "change": ["change", ref, srtm / "part.tif", "-o", out],
        "assess": ["assess", ref, "--ref", ref, "-o", out],
        "simulate": ["simulate", "--size", "64", "64", "-o", out],
    }[command]
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(code, err, command, r"out: folder is not writable \(Read-only file system")
    assert "/x" not in err
    assert list(out.iterdir()) == []


@pytest.mark.parametrize("alpha", [2.0, 0.0, float("nan"), -0.1])
def test_adjust_alpha_outside_0_1_is_refused(alpha):
    # before: `adjust --alpha 2` exited 0 saying "outliers: none" (every threshold NaN) and
    # wrote its model; the thresholds of every adjustment (one image, pair, N images) refuse it
    for f in (reliability.noncentrality, reliability.baarda_threshold):
        with pytest.raises(InputError, match=r"alpha .* between 0 and 1"):
            f(alpha)
    with pytest.raises(InputError, match=r"alpha .* between 0 and 1"):
        reliability.pope_threshold(alpha, 10)
    with pytest.raises(InputError, match=r"power .* between 0 and 1"):
        reliability.noncentrality(0.001, 1.5)


@pytest.mark.slow
def test_adjust_cli_alpha_2_writes_nothing(sim, tmp_path, capsys):
    argv = ["adjust", sim / "left.tif", "--gcps", sim / "points.csv", "--model", "rpc-shift"]
    code, _, err = run_cli(capsys, [*argv, "-o", tmp_path / "m.json", "--alpha", "2"])
    assert_clear_error(code, err, "adjust", r"alpha .* between 0 and 1")
    assert not (tmp_path / "m.json").exists()


@pytest.mark.parametrize("n", [-1, -2, 1.5])
def test_adjust_max_iterations_below_0_or_fractional_is_refused(n):
    # before: `adjust --max-iterations -1` exited 0 with an adjusted model and its report (one
    # unchecked Gauss-Newton step); 0 stays the initial model's statistics, nothing estimated
    A = np.eye(2)

    def evaluate(x):
        return A @ x - 1.0, A

    with pytest.raises(InputError, match=r"max_iterations must be a whole number from 0 to"):
        gauss_markov.solve(evaluate, np.zeros(2), ["a", "b"], max_iterations=n)
    with pytest.raises(InputError, match=r"max_iterations must be a whole number"):
        bundle_adjust(None, None, np.zeros((0, 4)), max_iterations=n)  # a pair
    with pytest.raises(InputError, match=r"max_iterations must be a whole number"):
        bundle_adjust_images([None, None], None, max_iterations=n)  # N images
    sol = gauss_markov.solve(evaluate, np.zeros(2), ["a", "b"], max_iterations=0)
    assert np.all(sol.x == 0) and sol.iterations == 0  # evaluated at x0, nothing estimated


@pytest.mark.parametrize("seconds", ["inf", "1e12", "nan", "0"])
def test_a_tile_timeout_that_is_no_number_of_seconds_is_refused(seconds, tmp_path, capsys):
    # before: --tile-timeout inf ended in a traceback from the tile's alarm timer ("timestamp
    # out of range for platform time_t")
    argv = ["dem", tmp_path / "l.tif", tmp_path / "r.tif", "-o", tmp_path / "d.tif"]
    code, _, err = run_cli(capsys, [*argv, f"--tile-timeout={seconds}"])
    assert_clear_error(code, err, "dem", r"tile_timeout must be a positive number of seconds")


def test_a_negative_seed_is_refused(sim, tmp_path, capsys):
    # before: NumPy's traceback ("ValueError: expected non-negative integer"), in `simulate`
    # and in `uncertainty`'s Monte Carlo; one rule now (core.stats.generator)
    out = tmp_path / "s"
    code, _, err = run_cli(capsys, ["simulate", "--size", "64", "64", "--seed=-1", "-o", out])
    assert_clear_error(code, err, "simulate", r"seed must be a whole number >= 0, got -1")
    assert not out.exists()
    argv = ["uncertainty", sim / "left.tif", "--dem", sim / "truth_dem.tif"]
    argv += ["--sigma", "roll_bias=1e-5", "--seed=-1", "-o", tmp_path / "u"]
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(code, err, "uncertainty", r"seed must be a whole number >= 0, got -1")


def test_filter_cloud_grow_below_0_is_refused_without_a_cloud_sign(srtm, tmp_path, capsys):
    # before: taken without a word when no --cloud-* sign made a mask (stack refused it)
    argv = ["filter", srtm / "ref.tif", "-o", tmp_path / "f.tif", "--cloud-grow=-1"]
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(code, err, "filter", r"cloud grow must be >= 0 cells, got -1")
    assert not (tmp_path / "f.tif").exists()


@pytest.mark.parametrize("radiance", [float("nan"), -1.0, 0.0])
def test_a_cloud_radiance_threshold_that_is_no_radiance_is_refused(radiance):
    # before: NaN compared false with every radiance (the sign off without a word)
    with pytest.raises(InputError, match=r"cloud max_radiance must be positive"):
        CloudSettings(max_radiance=radiance)


@pytest.mark.parametrize("angle", ["nan", "inf"])
def test_a_track_angle_that_is_no_angle_is_refused_by_the_library(angle, srtm):
    # before: a traceback from the along-track step ("negative dimensions are not allowed":
    # the profile's bin count from a NaN heading)
    ref = DEM.from_file(srtm / "ref.tif")
    dem = DEM(ref.heights + 2.0, ref.transform, ref.crs, ref.vertical)
    with pytest.raises(
        InputError, match=rf"heading must be a finite angle in degrees, got {angle}"
    ):
        AlongTrack().fit(ref, dem, track_angle_deg=float(angle))


@pytest.mark.parametrize("command", ["assess", "coregister", "change", "stack"])
@pytest.mark.parametrize("angle", ["nan", "inf", "-inf", "north"])
def test_a_track_angle_that_is_no_angle_is_refused_before_any_work(
    command, angle, srtm, tmp_path, capsys
):
    # before: NaN or infinity taken without a word where the chain had no along/cross-track
    # step (assess, coregister, stack with their default chains), a traceback where it had
    argv = {
        "assess": ["assess", srtm / "ref.tif", "--ref", srtm / "ref.tif"],
        "coregister": ["coregister", srtm / "ref.tif", "--ref", srtm / "ref.tif"],
        "change": ["change", srtm / "ref.tif", srtm / "ref.tif"],
        "stack": ["stack", srtm / "ref.tif", srtm / "ref.tif", "--ref", srtm / "ref.tif"],
    }[command]
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:  # a usage error, as argparse reports every one
        run_cli(capsys, [*argv, f"--track-angle={angle}", "-o", out])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" not in err
    assert f"stereodem {command}: error: argument --track-angle: " in err
    assert ("finite number of degrees" if angle != "north" else "heading in degrees") in err
    assert not out.exists()


@pytest.mark.parametrize("noise", ["nan", "-5", "inf"])
def test_simulate_noise_not_a_standard_deviation_is_refused(noise, tmp_path, capsys):
    # before: exit 0, noiseless images, scene.json saying noise NaN / -5
    out = tmp_path / "s"
    argv = ["simulate", "--size", "64", "64", f"--noise={noise}", "-o", out]
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(code, err, "simulate", r"noise must be a standard deviation from 0 to")
    assert not out.exists()


@pytest.mark.parametrize(
    "command, what",
    [("filter", "clean DEM"), ("mosaic", "mosaic"), ("ortho", "orthoimage")],
)
def test_a_geotiff_output_without_tif_is_refused(command, what, sim, srtm, tmp_path, capsys):
    """``ortho -o o3413`` wrote a GeoTIFF named ``o3413`` (``filter`` too); ``mosaic`` refused
    such a name. One rule for the three commands that write a GeoTIFF file: named .tif."""
    out = tmp_path / "out" / "product"
    argv = {
        "filter": ["filter", srtm / "ref.tif", "-o", out],
        "mosaic": ["mosaic", srtm / "ref.tif", srtm / "ref.tif", "-o", out],
        "ortho": ["ortho", sim / "left.tif", "--dem", sim / "truth_dem.tif", "-o", out],
    }[command]
    code, _, err = run_cli(capsys, [*argv, "--workers", "1"])
    assert_clear_error(code, err, command, rf"product: the {what} is a GeoTIFF; name it \.tif")
    assert not (tmp_path / "out").exists()
