"""stereodem batch: one job per scene on the process pool and on a dask LocalCluster; a
corrupt scene fails with its reason and the others are done; a second run skips done scenes."""

import json
import logging
import re
import subprocess
import sys

import numpy as np
import pytest
import rasterio

from stereodem import cli, progress
from stereodem.batch import expand_inputs, run_batch, scene_config, scene_pool
from stereodem.config import load_config
from stereodem.core import jsonutil, worker_logging
from stereodem.core.errors import InputError
from stereodem.sensor.simulation.simulate import simulate_scene, write_scene
from stereodem.stereo.execution import _check_tile_cache

CONFIG = """
[inputs]
left = "{d}/left.tif"
right = "{d}/right.tif"
reference_dem = "{d}/truth_dem.tif"
reference_vertical = "ellipsoid"

[output]
dir = "ignored"

[rectification]
tile_size = 160
height_range = [1000, 3500]

[ortho]
both = false
"""


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Two tiny simulated pairs (240 x 240, as configurations) and a corrupt granule."""
    root = tmp_path_factory.mktemp("batch")
    paths = []
    for seed in (4, 5):
        d = root / f"scene{seed}"
        write_scene(
            simulate_scene("aster", size=(240, 240), seed=seed, n_points=10), d, overwrite=True
        )
        cfg = root / f"scene{seed}.toml"
        cfg.write_text(CONFIG.format(d=d))
        paths.append(cfg)
    bad = root / "AST_L1A_corrupt.hdf"
    bad.write_bytes(b"\x0e\x03\x13\x01" + bytes(range(256)) * 8)  # HDF4 magic, then junk
    paths.append(bad)
    listing = root / "scenes.txt"
    listing.write_text("# three scenes\n" + "\n".join(p.name for p in paths) + "\n")
    return root, paths, listing


def _check(result, out):
    rows = {r["name"]: r for r in result["scenes"]}
    assert [rows[n]["status"] for n in ("scene4", "scene5", "AST_L1A_corrupt")] == [
        "done",
        "done",
        "failed",
    ]
    reason = rows["AST_L1A_corrupt"]["reason"]
    assert "AST_L1A_corrupt.hdf" in reason and "\n" not in reason and "Traceback" not in reason
    assert result["summary"] == {"done": 2, "failed": 1, "skipped": 0, "pending": 0}
    assert json.loads((out / "batch.json").read_text())["summary"] == result["summary"]
    for n in ("scene4", "scene5"):
        assert json.loads((out / n / "run.json").read_text())["status"] == "ok"
        with rasterio.open(out / n / "dem.tif") as ds:
            assert np.isfinite(ds.read(1)).mean() > 0.3
    assert not (out / "AST_L1A_corrupt" / "dem.tif").exists()


@pytest.mark.slow
def test_batch_on_the_pool_and_resume(scenes, tmp_path, capsys):
    _, _, listing = scenes
    out = tmp_path / "out"
    assert cli.main(["batch", str(listing), "-o", str(out), "--workers", "2"]) == 1  # one failed
    result = json.loads((out / "batch.json").read_text())
    assert result["backend"] == "pool" and result["workers"] == 2
    _check(result, out)
    printed = capsys.readouterr().out
    assert "FAILED" in printed and "2 done, 1 failed" in printed
    assert list((out / "scene4" / "tiles").glob("tile_*.npz"))  # kept by default
    # again: the done scenes are skipped, the corrupt one fails again, nothing recomputed
    mtime = (out / "scene4" / "dem.tif").stat().st_mtime_ns
    again = run_batch(expand_inputs([listing]), out, workers=2)
    st = {r["name"]: r["status"] for r in again["scenes"]}
    assert st == {"scene4": "skipped", "scene5": "skipped", "AST_L1A_corrupt": "failed"}
    assert (out / "scene4" / "dem.tif").stat().st_mtime_ns == mtime


@pytest.mark.slow
def test_batch_on_a_dask_local_cluster(scenes, tmp_path):
    pytest.importorskip("dask.distributed")
    _, paths, _ = scenes
    out = tmp_path / "out"
    result = run_batch(expand_inputs(paths), out, workers=2, dask="local", keep_tiles=False)
    assert result["backend"] == "dask"
    _check(result, out)
    for n in ("scene4", "scene5"):  # --clean-tiles: the done scenes' caches removed
        assert not (out / n / "tiles").exists()


def test_list_files_names_and_missing_scenes(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.toml").write_text("")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "x.toml").write_text("")
    lst = tmp_path / "l.txt"
    lst.write_text("a/x.toml\nb/x.toml  # the same stem\n\nnone.hdf\n")
    sc = expand_inputs([lst])
    assert [(s.name, s.kind) for s in sc] == [
        ("x", "config"),
        ("x_2", "config"),
        ("none", "missing"),
    ]
    result = run_batch([sc[2]], tmp_path / "out", workers=1)
    row = result["scenes"][0]
    assert row["status"] == "failed" and row["reason"].endswith(
        "none.hdf: cannot read the scene (No such file or directory)"
    )


def test_a_scene_that_is_neither_a_granule_nor_a_configuration_says_so(tmp_path):
    """A GeoTIFF or a folder given as a scene failed with "batch defaults: [inputs] needs
    'right' (only an ASTER granule is a pair alone)": true, but not what was wrong. The
    granule reader's reason and what a scene may be, in the scene's row; the others run."""
    tif = tmp_path / "dem.tif"
    tif.write_bytes(b"II*\x00")
    folder = tmp_path / "scenes"
    folder.mkdir()
    result = run_batch(expand_inputs([tif, folder]), tmp_path / "out", workers=1)
    tail = "; a batch scene is an ASTER L1A granule or a configuration (.toml)"
    reasons = [r["reason"] for r in result["scenes"]]
    assert reasons == [
        f"{tif}: not an ASTER L1A granule (neither an HDF4 file, as V004 granules are, nor a "
        "V003 zip or folder)" + tail,
        f"{folder}: not an ASTER L1A V003 granule (no AST_L1A_*.VNIR_Band3N.ImageData.tif / "
        "VNIR_Band3B images)" + tail,
    ]


def test_a_scene_given_twice_and_an_unreadable_template_are_refused(tmp_path):
    # the same configuration twice (a list and the command line) ran twice, into x and x_2;
    # a --template that does not exist was ignored when no granule needed it
    (tmp_path / "x.toml").write_text("")
    (tmp_path / "l.txt").write_text("x.toml\n")
    with pytest.raises(InputError, match=r"x.toml: scene given twice"):
        expand_inputs([tmp_path / "l.txt", tmp_path / "x.toml"])
    with pytest.raises(InputError, match=r"none.toml: cannot read the template configuration"):
        expand_inputs([tmp_path / "x.toml"], template=str(tmp_path / "none.toml"))
    (tmp_path / "bad.toml").write_text("[run\n")
    with pytest.raises(InputError, match=r"bad.toml: cannot read the template"):
        expand_inputs([tmp_path / "x.toml"], template=str(tmp_path / "bad.toml"))


def test_a_done_scene_whose_configuration_changed_is_not_skipped(tmp_path, monkeypatch):
    """A scene done before and edited since (another matcher) was skipped as "already done":
    its products, of the old settings, stood as the new configuration's. It fails naming its
    run.json until --overwrite; unchanged, it is skipped from any working folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "cfg").mkdir()
    cfg = tmp_path / "cfg" / "a.toml"
    cfg.write_text(CONFIG.format(d="../data"))
    out = tmp_path / "out"
    done = _done_scene(out, cfg, monkeypatch)
    for where, scene in ((tmp_path, "cfg/a.toml"), (tmp_path / "cfg", "a.toml")):
        monkeypatch.chdir(where)
        row = run_batch(expand_inputs([scene]), out.absolute(), workers=1)["scenes"][0]
        assert row["status"] == "skipped", row
    # a run.json of an older version, which lacked a key (and had one since removed): no edit
    older = done.to_dict()
    section = next(
        k for k, v in older.items() if isinstance(v, dict) and v and k not in ("run", "matching")
    )
    older[section].pop(sorted(older[section])[0])
    older[section]["a_key_since_removed"] = 1
    (out / "a" / "run.json").write_text(json.dumps({"status": "ok", "config": older}))
    row = run_batch(expand_inputs(["a.toml"]), out.absolute(), workers=1)["scenes"][0]
    assert row["status"] == "skipped", row
    cfg.write_text(CONFIG.format(d="../data") + '[matching]\nmatcher = "ncc"\n')
    row = run_batch(expand_inputs(["a.toml"]), out, workers=1)["scenes"][0]
    assert row["status"] == "failed" and "run.json: done with other settings" in row["reason"]
    assert "--overwrite" in row["reason"]


