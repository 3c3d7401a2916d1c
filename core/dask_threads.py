"""The Dask worker plugin of :mod:`stereodem.core.threads` (imported only when Dask is used)."""

from __future__ import annotations

from collections import Counter

from distributed.comm import get_address_host
from distributed.diagnostics.plugin import WorkerPlugin

from .errors import InputError, one_line
from .threads import cores, pin_threads


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
    workers together use its cores and no more."""

    name = "stereodem-threads"

    def __init__(self, threads: int | None = None, host_slots: dict[str, int] | None = None):
        self.threads = threads
        self.host_slots = dict(host_slots or {})

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
