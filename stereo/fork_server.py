"""The tile pool's fork server: started early, shared by concurrent pools, stopped by the last.

Pool workers start from a fork server that has imported the tile code once: a spawned
interpreter spends about 1 CPU s importing numpy, SciPy, OpenCV, rasterio and pyproj, a fork
of the server milliseconds (16 workers: ~16 CPU s saved per pool). Not a fork of this
process: a forked child inherits OpenCV's and PROJ's thread state and can deadlock in its
first cv2 call; the server has only imported modules.

The server this module starts is stopped when the process's last running tile pool ends
(:func:`pool_closed`), so that its workers' CPU time comes back to this process as a
waited-for child's (``RUSAGE_CHILDREN``: run.json's ``worker_cpu_s``); a server someone else
started is left alone.

A command that will run tiles on a pool starts the server first (:func:`warm_fork_server`,
:func:`fork_server_for_job`), so that the server's imports run on a core the command's own
start (its imports, the loading of the images) leaves idle. This module imports nothing
heavy for that reason: the commands call it before they load the pipeline.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading

from stereodem.core import threads

#: what the server imports before it forks workers: first a module that makes it ignore
#: SIGINT (:mod:`stereodem.core.ignore_interrupt`: a Ctrl-C during the next imports printed
#: their traceback), then one that starts the BLAS / OpenMP runtimes with one thread
#: (:mod:`stereodem.core.one_thread_runtimes`: the workers pin their own budget), then the
#: tile code and what it imports
_PRELOAD = [
    "stereodem.core.ignore_interrupt",
    "stereodem.core.one_thread_runtimes",
    "stereodem.stereo.pipeline",
    "stereodem.stereo.execution",
]

_OPEN_POOLS = 0  # tile pools of this process now running (threads may each run one)
_OWN_SERVER = None  # PID of the fork server this module started, while it runs
_SERVER_LOCK = threading.Lock()


def pool_size(workers: int | None, n_tiles: int | None, dask_address=None) -> int:
    """Worker processes :func:`stereodem.stereo.runner.run_tiles` starts for ``n_tiles``
    tiles: 0 when it runs them in this process (one worker, at most one tile, or Dask), else
    ``workers`` (None: all cores: :func:`stereodem.core.threads.pool_size`). ``n_tiles``
    None: not known yet (taken as more than one)."""
    n = threads.pool_size(workers)
    few = n_tiles is not None and n_tiles <= 1
    return 0 if dask_address is not None or n == 1 or few else n


def pool_context():
    """The multiprocessing context of the tile pool: ``forkserver`` with the tile code
    preloaded where the platform has it (Linux, macOS), else ``spawn``."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(_PRELOAD)
    return ctx


def _fork_server():
    """CPython's fork server object (None where there is none)."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return None
    from multiprocessing import forkserver

    return getattr(forkserver, "_forkserver", None)


def _start_fork_server() -> bool:
    """Start the fork server now (its imports then run in the background) and remember it as
    this module's if none ran; returns whether one runs. Caller holds ``_SERVER_LOCK``."""
    global _OWN_SERVER
    server = _fork_server()
    if server is None or not hasattr(server, "ensure_running"):
        return False
    was = getattr(server, "_forkserver_pid", None)
    server.ensure_running()
    if was is None:
        _OWN_SERVER = getattr(server, "_forkserver_pid", None)
    return True


def _stop_unused_fork_server():
    """Stop this module's fork server when no tile pool of this process runs: it is ended
    (``SIGTERM``), this process waits for it, and the CPU time of the workers it reaped is
    added to this process's ``RUSAGE_CHILDREN``.

    The signal ends it at once, with nothing lost: no pool runs, so every worker it forked
    has ended and been reaped (a pool's shutdown waits for its workers' exit codes, which the
    server sends after reaping them). Left to exit by itself, a server no pool used would
    first finish its imports (up to ~1 s), and one that served a pool would first tear down
    the modules it imported (0.14-0.18 s on the full ASTER granule at 2 workers, measured):
    time a job waits for on one core, between its stereo stage and the next. Caller holds
    ``_SERVER_LOCK``."""
    global _OWN_SERVER
    server = _fork_server()
    if _OPEN_POOLS or _OWN_SERVER is None or server is None:
        return
    if getattr(server, "_forkserver_pid", None) == _OWN_SERVER:
        stop = getattr(server, "_stop", None)  # CPython's own (its tests use it), 3.8+
        if stop is not None:
            with contextlib.suppress(OSError):
                os.kill(_OWN_SERVER, signal.SIGTERM)
            with contextlib.suppress(OSError, ChildProcessError):
                stop()
    _OWN_SERVER = None


def warm_fork_server(workers: int | None, n_tiles: int | None = None, dask_address=None) -> bool:
    """Start the fork server of a tile pool about to come, so that the server's imports
    (~1 s) overlap this process's work instead of delaying the first tiles. Returns whether
    one runs; nothing happens where ``run_tiles`` would not start a pool (one worker,
    ``n_tiles`` <= 1, Dask) or on a platform without a fork server (``n_tiles`` None: not
    known yet). A server no pool used is stopped by the next ``run_tiles`` or by
    :func:`stop_idle_fork_server` (its CPU is then counted as a waited-for child's)."""
    if pool_size(workers, n_tiles, dask_address) == 0:
        return False
    if pool_context().get_start_method() != "forkserver":
        return False
    with _SERVER_LOCK:
        return _start_fork_server()


@contextlib.contextmanager
def fork_server_for_job(workers: int | None, dask_address=None):
    """A command's whole job: the fork server started on entry (before the command imports
    its pipeline and loads its inputs, when ``workers`` asks for a pool) and, on exit, stopped
    unless a pool still runs, whether the job used it, ran its tiles here or failed first
    (an interrupted job's server ends with the process: nothing waits for it)."""
    warm_fork_server(workers, None, dask_address)
    interrupted = False
    try:
        yield
    except KeyboardInterrupt:  # left to end with this process, as an interrupted pool's is
        interrupted = True
        raise
    finally:
        if not interrupted:
            stop_idle_fork_server()


def pool_opened(ctx):
    """A tile pool of context ``ctx`` starts: a fork server (started here if needed) runs until
    it ends."""
    global _OPEN_POOLS
    with _SERVER_LOCK:
        if ctx.get_start_method() == "forkserver":
            _start_fork_server()
        _OPEN_POOLS += 1


def pool_closed(*, stop_server: bool = True):
    """A tile pool ended; the last one to end normally stops this module's fork server (on an
    interrupt it is left to end with this process: nothing waits for it)."""
    global _OPEN_POOLS
    with _SERVER_LOCK:
        _OPEN_POOLS -= 1
        if stop_server:
            _stop_unused_fork_server()


def stop_idle_fork_server():
    """Stop a fork server that :func:`warm_fork_server` started for a pool that did not come
    (the tiles ran here or on Dask, or the job ended first), unless a pool of another thread
    uses it."""
    with _SERVER_LOCK:
        _stop_unused_fork_server()