def _batch_folder(out, rows=()):
    """``out`` as an earlier batch left it: its ``batch.json`` (stamped, with ``rows``), which
    makes the folder a batch's (the overwrite policy refuses a folder of the user's)."""
    out.mkdir(parents=True, exist_ok=True)
    table = {"started": "2026-01-01T00:00:00.000000Z", "scenes": list(rows)}
    (out / "batch.json").write_text(jsonutil.dumps(jsonutil.stamped(table)))


def _done_scene(out, cfg, monkeypatch):
    """``out/<scene>/run.json`` as the job records a finished scene of ``cfg``
    (stereodem.pipeline.job.run), in a batch's folder, without running it; running a scene
    fails the test. Returns the scene's configuration."""
    _batch_folder(out)
    (out / cfg.stem).mkdir(parents=True)
    done = load_config(cfg.absolute())
    (out / cfg.stem / "run.json").write_text(json.dumps({"status": "ok", "config": done.to_dict()}))
    monkeypatch.setattr("stereodem.batch.run", lambda c: pytest.fail("ran a done scene"))
    return done


def test_a_skipped_scene_reads_with_one_level_of_brackets(tmp_path, monkeypatch, capsys):
    """The progress line and the status table say "skipped: already done (run.json status
    ok)" (it read "skipped (already done (run.json status ok))"); batch.json keeps its
    status and reason fields as they were."""
    monkeypatch.chdir(tmp_path)
    cfg = tmp_path / "a.toml"
    cfg.write_text(CONFIG.format(d="data"))
    out = tmp_path / "out"
    _done_scene(out, cfg, monkeypatch)
    capsys.readouterr()
    assert cli.main(["batch", str(cfg), "-o", str(out), "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    assert "  a: skipped: already done (run.json status ok)\n" in printed
    assert f"  {'a':24s} skipped: already done (run.json status ok)\n" in printed
    assert "((" not in printed and "))" not in printed
    row = json.loads((out / "batch.json").read_text())["scenes"][0]
    assert (row["status"], row["reason"]) == ("skipped", "already done (run.json status ok)")


@pytest.mark.slow
@pytest.mark.parametrize("verbose", [0, 1])
def test_the_scene_pools_workers_log_as_the_main_process(verbose, monkeypatch, capfd):
    """A warning logged in a batch worker reads "WARNING logger: message" as in a serial run
    (it printed the message alone: a spawned worker had no handler but Python's last resort),
    and -v's info lines of a worker are not lost."""
    monkeypatch.setattr(worker_logging, "_SPEC", None)
    progress.setup_logging(verbose=verbose)  # as the command line does (pytest's handlers stay)
    pool = scene_pool(1, 1)
    try:
        log = logging.getLogger("stereodem.post.assess")
        pool.submit(log.warning, "%s: only %d cells", "dem.tif", 12).result()
        pool.submit(log.info, "an info line").result()
    finally:
        pool.shutdown()
    err = capfd.readouterr().err
    assert re.search(r"^(\S+ )?WARNING stereodem.post.assess: dem.tif: only 12 cells$", err, re.M)
    assert ("INFO stereodem.post.assess: an info line" in err) == bool(verbose)
    if verbose:  # UTC timestamps with -v, as the main process's lines
        assert re.search(r"^\d{4}-\d\d-\d\dT\S+Z WARNING ", err, re.M), err


def test_a_failed_scene_whose_configuration_changed_says_what_batch_takes(tmp_path, monkeypatch):
    """A scene that failed (or was interrupted) and was edited since is refused by the tile
    cache's resume check; the reason was stereodem run's, "run again without --resume (and
    with --overwrite)", and batch has no --resume flag. It says to pass --overwrite (or use
    another -o); and --overwrite recomputes the scene."""
    cfg = tmp_path / "a.toml"
    cfg.write_text(CONFIG.format(d=tmp_path / "data"))
    out = tmp_path / "out"
    _batch_folder(out)
    tiles = out / "a" / "tiles"
    tiles.mkdir(parents=True)
    (tiles / "job.json").write_text(json.dumps({"key": "the failed run's settings"}))
    (tiles / "tile_0.npz").write_bytes(b"a finished tile of the failed run")

    def run(c):  # the job up to its tile cache check (stereodem.stereo.execution), no stereo
        _check_tile_cache(tiles, "the edited configuration's", c.run.resume)
        return {}

    monkeypatch.setattr("stereodem.batch.run", run)
    row = run_batch(expand_inputs([cfg]), out, workers=1)["scenes"][0]
    assert row["status"] == "failed"
    assert row["reason"].startswith(f"{tiles}: the cached tiles belong to a run with other")
    assert "pass --overwrite to recompute that scene" in row["reason"]
    assert "--resume" not in row["reason"]
    assert (tiles / "tile_0.npz").exists()  # kept: nothing was recomputed
    row = run_batch(expand_inputs([cfg]), out, workers=1, overwrite=True)["scenes"][0]
    assert row["status"] == "done", row
    assert not (tiles / "tile_0.npz").exists()


def test_a_scene_configuration_needs_no_output_dir(tmp_path):
    """batch writes each scene into OUT/<name>, whatever its [output] dir says: a
    configuration without one failed ("[output] needs 'dir'") though it would be ignored."""
    img = tmp_path / "l.tif"
    img.write_bytes(b"")
    cfg = tmp_path / "s.toml"
    cfg.write_text(f'[inputs]\nleft = "{img}"\nright = "{img}"\n')
    (scene,) = expand_inputs([cfg])
    got = scene_config(scene, tmp_path / "out" / "s")
    assert got.output_dir == str(tmp_path / "out" / "s")
    # `stereodem run` itself still needs it; a misspelt [output] key is still refused
    with pytest.raises(InputError, match=r"\[output\] needs 'dir'"):
        load_config(cfg)
    cfg.write_text(f'[inputs]\nleft = "{img}"\nright = "{img}"\n[output]\ndri = "x"\n')
    with pytest.raises(InputError, match=r"dri \(did you mean dir\?\)"):
        scene_config(scene, tmp_path / "out" / "s")


@pytest.mark.slow  # a LocalCluster's start and stop (~3 s)
def test_dask_local_prints_no_cluster_chatter(tmp_path):
    """`batch --dask local` printed some twenty INFO lines of distributed's (scheduler,
    nanny, connections) around its own: distributed sets its logger to INFO on import."""
    pytest.importorskip("dask.distributed")
    cfg = tmp_path / "a.toml"
    cfg.write_text('[inputs]\nleft = "none_l.tif"\nright = "none_r.tif"\n')
    code = "import sys; from stereodem.cli import main; sys.exit(main(sys.argv[1:]))"
    args = [str(cfg), "-o", str(tmp_path / "out"), "--dask", "local", "--workers", "1"]
    done = subprocess.run(
        [sys.executable, "-c", code, "batch", *args], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 1, done.stderr  # the scene fails: its images do not exist
    assert "1 failed" in done.stdout
    assert "distributed" not in done.stderr, done.stderr


def test_an_interrupted_batch_says_how_to_resume(tmp_path, monkeypatch, capsys):
    """Ctrl-C during a batch: the hint is batch's (run it again: done scenes are skipped), not
    "no product was written ... --overwrite" (which would recompute the done scenes), and
    batch.json lists the scene done and the one pending."""
    import signal

    from stereodem import batch
    from stereodem.batch import SceneStatus

    for n in ("a", "b"):
        (tmp_path / f"{n}.toml").write_text("")
    calls = []

    def fake(scene, out_root, *args, **kwargs):
        calls.append(scene.name)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return SceneStatus(scene.name, scene.path, "done")

    monkeypatch.setattr(batch, "run_scene", fake)
    out = tmp_path / "out"
    argv = ["batch", str(tmp_path / "a.toml"), str(tmp_path / "b.toml"), "-o", str(out)]
    rc = cli.main([*argv, "--workers", "1"])
    assert rc == 128 + signal.SIGINT
    err = capsys.readouterr().err
    assert "interrupted" in err and "run the same command again" in err
    assert "--overwrite" not in err and "no product was written" not in err
    table = json.loads((out / "batch.json").read_text())
    assert table["summary"] == {"done": 1, "failed": 0, "skipped": 0, "pending": 1}


def _fake_scenes(monkeypatch, outcome):
    """Scenes that run at once: ``outcome[name]`` is the status ``run_scene`` returns; the
    names run are returned in a list."""
    from stereodem import batch
    from stereodem.batch import SceneStatus

    ran = []

    def fake(scene, out_root, *args, **kwargs):
        ran.append(scene.name)
        status = outcome[scene.name]
        return SceneStatus(
            scene.name, scene.path, status, reason="bad" if status == "failed" else ""
        )

    monkeypatch.setattr(batch, "run_scene", fake)
    return ran


def test_batch_json_keeps_the_scenes_of_earlier_batches(tmp_path, monkeypatch, capsys):
    """`batch a b -o OUT` then `batch c a -o OUT`: batch.json listed c and a only, though b's
    products were in OUT. It lists every scene of OUT, merged by name (a's new row replaces
    its old one), says how many rows this run wrote, and the exit status is this run's."""
    for n in "abc":
        (tmp_path / f"{n}.toml").write_text("")
    out = tmp_path / "out"

    def batch(*names):
        argv = ["batch", *(str(tmp_path / f"{n}.toml") for n in names), "-o", str(out)]
        rc = cli.main([*argv, "--workers", "1"])
        return rc, json.loads((out / "batch.json").read_text()), capsys.readouterr().out

    outcome = {"a": "done", "b": "done", "c": "done"}
    ran = _fake_scenes(monkeypatch, outcome)
    rc, first, _ = batch("a", "b")
    assert rc == 0 and [r["name"] for r in first["scenes"]] == ["a", "b"]
    outcome["a"] = "failed"
    rc, table, printed = batch("c", "a")
    assert rc == 1 and ran == ["a", "b", "c", "a"]
    rows = {r["name"]: r for r in table["scenes"]}
    assert [r["name"] for r in table["scenes"]] == ["a", "b", "c"]
    assert rows["a"]["status"] == "failed" and rows["a"]["batch_started"] == table["started"]
    assert rows["b"] == next(r for r in first["scenes"] if r["name"] == "b")  # kept as it was
    assert rows["c"]["batch_started"] == table["started"] != first["started"]
    assert table["summary"] == {"done": 2, "failed": 1, "skipped": 0, "pending": 0}
    assert table["this_run"] == {"scenes": 2, "done": 1, "failed": 1, "skipped": 0, "pending": 0}
    assert "2 scene(s): 1 done, 1 failed" in printed
    assert "3 row(s), 2 from this run, 1 from earlier runs" in printed
    assert f"  {'b':24s}" not in printed  # the scene lines are this run's
    rc, table, _ = batch("b")  # a's failure is an earlier run's: not this run's exit status
    assert rc == 0 and table["summary"]["failed"] == 1 and len(table["scenes"]) == 3


def test_an_interrupted_batch_keeps_the_earlier_rows_of_scenes_it_did_not_reach(
    tmp_path, monkeypatch, capsys
):
    """`batch a b -o OUT`, then `batch c a b -o OUT` stopped while c runs: the table said a
    and b were pending, though their products were there, done. A scene this batch has not
    reached keeps its earlier row; this run's counts still say pending."""
    from stereodem import batch as batch_module

    for n in "abc":
        (tmp_path / f"{n}.toml").write_text("")
    out = tmp_path / "out"

    def argv(*names):
        return ["batch", *(str(tmp_path / f"{n}.toml") for n in names), "-o", str(out)]

    _fake_scenes(monkeypatch, {"a": "done", "b": "done"})
    assert cli.main([*argv("a", "b"), "--workers", "1"]) == 0
    first = {r["name"]: r for r in json.loads((out / "batch.json").read_text())["scenes"]}

    def stopped(scene, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(batch_module, "run_scene", stopped)
    with pytest.raises(KeyboardInterrupt):
        run_batch(expand_inputs([tmp_path / f"{n}.toml" for n in "cab"]), out, workers=1)
    table = json.loads((out / "batch.json").read_text())
    rows = {r["name"]: r for r in table["scenes"]}
    assert rows["a"] == first["a"] and rows["b"] == first["b"]
    assert rows["c"]["status"] == "pending"
    assert table["summary"] == {"done": 2, "failed": 0, "skipped": 0, "pending": 1}
    assert table["this_run"]["pending"] == 3


def test_the_batch_folder_is_under_the_overwrite_policy(tmp_path, monkeypatch, capsys):
    """OUTDIR was outside the overwrite policy: a folder of the user's was written into
    without --overwrite, and a batch.json of the user's replaced even so. Now: a folder
    holding files that are not a batch's is refused without --overwrite (nothing run or
    written); with it the batch writes beside them; a batch.json of the user's is refused
    even with it; a batch running in the folder holds its lock."""
    from stereodem.outlock import LOCK_NAME, OutputLock

    (tmp_path / "a.toml").write_text("")
    ran = _fake_scenes(monkeypatch, {"a": "done"})
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    argv = ["batch", str(tmp_path / "a.toml"), "--workers", "1", "-o", str(mine)]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert "mine: folder exists and is not empty (it holds notes.txt)" in err
    assert "pass --overwrite" in err and "Traceback" not in err
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"] and not ran
    assert cli.main([*argv, "--overwrite"]) == 0 and ran == ["a"]
    assert sorted(p.name for p in mine.iterdir()) == ["batch.json", "notes.txt"]
    assert (mine / "notes.txt").read_text() == "mine"
    assert cli.main(argv) == 0  # a batch's folder now: continued without --overwrite
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "batch.json").write_text('{"mine": 1}')
    for flags in ([], ["--overwrite"]):
        argv = ["batch", str(tmp_path / "a.toml"), "--workers", "1", "-o", str(theirs), *flags]
        assert cli.main(argv) == 1
        assert "batch.json" in capsys.readouterr().err
        assert (theirs / "batch.json").read_text() == '{"mine": 1}'
    with OutputLock(mine):
        assert cli.main(["batch", str(tmp_path / "a.toml"), "--workers", "1", "-o", str(mine)]) == 1
        assert "another stereodem job is writing this folder" in capsys.readouterr().err
    assert not (mine / LOCK_NAME).exists() and ran == ["a", "a"]
