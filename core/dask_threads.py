"""The Dask side of :mod:`stereodem.core.threads` (imported only when Dask is used): the worker
plugin that pins each worker's threads, the ``LocalCluster`` every command starts
(:func:`local_cluster`), and the connection to a given scheduler (:func:`connect`).

Dask's statistical profiler is off in the workers this package starts and in the workers of a
given cluster that run a Python with CPython's ``sys._current_frames`` deadlock
(:data:`PROFILER_DEADLOCKS`): every 10 ms the profiler thread takes every thread's frame under
the interpreter's runtime lock, and on Python 3.11 a garbage collection started there waits
for the GIL while a task thread that holds the GIL waits for that lock (CPython issues 106883
and 116969, dask/distributed issue 8616). A ``mosaic --dask`` test hung there for good (both
block threads and the worker's event loop idle, the client waiting on a block).
"""

from __future__ import annotations

import logging
import sys
from collections import Counter

from distributed.comm import get_address_host
from distributed.diagnostics.plugin import WorkerPlugin

from . import worker_logging
from .errors import InputError, one_line
from .threads import cores, pin_threads

log = logging.getLogger(__name__)

#: whether this Python can deadlock in ``sys._current_frames`` (Dask's profiler) when a
#: garbage collection starts there: 3.11, where a collection can start at any allocation
#: (3.12 collects only between bytecodes; a later 3.11 backport is not relied on)
PROFILER_DEADLOCKS = sys.version_info[:2] == (3, 11)

#: the Dask configuration of the clusters :func:`local_cluster` starts: no statistical
#: profiler (nothing here reads its samples; it is what deadlocks, see the module's text)
LOCAL_CLUSTER_CONFIG = {"distributed.worker.profile.enabled": False}


def local_cluster(n_workers: int, threads_per_worker: int = 1, processes: bool = True):
    """A ``LocalCluster`` as every command starts one (``batch --dask local``, ``mosaic``; the
    tests' clusters too):
    ``n_workers`` workers of ``threads_per_worker`` task slots, in processes or in this
    one, without the profiler (:data:`LOCAL_CLUSTER_CONFIG`), and its HTTP server on a free
    port (``dashboard_address=None`` turns the dashboard off but the scheduler's HTTP server
    still took port 8787, or warned "Port 8787 is already in use" and took another when a
    second cluster ran on the machine)."""
    import dask
    from dask.distributed import LocalCluster

    with dask.config.set(LOCAL_CLUSTER_CONFIG):  # read by each worker (nanny) as it starts
        return LocalCluster(
            n_workers=n_workers,
            threads_per_worker=threads_per_worker,
            processes=processes,
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": ":0"},
        )


def stop_profiler(worker) -> bool:
    """Stop the statistical profiler of a Dask ``worker`` (its periodic callbacks
    ``profile`` and ``profile-cycle``); returns whether it was running."""
    stopped = False
    for name in ("profile", "profile-cycle"):
        pc = getattr(worker, "periodic_callbacks", {}).pop(name, None)
        if pc is not None:
            pc.stop()
            stopped = True
    return stopped


def slots_by_host(client) -> dict[str, int]:
    """Task slots (``nthreads``) of ``client``'s cluster summed per host: the workers that
    share a node's cores (a ``LocalCluster`` of N single-slot processes: N on one host)."""
    slots: Counter = Counter()
    for address, info in client.scheduler_info().get("workers", {}).items():
        host = info.get("host") or get_address_host(address)
        slots[host] += max(1, int(info.get("nthreads", 1) or 1))
    return dict(slots)


class ThreadsPlugin(WorkerPlugin):
    """Pins a Dask worker process's BLAS/OpenMP, OpenCV and GDAL threads at its start:
    ``threads`` per task slot, default the node's cores shared out over every task slot of
    the workers on that node (``host_slots``: :func:`slots_by_host` when the plugin was
    registered; a worker on a host not in it counts its own slots), at least 1, so a node's
    workers together use its cores and no more. ``logging_setup``: how the workers set up
    their logging (:func:`stereodem.core.worker_logging.spec` of the process that started the
    cluster; None: left alone). Stops the statistical profiler where it deadlocks."""

    name = "stereodem-threads"

    def __init__(
        self,
        threads: int | None = None,
        host_slots: dict[str, int] | None = None,
        logging_setup: tuple | None = None,
    ):
        self.threads = threads
        self.host_slots = dict(host_slots or {})
        self.logging_setup = logging_setup  # stereodem.core.worker_logging.spec(), or None

    def slots(self, worker) -> int:
        """Task slots sharing ``worker``'s node: the registered count for its host, at least
        its own."""
        own = max(1, int(getattr(worker, "nthreads", 1) or 1))
        try:
            host = get_address_host(worker.address)
        except (AttributeError, TypeError, ValueError):
            return own
        return max(own, int(self.host_slots.get(host, own)))

    def setup(self, worker):
        pin_threads(self.threads or max(1, cores() // self.slots(worker)))
        # the workers of a cluster this process started log as it does (-q, -v, the format);
        # a given cluster's workers keep their own logging
        worker_logging.apply(self.logging_setup)
        if PROFILER_DEADLOCKS and stop_profiler(worker):
            log.info(
                "Dask worker %s: statistical profiler stopped (Python %s can deadlock in "
                "sys._current_frames, CPython issue 116969)",
                getattr(worker, "address", "?"),
                ".".join(map(str, sys.version_info[:3])),
            )


def connect(address, timeout: str = "20s"):
    """A ``Client`` of the Dask scheduler at ``address`` (``tcp://host:port``, a scheduler
    file's address...), waiting up to ``timeout`` (Dask's duration string) for it; a
    scheduler that cannot be reached is an :class:`InputError` naming it, not a traceback."""
    from distributed import Client

    try:
        return Client(address, timeout=timeout)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(
            f"--dask {address}: cannot connect to the scheduler "
            f"({type(exc).__name__}: {one_line(exc)})"
        ) from None


def quiet_distributed_logging() -> None:
    """Bring ``distributed``'s loggers to the root logger's level when that is above INFO.

    ``distributed`` sets its logger to INFO when it is imported (its default configuration)
    and lets the records propagate: under the command line's handler (warnings and errors by
    default) ``stereodem batch --dask local`` printed some twenty lines of scheduler, nanny
    and connection chatter around its own result lines. With ``-v`` (root at INFO or DEBUG),
    or an application whose root logger shows INFO, they are left as ``distributed`` set them.
    Call it after importing ``dask.distributed``.
    """
    import logging

    level = logging.getLogger().getEffectiveLevel()
    if level <= logging.INFO:
        return
    logger = logging.getLogger("distributed")
    if logger.level != logging.NOTSET and logger.level < level:
        logger.setLevel(level)
