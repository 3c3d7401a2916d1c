"""One thread budget per process: BLAS/OpenMP, OpenCV and GDAL pinned together.

A job has one setting, ``--workers`` / ``[run] workers`` (N, default all cores). It governs

* the **pool**: N worker processes (stereo tiles, scenes of ``stereodem batch``), each pinned
  to ``worker_threads(N)`` = ``cores // N`` threads (1 when N = cores), so N workers keep N
  cores busy and no more: no BLAS / OpenCV / GDAL threads stacked on top of the processes;
* the **main process**: pinned to N threads, at most the cores (:func:`job_threads`), for its
  own stages (post, ortho, assessment, GDAL compression); it computes while the pool idles,
  and idles (waits) while the pool computes.

:func:`pin_threads` sets, in the calling process,

* BLAS and OpenMP thread pools of every loaded library (``threadpoolctl.threadpool_limits``,
  kept for the life of the process), and ``OMP_NUM_THREADS`` / ``OPENBLAS_NUM_THREADS`` /
  ``MKL_NUM_THREADS`` for libraries loaded later and for child processes;
* OpenCV's ``cv2.setNumThreads``;
* GDAL's ``GDAL_NUM_THREADS`` (environment and rasterio's GDAL configuration), which
  :func:`stereodem.core.raster.reading_env` and GDAL's multi-threaded codecs read (1 with a
  GDAL older than 3.8, whose threaded decoding hides damaged blocks: :func:`gdal_threads`).

:func:`current_limits` reads all of them back (what a test or ``run.json`` reports).
:func:`pool_initializer` is the process-pool ``initializer`` and :func:`register_dask_plugin`
installs the Dask worker plugin that do the same in every worker.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import threading

from . import cgroup, worker_logging  # no third-party import: loads nothing before the pin

#: the environment variables that size BLAS / OpenMP / numexpr thread pools when a runtime is loaded
ENV_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)
_LIMITS = None  # the threadpoolctl limiter of this process (kept alive: the pin holds)
_PINNED: int | None = None


def cores() -> int:
    """CPU cores this process may use: its affinity mask where the OS has one, and no more
    than its control groups' CPU quota rounded up (:func:`stereodem.core.cgroup.cpu_quota`:
    a container's ``--cpus``, a pod's CPU limit), which no affinity mask shows."""
    try:
        n = len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    quota = cgroup.cpu_quota()
    return n if quota is None else max(1, min(n, math.ceil(quota)))


def pool_size(workers: int | None) -> int:
    """Worker processes of a job's pool for ``--workers`` (None: all cores); as many as asked,
    even beyond the cores (each then gets one thread: :func:`worker_threads`)."""
    return max(1, int(workers)) if workers else cores()


def job_threads(workers: int | None) -> int:
    """Threads of a job's main process for ``--workers`` (None: all cores): the workers asked
    for, but never more than the cores (threads beyond them only add switching: on 2 cores,
    ``--workers 16`` ran the main process's stages on 16 threads: ortho and the assessment
    took 1.3-1.4x the CPU seconds they take on 2)."""
    return min(pool_size(workers), cores())


def worker_threads(workers: int | None, n_cores: int | None = None) -> int:
    """Threads of each of ``workers`` pool processes on ``n_cores`` cores: the cores shared
    out (``n_cores // workers``, at least 1). ``workers`` = cores gives 1 thread each."""
    n_cores = n_cores or cores()
    return max(1, n_cores // pool_size(workers))


def _controller():
    """A threadpoolctl controller of the BLAS and OpenMP runtimes loaded now: one scan of the
    process's loaded libraries (``/proc/self/maps`` on Linux, 2-8 ms in a process with many
    mappings), which its ``limit`` and ``info`` then reuse; ``threadpool_limits`` and
    ``threadpool_info`` scan again at every call (four scans per :func:`thread_budget`, 15 s of
    the fast test subset's profile, before)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


#: the first GDAL whose multi-threaded GeoTIFF decoding reports a block it cannot decode
#: (3.8.4, 3.9.2 and 3.10.3 raise on a DEFLATE block damaged in the middle of a file; 3.6.4,
#: in rasterio 1.3.8's wheels, decodes it into zeros on 2 threads without a word: heights of
#: 0 m read as data, and a single thread raises there too)
GDAL_REPORTS_THREADED_DECODE_ERRORS = (3, 8)


def gdal_threads(n) -> str:
    """What ``GDAL_NUM_THREADS`` is set to for a budget of ``n`` threads (an int, or GDAL's
    ``"ALL_CPUS"``): ``n``, but ``"1"`` with a GDAL older than
    :data:`GDAL_REPORTS_THREADED_DECODE_ERRORS`, whose threaded decoding of GeoTIFF blocks
    hides damaged blocks (one rule for the pin and :func:`stereodem.core.raster.reading_env`;
    the products' compression threads are set per write, ``NUM_THREADS``, and unaffected)."""
    import rasterio

    version = tuple(int(v) for v in rasterio.__gdal_version__.split(".")[:2])
    return str(n) if version >= GDAL_REPORTS_THREADED_DECODE_ERRORS else "1"


def pin_threads(n: int, *, controller=None) -> dict:
    """Pin this process's BLAS/OpenMP, OpenCV and GDAL threads to ``n`` (>= 1); returns
    :func:`current_limits`. Calling it again re-pins (the last call wins). ``controller``: a
    :func:`_controller` taken just before (else a new one: the runtimes loaded now)."""
    global _LIMITS, _PINNED
    n = max(1, int(n))
    for var in ENV_VARS:
        os.environ[var] = str(n)
    gdal = gdal_threads(n)
    os.environ["GDAL_NUM_THREADS"] = gdal
    from rasterio.env import set_gdal_config

    set_gdal_config("GDAL_NUM_THREADS", gdal)
    controller = controller or _controller()
    _LIMITS = controller.limit(limits=n)  # every loaded BLAS and OpenMP runtime
    import cv2

    cv2.setNumThreads(n)
    _PINNED = n
    return current_limits(controller=controller)


@contextlib.contextmanager
def thread_budget(n: int | None):
    """``with thread_budget(workers):`` pin this process to :func:`job_threads` (``workers``)
    threads for the block, then restore the previous BLAS/OpenMP, OpenCV and GDAL limits.

    The BLAS / OpenMP runtimes that load from the block's start (the command line's process:
    NumPy's, SciPy's and OpenCV's OpenBLAS, with OpenCV here) start with the budget's threads:
    each starts a spinning thread per core when it loads (numpy, SciPy and OpenCV took 0.40
    instead of 0.22 CPU s to import on 2 cores for a budget of 1), threads a budget smaller
    than the cores never uses."""
    global _LIMITS, _PINNED
    saved_env = {v: os.environ.get(v) for v in (*ENV_VARS, "GDAL_NUM_THREADS")}
    threads = job_threads(n)
    for var in ENV_VARS:
        os.environ[var] = str(threads)
    try:
        import cv2

        saved = (_LIMITS, _PINNED, cv2.getNumThreads())
        from rasterio.env import get_gdal_config, set_gdal_config

        saved_gdal = get_gdal_config("GDAL_NUM_THREADS")
        controller = _controller()  # one scan of the loaded runtimes for the record and the pin
        outer = controller.limit(limits=None)  # a record of the limits before the block
    except BaseException:
        _restore_env(saved_env)
        raise
    try:
        yield pin_threads(threads, controller=controller)
    finally:
        outer.restore_original_limits()
        cv2.setNumThreads(saved[2])
        _restore_env(saved_env)
        if saved_gdal is None:  # unset it (set_gdal_config(k, None) sets "None")
            from rasterio._env import del_gdal_config

            del_gdal_config("GDAL_NUM_THREADS")
        else:
            set_gdal_config("GDAL_NUM_THREADS", saved_gdal)
        _LIMITS, _PINNED = saved[0], saved[1]


def _restore_env(saved: dict) -> None:
    """Set the environment variables of ``saved`` back (None: unset)."""
    for var, value in saved.items():
        if value is None:
            os.environ.pop(var, None)
        else:
            os.environ[var] = value


#: how much less CPU priority a background thread takes (nice increment): weight 110 against
#: 1024 under Linux's scheduler, so the thread takes ~10 % of a core wanted by another, and
#: all of a core nobody else wants
BACKGROUND_NICE = 10


def lower_thread_priority(increment: int = BACKGROUND_NICE) -> bool:
    """Let the calling thread yield its core to the process's other threads: raise its nice
    value by ``increment`` (at most 19). Linux only, where the nice value belongs to each
    thread (elsewhere ``setpriority`` would act on the whole process, or on a process whose
    PID happened to equal a thread id): returns whether the priority was lowered. A thread
    cannot raise it back (that needs CAP_SYS_NICE), so call it in a thread of its own, e.g. a
    pool's ``initializer``; threads it starts (GDAL's) inherit it. Background work at this
    priority fills the cores the foreground leaves idle instead of slowing it (as RocksDB
    lowers the priority of its compaction threads)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        tid = threading.get_native_id()
        nice = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(19, nice + int(increment)))
    except (AttributeError, OSError):
        return False
    return True


def pinned() -> int | None:
    """The budget this process was pinned to by :func:`pin_threads` (None if never)."""
    return _PINNED


def current_limits(*, controller=None) -> dict:
    """The thread limits in force in this process: ``opencv`` (``cv2.getNumThreads``),
    ``blas`` and ``openmp`` (largest pool per API, threadpoolctl; None when none is loaded),
    ``gdal`` (``GDAL_NUM_THREADS`` as GDAL sees it) and the ``pinned`` budget. ``controller``:
    a :func:`_controller` of the runtimes loaded now (else a new one)."""
    import cv2

    out = {"opencv": cv2.getNumThreads(), "blas": None, "openmp": None}
    for pool in (controller or _controller()).info():
        api = pool.get("user_api")
        if api in ("blas", "openmp"):
            out[api] = max(out[api] or 0, int(pool["num_threads"]))
    from rasterio.env import get_gdal_config

    gdal = get_gdal_config("GDAL_NUM_THREADS")
    out["gdal"] = str(gdal if gdal is not None else os.environ.get("GDAL_NUM_THREADS"))
    out["pinned"] = _PINNED
    return out


def pool_initializer(n: int, log=None, then=None, *args):
    """``ProcessPoolExecutor(initializer=pool_initializer, initargs=pool_initargs(n, then,
    *args))``: pin the worker to ``n`` threads, set up its logging as the main process's
    (``log``: :func:`stereodem.core.worker_logging.spec`), then run ``then(*args)`` (the
    pool's own initializer)."""
    pin_threads(n)
    worker_logging.apply(log)
    if then is not None:
        then(*args)


def pool_initargs(n: int, then=None, *args) -> tuple:
    """The ``initargs`` of :func:`pool_initializer`: ``n`` threads, this process's worker
    logging (:mod:`stereodem.core.worker_logging`), the pool's own initializer and its
    arguments."""
    return (n, worker_logging.spec(), then, *args)


def register_dask_plugin(client, threads: int | None = None, *, own_workers: bool = False):
    """Pin every present and future worker of ``client``'s cluster to ``threads`` per task
    slot (default: each node's cores shared out over the task slots of all the workers on that
    node, counted now: :func:`stereodem.core.dask_threads.slots_by_host`):
    :class:`stereodem.core.dask_threads.ThreadsPlugin`. ``own_workers``: the cluster is one
    this process started (``--dask local``), whose workers then log as this process does
    (:mod:`stereodem.core.worker_logging`: ``-q`` silenced the pool's workers' warnings, not
    the Dask workers'); a given cluster's workers keep their logging."""
    from .dask_threads import ThreadsPlugin, slots_by_host

    plugin = ThreadsPlugin(
        threads,
        None if threads else slots_by_host(client),
        worker_logging.spec() if own_workers else None,
    )
    if hasattr(client, "register_plugin"):
        client.register_plugin(plugin, name=ThreadsPlugin.name)
    else:  # pragma: no cover - dask < 2023.9
        client.register_worker_plugin(plugin, name=ThreadsPlugin.name)
    return plugin


def worker_limits() -> dict:
    """:func:`current_limits` of the calling worker (a picklable task for pools and Dask)."""
    return current_limits()
