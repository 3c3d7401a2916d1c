"""Running a tile function over a scene: serially, in a process pool, or on Dask.

The tile function is a pure function ``fn(tile, context) -> dict[str, ndarray]`` of one
:class:`stereodem.stereo.tiling.Tile` and a read-only context (images, models, settings). The runner

* sends the context to each worker once (pool initializer / Dask scatter), not per tile;
* enforces a per-tile timeout inside the worker (``SIGALRM``), so a hung tile is reported and
  its worker goes on with the next tile;
* logs failed tiles (exception or timeout) and returns them instead of failing the run;
* with ``cache_dir``, stores each finished tile as ``tile_<index>.npz`` (atomically) and, on
  ``resume``, skips tiles already there; when the caller reads the tiles back from there
  (``hold_results=False``) a process pool's workers store them themselves, so their arrays
  never travel through the main process;
* submits the tiles in :func:`~stereodem.stereo.tiling.tile_order` (largest first: scene-edge
  tiles are smaller);
* hands each tile to the caller as it finishes (:func:`iter_tiles`), so the caller merges
  tiles while the pool runs the others;
* pins each worker's BLAS/OpenMP, OpenCV and GDAL threads to its share of the cores
  (:mod:`stereodem.core.threads`);
* tells each result's tile index: a caller that merges in one fixed order (the stereo DEM:
  :func:`~stereodem.stereo.tiling.tile_order`) gets bit-identical output for any
  ``workers``.

Memory: large read-only arrays of the context (the images) go to workers as
:class:`SharedArray` memory maps, not copies, so a worker holds one tile's working arrays
plus the pages of the images that tile reads; the bound is set by the tile size and the
disparity range (see the stereo pipeline), not by the scene size.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import logging
import multiprocessing
import os
import resource
import select
import shutil
import signal
import tempfile
import threading
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stereodem.core import interrupt, worker_logging
from stereodem.core.errors import InputError
from stereodem.core.memory import keep_freed_memory
from stereodem.core.pool import stop_pool
from stereodem.core.raster import atomic_path
from stereodem.core.threads import register_dask_plugin, worker_threads

from .fork_server import (
    pool_closed,
    pool_context,
    pool_opened,
    pool_size,
    stop_idle_fork_server,
)
from .tiling import tile_order

log = logging.getLogger(__name__)


def process_peak_rss_mb() -> float:
    """Peak resident memory (MB) of the calling process's own address space (``VmHWM``).

    ``ru_maxrss`` would also count a parent's peak from before an ``exec`` and, for a pool
    worker, the parent's pages at the fork; ``VmHWM`` is the process's own high-water mark.
    Falls back to ``ru_maxrss`` where ``/proc`` is absent.
    """
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmHWM")) / 1024.0
    except (OSError, StopIteration, ValueError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def reset_peak_rss() -> bool:
    """Reset this process's resident-memory high-water mark (``VmHWM``: Linux
    ``/proc/self/clear_refs`` 5), so :func:`process_peak_rss_mb` then gives the peak since
    this call; False where that is not possible (the figure then runs from process start)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


class SharedArray:
    """A read-only array stored as a ``.npy`` file and memory-mapped where it is used.

    It pickles as its path, so a process pool sends a few bytes instead of the array, and
    every worker maps the same pages (the OS page cache holds them once). Supports what
    tile functions need: ``shape``, ``dtype``, ``ndim``, slicing and ``np.asarray``.
    """

    def __init__(self, path):
        self.path = str(path)
        self._mm = None

    @classmethod
    def create(cls, array, directory, name):
        """Write ``array`` to ``directory/name.npy`` (atomically) and return it shared."""
        path = Path(directory) / f"{name}.npy"
        fd, tmp = tempfile.mkstemp(dir=directory, suffix=".npy.part")
        with os.fdopen(fd, "wb") as f:
            np.save(f, np.ascontiguousarray(array))
        os.replace(tmp, path)
        return cls(path)

    def _map(self):
        if self._mm is None:
            self._mm = np.load(self.path, mmap_mode="r")
        return self._mm

    shape = property(lambda self: self._map().shape)
    dtype = property(lambda self: self._map().dtype)
    ndim = property(lambda self: self._map().ndim)

    def __getitem__(self, key):
        return self._map()[key]

    def __array__(self, dtype=None, copy=None):
        a = np.asarray(self._map())
        return a if dtype is None else a.astype(dtype)

    def __getstate__(self):
        return {"path": self.path}

    def __setstate__(self, state):
        self.path, self._mm = state["path"], None


