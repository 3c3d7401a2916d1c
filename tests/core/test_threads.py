"""Thread budgets (stereodem.core.threads): the pool, Dask and the main process pin BLAS/OpenMP,
OpenCV and GDAL threads to what the job's one setting gives them."""

import logging
import multiprocessing
import os
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor

import cv2
import numpy as np
import pytest
from rasterio.env import get_gdal_config

from stereodem.config import config_from_dict
from stereodem.core import threads
from stereodem.core.errors import InputError
from stereodem.pipeline import job
from stereodem.stereo.runner import run_tiles
from stereodem.stereo.tiling import Tile, tile_grid


def _limits_tile(tile, ctx):
    """A tile function reporting the thread limits of the process that ran it."""
    lim = threads.current_limits()
    return {
        "opencv": np.array(lim["opencv"]),
        "blas": np.array(lim["blas"] or -1),
        "gdal": np.array(int(lim["gdal"])),
        "env_omp": np.array(int(os.environ["OMP_NUM_THREADS"])),
        "pid": np.array(os.getpid()),
    }


def test_worker_threads_share_the_cores():
    assert threads.worker_threads(16, 16) == 1
    assert threads.worker_threads(4, 16) == 4
    assert threads.worker_threads(3, 16) == 5
    assert threads.worker_threads(32, 16) == 1
    assert threads.job_threads(None) == threads.cores()
    n = threads.cores()
    # the pool gets the processes asked for; the main process never more threads than cores
    assert threads.pool_size(n + 5) == n + 5 and threads.pool_size(None) == n
    assert threads.job_threads(n + 5) == n and threads.job_threads(1) == 1
    assert threads.worker_threads(n + 5) == 1


def test_main_process_threads_are_capped_at_the_cores(monkeypatch):
    monkeypatch.setattr(threads, "cores", lambda: 2)
    assert threads.job_threads(16) == 2 and threads.pool_size(16) == 16
    with threads.thread_budget(16) as lim:
        assert lim["opencv"] == 2 and lim["gdal"] == threads.gdal_threads(2) and lim["pinned"] == 2


def test_pin_threads_sets_blas_opencv_gdal_and_thread_budget_restores():
    before = threads.current_limits()
    with threads.thread_budget(1) as lim:
        assert lim["opencv"] == 1 and lim["gdal"] == threads.gdal_threads(1) and lim["pinned"] == 1
        assert lim["blas"] in (None, 1)
        assert cv2.getNumThreads() == 1 and os.environ["OPENBLAS_NUM_THREADS"] == "1"
    after = threads.current_limits()
    assert after["opencv"] == before["opencv"] and after["blas"] == before["blas"]
    assert after["gdal"] == before["gdal"]

    assert get_gdal_config("GDAL_NUM_THREADS") != "None"  # unset again, not the string "None"


@pytest.mark.slow
def test_pool_initializer_pins_a_worker_to_the_budget_given():
    ctx = multiprocessing.get_context("spawn")
    for n in (1, 3):
        with ProcessPoolExecutor(
            1, mp_context=ctx, initializer=threads.pool_initializer, initargs=(n,)
        ) as ex:
            lim = ex.submit(threads.worker_limits).result()
        assert lim["opencv"] == n and lim["gdal"] == threads.gdal_threads(n) and lim["pinned"] == n
        assert lim["blas"] == n  # numpy's OpenBLAS is loaded in every worker


def _fresh_python(script: str) -> list[str]:
    """The words ``script`` prints in a fresh interpreter whose environment sets no BLAS /
    OpenMP thread count (the runtimes then start one thread per core unless told otherwise)."""
    env = {k: v for k, v in os.environ.items() if k not in threads.ENV_VARS}
    r = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, env=env
    )
    assert r.returncode == 0, r.stderr
    return r.stdout.split()


def test_the_fork_server_loads_blas_with_one_thread_and_workers_still_get_their_budget():
    """The fork server imports the tile code with its BLAS / OpenMP runtimes at one thread
    (each OpenBLAS starts a thread per core that spins at load: 0.85 instead of 0.48 CPU s of
    imports on 2 cores); a worker forked from it that is given 3 threads has 3 in each of
    those runtimes (the pin raises them; an OpenBLAS loaded later with OpenCV keeps its own
    cap at the cores), and the module imports nothing heavy itself."""
    from stereodem.stereo import fork_server

    pre = fork_server._PRELOAD
    first_heavy = min(i for i, m in enumerate(pre) if m.startswith("stereodem.stereo"))
    assert pre.index("stereodem.core.one_thread_runtimes") < first_heavy
    script = (
        "import sys; import stereodem.core.one_thread_runtimes; "
        "light = not ({'numpy', 'cv2', 'rasterio'} & set(sys.modules)); "
        "import numpy, scipy.linalg; from threadpoolctl import threadpool_info; "
        "at_load = {p['filepath']: p['num_threads'] for p in threadpool_info()}; "
        "from stereodem.core.threads import pin_threads; pin_threads(3); "
        "pinned = {p['filepath']: p['num_threads'] for p in threadpool_info()}; "
        "print(light, sorted(set(at_load.values())), sorted({pinned[f] for f in at_load}))"
    )
    assert _fresh_python(script) == ["True", "[1]", "[3]"]


