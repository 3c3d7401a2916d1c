import os
import resource
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from multiprocessing import forkserver

import numpy as np
import pytest

import stereodem.stereo.runner as runner
from stereodem.config import RunSettings
from stereodem.stereo.fork_server import warm_fork_server
from stereodem.stereo.grid import CellSums
from stereodem.stereo.runner import TileDone, TileFailure, load_cached, run_tiles
from stereodem.stereo.tiling import tile_grid, tile_order


def _tile_fn(tile, ctx):
    """A deterministic tile job: a noisy block depending only on the tile and context."""
    c0, r0, c1, r1 = tile.bounds
    rows, cols = slice(r0, r1 + 1), slice(c0, c1 + 1)
    if tile.index in ctx.get("fail", ()):
        raise RuntimeError("boom")
    if tile.index in ctx.get("hang", ()):
        time.sleep(30)
    rng = np.random.default_rng(tile.index + ctx["seed"])
    block = ctx["image"][rows, cols].astype(np.float64)
    return {
        "value": (block * rng.random(block.shape)).astype(np.float32),
        "pid": np.array(os.getpid()),
    }


def _ctx(**kw):
    img = np.arange(100 * 130, dtype=np.float32).reshape(100, 130)
    return dict(image=img, shape=img.shape, seed=1, **kw)


def test_tile_grid_covers_image_once_in_index_order():
    tiles = tile_grid(130, 100, 32)
    cover = np.zeros((100, 130), int)
    for t in tiles:
        c0, r0, c1, r1 = t.bounds
        cover[r0 : r1 + 1, c0 : c1 + 1] += 1
    assert (cover == 1).all()
    assert [t.index for t in tiles] == list(range(len(tiles)))


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_pool_results_identical_to_serial():
    tiles = tile_grid(130, 100, 32)
    ser, f1, _ = run_tiles(_tile_fn, tiles, _ctx(), workers=1)
    par, f2, _ = run_tiles(_tile_fn, tiles, _ctx(), workers=2)
    assert not f1 and not f2 and ser.keys() == par.keys()
    for k in ser:
        assert np.array_equal(ser[k]["value"], par[k]["value"])
    # really ran in other processes
    assert {int(v["pid"]) for v in par.values()} != {os.getpid()}


@pytest.mark.slow
def test_failed_and_timed_out_tiles_are_reported_and_the_rest_completes():
    tiles = tile_grid(130, 100, 32)
    res, failures, _ = run_tiles(
        _tile_fn, tiles, _ctx(fail=(2,), hang=(5,)), workers=2, timeout=2.0
    )
    assert [f.tile.index for f in failures] == [2, 5]
    assert "boom" in failures[0].reason and "timed out" in failures[1].reason
    assert set(res) == {t.index for t in tiles} - {2, 5}


def test_resume_skips_done_tiles(tmp_path):
    tiles = tile_grid(130, 100, 64)
    calls = []

    def progress(done, total):
        calls.append(done)

    res1, _, t1 = run_tiles(_tile_fn, tiles, _ctx(fail=(1,)), cache_dir=tmp_path)
    assert 1 not in res1 and len(t1) == len(tiles)
    res2, fail2, t2 = run_tiles(
        _tile_fn, tiles, _ctx(), cache_dir=tmp_path, resume=True, progress=progress
    )
    assert not fail2 and list(t2) == [1]  # only the failed tile is recomputed
    assert np.array_equal(res2[0]["value"], res1[0]["value"])
    assert calls[-1] == len(tiles)
    assert calls[0] == len(tiles) - 1  # the bar starts at the tiles the cache had


@pytest.mark.slow
def test_dask_local_cluster_same_results():
    distributed = pytest.importorskip("dask.distributed")
    tiles = tile_grid(130, 100, 50)
    ser, _, _ = run_tiles(_tile_fn, tiles, _ctx(), workers=1)
    from stereodem.core.dask_threads import local_cluster

    with local_cluster(2) as cluster, distributed.Client(cluster) as client:
        res, failures, _ = run_tiles(_tile_fn, tiles, _ctx(), dask_address=client)
    assert not failures
    for k in ser:
        assert np.array_equal(ser[k]["value"], res[k]["value"])