@dataclass
class TileFailure:
    """A tile that raised or timed out, with its place in the image (pixels)."""

    tile: Any
    reason: str

    def to_dict(self):
        return {**self.tile.to_dict(), "reason": self.reason}


class TileTimeout(Exception):
    pass


# --------------------------------------------------------------------------- worker side
_CONTEXT = None


def _init_worker(context, threads=1, log=None):
    """Pool initializer: the shared context, the parent watch, the worker's thread budget
    (BLAS/OpenMP, OpenCV, GDAL pinned to ``threads``: :func:`stereodem.core.threads.pin_threads`;
    N workers x ``cores // N`` threads = the cores, none stacked on top), and its logging as
    the main process's (``log``: :func:`stereodem.core.worker_logging.spec`)."""
    global _CONTEXT
    _CONTEXT = context
    _die_with_parent()
    # Ctrl-C reaches the whole process group: the parent stops the pool, workers just go
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from stereodem.core.threads import pin_threads

    pin_threads(threads)
    worker_logging.apply(log)
    keep_freed_memory()  # a tile reuses the pages the previous one freed


def _die_with_parent():
    """End this worker when the process that started its pool ends, however it ends (kill -9
    included).

    A spawned worker is that process's child: ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` on Linux.
    A worker forked by the fork server (:func:`pool_context`) is the server's child, and the
    server lives as long as any of its workers does, so the worker watches the pool's process
    itself: a thread waiting on its pidfd (Linux), else polling its PID. The death signal is
    armed in both cases (the fork server's end ends its workers too)."""
    parent = multiprocessing.parent_process()
    owner = parent.pid if parent is not None else os.getppid()
    ppid = os.getppid()
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(1, signal.SIGKILL, 0, 0, 0) != 0:  # 1 = PR_SET_PDEATHSIG
            raise OSError(ctypes.get_errno(), "prctl")
        armed = True
    except (OSError, AttributeError):
        armed = False
    if os.getppid() != ppid:  # the parent died before prctl
        os._exit(1)
    if armed and owner == ppid:
        return
    _watch_process(owner, ppid)


def _watch_process(owner, ppid):
    """A daemon thread that ends this process (exit status 1) when the process ``owner`` ends:
    through its pidfd (Linux >= 5.3), else by polling that this process's parent is still
    ``ppid`` (it is reparented when its parent ends) and, when ``owner`` is not that parent (a
    fork server's worker, POSIX only), that ``owner`` exists."""
    try:
        fd = os.pidfd_open(owner)
    except ProcessLookupError:  # already gone
        os._exit(1)
    except (AttributeError, OSError):  # no pidfd: poll
        fd = None

    def gone(pid):
        try:
            os.kill(pid, 0)  # POSIX: signal 0 only checks that the process exists
        except ProcessLookupError:
            return True
        except PermissionError:
            pass
        return False

    def watch():
        if fd is not None:
            select.select([fd], [], [])  # readable when the process ends
            os._exit(1)
        while os.getppid() == ppid and (owner == ppid or not gone(owner)):
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="pool-owner-watchdog").start()


def _alarm(signum, frame):
    raise TileTimeout()


