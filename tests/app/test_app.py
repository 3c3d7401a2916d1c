"""The application: configuration, end-to-end run, workers, failures, CLI behaviour."""

import dataclasses
import io
import json
import pickle
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rasterio.shutil
from helpers.strict_json import strict_loads

import stereodem.pipeline.job as job
import stereodem.stereo.pipeline as sp
from stereodem import cli
from stereodem.commands import COMMANDS
from stereodem.config import config_from_dict, load_config
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError, OutputExistsError
from stereodem.core.threads import job_threads
from stereodem.dem_cli import sparse_line
from stereodem.pipeline.job import run
from stereodem.run_cli import summarize
from stereodem.sensor.simulation.aster_granule import granule_right_size, write_granule_scene
from stereodem.sensor.simulation.simulate import simulate_scene, write_scene
from stereodem.stereo.runner import SharedArray


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene")
    sc = simulate_scene("aster", size=(420, 400), seed=2, n_points=30)
    write_scene(sc, d, overwrite=True)
    return d


def _cfg(scene_dir, out, **run):
    raw = {
        "inputs": {
            "left": str(scene_dir / "left.tif"),
            "right": str(scene_dir / "right.tif"),
            "reference_dem": str(scene_dir / "truth_dem.tif"),
            "reference_vertical": "ellipsoid",
            "checkpoints": str(scene_dir / "points.csv"),
        },
        "output": {"dir": str(out)},
        "rectification": {"tile_size": 200, "height_range": [1000, 3500]},
        "run": {"workers": 1, **run},
    }
    return config_from_dict(raw)


@pytest.mark.slow
def test_run_writes_products_and_run_json(scene_dir, tmp_path):
    info = run(_cfg(scene_dir, tmp_path / "out"))
    out = tmp_path / "out"
    for name in (
        "dem.tif",
        "dem_edit_mask.tif",
        "raw/dem.tif",
        "raw/score.tif",
        "raw/count.tif",
        "raw/raygap.tif",
        "ortho_left.tif",
        "ortho_right.tif",
        "assess/report.json",
        "run.json",
    ):
        assert (out / name).exists(), name
    rj = json.loads((out / "run.json").read_text())
    # the tile cache is kept by default (for --resume) and listed with the outputs
    assert "tiles" in rj["outputs"] and list((out / "tiles").glob("tile_*.npz"))
    # every JSON file of the job is strict JSON (jq, JavaScript): no NaN or Infinity
    for f in out.rglob("*.json"):
        strict_loads(f.read_text())
    assert set(rj["stages"]) >= {"load", "stereo", "post", "ortho", "assess"}
    assert all(s["seconds"] >= 0 and s["peak_rss_mb"] > 0 for s in rj["stages"].values())
    # CPU seconds per stage: the stereo stage's matching is work of this process or its workers
    st = rj["stages"]
    assert all(s["cpu_s"] >= 0 and s["worker_cpu_s"] >= 0 for s in st.values())
    assert st["stereo"]["cpu_s"] + st["stereo"]["worker_cpu_s"] > 0
    assert {s["peak_rss_scope"] for s in st.values()} <= {"stage", "process"}
    assert rj["config"]["rectification"]["tile_size"] == 200 and rj["versions"]["gdal"]
    # the headline accuracy is real: the stereo DEM against the simulator's truth
    h = info["headline"]
    assert h["nmad"] < 4.0 and abs(h["median"]) < 1.5
    with rasterio.open(out / "ortho_left.tif") as a, rasterio.open(out / "ortho_right.tif") as b:
        assert a.transform == b.transform and a.shape == b.shape  # same grid for both