def test_runtimes_loaded_under_a_budget_start_with_its_threads():
    """A command's process loads NumPy's and OpenCV's BLAS in its thread budget's block: each
    OpenBLAS started a thread per core there, spinning, which a budget of 1 never used; now
    none beyond the budget (on a machine of 2 cores or more the process held 3 threads in
    ``thread_budget(1)``, now 1), and the environment is as it was after the block."""
    script = (
        "import os, sys; from stereodem.core.threads import thread_budget\n"
        "assert 'numpy' not in sys.modules\n"
        "with thread_budget(1):\n"
        "    import numpy, cv2\n"
        "    inside = len(os.listdir('/proc/self/task'))\n"
        "print(inside, os.environ.get('OPENBLAS_NUM_THREADS'))"
    )
    assert _fresh_python(script) == ["1", "None"]


@pytest.mark.slow
def test_tile_pool_workers_run_with_their_share_of_the_cores():
    tiles = tile_grid(64, 64, 16)
    res, fails, _ = run_tiles(_limits_tile, tiles, {}, workers=2)
    assert not fails and len(res) == len(tiles)
    want = threads.worker_threads(2)
    pids = {int(r["pid"]) for r in res.values()}
    assert os.getpid() not in pids
    for r in res.values():
        assert int(r["opencv"]) == want and int(r["env_omp"]) == want
        assert str(int(r["gdal"])) == threads.gdal_threads(want)
        assert int(r["blas"]) == want


@pytest.mark.slow
def test_dask_workers_are_pinned():
    distributed = pytest.importorskip("dask.distributed")
    from stereodem.core.dask_threads import local_cluster

    tiles = tile_grid(32, 32, 16)
    with local_cluster(1) as cluster, distributed.Client(cluster) as client:
        res, fails, _ = run_tiles(_limits_tile, tiles, {"job": 1}, dask_address=client)
    assert not fails
    want = threads.cores()  # one task slot on this node: all its cores
    for r in res.values():
        assert int(r["opencv"]) == want and str(int(r["gdal"])) == threads.gdal_threads(want)