def _run_one(fn, tile, timeout, context=None):
    """Run ``fn`` on one tile with a timeout; returns (index, result | None, error | None,
    seconds)."""
    ctx = _CONTEXT if context is None else context
    t0 = time.perf_counter()
    # SIGALRM only in a main thread (a Dask task runs in a worker thread: no per-tile timeout)
    use_alarm = (
        bool(timeout)
        and hasattr(signal, "SIGALRM")
        and threading.current_thread() is threading.main_thread()
    )
    old, armed = None, False
    try:
        # armed inside the try: a timer that fires at once (1e-300 s) is this tile's timeout,
        # not a traceback
        if use_alarm:
            old, armed = signal.signal(signal.SIGALRM, _alarm), True
            signal.setitimer(signal.ITIMER_REAL, float(timeout))
        out = fn(tile, ctx)
        return tile.index, out, None, time.perf_counter() - t0
    except TileTimeout:
        return tile.index, None, f"timed out after {timeout:g} s", time.perf_counter() - t0
    except Exception as exc:  # a failing tile must not fail the run
        tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
        return tile.index, None, tb, time.perf_counter() - t0
    finally:
        if armed:
            _disarm(old)


def _disarm(old_handler):
    """Stop the tile's timer and restore ``old_handler``; a timeout that fires as the tile
    ends is dropped (the tile is done)."""
    while True:
        try:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, signal.SIG_DFL if old_handler is None else old_handler)
            return
        except TileTimeout:
            continue


#: what a pool worker returns for a tile it stored in the cache itself (:func:`_run_and_store`)
_STORED = "stored in the tile cache"


def _run_and_store(fn, tile, timeout, cache_dir, cache_key):
    """:func:`_run_one`, the finished tile then stored in ``cache_dir`` by the worker itself
    (:func:`_save`: identity, job key, checksum): its arrays need not travel back to the main
    process, which reads them from the cache when it merges the tiles."""
    index, out, err, secs = _run_one(fn, tile, timeout)
    if err is None:
        _save(cache_dir, tile, out, cache_key)
        out = _STORED
    return index, out, err, secs


# --------------------------------------------------------------------------- cache
# Each cached tile stores, beside its result arrays, the tile's identity (index and bounds),
# the job key and a SHA-256 of the result arrays; a file that is not a readable archive, was
# copied from another tile or job, or whose arrays changed is recomputed, never reused.
_META = ("__tile__", "__job__", "__sha256__")


def cache_file(cache_dir, tile) -> Path:
    """The cache file of ``tile`` in ``cache_dir``."""
    return Path(cache_dir) / f"tile_{tile.index:05d}.npz"


def _identity(tile):
    return np.array([tile.index, tile.col0, tile.row0, tile.cols, tile.rows], np.int64)