@pytest.mark.slow
def test_results_can_stay_in_the_cache_only(tmp_path):
    """hold_results=False keeps no tile in memory: each is read back from its cache file,
    identical to the held result (what lets a scene's stereo hold one tile at a time)."""
    tiles = tile_grid(130, 100, 32)
    held, _, _ = run_tiles(_tile_fn, tiles, _ctx(), workers=1, cache_dir=tmp_path / "a")
    lean, fails, _ = run_tiles(
        _tile_fn, tiles, _ctx(), workers=2, cache_dir=tmp_path / "b", hold_results=False
    )
    assert not fails and sorted(lean) == sorted(held) == [t.index for t in tiles]
    assert all(v is None for v in lean.values())
    for t in tiles:
        got = load_cached(tmp_path / "b", t)
        assert got.keys() == held[t.index].keys()
        np.testing.assert_array_equal(got["value"], held[t.index]["value"])


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_pool_workers_store_their_tiles_when_results_stay_in_the_cache(tmp_path, monkeypatch):
    """With hold_results=False a pool's workers write their tiles to the cache themselves (the
    main process stores none), with the identity, job key and checksum that --resume checks;
    a failed tile is not stored."""
    stored_here = []
    monkeypatch.setattr(runner, "_save", lambda *a, **k: stored_here.append(a[1].index))
    tiles = tile_grid(130, 100, 32)
    res, fails, _ = run_tiles(
        _tile_fn,
        tiles,
        _ctx(fail=(3,)),
        workers=2,
        cache_dir=tmp_path,
        cache_key="job-a",
        hold_results=False,
    )
    assert [f.tile.index for f in fails] == [3] and not stored_here
    assert sorted(p.name for p in tmp_path.glob("tile_*.npz")) == [
        f"tile_{t.index:05d}.npz" for t in tiles if t.index != 3
    ]
    monkeypatch.undo()
    again, fails, timings = run_tiles(
        _tile_fn, tiles, _ctx(), cache_dir=tmp_path, resume=True, cache_key="job-a"
    )
    assert not fails and list(timings) == [3]  # only the failed tile is computed again
    serial, _, _ = run_tiles(_tile_fn, tiles, _ctx(), workers=1)
    for t in tiles:
        np.testing.assert_array_equal(again[t.index]["value"], serial[t.index]["value"])


def _busy_tile(tile, ctx):
    """A tile that burns ``ctx["cpu_s"]`` CPU seconds and says what its worker had imported
    before the tile ran, who its parent is and how much CPU it had used."""
    preloaded = "stereodem.stereo.pipeline" in sys.modules  # this module does not import it
    t0 = time.process_time()
    while time.process_time() - t0 < ctx["cpu_s"]:
        pass
    return {
        "pid": np.array(os.getpid()),
        "ppid": np.array(os.getppid()),
        "preloaded": np.array(preloaded),
        "cpu_s": np.array(sum(resource.getrusage(resource.RUSAGE_SELF)[:2])),
    }


@pytest.mark.slow
@pytest.mark.skipif(
    "forkserver" not in __import__("multiprocessing").get_all_start_methods(),
    reason="no fork server on this platform",
)
def test_pool_workers_fork_from_a_preloaded_server_whose_cpu_is_counted():
    """Workers are forked from a server that imported the tile code once (a spawned worker
    imports numpy, SciPy, OpenCV, rasterio, pyproj itself: ~1 CPU s each), and the server is
    stopped and waited for after the pool, so the workers' CPU seconds reach this process's
    RUSAGE_CHILDREN (run.json's worker_cpu_s) although they were not its children."""
    import stereodem.stereo.pipeline  # noqa: F401  (not what the workers' check looks at)

    tiles = tile_grid(130, 100, 50)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    res, failures, _ = run_tiles(_busy_tile, tiles, {"cpu_s": 0.2}, workers=2)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert not failures
    assert all(bool(r["preloaded"]) for r in res.values())
    assert {int(r["ppid"]) for r in res.values()} != {os.getpid()}  # the server's children
    # each worker's CPU at its last tile, summed: all of it is now this process's children's
    last = {}
    for r in res.values():
        last[int(r["pid"])] = max(last.get(int(r["pid"]), 0.0), float(r["cpu_s"]))
    counted = sum(after[:2]) - sum(before[:2])
    assert len(tiles) >= 4 and sum(last.values()) >= len(tiles) * 0.2
    assert counted >= sum(last.values())
    assert forkserver._forkserver._forkserver_pid is None  # stopped with its pool


