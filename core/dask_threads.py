"""The Dask worker plugin of :mod:`stereodem.core.threads` (imported only when Dask is used)."""

from __future__ import annotations

from distributed.diagnostics.plugin import WorkerPlugin

from .threads import cores, pin_threads


class ThreadsPlugin(WorkerPlugin):
    """Pins a Dask worker process's BLAS/OpenMP, OpenCV and GDAL threads at its start:
    ``threads`` per task slot, default the node's cores shared out over the worker's
    ``nthreads`` slots (at least 1), so a node's workers use its cores and no more."""

    name = "stereodem-threads"

    def __init__(self, threads: int | None = None):
        self.threads = threads

    def setup(self, worker):
        slots = max(1, int(getattr(worker, "nthreads", 1) or 1))
        pin_threads(self.threads or max(1, cores() // slots))