def _digest(result) -> str:
    h = hashlib.sha256()
    for k in sorted(result):
        a = np.ascontiguousarray(result[k])
        h.update(f"{k}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _save(cache_dir, tile, result, key=None):
    """Store a finished tile atomically, with the permissions of every other output, its
    identity, job key and checksum."""
    meta = {
        "__tile__": _identity(tile),
        "__job__": np.array(key or ""),
        "__sha256__": np.array(_digest(result)),
    }
    with atomic_path(cache_file(cache_dir, tile)) as tmp, open(tmp, "wb") as f:
        np.savez(f, **result, **meta)


def _load(cache_dir, tile, key=None):
    """A cached tile's result, or None (with the reason logged) when it is not this tile's
    intact result of this job."""
    path = cache_file(cache_dir, tile)
    try:  # the file opened here: np.load leaves its own open when the file is no zip
        with open(path, "rb") as f, np.load(f, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as exc:  # BadZipFile, truncated, not an npz, ...
        log.warning("%s: unreadable cached tile (%s); recomputing it", path, type(exc).__name__)
        return None
    if not all(k in arrays for k in _META):
        reason = "no identity or checksum"
    elif not np.array_equal(arrays["__tile__"], _identity(tile)):
        reason = f"it holds tile {arrays['__tile__'].tolist()}, not {_identity(tile).tolist()}"
    elif key is not None and str(arrays["__job__"]) != key:
        reason = "it belongs to another job"
    else:
        result = {k: v for k, v in arrays.items() if k not in _META}
        if _digest(result) == str(arrays["__sha256__"]):
            return result
        reason = "checksum mismatch"
    log.warning("%s: cached tile not reused (%s); recomputing it", path, reason)
    return None


def load_cached(cache_dir, tile) -> dict:
    """The result arrays of a tile this run has just stored in ``cache_dir`` (no identity or
    checksum test: see :func:`_load` for files of earlier runs)."""
    with np.load(cache_file(cache_dir, tile), allow_pickle=False) as z:
        return {k: z[k] for k in z.files if k not in _META}


def clean_cache(cache_dir):
    """Remove what an interrupted run may leave in a tile cache: partial tile files and
    shared image maps (finished tiles stay)."""
    d = Path(cache_dir)
    for p in d.glob("*.part"):
        p.unlink(missing_ok=True)
    for p in d.glob("shared-*"):
        shutil.rmtree(p, ignore_errors=True)


# --------------------------------------------------------------------------- driver
@dataclass(frozen=True)
class TileDone:
    """A tile :func:`iter_tiles` has finished (or loaded from the cache).

    ``result``: its arrays; None when it failed, or when they stay in the cache
    (``hold_results=False``: :func:`load_cached`). ``failure``: None when it succeeded.
    ``seconds``: its run time, None when it was loaded from the cache."""

    index: int
    result: Any
    failure: TileFailure | None
    seconds: float | None


def run_tiles(fn, tiles, context, **options):
    """Run ``fn(tile, context)`` over ``tiles`` (:func:`iter_tiles`, all of them; ``options``
    are its keywords: ``workers``, ``timeout``, ``cache_dir``, ``resume``, ``progress``,
    ``dask_address``, ``cache_key``, ``hold_results``).

    Returns
    -------
    results : dict[int, dict[str, ndarray]]
        By tile index (None for a tile left in the cache: ``hold_results=False``).
    failures : list[TileFailure]
        By tile index.
    timings : dict[int, float] seconds per computed tile
    """
    results, failures, timings = {}, [], {}
    with contextlib.closing(iter_tiles(fn, tiles, context, **options)) as finished:
        for d in finished:
            if d.failure is None:
                results[d.index] = d.result
            else:
                failures.append(d.failure)
            if d.seconds is not None:
                timings[d.index] = d.seconds
    failures.sort(key=lambda f: f.tile.index)
    return results, failures, timings


def iter_tiles(
    fn,
    tiles,
    context,
    *,
    workers: int | None = 1,
    timeout: float | None = None,
    cache_dir=None,
    resume: bool = False,
    progress=None,
    dask_address: str | None = None,
    cache_key: str | None = None,
    hold_results: bool = True,
    reusable=None,
):
    """Run ``fn(tile, context)`` over ``tiles``, yielding a :class:`TileDone` for each tile as
    it finishes: the cached ones first (``resume``), then the others in the order they end;
    they are submitted in :func:`~stereodem.stereo.tiling.tile_order` (largest first).

    The caller can work on each finished tile while the pool runs the others. Closing the
    generator early (``contextlib.closing``, or an error in the caller) stops the pool.

    Parameters
    ----------
    workers : int or None
        1 runs in this process (its allocator then set like a pool worker's, for the rest
        of the process: :func:`stereodem.core.memory.keep_freed_memory`); N > 1 a process
        pool of N; None uses all cores.
    timeout : float, optional
        Per-tile limit in seconds; a tile over it is reported as failed.
    cache_dir : path, optional
        Folder for finished tiles; with ``resume`` those are loaded instead of recomputed
        (only a tile's own intact result: see :func:`_load`).
    cache_key : str, optional
        Identifies the job in each cached tile; tiles of another key are recomputed.
    hold_results : bool
        With ``cache_dir``, False keeps no result in memory: a finished tile's ``result`` is
        then None and its arrays are read back from its cache file (:func:`load_cached`), so
        the caller can take them one at a time.
    reusable : callable(tile) -> bool, optional
        With ``resume``, a cached tile is reused only when this also holds (e.g. the tile's
        point file is still there); the others are recomputed.
    progress : callable(done, total), optional
    dask_address : str, optional
        A ``dask.distributed`` scheduler address (``tcp://host:port``) or a ``Client``; tiles
        are then submitted there.
    """
    tiles = list(tiles)
    todo, cached = [], []
    if cache_dir is not None:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
    for t in tiles:
        got = None
        if (
            resume
            and cache_dir is not None
            and cache_file(cache_dir, t).exists()
            and (reusable is None or reusable(t))
        ):
            got = _load(cache_dir, t, cache_key)
        if got is not None:
            cached.append(TileDone(t.index, got if hold_results else None, None, None))
        else:
            todo.append(t)
    if resume and cached:
        log.info("resume: %d of %d tile(s) already done", len(cached), len(tiles))
    total, done = len(tiles), len(cached)
    if progress and done:  # a resumed run's bar starts at the tiles it has
        progress(done, total)
    yield from cached
    cached = None
    by_index = {t.index: t for t in tiles}

    def collect(index, out, err, secs) -> TileDone:
        nonlocal done
        interrupt.check()  # a stop request that an earlier KeyboardInterrupt did not deliver
        done += 1
        failure = None
        if err is not None:
            log.warning(
                "tile %d (row %d, col %d) failed: %s",
                index,
                by_index[index].row0,
                by_index[index].col0,
                err,
            )
            failure = TileFailure(by_index[index], err)
            out = None
        else:
            if cache_dir is not None and out != _STORED:  # a dict of arrays, or _STORED
                _save(cache_dir, by_index[index], out, cache_key)
            if not hold_results and cache_dir is not None:
                out = None
        if progress:
            progress(done, total)
        return TileDone(index, out, failure, secs)

    # largest tiles first: the pool's last tiles are small ones, so no core idles behind a big
    # tile at the end
    todo = tile_order(todo)
    n = pool_size(workers, len(todo), dask_address)
    if dask_address is not None:
        yield from _run_dask(fn, todo, context, timeout, dask_address, collect)
        stop_idle_fork_server()
    elif n == 0:
        # in this process, as in a pool worker: each tile reuses the pages the last one freed
        keep_freed_memory()
        for t in todo:
            yield collect(*_run_one(fn, t, timeout, context))
        stop_idle_fork_server()
    else:
        ctx = pool_context()
        pool_opened(ctx)
        ex = ProcessPoolExecutor(
            max_workers=n,
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(context, worker_threads(n), worker_logging.spec()),
        )
        # a pool's workers store their tiles themselves when the caller reads them back from
        # the cache (the main process then neither unpickles nor checksums nor writes them)
        job = (
            functools.partial(_run_and_store, cache_dir=cache_dir, cache_key=cache_key)
            if cache_dir is not None and not hold_results
            else _run_one
        )
        try:
            futs = [ex.submit(job, fn, t, timeout) for t in todo]
            for f in as_completed(futs):
                yield collect(*f.result())
        except BaseException:  # Ctrl-C, SIGTERM, an error, the caller closing the generator:
            stop_pool(ex)  # stop the workers now (the fork server, if any, then ends with this
            pool_closed(stop_server=False)  # process: nothing waits for it)
            raise
        ex.shutdown(wait=True)
        pool_closed()


def _run_dask(fn, todo, context, timeout, address, collect):
    """:func:`iter_tiles` on Dask: yields ``collect(...)`` of each tile as it finishes."""
    try:
        from dask.distributed import as_completed as dask_completed
    except ImportError:
        raise InputError("--dask needs dask.distributed: pip install 'stereodem[dask]'") from None
    from stereodem.core.dask_threads import quiet_distributed_logging

    quiet_distributed_logging()
    own = not hasattr(address, "submit")
    if own:
        from stereodem.core.dask_threads import connect

        client = connect(address)
    else:
        client = address
    try:
        register_dask_plugin(client)  # each worker's BLAS/OpenCV/GDAL threads pinned
        ctx = client.scatter(context, broadcast=True)
        futs = [client.submit(_run_one, fn, t, timeout, ctx, pure=False) for t in todo]
        for f in dask_completed(futs):
            yield collect(*f.result())
    finally:
        if own:
            client.close()