@pytest.mark.slow
@pytest.mark.skipif(
    "forkserver" not in __import__("multiprocessing").get_all_start_methods(),
    reason="no fork server on this platform",
)
def test_pools_in_two_threads_share_the_fork_server_until_the_last_ends():
    """Two threads' pools fork their workers from one server: both complete (the first to end
    leaves the server to the other, whose workers it serves), and the last stops it."""
    tiles = tile_grid(130, 100, 50)
    with ThreadPoolExecutor(2) as tp:
        short = tp.submit(run_tiles, _busy_tile, tiles, {"cpu_s": 0.05}, workers=2)
        long = tp.submit(run_tiles, _busy_tile, tiles, {"cpu_s": 0.2}, workers=2)
        (r1, f1, _), (r2, f2, _) = short.result(timeout=120), long.result(timeout=120)
    assert not f1 and not f2 and len(r1) == len(r2) == len(tiles)
    assert forkserver._forkserver._forkserver_pid is None


@pytest.mark.slow
@pytest.mark.skipif(
    "forkserver" not in __import__("multiprocessing").get_all_start_methods(),
    reason="no fork server on this platform",
)
def test_a_warmed_fork_server_is_used_by_the_pool_or_stopped_without_one():
    """warm_fork_server starts the coming pool's server early (its imports overlap the
    sparse stage); the pool then forks from it, and where no pool comes (the tiles ran here)
    the next run_tiles ends it: no server outlives the stage, its CPU counted as a child's."""
    tiles = tile_grid(130, 100, 50)
    assert not warm_fork_server(1, len(tiles))  # one worker: no pool, no server
    assert not warm_fork_server(2, 1)  # one tile: no pool
    assert forkserver._forkserver._forkserver_pid is None
    assert warm_fork_server(2, len(tiles))
    server = forkserver._forkserver._forkserver_pid
    used = sum(resource.getrusage(resource.RUSAGE_CHILDREN)[:2])
    res, failures, _ = run_tiles(_busy_tile, tiles, {"cpu_s": 0.1}, workers=2)
    assert not failures and {int(r["ppid"]) for r in res.values()} == {server}
    assert forkserver._forkserver._forkserver_pid is None
    # the server that served the pool is ended at once (SIGTERM) and waited for: its
    # workers, reaped before, count as children of this process with all their CPU
    used = sum(resource.getrusage(resource.RUSAGE_CHILDREN)[:2]) - used
    assert used >= 0.9 * 0.1 * len(tiles)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert warm_fork_server(2, len(tiles))
    res, failures, _ = run_tiles(_busy_tile, tiles, {"cpu_s": 0.01}, workers=1)
    assert not failures and {int(r["pid"]) for r in res.values()} == {os.getpid()}
    assert forkserver._forkserver._forkserver_pid is None
    # the unused server was ended (SIGTERM: it need not finish its imports) and waited for:
    # its CPU came back as a child's, and no zombie is left
    assert sum(resource.getrusage(resource.RUSAGE_CHILDREN)[:2]) > sum(before[:2])


def _working_set_tile(tile, ctx):
    """A tile's memory pattern: ~100 MB of arrays alive at once, then all freed; returns the
    page faults of its second pass (the first may fault: the pages are new to the worker)."""

    def one_pass():
        live = [np.ones(s * 2**20 // 8) for s in (20, 12, 24, 8, 16, 20)]
        return sum(float(a[0]) for a in live)

    one_pass()
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    one_pass()
    return {"faults": np.array(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)}


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
@pytest.mark.skipif(__import__("platform").libc_ver()[0] != "glibc", reason="glibc's mallopt only")
def test_pool_workers_keep_the_memory_their_tiles_free():
    """glibc trims the freed top of its heap back to the system beyond a threshold that grows
    only to 2 x 32 MB, so each tile would fault its working set in afresh; the pool's workers
    raise it (``mallopt``), so a tile reuses the pages the previous one freed. In a fresh
    interpreter without it the same pattern faults ~3 000 pages per pass here (measured
    below, so that the test compares against the trimming)."""
    tiles = tile_grid(40, 40, 20)[:2]
    res, failures, _ = run_tiles(_working_set_tile, tiles, {}, workers=2)
    assert not failures
    in_pool = [int(r["faults"]) for r in res.values()]
    code = (
        "import numpy as np, resource\n"
        "def one_pass():\n"
        "    live = [np.ones(s * 2**20 // 8) for s in (20, 12, 24, 8, 16, 20)]\n"
        "    return sum(float(a[0]) for a in live)\n"
        "one_pass()\n"
        "f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "one_pass()\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)\n"
    )
    plain = int(
        subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True
        ).stdout
    )
    if plain < 200:  # e.g. transparent huge pages for everything: 2 MB per fault
        pytest.skip(f"{plain} page faults per pass without it: too few to compare")
    assert max(in_pool) < plain / 10, (in_pool, plain)


