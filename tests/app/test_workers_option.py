"""``--workers`` in every command that computes (issue 28, "threads under control"): the
option is accepted, ``--workers 0`` / negative is refused before any work, the command runs
under that thread budget (OpenCV, BLAS/OpenMP, GDAL, :mod:`stereodem.core.blocks`), and its
products do not depend on it."""

from __future__ import annotations

import importlib
import json

import numpy as np
import pytest
import rasterio

from stereodem import cli
from stereodem.core import blocks, threads
from stereodem.core.dem import DEM

#: commands whose numeric work ran on the libraries' defaults (all cores) before they took
#: ``--workers``, and mosaic (whose --workers was the Dask cluster's only)
COMMANDS = ("assess", "coregister", "filter", "adjust", "mosaic", "simulate", "compare-models")

#: commands that read no image and only list or describe: no --workers
NO_NUMERIC_WORK = {"info"}


class Seen(Exception):
    """Raised by a patched library function once it has recorded what it ran under."""


def _subparsers():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return sub.choices


def test_every_computing_command_takes_workers():
    for name, p in _subparsers().items():
        has = any("--workers" in a.option_strings for a in p._actions)
        assert has == (name not in NO_NUMERIC_WORK), name
        if name in COMMANDS:
            help_text = next(a.help for a in p._actions if "--workers" in a.option_strings)
            assert help_text.endswith("(default: all cores)"), (name, help_text)


@pytest.fixture(scope="module")
def dems(tmp_path_factory):
    """A DEM (600 x 400 cells of the bundled SRTM: two assessment blocks, several row bands)
    shifted, offset and noisy with blunders and a hole, and its reference."""
    d = tmp_path_factory.mktemp("dems")
    b = DEM.bundled()
    z = b.heights[:600, :400].astype(np.float32)
    rng = np.random.default_rng(3)
    noisy = (np.roll(z, (1, -1), axis=(0, 1)) + 3.0 + rng.normal(0, 2.0, z.shape)).astype(
        np.float32
    )
    spikes = rng.integers(0, z.size, 300)
    noisy.flat[spikes] += rng.choice([-1, 1], 300) * 200.0
    noisy[250:270, 100:140] = np.nan
    DEM(z, b.transform, b.crs, "geoid").write(d / "ref.tif")
    DEM(noisy, b.transform, b.crs, "geoid").write(d / "dem.tif")
    return d


def _argv(command, d, out):
    """A run of ``command`` on the fixture's files into ``out``."""
    dem, ref = str(d / "dem.tif"), str(d / "ref.tif")
    return {
        "assess": ["assess", dem, "--ref", ref, "-o", str(out)],
        "coregister": ["coregister", dem, "--ref", ref, "--no-figures", "-o", str(out)],
        "filter": ["filter", dem, "-o", str(out / "clean.tif")],
        "adjust": [
            "adjust",
            str(d / "img.tif"),
            "--model",
            "rpc-shift",
            "--gcps",
            str(d / "gcps.csv"),
            "-o",
            str(out / "adj.model.json"),
        ],
        "mosaic": ["mosaic", dem, ref, "-o", str(out / "m.tif")],
        "simulate": ["simulate", "--size", "60", "60", "-o", str(out)],
        "compare-models": [
            "compare-models",
            str(d / "img.tif"),
            "--gcps",
            str(d / "gcps.csv"),
            "-o",
            str(out),
        ],
    }[command]


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("workers", ["0", "-2"])
def test_workers_below_one_is_refused_before_any_work(command, workers, dems, tmp_path, capsys):
    out = tmp_path / "out"
    argv = [*_argv(command, dems, out), "--workers", workers]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert f"stereodem {command}: error: --workers must be at least 1, got {workers}" in err
    assert "Traceback" not in err and not out.exists()


#: a library function each command calls once its inputs are checked, by module and name
PATCHED = {
    "assess": ("stereodem.pipeline.assessment", "assess_dem"),
    "coregister": ("stereodem.post.coreg_run", "run"),
    "filter": ("stereodem.pipeline.stages", "post_stage"),
    "adjust": ("stereodem.sensor.io.gcps", "read_gcps"),
    "mosaic": ("stereodem.post.mosaic", "plan_mosaic"),
    "simulate": ("stereodem.sensor.simulation.simulate", "simulate_scene"),
    "compare-models": ("stereodem.pipeline.inputs", "image_model"),
}


@pytest.mark.parametrize("command", COMMANDS)
def test_the_command_runs_under_its_workers_budget(command, dems, tmp_path, monkeypatch):
    """Inside the command (a library function it calls, patched to record and stop), OpenCV,
    BLAS, GDAL and the row blocks are pinned to ``--workers`` (at most the cores: 4 here),
    and restored after it."""
    module, name = PATCHED[command]
    mod = importlib.import_module(module)
    seen = {}

    def record(*args, **kwargs):
        seen.update(threads.current_limits(), blocks=blocks.default_threads())
        seen["threads_kwarg"] = kwargs.get("threads")
        cfg = next((a for a in args if hasattr(a, "run") and hasattr(a, "inputs")), None)
        seen["cfg_workers"] = None if cfg is None else cfg.run.workers
        raise Seen

    if command in ("adjust", "compare-models"):
        (dems / "img.tif").touch()
        (dems / "gcps.csv").write_text("id,lon,lat,h,col,row\n")
    monkeypatch.setattr(mod, name, record)
    monkeypatch.setattr(threads, "cores", lambda: 4)
    before = threads.current_limits()
    for workers, want in ((1, 1), (3, 3), (6, 4)):
        seen.clear()
        with pytest.raises(Seen):
            cli.main([*_argv(command, dems, tmp_path / f"o{workers}"), "--workers", str(workers)])
        assert seen["opencv"] == want, (command, seen)
        assert seen["gdal"] == threads.gdal_threads(want), (command, seen)
        assert seen["pinned"] == want and seen["blocks"] == want, (command, seen)
        assert seen["blas"] in (None, want), (command, seen)
        if command == "assess":  # the assessment's blocks: the budget, via [run] workers
            assert seen["threads_kwarg"] == want
        if command == "filter":  # the config the post stage reads: [run] workers = --workers
            assert seen["cfg_workers"] == workers
    assert threads.current_limits() == before


def _raster(path):
    with rasterio.open(path) as ds:
        return ds.read()


@pytest.mark.slow
def test_filter_and_assess_give_the_same_products_on_1_and_2_workers(dems, tmp_path, monkeypatch):
    monkeypatch.setattr(threads, "cores", lambda: 4)  # 2 threads even on a 1-core machine
    out = {}
    for w in (1, 2):
        o = tmp_path / f"w{w}"
        o.mkdir()
        assert cli.main(["-q", *_argv("filter", dems, o), "--workers", str(w)]) == 0
        assert cli.main(["-q", *_argv("assess", dems, o / "a"), "--workers", str(w)]) == 0
        report = json.loads((o / "a" / "report.json").read_text())
        out[w] = (
            _raster(o / "clean.tif"),
            _raster(o / "clean_edit_mask.tif"),
            {k: v for k, v in report.items() if k not in ("provenance", "files")},
        )
    clean1, mask1, rep1 = out[1]
    clean2, mask2, rep2 = out[2]
    assert (mask1 > 0).any() and np.isfinite(clean1).any()  # the filters did something
    np.testing.assert_array_equal(clean1, clean2)
    np.testing.assert_array_equal(mask1, mask2)
    assert rep1 == rep2 and rep1["stats"]["n"] > 0
