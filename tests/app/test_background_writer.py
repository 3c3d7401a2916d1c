"""The run's background writer: writes overlap the next stage, errors reach the caller, and
no write is left running when the run ends or fails."""

import os
import sys
import threading
import time

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import CRS

from stereodem.core.dem import DEM
from stereodem.pipeline.job import BackgroundWriter


def test_writes_run_off_the_calling_thread_side_by_side_and_finish_on_exit(tmp_path):
    """With a budget of two threads (the default), a second write runs while the first one is
    still going (the first waits for the second to start: one thread would make it time out);
    ``wait_for(i)`` waits for the ``i``-th write, and leaving the context for all of them."""
    done, threads = [], []
    second_started = threading.Event()

    def first():
        ok = second_started.wait(timeout=30)
        threads.append(threading.current_thread().name)
        time.sleep(0.1)
        (tmp_path / "a").write_text("a")
        done.append(("a", ok))

    def second(name):
        second_started.set()
        threads.append(threading.current_thread().name)
        (tmp_path / name).write_text(name)
        done.append(name)

    with BackgroundWriter() as w:
        w.submit(first)
        w.submit(second, "b")
        w.submit(second, "c")
        w.wait_for(0)
        assert ("a", True) in done
    assert sorted(map(str, done)) == ["('a', True)", "b", "c"] and w.count == 3
    assert w.seconds >= 0.1 and (tmp_path / "c").read_text() == "c"
    assert len(set(threads)) == 2 and threading.current_thread().name not in threads


def test_write_error_reaches_the_caller():
    def fail():
        raise OSError("disk full")

    with BackgroundWriter() as w:
        w.submit(fail)
        with pytest.raises(OSError, match="disk full"):
            w.wait()


def test_with_one_thread_writes_run_at_once_in_the_calling_thread(tmp_path):
    """A job of one worker has no core to spare: each write runs when it is submitted, in the
    caller's thread; an error is raised there and then (the job stops at the failed write,
    not after its later stages), and again by a later submit or ``wait``."""
    done, threads = [], []

    def write(name):
        threads.append(threading.current_thread().name)
        done.append(name)

    def fail():
        raise OSError("disk full")

    with BackgroundWriter(threads=1) as w:
        w.submit(write, "a")
        assert done == ["a"]
        with pytest.raises(OSError, match="disk full"):
            w.submit(fail)
        with pytest.raises(OSError, match="disk full"):
            w.submit(write, "b")
        assert done == ["a"] and w.count == 2
        w.wait_for(0)
        with pytest.raises(OSError, match="disk full"):
            w.wait()
    assert threads == [threading.current_thread().name]


def test_a_failed_background_write_stops_the_next_submit():
    """A write that failed on the writer's thread stops the job at its next write, not only
    at the final wait (a full disk after the stereo stage: not after the orthoimages)."""

    def fail():
        raise OSError("disk full")

    with BackgroundWriter(threads=2) as w:
        w.submit(fail)
        with pytest.raises(OSError, match="disk full"):
            w.wait_for(0)
        with pytest.raises(OSError, match="disk full"):
            w.submit(lambda: None)
        assert w.count == 1


def test_dem_prepared_write_is_independent_of_later_changes(tmp_path):
    """The heights and layers are converted when the write is prepared: changing the DEM
    afterwards (the post stage works on it) does not change what is written."""
    z = np.arange(12.0).reshape(3, 4)
    g = DEM(
        z.copy(),
        Affine(30, 0, 500000, 0, -30, 4000000),
        CRS.from_epsg(32637),
        "ellipsoid",
        count=np.ones((3, 4)),
        score=np.full((3, 4), 0.9),
        ray_gap=np.full((3, 4), 0.5),
    )
    write = g.prepare_write(tmp_path / "dem.tif")
    g.heights[:] = -1.0
    g.score[:] = 0.0
    paths = write()
    assert sorted(paths) == ["count", "dem", "ray_gap", "score"]
    with rasterio.open(tmp_path / "dem.tif") as ds:
        np.testing.assert_array_equal(ds.read(1), z.astype(np.float32))
    with rasterio.open(tmp_path / "score.tif") as ds:
        np.testing.assert_array_equal(ds.read(1), np.float32(0.9))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice: Linux")
def test_writer_thread_yields_the_cpu_to_the_job_and_the_caller_keeps_its_priority():
    """The writer thread runs 10 nice levels below the caller (at most 19), so that its
    compression takes the cores the job's stages leave idle; the caller's own priority, and
    that of a write done in the caller's thread (one worker), are unchanged."""

    def nice():
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    mine = nice()
    with BackgroundWriter(threads=2) as w:
        w.submit(nice)
        writer = w._futures[0].result()
    assert writer == min(19, mine + 10)
    assert nice() == mine
    with BackgroundWriter(threads=1) as w:
        w.submit(nice)
        assert w._futures[0].result() == mine