def test_tile_runner_yields_each_tile_in_tile_order_as_soon_as_its_turn_comes(monkeypatch):
    """The stereo tile runner hands the tiles over in ``tile_order`` (largest first, the order
    their sums are added in, whatever the pool's completion order), each as soon as it and
    every tile before it have finished, not after the pool: here the pool finishes them in a
    scrambled order, one tile fails (skipped, reported by index) and the caller closing the
    runner early closes the pool's generator."""
    # not at the top: this module must not load stereo.pipeline (which stereo.execution
    # imports), or _busy_tile's workers would find it loaded whatever their server did
    from stereodem.stereo import execution
    from stereodem.stereo.pipeline import TileResult

    tiles = tile_grid(130, 100, 32)  # 12 tiles of 32-33 x 33-34 px
    order = [t.index for t in tile_order(tiles)]
    sizes = [tiles[i].size for i in order]
    assert order != sorted(order) and sizes == sorted(sizes, reverse=True)  # largest first
    finishing = [order[k] for k in (2, 0, 1, 5, 3, 4, 6, 7, 11, 10, 9, 8)]  # the pool's order
    failing = order[4]
    state = {"yielded": 0, "closed": False}

    def fake_iter_tiles(fn, tiles_, ctx, **kw):
        try:
            for i in finishing:
                state["yielded"] += 1
                if i == failing:
                    yield TileDone(i, None, TileFailure(tiles[i], "boom"), 0.1)
                else:
                    summary = {"tile": list(tiles[i].bounds), "index": i}
                    res = TileResult(CellSums(0, 0, np.zeros((1, 0, 0)), 0), summary)
                    yield TileDone(i, res.to_arrays(), None, 0.1)
        finally:
            state["closed"] = True

    monkeypatch.setattr(execution, "iter_tiles", fake_iter_tiles)
    monkeypatch.setattr(execution, "_cache_key", lambda *a: "k")
    runner = execution.tile_runner(RunSettings(workers=1))
    got, seen = [], []
    for res in runner(None, tiles, None, None):
        got.append(res.summary["index"])
        seen.append(state["yielded"])
    expected = [i for i in order if i != failing]
    assert got == expected
    # each tile came as soon as the pool had finished it and every tile before it
    needed = [max(finishing.index(j) for j in order[: order.index(i) + 1]) + 1 for i in got]
    assert seen == needed and seen[0] < len(finishing)
    assert [f.tile.index for f in runner.failures] == [failing] and state["closed"]

    state.update(yielded=0, closed=False)
    first = runner(None, tiles, None, None)
    next(first)
    first.close()  # the caller stops early (an error while adding): the pool is closed
    assert state["closed"] and state["yielded"] < len(finishing)


def _log_setup(fmt):
    """A worker's logging set-up (what the command line registers: progress.setup_logging)."""
    import logging

    logging.basicConfig(level=logging.INFO, format=fmt)


def _warning_tile(tile, ctx):
    import logging

    logging.getLogger("stereodem.stereo.match").warning("tile %d: few matches", tile.index)
    return {"value": np.zeros(1, np.float32)}


@pytest.mark.slow
def test_tile_workers_log_as_the_main_process(monkeypatch, capfd):
    """A tile worker (fork server or spawned) started with no log handler: its warnings went
    to Python's last-resort handler, the message alone ("tile 3: few matches"), and its info
    lines were lost at -v. It now sets up logging as the main process registered
    (stereodem.core.worker_logging)."""
    from stereodem.core import worker_logging

    monkeypatch.setattr(worker_logging, "_SPEC", None)
    worker_logging.register(_log_setup, "[worker] %(levelname)s %(name)s: %(message)s")
    tiles = tile_grid(130, 100, 50)
    res, fails, _ = run_tiles(_warning_tile, tiles, _ctx(), workers=2)
    assert not fails and len(res) == len(tiles)
    err = capfd.readouterr().err
    for t in tiles:
        assert f"[worker] WARNING stereodem.stereo.match: tile {t.index}: few matches" in err
