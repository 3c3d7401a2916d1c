"""Hostile inputs, crashes and concurrency (issue #16): every case ends either in a clear
one-line error (exit status 1, ``stereodem CMD: error: ...`` on stderr, no traceback, no
partial or stale output) or in a correct product.

The scene is a small simulated ASTER-like pair, built once per module; the derived hostile
files (constant images, a 16-bit image, seed DEMs elsewhere or in feet, a huge declared image,
binary files, bad TOML files) are made from it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
from helpers.cli_scene import HR, assert_clear_error, job_toml, run_cli, write_sim_scene

from stereodem import cli
from stereodem.core import jsonutil
from stereodem.core.errors import InputError, OutputExistsError
from stereodem.outlock import (
    LOCK_NAME,
    PROBE_PREFIX,
    REMOVING_PREFIX,
    OutputLock,
    OutputLockedError,
    Products,
    output_folder,
    remove_products,
)
from stereodem.sensor.io.sidecar import load_image_model
from stereodem.stereo.plan import base_to_height
from stereodem.stereo.runner import run_tiles
from stereodem.stereo.sanity import MIN_BASE_TO_HEIGHT, check_texture
from stereodem.stereo.tiling import Tile

# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return write_sim_scene(tmp_path_factory.mktemp("sim"))


def _copy_image(src: Path, dst: Path, data, dtype=None):
    """``dst``: ``src`` with other pixel values (same metadata) and ``src``'s model sidecar."""
    with rasterio.open(src) as ds:
        prof, tags, rpcs = ds.profile, ds.tags(), ds.rpcs
    prof.update(dtype=dtype or prof["dtype"])
    with rasterio.open(dst, "w", **prof, rpcs=rpcs) as out:
        out.write(np.asarray(data).astype(prof["dtype"])[None])
        out.update_tags(**{**tags, "STEREODEM_MODEL": f"{dst.stem}.model.json"})
    shutil.copy(src.with_name(f"{src.stem}.model.json"), dst.with_name(f"{dst.stem}.model.json"))
    return dst


@pytest.fixture(scope="module")
def hostile(sim, tmp_path_factory):
    """Derived hostile files, by name."""
    d = tmp_path_factory.mktemp("hostile")
    left = sim / "left.tif"
    with rasterio.open(left) as ds:
        img = ds.read(1)
    f = {}
    f["zeros"] = _copy_image(left, d / "zeros.tif", np.zeros_like(img))
    f["constant"] = _copy_image(left, d / "constant.tif", np.full_like(img, 117))
    f["left16"] = _copy_image(left, d / "left16.tif", img.astype(np.uint16) * 257, "uint16")
    with rasterio.open(sim / "truth_dem.tif") as ds:
        prof, z = ds.profile, ds.read(1)
    far = dict(prof, transform=prof["transform"] @ rasterio.Affine.translation(40000, 0))
    with rasterio.open(d / "seed_far.tif", "w", **far) as out:  # ~600 km east of the scene
        out.write(z[None])
    with rasterio.open(d / "seed_feet.tif", "w", **prof) as out:
        out.write((z * 3.28084)[None].astype(prof["dtype"]))
    # a GeoTIFF declaring 200 000 x 200 000 pixels (sparse: the file itself is tiny)
    with rasterio.open(
        d / "huge.tif",
        "w",
        driver="GTiff",
        width=200_000,
        height=200_000,
        count=1,
        dtype="uint8",
        tiled=True,
        compress="deflate",
        SPARSE_OK=True,
    ) as out:
        pass
    shutil.copy(sim / "left.model.json", d / "huge.model.json")
    f["huge"] = d / "huge.tif"
    f["binary"] = d / "binary.bin"
    f["binary"].write_bytes(bytes(range(256)) * 64)
    f["seed_far"], f["seed_feet"] = d / "seed_far.tif", d / "seed_feet.tif"
    f["a_file"] = d / "a_file.txt"
    f["a_file"].write_text("not a folder\n")
    return f


# ----------------------------------------------------------------------------- helpers


