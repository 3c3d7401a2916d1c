"""The run record (``run.json``): per-stage wall and CPU seconds and peak memory, the
versions of the libraries that shape the results, the accuracy headline."""

from __future__ import annotations

import logging
import os
import platform
import resource
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import pyproj
import rasterio
import rasterio.warp
import scipy

from stereodem.core import interrupt
from stereodem.stereo.runner import (
    process_peak_rss_mb,
    reset_peak_rss,
)

from .. import __version__

log = logging.getLogger(__name__)


def _peak_rss_mb():
    """Peak resident memory (MB) of this process (:func:`process_peak_rss_mb`) and of its
    largest finished child (``ru_maxrss``, which for a forked child includes the parent's
    pages at the fork: tile summaries carry each worker's own figure)."""
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return round(process_peak_rss_mb(), 1), round(kids, 1)


def _cpu_seconds():
    """CPU seconds (user + system) of this process (all its threads) and of its finished,
    waited-for child processes (the tile pool's workers once the pool is shut down)."""
    t = os.times()
    return t.user + t.system, t.children_user + t.children_system


@dataclass
class StageLog:
    """Per stage: wall seconds, CPU seconds (this process's threads: ``cpu_s``; worker
    processes: ``worker_cpu_s``) and peak resident memory (MB) of this process during the
    stage (``peak_rss_mb``; since the process started where the high-water mark cannot be
    reset, ``peak_rss_scope`` says which) and of its largest finished worker."""

    stages: dict = field(default_factory=dict)
    _cpu0: tuple = (0.0, 0.0)
    _scope: str = "process"

    def start(self) -> float:
        """Mark the start of a stage; returns its ``time.perf_counter()``. A pending stop
        request (:mod:`stereodem.core.interrupt`) stops the job here."""
        interrupt.check()
        self._scope = "stage" if reset_peak_rss() else "process"
        self._cpu0 = _cpu_seconds()
        return time.perf_counter()

    def record(self, name, t0, **extra):
        own, kids = _peak_rss_mb()
        cpu, workers = _cpu_seconds()
        self.stages[name] = dict(
            seconds=round(time.perf_counter() - t0, 3),
            cpu_s=round(cpu - self._cpu0[0], 2),
            worker_cpu_s=round(workers - self._cpu0[1], 2),
            peak_rss_mb=own,
            peak_rss_scope=self._scope,
            peak_worker_rss_mb=kids,
            **extra,
        )
        log.info("stage %s: %.1f s", name, self.stages[name]["seconds"])


def versions() -> dict:
    """Versions of stereodem and of the libraries that shape its results."""
    return dict(
        stereodem=__version__,
        python=platform.python_version(),
        numpy=np.__version__,
        scipy=scipy.__version__,
        opencv=cv2.__version__,
        rasterio=rasterio.__version__,
        gdal=rasterio.__gdal_version__,
        pyproj=pyproj.__version__,
        platform=platform.platform(),
    )


def headline(report) -> dict | None:
    """The accuracy figures of ``run.json``'s ``headline`` from an assessment report."""
    if not report:
        return None
    s = report["stats"]
    h = dict(
        n=s["n"],
        valid_pct=s["valid_pct"],
        median=s["median"],
        nmad=s["nmad"],
        rmse=s["rmse"],
        le90=s["le90"],
    )
    if report.get("coregistration"):
        h["coregistration"] = {k: report["coregistration"].get(k) for k in ("dx", "dy", "dz")}
        h["nmad_after_coregistration"] = report["after_coregistration"]["stats"]["nmad"]
    return h