@pytest.mark.slow
def test_dask_workers_on_one_node_share_its_cores(monkeypatch):
    """Two single-slot worker processes on this node (a ``LocalCluster``, as ``batch --dask
    local`` starts): each gets half the cores, not all of them (2 x the cores in all), and,
    a cluster of this process's own, they log as it does (here ``-q``: errors only; before,
    ``batch -q --dask local`` printed the scenes' warnings)."""
    distributed = pytest.importorskip("dask.distributed")
    from stereodem.core import worker_logging
    from stereodem.core.dask_threads import local_cluster
    from stereodem.progress import setup_logging

    monkeypatch.setattr(worker_logging, "_SPEC", (setup_logging, (0, True)))
    with local_cluster(2) as cluster, distributed.Client(cluster) as client:
        threads.register_dask_plugin(client, own_workers=True)
        limits = client.run(threads.worker_limits)
        levels = client.run(lambda: __import__("logging").getLogger().getEffectiveLevel())
        # no statistical profiler in the workers (it deadlocks on Python 3.11: dask_threads)
        profiling = client.run(lambda dask_worker: "profile" in dask_worker.periodic_callbacks)
        http = cluster.scheduler.http_server.port  # a free port, not Dask's default 8787
    assert len(limits) == 2 and not any(profiling.values()) and http != 8787
    assert set(levels.values()) == {logging.ERROR}
    want = max(1, threads.cores() // 2)
    for lim in limits.values():
        assert lim["opencv"] == want and lim["pinned"] == want
        assert lim["gdal"] == threads.gdal_threads(want)


def test_threads_plugin_counts_the_slots_of_its_host(monkeypatch):
    dask_threads = pytest.importorskip("stereodem.core.dask_threads")
    pinned = []
    monkeypatch.setattr(dask_threads, "pin_threads", pinned.append)
    monkeypatch.setattr(dask_threads, "cores", lambda: 16)

    class Worker:
        def __init__(self, address, nthreads):
            self.address, self.nthreads = address, nthreads

    class Client:
        def scheduler_info(self):
            return {
                "workers": {
                    "tcp://10.0.0.1:4001": {"host": "10.0.0.1", "nthreads": 1},
                    "tcp://10.0.0.1:4002": {"host": "10.0.0.1", "nthreads": 1},
                    "tcp://10.0.0.1:4003": {"host": "10.0.0.1", "nthreads": 2},
                    "tcp://10.0.0.2:4001": {"host": "10.0.0.2", "nthreads": 4},
                }
            }

    slots = dask_threads.slots_by_host(Client())
    assert slots == {"10.0.0.1": 4, "10.0.0.2": 4}
    plugin = dask_threads.ThreadsPlugin(None, slots)
    plugin.setup(Worker("tcp://10.0.0.1:4001", 1))  # 4 slots share 16 cores
    plugin.setup(Worker("tcp://10.0.0.3:4001", 2))  # a host that joined later: its own slots
    plugin.setup(Worker("inproc://x", 1))  # an address without a host it counts: its own
    dask_threads.ThreadsPlugin(3, slots).setup(Worker("tcp://10.0.0.1:4001", 1))  # given
    assert pinned == [4, 8, 16, 3]


@pytest.mark.parametrize("deadlocks", [True, False])
def test_threads_plugin_stops_the_profiler_where_it_deadlocks(monkeypatch, deadlocks):
    """On a given cluster (``--dask tcp://...``), the workers' statistical profiler is stopped
    where their Python can deadlock in it (3.11: ``dask_threads.PROFILER_DEADLOCKS``) and left
    running elsewhere."""
    dask_threads = pytest.importorskip("stereodem.core.dask_threads")
    monkeypatch.setattr(dask_threads, "pin_threads", lambda n: None)
    monkeypatch.setattr(dask_threads, "PROFILER_DEADLOCKS", deadlocks)

    class Callback:
        running = True

        def stop(self):
            self.running = False

    class Worker:
        address, nthreads = "tcp://10.0.0.1:4001", 1

        def __init__(self):
            self.periodic_callbacks = {"profile": Callback(), "profile-cycle": Callback()}
            self.periodic_callbacks["heartbeat"] = Callback()
            self.callbacks = dict(self.periodic_callbacks)

    applied = []
    monkeypatch.setattr(dask_threads.worker_logging, "apply", applied.append)
    w = Worker()
    dask_threads.ThreadsPlugin(1).setup(w)
    assert applied == [None]  # a given cluster's workers keep their own logging
    assert w.callbacks["profile"].running is not deadlocks
    assert w.callbacks["profile-cycle"].running is not deadlocks
    assert w.callbacks["heartbeat"].running and "heartbeat" in w.periodic_callbacks
    assert ("profile" in w.periodic_callbacks) is not deadlocks


@pytest.mark.slow
def test_an_unreachable_scheduler_is_one_clear_error():
    dask_threads = pytest.importorskip("stereodem.core.dask_threads")
    with pytest.raises(InputError, match=r"--dask tcp://127\.0\.0\.1:9: cannot connect"):
        dask_threads.connect("tcp://127.0.0.1:9", timeout="1s")


def test_a_job_pins_its_main_process_to_workers(tmp_path, monkeypatch):
    """``stereodem.run`` computes its stages under the job's budget and restores the old one."""
    seen = {}

    def fake_run_in(cfg, out, progress_factory):
        seen.update(threads.current_limits())
        return {}

    monkeypatch.setattr(job, "_run_in", fake_run_in)
    monkeypatch.setattr(threads, "cores", lambda: 4)  # 6 workers: 4 threads, the cores
    before = threads.current_limits()
    for workers, want in ((1, 1), (3, 3), (6, 4)):
        cfg = config_from_dict(
            {
                "inputs": {"left": "l.tif", "right": "r.tif"},
                "output": {"dir": str(tmp_path / f"o{workers}")},
                "run": {"workers": workers},
            }
        )
        job.run(cfg)
        assert seen["opencv"] == want and seen["gdal"] == threads.gdal_threads(want)
        assert seen["pinned"] == want and seen["blas"] in (None, want)
    assert threads.current_limits() == before


def _order_tile(tile, ctx):
    ctx["order"].append(tile.index)
    return {"n": np.array(tile.cols * tile.rows)}


def test_tiles_are_run_largest_first_and_keyed_by_index():
    tiles = [
        Tile(0, 0, 10, 10, 0),
        Tile(10, 0, 50, 40, 1),
        Tile(60, 0, 20, 20, 2),
        Tile(80, 0, 50, 41, 3),
    ]
    ctx = {"order": []}
    res, fails, _ = run_tiles(_order_tile, tiles, ctx, workers=1)
    assert ctx["order"] == [3, 1, 2, 0] and not fails
    assert {i: int(r["n"]) for i, r in res.items()} == {0: 100, 1: 2000, 2: 400, 3: 2050}