@pytest.mark.slow
def test_workers_2_bit_identical_to_workers_1(scene_dir, tmp_path):
    # 3 workers on any machine: 3 tile processes, 3 threads for the main process's stages
    for w in (1, 2, 3):  # the last without its tile cache: the products do not change
        run(_cfg(scene_dir, tmp_path / f"w{w}", workers=w, keep_tiles=w < 3))
    assert (tmp_path / "w2" / "tiles").is_dir() and not (tmp_path / "w3" / "tiles").exists()
    assert "tiles" not in json.loads((tmp_path / "w3" / "run.json").read_text())["outputs"]
    for w in (2, 3):
        for name in (
            "raw/dem.tif",
            "raw/score.tif",
            "raw/count.tif",
            "dem.tif",
            "dem_edit_mask.tif",
            "ortho_left.tif",
            "ortho_right.tif",
        ):
            with (
                rasterio.open(tmp_path / "w1" / name) as a,
                rasterio.open(tmp_path / f"w{w}" / name) as b,
            ):
                x, y = a.read(), b.read()
                assert np.array_equal(x, y, equal_nan=True), (w, name)
        # the assessment's statistics too (blocks on threads, sums merged in block order)
        reports = [
            json.loads((tmp_path / d / "assess" / "report.json").read_text())
            for d in ("w1", f"w{w}")
        ]
        for key in ("stats", "by_slope", "by_elevation", "slope_fit", "checkpoints"):
            assert json.dumps(reports[0][key]) == json.dumps(reports[1][key]), (w, key)


@pytest.mark.slow
@pytest.mark.parametrize("assess", [True, False])
def test_writes_overlapping_a_stage_compress_on_one_thread(
    scene_dir, tmp_path, monkeypatch, assess
):
    """The background writer is one thread of the budget: a GeoTIFF written while a following
    stage runs compresses on that thread alone; a write the job waits for at its end (the
    orthoimages when no assessment follows) compresses on all the job's workers."""
    seen, copy = {}, rasterio.shutil.copy

    def record(src, dst, **kw):
        if not str(dst).startswith("/vsimem/"):  # not a probe of the options (in memory)
            seen[str(dst)] = kw.get("num_threads")
        return copy(src, dst, **kw)

    monkeypatch.setattr(rasterio.shutil, "copy", record)
    cfg = _cfg(scene_dir, tmp_path / "out", workers=3)
    if not assess:
        cfg = dataclasses.replace(cfg, assess=dataclasses.replace(cfg.assess, enabled=False))
    run(cfg)
    threads = {
        name: {n for path, n in seen.items() if f"{name}." in Path(path).name}
        for name in ("dem", "dem_edit_mask", "ortho_left", "ortho_right")
    }
    assert threads["dem"] == {"1"}  # raw/dem.tif and dem.tif: the next stage runs meanwhile
    assert threads["dem_edit_mask"] == {"1"}
    last = "1" if assess else str(job_threads(3))  # the budget: 3 threads, at most the cores
    assert threads["ortho_left"] == threads["ortho_right"] == {last}
    # a configured NUM_THREADS is the user's choice, kept for every write
    seen.clear()
    cfg = _cfg(scene_dir, tmp_path / "out2", workers=3, creation_options={"NUM_THREADS": "2"})
    run(cfg)
    assert set(seen.values()) == {"2"}


@pytest.mark.slow
def test_run_reads_the_reference_dem_once(scene_dir, tmp_path, monkeypatch):
    """The input checks look at the reference DEM's header and first block before the stereo
    work; the assessment reads it: one full read of a file that may hold tens of millions of
    cells (it was two)."""
    real, reads = DEM.from_file.__func__, []

    def counting(cls, path, *a, **k):
        reads.append(str(path))
        return real(cls, path, *a, **k)

    monkeypatch.setattr(DEM, "from_file", classmethod(counting))
    info = run(_cfg(scene_dir, tmp_path / "once"))
    assert reads.count(str(scene_dir / "truth_dem.tif")) == 1
    assert info["headline"]["nmad"] < 4.0