def _sha(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _read(path):
    with rasterio.open(path) as ds:
        return ds.read(1), ds.transform


# ------------------------------------------------------------------------ fast: checked before work


def _dem(sim, out, *extra):
    return ["dem", sim / "left.tif", sim / "right.tif", "-o", out, "--workers", "1", *extra]


def _adjust(t, model="rpc-shift", *image2):
    return ["adjust", t / "in.tif", *image2, "--gcps", t / "gcps.csv", "--model", model]


BEFORE_WORK = {
    # id: (argv builder(sim, hostile, tmp), command, message pattern)
    "out_under_regular_file": (
        lambda s, h, t: _dem(s, h["a_file"] / "out", *HR),
        "dem",
        r"not a (writable )?folder|cannot be created",
    ),
    "out_under_proc": (
        lambda s, h, t: _dem(s, "/proc/stereodem_test/out", *HR),
        "dem",
        r"cannot be created|not a writable folder",
    ),
    "declared_image_200000_squared": (
        lambda s, h, t: ["dem", h["huge"], s / "right.tif", "-o", t / "out", *HR],
        "dem",
        r"memory|too large",
    ),
    "res_0.001_absurd_lattice": (
        lambda s, h, t: _dem(s, t / "out", "--res", "0.001", *HR),
        "dem",
        r"lattice|cells",
    ),
    "res_negative": (lambda s, h, t: _dem(s, t / "out", "--res", "-30", *HR), "dem", r"--res"),
    "tile_size_0": (
        lambda s, h, t: _dem(s, t / "out", "--tile-size", "0", *HR),
        "dem",
        r"tile_size",
    ),
    "tile_timeout_negative": (
        lambda s, h, t: _dem(s, t / "out", "--tile-timeout", "-5", *HR),
        "dem",
        r"tile_timeout",
    ),
    "workers_0": (lambda s, h, t: _dem(s, t / "out", "--workers", "0", *HR), "dem", r"workers"),
    "height_range_inverted": (
        lambda s, h, t: _dem(s, t / "out", "--height-range", "3500", "1000"),
        "dem",
        r"height.range",
    ),
    "same_image_twice_zero_base": (
        lambda s, h, t: ["dem", s / "left.tif", s / "left.tif", "-o", t / "out", *HR],
        "dem",
        r"base",
    ),
    "all_zeros_image": (
        lambda s, h, t: ["dem", h["zeros"], s / "right.tif", "-o", t / "out", *HR],
        "dem",
        r"texture|constant",
    ),
    "constant_image": (
        lambda s, h, t: ["dem", s / "left.tif", h["constant"], "-o", t / "out", *HR],
        "dem",
        r"texture|constant",
    ),
    "seed_dem_outside_scene": (
        lambda s, h, t: _dem(
            s, t / "out", "--seed-dem", h["seed_far"], "--dem-vertical", "ellipsoid"
        ),
        "dem",
        r"seed DEM.*(cover|outside)",
    ),
    "missing_image": (
        lambda s, h, t: ["dem", t / "nope.tif", s / "right.tif", "-o", t / "out", *HR],
        "dem",
        r"nope.tif",
    ),
    "binary_image": (
        lambda s, h, t: ["dem", h["binary"], s / "right.tif", "-o", t / "out", *HR],
        "dem",
        r"binary.bin",
    ),
    "assess_checkpoints_binary": (
        lambda s, h, t: [
            "assess",
            s / "truth_dem.tif",
            "--ref",
            s / "truth_dem.tif",
            "--checkpoints",
            h["binary"],
            "-o",
            t / "out",
        ],
        "assess",
        r"binary.bin.*(text|check)",
    ),
    "assess_checkpoints_missing": (
        lambda s, h, t: [
            "assess",
            s / "truth_dem.tif",
            "--ref",
            s / "truth_dem.tif",
            "--checkpoints",
            t / "none.csv",
            "-o",
            t / "out",
        ],
        "assess",
        r"none.csv",
    ),
    "ortho_out_is_its_input": (
        lambda s, h, t: ["ortho", t / "in.tif", "--dem", s / "truth_dem.tif", "-o", t / "in.tif"],
        "ortho",
        r"input",
    ),
    "ortho_out_is_its_input_overwrite": (
        lambda s, h, t: [
            "ortho",
            t / "in.tif",
            "--dem",
            s / "truth_dem.tif",
            "-o",
            t / "in.tif",
            "--overwrite",
        ],
        "ortho",
        r"input",
    ),
    "ortho_out_is_its_dem_overwrite": (
        lambda s, h, t: [
            "ortho",
            t / "in.tif",
            "--dem",
            t / "dem.tif",
            "-o",
            t / "dem.tif",
            "--overwrite",
        ],
        "ortho",
        r"input",
    ),
    "filter_out_is_its_input_overwrite": (
        lambda s, h, t: ["filter", t / "dem.tif", "-o", t / "dem.tif", "--overwrite"],
        "filter",
        r"input",
    ),
    # the DEM named like one of the maps in the output folder was replaced with --overwrite
    "uncertainty_dem_is_one_of_its_maps_overwrite": (
        lambda s, h, t: [
            "uncertainty",
            t / "in.tif",
            "--dem",
            t / "rep" / "ce90.tif",
            "--sigma",
            "roll_bias=5",
            "-o",
            t / "rep",
            "--overwrite",
        ],
        "uncertainty",
        r"ce90.tif.*input",
    ),
    # uncertainty's new --workers (the maps' threads), refused before any work
    "uncertainty_workers_0": (
        lambda s, h, t: [
            "uncertainty",
            t / "in.tif",
            "--dem",
            t / "dem.tif",
            "--sigma",
            "roll_bias=5",
            "-o",
            t / "u",
            "--workers",
            "0",
        ],
        "uncertainty",
        r"--workers must be at least 1",
    ),
    # a folder as the output file: "exists; pass --overwrite", which then said "is a folder"
    "filter_out_is_a_folder": (
        lambda s, h, t: ["filter", t / "dem.tif", "-o", t / "rep"],
        "filter",
        r"rep: is a folder",
    ),
    "filter_out_is_its_score_layer": (
        lambda s, h, t: ["filter", t / "dem.tif", "-o", t / "score.tif", "--overwrite"],
        "filter",
        r"input",
    ),
    "ortho_res_0.0001_absurd_grid": (
        lambda s, h, t: [
            "ortho",
            t / "in.tif",
            "--dem",
            s / "truth_dem.tif",
            "-o",
            t / "out" / "o.tif",
            "--res",
            "0.0001",
        ],
        "ortho",
        r"cells|grid",
    ),
    # adjust wrote its model over the GCP file, the image or its sidecar with --overwrite; -o
    # and --out2 naming one file kept the second model only; an existing residual figure of
    # the report was found after the model had been written
    "adjust_out_is_its_gcps_overwrite": (
        lambda s, h, t: [*_adjust(t), "-o", t / "gcps.csv", "--overwrite"],
        "adjust",
        r"gcps.csv.*input",
    ),
    "adjust_out_is_its_image_overwrite": (
        lambda s, h, t: [*_adjust(t), "-o", t / "in.tif", "--overwrite"],
        "adjust",
        r"in.tif.*input",
    ),
    "adjust_out_is_its_model_sidecar_overwrite": (
        lambda s, h, t: [*_adjust(t), "-o", t / "in.model.json", "--overwrite"],
        "adjust",
        r"in.model.json.*input",
    ),
    "adjust_out2_is_out": (
        lambda s, h, t: [
            *_adjust(t, "bundle", s / "right.tif"),
            "-o",
            t / "m.json",
            "--out2",
            t / "rep" / ".." / "m.json",
            "--overwrite",
        ],
        "adjust",
        r"m.json: given twice",
    ),
    "adjust_report_figure_exists": (
        lambda s, h, t: [*_adjust(t), "-o", t / "m.json", "--report", t / "rep"],
        "adjust",
        r"adjust_residuals.png: exists",
    ),
    "overwrite_foreign_folder_holding_a_products_name": (
        lambda s, h, t: _dem(s, t / "foreign", "--overwrite", *HR),
        "dem",
        r"not a stereodem output.*holds dem.tif",
    ),
}


@pytest.mark.parametrize("case", sorted(BEFORE_WORK))
def test_clear_error_before_any_work(case, sim, hostile, tmp_path, capsys):
    build, command, pattern = BEFORE_WORK[case]
    shutil.copy(sim / "left.tif", tmp_path / "in.tif")
    shutil.copy(sim / "left.model.json", tmp_path / "in.model.json")
    shutil.copy(sim / "truth_dem.tif", tmp_path / "dem.tif")
    shutil.copy(sim / "truth_dem.tif", tmp_path / "score.tif")
    shutil.copy(sim / "points.csv", tmp_path / "gcps.csv")
    (tmp_path / "rep").mkdir()
    (tmp_path / "rep" / "adjust_residuals.png").write_bytes(b"the user's figure")
    shutil.copy(sim / "truth_dem.tif", tmp_path / "rep" / "ce90.tif")
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("my notes\n")
    (tmp_path / "foreign" / "dem.tif").write_text("the user's own file named like a product\n")
    before = {p: _sha(p) for p in tmp_path.rglob("*") if p.is_file()}
    before_sim = {p: _sha(p) for p in sim.rglob("*") if p.is_file()}
    code, _, err = run_cli(capsys, build(sim, hostile, tmp_path))
    assert_clear_error(code, err, command, pattern)
    # nothing written, nothing replaced: the inputs and the folder are as before
    assert not (tmp_path / "out").exists()
    after = {p: _sha(p) for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before
    assert {p: _sha(p) for p in sim.rglob("*") if p.is_file()} == before_sim


TOML_CASES = {
    "tile_size_string": ('[rectification]\ntile_size = "big"', r"tile_size"),
    "tile_size_1": ("[rectification]\ntile_size = 1", r"tile_size"),
    "workers_string": ('[run]\nworkers = "two"', r"workers"),
    "workers_negative": ("[run]\nworkers = -3", r"workers"),
    "height_range_string": ('[rectification]\nheight_range = "1000-3500"', r"height_range"),
    "enabled_no": ('[filters]\nenabled = "no"', r"enabled"),
    "model_lidar": (None, r"model"),
    "max_hole_size_negative": ("[fill]\nmax_hole_size = -5", r"max_hole_size"),
    "unknown_key": ('[matching]\nmatch = "sgm"', r"unknown"),
    "unknown_section": ("[stereo]\ntile_size = 256", r"stereo"),
    "tile_timeout_negative": ("[run]\ntile_timeout = -5", r"tile_timeout"),
    "res_string": ('[gridding]\nres = "30 m"', r"res"),
    # accepted before, then a traceback (bounds), every tile failing with "no point was
    # matched" (sigma, max_ray_gap) or the DEM made before the uncertainty maps failed
    "bounds_nan": ("[gridding]\nbounds = [nan, 0, 1, 1]", r"bounds.*finite"),
    "bounds_two_values": ("[gridding]\nbounds = [10, 10]", r"bounds must be"),
    "height_range_infinite": ("[rectification]\nheight_range = [-inf, inf]", r"height_range"),
    "halo_negative": ("[rectification]\nhalo = [-5, -5]", r"halo"),
    "refinement_sigma_negative": ("[refinement]\nsigma = -3", r"\[refinement\] sigma"),
    "max_ray_gap_negative": ("[gridding]\nmax_ray_gap = -1", r"max_ray_gap"),
    "uncertainty_sigma_string": (
        '[uncertainty]\nenabled = true\nsigma = {dem_height = "five"}',
        r"sigma dem_height",
    ),
    "output_key_typo": ('dri = "elsewhere"', r"unknown key.*\[output\]: dri"),
    # accepted before: every tile failed with a TypeError (unknown keyword, a string compared
    # with a number) and the job ended "no point was matched in any tile", or the sparse
    # stage failed with a traceback; now one line naming the key, with the closest known one
    "matching_option_typo": (
        "[matching]\noptions = {windw = 5}",
        r"unknown key.*\[matching\] options: windw \(did you mean window\?\)",
    ),
    "matching_option_of_the_caller": (
        "[matching]\noptions = {matcher = 'ncc'}",
        r"\[matching\] options: matcher",
    ),
    "matching_option_string": ('[matching]\noptions = {window = "5"}', r"options window"),
    "matching_option_min_score_2": ("[matching]\noptions = {min_score = 2}", r"min_score"),
    "matching_option_sgm_mode": ('[matching]\noptions = {sgm_mode = "fast"}', r"sgm_mode"),
    "sparse_option_typo": (
        "[rectification]\nsparse_options = {max_ofset = 80}",
        r"sparse_options: max_ofset \(did you mean max_offset\?\)",
    ),
    "sparse_option_of_the_caller": (
        "[rectification]\nsparse_options = {height_range = [0, 1]}",
        r"sparse_options: height_range",
    ),
    "sparse_option_ratio_2": ("[rectification]\nsparse_options = {ratio = 2}", r"ratio"),
    "sparse_option_refine_string": (
        '[rectification]\nsparse_options = {refine = "yes"}',
        r"sparse_options refine.*true or false",
    ),
    "section_key_typo": ('[matching]\nmatchr = "ncc"', r"matchr \(did you mean matcher\?\)"),
    # accepted before, and the run succeeded: a score threshold no ZNCC reaches dropped every
    # refined match (min_score), a negative gain turned the first pass's detail upside down
    "refinement_min_score_5": ("[refinement]\nmin_score = 5", r"\[refinement\] min_score"),
    "refinement_detail_gain_negative": (
        "[refinement]\ndetail_gain = -1",
        r"\[refinement\] detail_gain",
    ),
    # tenth round (tests/app/test_hostile_config.py): values beyond their bounds
    "n_features": ("[rectification]\nsparse_options = {n_features = 99999999999}", "n_features"),
    "n_heights": ("[rectification]\nsparse_options = {n_heights = 99999999999}", "n_heights"),
    "speckle_range": ("[matching]\noptions = {sgm_speckle_range = 99999999999}", "speckle_range"),
    "speckle_window": (
        "[matching]\noptions = {sgm_speckle_window = 99999999999}",
        "speckle_window",
    ),
    "uniqueness": ("[matching]\noptions = {sgm_uniqueness = 101}", "sgm_uniqueness"),
    "p1": ("[matching]\noptions = {sgm_p1 = 99999999999}", "sgm_p1"),
    "lr_tolerance": ("[matching]\noptions = {lr_tolerance = 1e30}", "lr_tolerance"),
    "levels": ("[matching]\noptions = {levels = 99999999999}", "levels"),
    "window": ("[matching]\noptions = {window = 301}", "window"),
    "refinement_window": ("[refinement]\nwindow = 99999999999", r"\[refinement\] window"),
    "refinement_sigma": ("[refinement]\nsigma = 1e6", r"\[refinement\] sigma"),
    "smooth_sigma": ("[fill]\nsmooth_sigma = 1e308", "smooth_sigma"),
    "height_margin": ("[rectification]\nheight_margin = 1e308", "height_margin"),
    "halo": ("[rectification]\nhalo = [1000, 1000]", "halo"),
    "disparity_margin": ("[rectification]\ndisparity_margin = 1e6", "disparity_margin"),
    "uncertainty_samples": (
        "[uncertainty]\nenabled = true\nsigma = {roll_bias = 1e-5}\nmethod = 'monte-carlo'\n"
        "samples = 99999999999",
        r"\[uncertainty\] samples must be 10\.\.100000",
    ),
    "uncertainty_sigma": (
        "[uncertainty]\nenabled = true\nsigma = {roll_bias = 1e308}",
        r"\[uncertainty\] sigma roll_bias.*variance",
    ),
}


@pytest.mark.parametrize("case", sorted(TOML_CASES))
def test_bad_toml_is_a_clear_error(case, sim, tmp_path, capsys):
    body, pattern = TOML_CASES[case]
    cfg = tmp_path / "job.toml"
    if case == "model_lidar":
        job_toml(cfg, sim, tmp_path / "out", inputs='model = "lidar"')
    else:
        cfg.write_text(f"""[inputs]
left = "{sim / "left.tif"}"
right = "{sim / "right.tif"}"
[output]
dir = "{tmp_path / "out"}"
{body}
""")
    code, _, err = run_cli(capsys, ["run", cfg])
    assert_clear_error(code, err, "run", pattern)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("what", ["binary", "folder", "missing", "out_under_file"])
def test_unusable_config_file_is_a_clear_error(what, sim, hostile, tmp_path, capsys):
    path = {"binary": hostile["binary"], "folder": tmp_path, "missing": tmp_path / "none.toml"}.get(
        what
    )
    if what == "out_under_file":
        path = job_toml(tmp_path / "job.toml", sim, hostile["a_file"] / "out")
    code, _, err = run_cli(capsys, ["run", path])
    assert_clear_error(code, err, "run", r"toml|configuration|folder|cannot be created|not a")


def test_a_one_line_error_for_every_cli_failure(capsys, tmp_path):
    """An error message carrying a newline (e.g. from GDAL) is printed on one line."""
    bad = tmp_path / "bad.tif"
    bad.write_text("II*\x00 garbage\nsecond line\n")
    code, _, err = run_cli(capsys, ["ortho", bad, "--dem", bad, "-o", tmp_path / "o.tif"])
    assert_clear_error(code, err, "ortho", r"bad.tif")


# --------------------------------------------------------------------------- the output-folder lock


def test_lock_is_exclusive_between_processes_and_released(tmp_path):
    folder = tmp_path / "out"
    folder.mkdir()
    code = (
        "import sys, time; from stereodem.outlock import OutputLock\n"
        "with OutputLock(sys.argv[1]):\n    print('locked', flush=True); time.sleep(60)\n"
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(OutputLockedError, match=rf"PID {holder.pid}"):
            with OutputLock(folder):
                pass
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    # the holder died without cleaning up (kill -9): the stale lock is recovered
    with OutputLock(folder) as lock:
        assert lock.path.exists()
    assert not any(folder.iterdir())  # released: the lock file is gone


def test_lock_file_left_by_a_dead_process_does_not_block(tmp_path):
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / LOCK_NAME).write_text(json.dumps({"pid": 2**22 + 12345, "host": "x"}))
    with OutputLock(folder) as lock:  # taken over, not OutputLockedError
        assert json.loads(lock.path.read_text())["pid"] == os.getpid()
    assert not (folder / LOCK_NAME).exists()


def test_a_second_job_starting_at_the_same_moment_does_not_make_the_folder_non_empty(tmp_path):
    """Two jobs started together into a new folder: the one that takes the lock must not count
    the other's writability probe as a file of the user's (both then failed: one on 'folder
    exists and is not empty', the other on the lock; seen once in 20 x 2 concurrent runs)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / f"{PROBE_PREFIX}4242").touch()  # the other job's probe, between touch and unlink
    with output_folder(out) as p:
        (p / "run.json").write_text("{}")
    assert (out / "run.json").exists()
    (out / f"{PROBE_PREFIX}4242").unlink()
    (out / "run.json").unlink()
    (out / "notes.txt").touch()  # a real file of the user's still counts
    with pytest.raises(OutputExistsError, match="not empty"):
        with output_folder(out):
            pass


def test_overwrite_removes_only_stereodem_products(tmp_path):
    out = tmp_path / "out"
    (out / "raw").mkdir(parents=True)
    (out / "assess").mkdir()
    for name in (
        "run.json",
        "dem.tif",
        "ortho_left.tif",
        "raw/dem.tif",
        "assess/report.json",
        "notes.txt",
    ):
        (out / name).write_text("x")
    remove_products(out, keep_tiles=False)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def _previous_job(out):
    """A previous job's products in ``out`` (a finished ``run.json``, ``dem.tif``, a tile
    cache) beside a file of the user's; returns the folder's names."""
    (out / "tiles").mkdir(parents=True)
    for name in ("dem.tif", "tiles/tile_00001.npz", "notes.txt"):
        (out / name).write_text("old")
    (out / "run.json").write_text(jsonutil.dumps(jsonutil.stamped({"status": "ok"})))
    return sorted(p.name for p in out.iterdir())


def test_resume_sets_the_products_aside_until_the_job_writes_its_own(tmp_path):
    """--resume removed the previous job's products before the job checked its tile cache:
    a resume refused as another job's (changed settings) left only tiles/. They are set aside
    now: put back when the job stops before writing any of its own, replaced when it
    succeeds, and the tile cache is kept either way."""
    out = tmp_path / "out"
    files = _previous_job(out)
    with pytest.raises(InputError, match="refused"):
        with output_folder(out, resume=True) as o:
            assert sorted(p.name for p in o.iterdir() if not p.name.startswith(".")) == [
                "notes.txt",
                "tiles",
            ]
            raise InputError("cached tiles refused")
    assert sorted(p.name for p in out.iterdir()) == files
    assert (out / "dem.tif").read_text() == "old"
    # a job that wrote its own products before failing: the old ones are not mixed in
    with pytest.raises(RuntimeError):
        with output_folder(out, resume=True) as o:
            (o / "dem.tif").write_text("new")
            raise RuntimeError("ortho failed")
    assert sorted(p.name for p in out.iterdir()) == ["dem.tif", "notes.txt", "tiles"]
    assert (out / "dem.tif").read_text() == "new"
    (out / "run.json").write_text(jsonutil.dumps(jsonutil.stamped({"status": "ok"})))
    with output_folder(out, resume=True) as o:  # success: the job's own, nothing hidden left
        (o / "dem.tif").write_text("newer")
    assert sorted(p.name for p in out.iterdir()) == ["dem.tif", "notes.txt", "tiles"]
    assert (out / "tiles" / "tile_00001.npz").read_text() == "old"


def test_overwrite_sets_the_products_aside_until_the_job_writes_its_own(tmp_path):
    """--overwrite deleted the previous job's products before the job started: a rerun that
    failed left nothing. They are moved out of its way (a hidden folder) and put back when
    the job stops before writing any of its own; a job that wrote some leaves only those (no
    mix of two jobs' products); one that succeeds leaves its own and nothing hidden. The
    user's files stay throughout, and a hidden folder a killed job left is removed by the
    next --overwrite, which still knows the folder for a stereodem output."""
    out = tmp_path / "out"
    files = _previous_job(out)
    with pytest.raises(RuntimeError, match="stereo failed"):
        with output_folder(out, overwrite=True) as o:
            names = sorted(p.name for p in o.iterdir() if p.name != LOCK_NAME)
            assert len(names) == 2 and names[1] == "notes.txt"  # out of the job's way
            assert names[0].startswith(REMOVING_PREFIX)
            assert sorted(p.name for p in (o / names[0]).iterdir()) == [
                "dem.tif",
                "run.json",
                "tiles",
            ]
            raise RuntimeError("stereo failed")
    assert sorted(p.name for p in out.iterdir()) == files  # all back, the tile cache too
    assert (out / "dem.tif").read_text() == "old"
    assert (out / "tiles" / "tile_00001.npz").read_text() == "old"
    with pytest.raises(RuntimeError):  # wrote its own before failing: only those
        with output_folder(out, overwrite=True) as o:
            (o / "dem.tif").write_text("new")
            raise RuntimeError("ortho failed")
    assert sorted(p.name for p in out.iterdir()) == ["dem.tif", "notes.txt"]
    assert (out / "dem.tif").read_text() == "new"
    (out / "run.json").write_text(jsonutil.dumps(jsonutil.stamped({"status": "ok"})))
    with output_folder(out, overwrite=True) as o:  # success: its own, nothing hidden left
        (o / "dem.tif").write_text("newer")
    assert sorted(p.name for p in out.iterdir()) == ["dem.tif", "notes.txt"]
    assert (out / "dem.tif").read_text() == "newer"
    # what a job killed while the products were set aside leaves: only the hidden folder
    (out / "dem.tif").unlink()
    (out / f"{REMOVING_PREFIX}123-4").mkdir()
    (out / f"{REMOVING_PREFIX}123-4" / "run.json").write_text("x")
    with output_folder(out, overwrite=True):
        pass
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_a_failed_reruns_record_of_its_failure_gives_way_to_the_previous_products(tmp_path):
    """A command that records its own failure in its marker (``stack``: ``stack.json`` says
    ``failed``) wrote that file and nothing else when it failed early: with --overwrite the
    previous products still come back whole (the failure is on the terminal), while a
    partial product beside the record is the failed job's own, and stays."""
    products = Products(("stack.json", "stack.zarr", "rate.tif"), markers=("stack.json",))
    out = tmp_path / "out"
    (out / "stack.zarr").mkdir(parents=True)
    (out / "rate.tif").write_text("old")
    (out / "stack.json").write_text(jsonutil.dumps(jsonutil.stamped({"status": "ok"})))
    before = {p.name: p.is_dir() or p.read_text() for p in out.iterdir()}
    failed = jsonutil.dumps(jsonutil.stamped({"status": "failed", "error": "unreadable DEM"}))
    with pytest.raises(InputError):
        with output_folder(out, products, overwrite=True) as o:
            (o / "stack.json").write_text(failed)
            raise InputError("unreadable DEM")
    assert {p.name: p.is_dir() or p.read_text() for p in out.iterdir()} == before
    with pytest.raises(InputError):  # the record and a partial store: the failed job's
        with output_folder(out, products, overwrite=True) as o:
            (o / "stack.json").write_text(failed)
            (o / "stack.zarr").mkdir()
            raise InputError("unreadable DEM")
    assert sorted(p.name for p in out.iterdir()) == ["stack.json", "stack.zarr"]
    assert json.loads((out / "stack.json").read_text())["status"] == "failed"


# ----------------------------------------------------------------------------- the tile cache


def test_cache_entry_of_another_tile_or_corrupt_is_not_reused(tmp_path):
    tiles = [Tile(0, 0, 10, 10, 0), Tile(10, 0, 10, 10, 1)]
    calls = []

    def fn(tile, ctx):
        calls.append(tile.index)
        return {"v": np.full(3, tile.index * 10.0 + ctx)}

    res, fails, _ = run_tiles(fn, tiles, 1, cache_dir=tmp_path, cache_key="job-a")
    assert not fails and calls == [0, 1]
    files = sorted(tmp_path.glob("tile_*.npz"))
    shutil.copy(files[0], files[1])  # tile 0's result under tile 1's name
    calls.clear()
    res, fails, _ = run_tiles(fn, tiles, 1, cache_dir=tmp_path, cache_key="job-a", resume=True)
    assert calls == [1] and res[1]["v"][0] == 11.0
    files[0].write_bytes(files[0].read_bytes()[:100])  # truncated: a corrupt zip
    calls.clear()
    res, fails, _ = run_tiles(fn, tiles, 1, cache_dir=tmp_path, cache_key="job-a", resume=True)
    assert calls == [0] and res[0]["v"][0] == 1.0
    calls.clear()  # another job's tiles are never reused
    res, fails, _ = run_tiles(fn, tiles, 2, cache_dir=tmp_path, cache_key="job-b", resume=True)
    assert calls == [0, 1] and res[1]["v"][0] == 12.0
    # bit rot in a stored array: the checksum no longer matches
    with np.load(files[1]) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["v"] = arrays["v"] + 1
    np.savez(files[1], **arrays)
    calls.clear()
    run_tiles(fn, tiles, 2, cache_dir=tmp_path, cache_key="job-b", resume=True)
    assert calls == [1]


# ----------------------------------------------------------------------------- slow: whole runs


def _run_toml(
    tmp_path,
    sim,
    out,
    *,
    extra="",
    rect="tile_size = 150\nheight_range = [1000, 3500]",
    inputs=None,
    name="job.toml",
):
    inputs = (
        inputs
        if inputs is not None
        else (
            f'reference_dem = "{sim / "truth_dem.tif"}"\nreference_vertical = "ellipsoid"\n'
            f'checkpoints = "{sim / "points.csv"}"'
        )
    )
    return job_toml(tmp_path / name, sim, out, extra=extra, rect=rect, inputs=inputs)


@pytest.fixture(scope="module")
def reference_run(sim, tmp_path_factory):
    """An uninterrupted ``stereodem run`` (workers 1) to compare resumed runs with."""
    d = tmp_path_factory.mktemp("ref")
    cfg = _run_toml(
        d,
        sim,
        d / "out",
        rect="tile_size = 64\nheight_range = [1000, 3500]",
        extra="[ortho]\nboth = false\n[run]\nworkers = 1",
    )
    assert cli.main(["-q", "run", str(cfg)]) == 0
    return d / "out"


RASTERS = (
    "raw/dem.tif",
    "raw/score.tif",
    "raw/count.tif",
    "raw/raygap.tif",
    "dem.tif",
    "ortho_left.tif",
)


def _assert_same_rasters(a, b):
    for name in RASTERS:
        za, ta = _read(a / name)
        zb, tb = _read(b / name)
        assert ta == tb, name
        np.testing.assert_array_equal(za, zb, err_msg=name)


@pytest.mark.slow
def test_wrong_height_range_is_suspect_not_silent(sim, tmp_path, capsys):
    code, _, err = run_cli(capsys, _dem(sim, tmp_path / "d", "--height-range", "0", "500"))
    assert_clear_error(code, err, "dem", r"suspect|search range|height range")
    rep = json.loads((tmp_path / "d" / "dem_report.json").read_text())
    codes = [w["code"] for w in rep["warnings"]]
    assert "heights_at_search_bound" in codes and rep["status"] == "suspect"
    # --force keeps the product but the report still says why it is suspect
    code, _, err = run_cli(
        capsys, _dem(sim, tmp_path / "f", "--height-range", "0", "500", "--force")
    )
    assert code == 0, err
    rep = json.loads((tmp_path / "f" / "dem_report.json").read_text())
    assert "heights_at_search_bound" in [w["code"] for w in rep["warnings"]]
    # the right range gives no such warning
    code, _, err = run_cli(capsys, _dem(sim, tmp_path / "ok", *HR))
    assert code == 0, err
    rep = json.loads((tmp_path / "ok" / "dem_report.json").read_text())
    assert rep["warnings"] == [] and rep["status"] == "ok"


@pytest.mark.slow
def test_wrong_height_range_in_run_stops_before_ortho(sim, tmp_path, capsys):
    cfg = _run_toml(
        tmp_path, sim, tmp_path / "out", rect="tile_size = 300\nheight_range = [0, 500]"
    )
    code, _, err = run_cli(capsys, ["run", cfg])
    assert_clear_error(code, err, "run", r"suspect|search range")
    info = json.loads((tmp_path / "out" / "run.json").read_text())
    assert info["status"] == "suspect"
    assert "heights_at_search_bound" in [w["code"] for w in info["warnings"]]
    assert not (tmp_path / "out" / "ortho_left.tif").exists()
    assert not (tmp_path / "out" / "dem.tif").exists()


@pytest.mark.slow
def test_seed_dem_in_feet_is_not_used_quietly(sim, hostile, tmp_path, capsys):
    code, _, err = run_cli(
        capsys,
        _dem(
            sim, tmp_path / "d", "--seed-dem", hostile["seed_feet"], "--dem-vertical", "ellipsoid"
        ),
    )
    assert_clear_error(code, err, "dem", r"seed DEM|suspect|search range")


@pytest.mark.slow
def test_geographic_crs_gets_a_posting_in_degrees(sim, tmp_path, capsys, caplog):
    with caplog.at_level(logging.INFO, logger="stereodem.stereo.pipeline"):
        code, _, err = run_cli(capsys, _dem(sim, tmp_path / "g", "--crs", "EPSG:4326", *HR))
    assert code == 0, err
    # -v's plan line says the unit (it read "posting 0.000273": metres or degrees?)
    assert re.search(r"stereo DEM: .* posting 0\.000\d+°", caplog.text), caplog.text
    z, t = _read(tmp_path / "g" / "dem.tif")
    # 2 x 15 m GSD ~ 2.7e-4 degrees; the scene (~4.5 km) spans ~0.05 degrees
    assert 1e-4 < t.a < 1e-3 and z.shape[0] > 100 and z.shape[1] > 100
    assert np.isfinite(z).mean() > 0.5


@pytest.mark.slow
def test_16_bit_left_with_8_bit_right_gives_the_same_coverage(sim, hostile, tmp_path, capsys):
    code, _, err = run_cli(capsys, _dem(sim, tmp_path / "both8", *HR))
    assert code == 0, err
    code, _, err = run_cli(
        capsys,
        [
            "dem",
            hostile["left16"],
            sim / "right.tif",
            "-o",
            tmp_path / "mixed",
            "--workers",
            "1",
            *HR,
        ],
    )
    assert code == 0, err
    z8, _ = _read(tmp_path / "both8" / "dem.tif")
    zm, _ = _read(tmp_path / "mixed" / "dem.tif")
    assert np.isfinite(zm).mean() > 0.9 * np.isfinite(z8).mean()
    rep = json.loads((tmp_path / "mixed" / "dem_report.json").read_text())
    assert "radiometry_rescaled" in [w["code"] for w in rep["warnings"]]


@pytest.mark.slow
def test_run_overwrite_with_another_configuration_leaves_nothing_stale(sim, tmp_path, capsys):
    out = tmp_path / "out"
    cfg = _run_toml(tmp_path, sim, out, rect="tile_size = 300\nheight_range = [1000, 3500]")
    assert run_cli(capsys, ["run", cfg])[0] == 0
    assert (out / "ortho_right.tif").exists() and (out / "assess" / "report.json").exists()
    cfg2 = _run_toml(
        tmp_path,
        sim,
        out,
        rect="tile_size = 300\nheight_range = [1000, 3500]",
        extra="[ortho]\nenabled = false\n[assess]\nenabled = false",
        name="job2.toml",
    )
    code, _, err = run_cli(capsys, ["run", cfg2, "--overwrite"])
    assert code == 0, err
    assert not (out / "ortho_left.tif").exists() and not (out / "ortho_right.tif").exists()
    assert not (out / "assess").exists()
    info = json.loads((out / "run.json").read_text())
    assert not any(o.startswith(("ortho", "assess")) for o in info["outputs"])
    assert all((out / o).exists() for o in info["outputs"])
    assert not list(out.glob(".stereodem-removing-*"))  # deleted while the job ran


@pytest.mark.slow
def test_dem_overwrite_on_two_workers_replaces_the_products(sim, tmp_path, capsys):
    """`stereodem dem --overwrite` with threads to spare deletes the previous products on a
    thread while it runs, as `run` does: the new products are there, nothing else is."""
    out = tmp_path / "out"
    argv = ["dem", sim / "left.tif", sim / "right.tif", "-o", out, "--workers", "2", *HR]
    assert run_cli(capsys, argv)[0] == 0
    (out / "dem.tif").write_bytes(b"the previous job's")  # must not survive
    code, _, err = run_cli(capsys, [*argv, "--overwrite"])
    assert code == 0, err
    with rasterio.open(out / "dem.tif") as ds:
        assert np.isfinite(ds.read(1)).mean() > 0.2
    assert not list(out.glob(".stereodem-removing-*"))


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["copied_over_another_index", "corrupt_zip"])
def test_damaged_cache_entry_is_recomputed_on_resume(damage, sim, reference_run, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(reference_run, out)
    tiles = sorted((out / "tiles").glob("tile_*.npz"))
    assert len(tiles) >= 4
    if damage == "copied_over_another_index":
        shutil.copy(tiles[0], tiles[3])
    else:
        tiles[3].write_bytes(b"PK\x03\x04 not a zip")
    cfg = _run_toml(
        tmp_path,
        sim,
        out,
        rect="tile_size = 64\nheight_range = [1000, 3500]",
        extra="[ortho]\nboth = false\n[run]\nworkers = 1",
    )
    code, _, err = run_cli(capsys, ["run", cfg, "--resume"])
    assert code == 0, err
    _assert_same_rasters(reference_run, out)


def _default_sigint():
    """In the child before exec: SIGINT to its default (Python then raises KeyboardInterrupt)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _children(pid):
    """PIDs whose parent is ``pid`` (Linux /proc)."""
    kids = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                stat = (p / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(p.name))
    return kids


def _alive(pid):
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize(
    "sig", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT], ids=["SIGKILL", "SIGTERM", "SIGINT"]
)
def test_killed_run_leaves_no_process_and_resumes_bit_identical(sig, sim, reference_run, tmp_path):
    out = tmp_path / "out"
    cfg = _run_toml(
        tmp_path,
        sim,
        out,
        rect="tile_size = 64\nheight_range = [1000, 3500]",
        extra="[ortho]\nboth = false",
    )
    # output to files, not pipes: orphaned workers would hold a pipe open
    log = open(tmp_path / "stderr.txt", "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "stereodem.cli", "run", str(cfg), "--workers", "2"],
        stdout=subprocess.DEVNULL,
        stderr=log,
        text=True,
        # as from a terminal: a suite started in the background (`cmd &`, CI) ignores SIGINT,
        # and a child inherits that, so Ctrl-C would never reach it
        preexec_fn=_default_sigint,
    )
    workers = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:  # until the pool works on tiles
        workers = [k for k in _children(proc.pid)]
        if len(list((out / "tiles").glob("tile_*.npz"))) >= 2 and len(workers) >= 2:
            break
        time.sleep(0.2)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    family = set(workers) | {g for k in workers for g in _children(k)}
    proc.send_signal(sig)
    proc.wait(timeout=60)
    log.close()
    err = (tmp_path / "stderr.txt").read_text()
    time.sleep(2.0)
    left = [p for p in family if _alive(p)]
    for p in left:  # do not leave them to the next test
        os.kill(p, signal.SIGKILL)
    assert left == []
    assert proc.returncode != 0
    if sig != signal.SIGKILL:
        assert "Traceback" not in err
        # the run's message is the last line: multiprocessing's resource tracker, a helper
        # process on the same stream, once reported the pool's semaphores below it (seen in
        # CI under load; stereodem.core.pool.quiet_resource_tracker)
        assert "--resume" in err.strip().splitlines()[-1]
        assert "resource_tracker" not in err
    assert not (out / "run.json").exists()
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "stereodem.cli",
            "-q",
            "run",
            str(cfg),
            "--resume",
            "--workers",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    _assert_same_rasters(reference_run, out)


@pytest.mark.slow
def test_two_concurrent_runs_into_one_folder_exactly_one_proceeds(sim, tmp_path):
    cfgs = [
        _run_toml(
            tmp_path,
            sim,
            tmp_path / "out",
            name=f"job{k}.toml",
            rect="tile_size = 300\nheight_range = [1000, 3500]",
            extra=f'[matching]\nmatcher = "{m}"\n[ortho]\nenabled = false\n[assess]\nenabled = '
            "false\n[run]\nworkers = 1",
            inputs="",
        )
        for k, m in enumerate(("sgm", "ncc"))
    ]
    for it in range(20):
        shutil.rmtree(tmp_path / "out", ignore_errors=True)
        procs = [
            subprocess.Popen(
                [sys.executable, "-m", "stereodem.cli", "-q", "run", str(c)],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for c in cfgs
        ]
        res = [(p.wait(timeout=600), p.communicate()[1]) for p in procs]
        codes = sorted(c for c, _ in res)
        assert codes == [0, 1], (it, res)
        loser = next(e for c, e in res if c == 1)
        assert "Traceback" not in loser and "error:" in loser, loser
        assert len(loser.strip().splitlines()) == 1, loser
        winner = cfgs[[c for c, _ in res].index(0)]
        info = json.loads((tmp_path / "out" / "run.json").read_text())
        assert info["config"]["matching"]["matcher"] == ("sgm" if winner == cfgs[0] else "ncc")
        assert not list((tmp_path / "out").glob(".stereodem*"))  # the lock is released


# ----------------------------------------------------------------------------- the sanity measures


def test_base_to_height_of_the_simulated_aster_pair(sim):
    """ASTER 3N (nadir) / 3B (27.6 deg backward) has B/H ~ 0.6 (tan 27.6 deg = 0.52 plus the
    Earth's curvature over the ~370 km baseline); the same image twice has none."""
    left, right = load_image_model(sim / "left.tif"), load_image_model(sim / "right.tif")
    bh = base_to_height(left, right, 2300.0)
    assert 0.5 < bh < 0.7
    assert base_to_height(left, left, 2300.0) < 1e-6 < MIN_BASE_TO_HEIGHT


def test_texture_check_tells_noise_from_a_constant(sim):
    rng = np.random.default_rng(0)
    check_texture(rng.normal(100, 5, (64, 64)).astype(np.float32), "noise")
    img = np.full((64, 64), 7.0, np.float32)
    img[::16, ::16] = 8.0  # a few specks: still no texture
    with pytest.raises(InputError, match="no texture"):
        check_texture(img, "specks")
    with pytest.raises(InputError, match="no valid pixel"):
        check_texture(np.full((64, 64), np.nan, np.float32), "void")