@pytest.mark.slow
def test_failing_tile_is_reported_and_scene_completes(scene_dir, tmp_path, monkeypatch):
    real = sp.process_tile
    calls = {"n": 0}

    def flaky(tile, inputs, settings):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("simulated tile failure")
        return real(tile, inputs, settings)

    monkeypatch.setattr(sp, "process_tile", flaky)
    info = run(_cfg(scene_dir, tmp_path / "f"))
    assert (
        len(info["failed_tiles"]) == 1
        and "simulated tile failure" in info["failed_tiles"][0]["reason"]
    )
    assert info["stages"]["stereo"]["tiles"] >= 3
    with rasterio.open(tmp_path / "f" / "dem.tif") as ds:
        assert np.isfinite(ds.read(1)).mean() > 0.2


def test_existing_output_needs_overwrite(scene_dir, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("user data")

    with pytest.raises(OutputExistsError):
        run(_cfg(scene_dir, out))
    assert (out / "keep.txt").read_text() == "user data"


def test_config_errors(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[inputs]\nleft = 'a.tif'\n")
    with pytest.raises(InputError, match="needs 'right'"):
        load_config(p)
    p.write_text("[inputs]\nleft='a'\nright='b'\n[output]\ndir='o'\n[rectification]\ntile_sise=3\n")
    with pytest.raises(InputError, match="unknown key.*tile_sise"):
        load_config(p)
    p.write_text("[inputs]\nleft='a'\nright='b'\n[output]\ndir='o'\n[stereo]\ntile_size=300\n")
    with pytest.raises(InputError, match="split into"):
        load_config(p)
    for table, msg in (
        ("[filters]\nenabled='no'", "expected true or false"),
        ("[rectification]\ntile_size='big'", "whole number"),
        ("[run]\nworkers=-3", "at least 1"),
        ("[rectification]\nheight_range='1000-3500'", "list of numbers"),
        ("[inputs]\nmodel='lidar'", "physical"),
        ("[fill]\nmax_hole_size=-5", ">= 0"),
    ):
        sec, line = table.split("\n")
        head = "[inputs]\nleft='a'\nright='b'\n" + (line + "\n" if sec == "[inputs]" else "")
        body = "" if sec == "[inputs]" else f"{sec}\n{line}\n"
        p.write_text(head + "[output]\ndir='o'\n" + body)
        with pytest.raises(InputError, match=msg):
            load_config(p)
    p.write_text("not = [toml")
    with pytest.raises(InputError, match="not valid TOML"):
        load_config(p)


def test_config_tilde_is_the_home_folder(tmp_path, monkeypatch):
    """``~`` in a configuration's paths was taken as a folder named ``~`` beside the file
    (``dir = "~/out"`` made ``CONFIG_DIR/~/out``); it is the home folder, as in a shell."""
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    p = tmp_path / "cfg" / "job.toml"
    p.parent.mkdir()
    p.write_text(
        "[inputs]\nleft = '~/l.tif'\nright = 'r.tif'\nseed_dem = '~/seed.tif'\n"
        "[output]\ndir = '~/out'\n[ortho]\nfill_dem = '~/fill.tif'\n"
    )
    cfg = load_config(p)
    home = tmp_path / "home"
    assert cfg.output_dir == str(home / "out")
    assert (cfg.inputs.left, cfg.inputs.seed_dem) == (str(home / "l.tif"), str(home / "seed.tif"))
    assert cfg.ortho.fill_dem == str(home / "fill.tif")
    assert cfg.inputs.right == str(p.parent / "r.tif")  # relative: to the file


def test_cli_exit_codes_and_help(tmp_path, capsys):
    assert cli.main([]) == 2
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    for cmd in ("demo", "run", "simulate", "dem", "ortho", "assess"):
        with pytest.raises(SystemExit) as e:
            cli.main([cmd, "--help"])
        assert e.value.code == 0
        assert "example" in capsys.readouterr().out.lower()
    with pytest.raises(SystemExit) as e:
        cli.main(["run"])  # missing argument: bad usage
    assert e.value.code == 2
    assert cli.main(["run", str(tmp_path / "missing.toml")]) == 1
    assert "cannot read the configuration file (No such file" in capsys.readouterr().err


@pytest.mark.slow
def test_demo_command(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "stereodem.cli",
            "demo",
            "-o",
            str(tmp_path / "d"),
            "--size",
            "400",
            "400",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "NMAD" in r.stdout and (tmp_path / "d" / "result" / "dem.tif").exists()
    nmad = float(r.stdout.split("NMAD")[1].split("m")[0])
    assert nmad < 4.0


@pytest.mark.slow
def test_resume_reuses_finished_tiles(scene_dir, tmp_path, monkeypatch):
    first = run(_cfg(scene_dir, tmp_path / "r"))
    n_tiles = first["stages"]["stereo"]["tiles"]
    assert len(list((tmp_path / "r" / "tiles").glob("tile_*.npz"))) == n_tiles

    def must_not_run(*a, **k):
        raise AssertionError("a finished tile was recomputed")

    monkeypatch.setattr(sp, "process_tile", must_not_run)
    again = run(_cfg(scene_dir, tmp_path / "r", resume=True))
    assert not again["failed_tiles"]
    with rasterio.open(tmp_path / "r" / "raw" / "dem.tif") as ds:
        z = ds.read(1)
    assert np.isfinite(z).mean() > 0.2
    assert again["headline"]["nmad"] == pytest.approx(first["headline"]["nmad"])


@pytest.mark.slow
def test_a_pool_run_clears_an_interrupted_runs_leftovers_but_not_its_own_image_maps(
    scene_dir, tmp_path
):
    """The images' maps for the workers are written while the cache key is hashed: the
    leftovers of an interrupted run (maps, partial tiles) are removed before, this run's maps
    are what the workers read, and none is left after the run, refused or not."""
    out = tmp_path / "r"
    first = run(_cfg(scene_dir, out, workers=2))
    # with a second core the reference DEM was read ahead (pipeline.prefetch)
    assert first["stages"]["assess"]["reference_wait_s"] >= 0.0
    tiles = out / "tiles"
    (tiles / "shared-interrupted").mkdir()
    (tiles / "shared-interrupted" / "left.npy").write_bytes(b"old map")
    (tiles / "tile_0.npz.part").write_bytes(b"half a tile")
    again = run(_cfg(scene_dir, out, workers=2, resume=True))
    assert again["headline"]["nmad"] == pytest.approx(first["headline"]["nmad"])
    assert not list(tiles.glob("shared-*")) and not list(tiles.glob("*.part"))
    cfg = _cfg(scene_dir, out, workers=2, resume=True)
    cfg.stereo.matching.matcher = "ncc"
    with pytest.raises(InputError, match="other inputs or settings"):
        run(cfg)
    assert not list(tiles.glob("shared-*"))


@pytest.mark.slow
def test_resume_refuses_tiles_of_another_job(scene_dir, tmp_path, monkeypatch):
    out = tmp_path / "r"
    run(_cfg(scene_dir, out))
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert "dem.tif" in before and "run.json" in before
    cfg = _cfg(scene_dir, out, resume=True)
    cfg.stereo.matching.matcher = "ncc"  # other settings: the cache is not this job's
    with pytest.raises(InputError, match="other inputs or settings"):
        run(cfg)
    # the refused resume took nothing of the previous job (set aside, then put back)
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert after == before
    assert not list(out.glob(".stereodem-removing-*"))
    # nor does a rerun with --overwrite that fails before writing its own products

    def failing_stereo(*args, **kwargs):
        raise InputError("no tile could be matched")

    with monkeypatch.context() as m:
        m.setattr(job, "stereo_stage", failing_stereo)
        with pytest.raises(InputError, match="no tile could be matched"):
            run(_cfg(scene_dir, out, overwrite=True))
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert after == before
    assert not list(out.glob(".stereodem-removing-*"))
    # a fresh (non-resumed) run replaces the cache, so a later resume is consistent again
    stale = out / "tiles" / "tile_99999.npz"
    stale.write_bytes(b"stale")
    cfg = _cfg(scene_dir, out, overwrite=True)
    cfg.stereo.matching.matcher = "ncc"
    run(cfg)
    assert not stale.exists()


def test_pool_workers_get_memory_mapped_images(tmp_path):
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    sa = SharedArray.create(a, tmp_path, "img")
    clone = pickle.loads(pickle.dumps(sa))
    assert len(pickle.dumps(sa)) < 200  # the path, not the pixels
    assert clone.shape == (3, 4) and clone.dtype == np.float32 and clone.ndim == 2
    np.testing.assert_array_equal(clone[1:, 2:], a[1:, 2:])
    np.testing.assert_array_equal(np.asarray(clone, dtype=np.float64), a)


EXPECTED_COMMANDS = {"demo", "run", "simulate", "dem", "filter", "ortho", "assess"}


def test_every_subcommand_is_wired_to_its_run_function():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert EXPECTED_COMMANDS <= set(sub.choices), EXPECTED_COMMANDS - set(sub.choices)
    for name, p in sub.choices.items():
        assert callable(p.get_default("run")), name


@pytest.mark.slow
def test_hand_route_gives_the_rasters_of_run(scene_dir, tmp_path):
    """dem -> filter -> ortho -> assess on the command line equals `stereodem run`."""
    run(_cfg(scene_dir, tmp_path / "run", workers=1))
    h = tmp_path / "hand"
    left, right = str(scene_dir / "left.tif"), str(scene_dir / "right.tif")
    assert (
        cli.main(
            [
                "dem",
                left,
                right,
                "-o",
                str(h / "dem"),
                "--tile-size",
                "200",
                "--height-range",
                "1000",
                "3500",
                "--workers",
                "1",
            ]
        )
        == 0
    )
    assert cli.main(["filter", str(h / "dem" / "dem.tif"), "-o", str(h / "clean.tif")]) == 0
    assert (
        cli.main(
            [
                "ortho",
                left,
                "--dem",
                str(h / "clean.tif"),
                "-o",
                str(h / "ortho.tif"),
                "--workers",
                "1",
            ]
        )
        == 0
    )
    assert (
        cli.main(
            [
                "assess",
                str(h / "clean.tif"),
                "--ref",
                str(scene_dir / "truth_dem.tif"),
                "--ref-vertical",
                "ellipsoid",
                "--checkpoints",
                str(scene_dir / "points.csv"),
                "--coregister",
                "-o",
                str(h / "assess"),
            ]
        )
        == 0
    )
    pairs = {
        "raw/dem.tif": "dem/dem.tif",
        "raw/score.tif": "dem/score.tif",
        "raw/raygap.tif": "dem/raygap.tif",
        "dem.tif": "clean.tif",
        "dem_edit_mask.tif": "clean_edit_mask.tif",
        "ortho_left.tif": "ortho.tif",
    }
    for a_name, b_name in pairs.items():
        with rasterio.open(tmp_path / "run" / a_name) as a, rasterio.open(h / b_name) as b:
            assert a.transform == b.transform and a.crs == b.crs, a_name
            assert np.array_equal(a.read(), b.read(), equal_nan=True), a_name
    ra = json.loads((tmp_path / "run" / "assess" / "report.json").read_text())
    rb = json.loads((h / "assess" / "report.json").read_text())
    assert ra["stats"] == rb["stats"]


@pytest.fixture(scope="module")
def granule(tmp_path_factory):
    """A small simulated ASTER L1A V004 granule (3N 300 x 300, 3B in the real size ratio)."""
    d = tmp_path_factory.mktemp("granule")
    sc = simulate_scene(
        "aster", size=(300, 300), right_size=granule_right_size((300, 300)), seed=3, n_points=20
    )
    return write_granule_scene(sc, d, version=4, seed=3), sc


@pytest.mark.slow
def test_granule_as_delivered_to_dem_and_ortho(granule, tmp_path):
    """`dem GRANULE` takes 3N/3B; `ortho GRANULE --band 3B` orthorectifies the backward band."""
    path, sc = granule
    lo, hi = sc.truth_dem.height_range()
    assert (
        cli.main(
            [
                "dem",
                str(path),
                "-o",
                str(tmp_path / "d"),
                "--height-range",
                str(lo - 100),
                str(hi + 100),
                "--workers",
                "1",
            ]
        )
        == 0
    )
    rep = json.loads((tmp_path / "d" / "dem_report.json").read_text())
    assert (
        rep["input_metadata"]["ASTER_BAND"] == "3N"
        and rep["input_metadata"]["RIGHT_ASTER_BAND"] == "3B"
    )
    with rasterio.open(tmp_path / "d" / "dem.tif") as ds:
        z = ds.read(1)
    assert np.isfinite(z).mean() > 0.5 and lo - 100 < np.nanmedian(z) < hi + 100
    assert (
        cli.main(
            [
                "ortho",
                str(path),
                "--band",
                "3B",
                "--dem",
                str(tmp_path / "d" / "dem.tif"),
                "-o",
                str(tmp_path / "o.tif"),
                "--workers",
                "1",
            ]
        )
        == 0
    )
    with rasterio.open(tmp_path / "o.tif") as ds:
        assert ds.tags()["ASTER_BAND"] == "3B" and ds.dtypes[0] == "float32"  # radiance
    # a band name on a plain GeoTIFF is a clear error
    assert (
        cli.main(
            [
                "ortho",
                str(tmp_path / "o.tif"),
                "--band",
                "3N",
                "--dem",
                str(tmp_path / "d" / "dem.tif"),
                "-o",
                str(tmp_path / "x.tif"),
            ]
        )
        == 1
    )


@pytest.mark.slow
def test_run_writes_uncertainty_maps_when_asked(scene_dir, tmp_path):
    raw = {
        "inputs": {"left": str(scene_dir / "left.tif"), "right": str(scene_dir / "right.tif")},
        "output": {"dir": str(tmp_path / "u")},
        "rectification": {"tile_size": 200, "height_range": [1000, 3500]},
        "ortho": {"both": False},
        "uncertainty": {"enabled": True, "sigma": {"pitch_bias": 1e-5, "dem_height": 5.0}},
        "run": {"workers": 1},
    }
    info = run(config_from_dict(raw))
    out = tmp_path / "u"
    for name in (
        "uncertainty/sigma_horizontal.tif",
        "uncertainty/sensitivity.json",
        "dem_sigma_vertical.tif",
    ):
        assert (out / name).exists(), name
    shares = info["stages"]["uncertainty"]["shares"]
    assert set(shares) == {"pitch_bias", "dem_height"} and sum(shares.values()) == pytest.approx(
        1.0
    )
    with (
        rasterio.open(out / "uncertainty" / "sigma_horizontal.tif") as a,
        rasterio.open(out / "ortho_left.tif") as b,
    ):
        assert a.transform == b.transform and a.shape == b.shape
        s = a.read(1)
    # 10 urad of pitch at ~700 km is ~7 m on the ground: the map is of that order
    assert 3.0 < np.nanmedian(s) < 30.0
    with pytest.raises(InputError, match="needs sigma"):
        config_from_dict({**raw, "uncertainty": {"enabled": True}})


@pytest.mark.parametrize(
    "argv, message",
    [
        (["dem", "a.tif", "b.tif", "-o", "o", "--co", "COMPRESS"], "KEY=VALUE"),
        (["dem", "a.tif", "b.tif", "-o", "o", "--co", "COMPRESS=NOPE"], "'NOPE' is an unexpected"),
        (["filter", "d.tif", "-o", "c.tif", "--co", "ZSTD_LEVL=9"], "ZSTD_LEVL"),
        (["dem", "a.tif", "b.tif", "-o", "o", "--jitter-correction"], "seed DEM"),
        (["dem", "a.tif", "b.tif", "-o", "o", "--pointing-from-seed"], "seed DEM"),
        (["filter", "d.tif", "-o", "c.tif", "--fill-from-seed"], "--seed-dem"),
    ],
)
def test_new_options_reject_bad_values_before_any_work(
    tmp_path, capsys, monkeypatch, argv, message
):
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "o").exists() and not (tmp_path / "c.tif").exists()


@pytest.mark.parametrize("extra", [[], ["--no-fill"]])
def test_filter_removing_every_cell_names_the_dem(tmp_path, capsys, extra):
    """A 3 x 3 DEM: the blunder filters remove all its cells; the error said "the DEM has no
    valid height to fill from" (no file), or with --no-fill named the output as all void."""
    z = np.arange(9, dtype=np.float32).reshape(3, 3) + 1500
    DEM(z, rasterio.Affine(30, 0, 5e5, 0, -30, 4.3e6), "EPSG:32637", "geoid").write(
        tmp_path / "tiny.tif"
    )
    out = tmp_path / "clean.tif"
    assert cli.main(["filter", str(tmp_path / "tiny.tif"), "-o", str(out), *extra]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert "tiny.tif: the blunder filters removed all 9 valid cells" in err[0], err
    assert not out.exists()


def test_band_names_are_checked_by_the_parser(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["ortho", "a.tif", "--dem", "d.tif", "-o", "o.tif", "--band", "3X"])
    assert e.value.code == 2 and "3N/3B" in capsys.readouterr().err


def test_top_level_help_lists_every_command_without_importing_them():
    """`stereodem --help` (and a bare or misspelt `stereodem`) lists the commands from
    stereodem.commands alone; each command's own parser carries the same summary."""
    code = (
        "import sys, contextlib, io\n"
        "from stereodem.cli import main\n"
        "buf = io.StringIO()\n"
        "with contextlib.redirect_stdout(buf):\n"
        "    try:\n"
        "        main(['--help'])\n"
        "    except SystemExit:\n"
        "        pass\n"
        "mods = sorted(m for m in sys.modules if m.endswith('_cli'))\n"
        "print(repr(mods)); print(buf.getvalue())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    first, _, text = out.stdout.partition("\n")
    assert first == "[]"
    for name in COMMANDS:
        assert name in text
    full = cli.build_parser()
    sub = next(a for a in full._actions if a.__class__.__name__ == "_SubParsersAction")
    helps = {a.dest: a.help for a in sub._choices_actions}
    assert helps == {name: summary for name, (_, summary) in COMMANDS.items()}
    with pytest.raises(SystemExit) as exc:
        cli.main(["no-such-command"])
    assert exc.value.code == 2


def test_command_parsers_load_no_numpy():
    """A command's parser loads no numpy/OpenCV/rasterio (DESIGN.md, imports, reason (a)):
    change, compare-models, mosaic and stack imported core.jsonutil (numpy) at their top;
    adjust's --model choices came from the sensor packages (now sensor.choices)."""
    names = list(COMMANDS)
    assert "adjust" in names
    code = (
        "import sys\n"
        "from stereodem.cli import build_parser\n"
        f"for name in {names!r}:\n"
        "    build_parser(name)\n"
        "    heavy = [m for m in ('numpy', 'cv2', 'rasterio', 'scipy') if m in sys.modules]\n"
        "    assert not heavy, (name, heavy)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_clean_tiles_option_reaches_the_job(tmp_path, monkeypatch):
    """``run --clean-tiles`` is ``[run] keep_tiles = false``; without it the TOML decides."""
    seen = []

    def fake_run(cfg, progress_factory=None):
        seen.append(cfg.run.keep_tiles)
        raise InputError("stop here")

    monkeypatch.setattr(job, "run", fake_run)
    toml = tmp_path / "job.toml"
    toml.write_text('[inputs]\nleft = "l.tif"\nright = "r.tif"\n[output]\ndir = "out"\n')
    assert cli.main(["-q", "run", str(toml), "--clean-tiles"]) == 1
    assert cli.main(["-q", "run", str(toml)]) == 1
    toml.write_text(toml.read_text() + "[run]\nkeep_tiles = false\n")
    assert cli.main(["-q", "run", str(toml)]) == 1
    assert seen == [False, True, False]
    toml.write_text(toml.read_text().replace("keep_tiles = false", 'keep_tiles = "no"'))
    assert cli.main(["-q", "run", str(toml)]) == 1  # a one-line error, the job not started
    assert seen == [False, True, False]


def test_summary_names_every_orthoimage_written():
    """The closing lines of ``stereodem run`` list each orthoimage of run.json's outputs (the
    right one too with ``[ortho] both``), not a fixed left one."""
    info = {
        "config": {"output": {"dir": "out"}},
        "stages": {"ortho": {}},
        "outputs": ["dem.tif", "ortho_left.tif", "ortho_right.tif", "run.json"],
        "warnings": [],
        "failed_tiles": [],
        "seconds": 1.0,
    }
    buf = io.StringIO()
    summarize(info, buf)
    lines = [ln for ln in buf.getvalue().splitlines() if ln.startswith("orthoimage:")]
    assert lines == ["orthoimage: out/ortho_left.tif", "orthoimage: out/ortho_right.tif"]
    info["outputs"] = ["dem.tif", "run.json"]  # [ortho] enabled = false
    buf = io.StringIO()
    summarize(info, buf)
    assert "orthoimage" not in buf.getvalue()


def test_no_option_help_states_its_default_twice():
    """Each option's help says its default once (``stack --workers`` said "(default: all
    cores) (default: all cores)": its text carried the default that ``add_workers`` adds)."""
    full = cli.build_parser()
    sub = next(a for a in full._actions if a.__class__.__name__ == "_SubParsersAction")
    for name in COMMANDS:
        for action in sub.choices[name]._actions:
            text = action.help or ""
            assert len(re.findall(r"\(default", text)) <= 1, (name, action.dest, text)


def test_the_sparse_line_says_the_margin_of_the_heights_searched():
    """``stereodem dem --height-range 2100 2600`` printed "heights 2050..2610 m (height
    range)": a range that is not the one given, without saying why (the 50 m margin each
    side, then the models' validity range, 2610 m on the real Pleiades pair)."""
    info = {"height_range": [2050.0, 2610.0], "height_source": "height range"}
    assert sparse_line({**info, "height_margin_m": 50.0}).startswith(
        "  heights 2050..2610 m (height range +/- 50 m, within the models' validity)"
    )
    no_margin = {"height_range": [-20.0, 2610.0], "height_source": "model validity range"}
    assert sparse_line(no_margin).startswith("  heights -20..2610 m (model validity range)")


def test_filter_summary_counts_the_cells_filled_from_the_seed():
    """``filter --fill-from-seed``'s result line counted the IDW fills alone ("filled": 2 on a
    simulated DEM brought to 100 % valid by 10 119 cells from the seed DEM)."""
    from stereodem.filter_cli import _summary

    report = {"fill": {"filled_idw": 2, "filled_fallback": 10119}}
    assert _summary(report) == {"filled": 2, "filled_from_seed": 10119}
    assert _summary({"fill": {"filled_idw": 2, "filled_fallback": 0}}) == {"filled": 2}
