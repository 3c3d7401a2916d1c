"""The assessment's inputs read ahead: ``stereodem run`` starts reading the reference DEM (and
importing the report's figure modules, matplotlib among them) at its start, in a background
thread of low CPU priority, so that the assessment, the job's last stage, does not begin
with them.

Neither depends on anything the stereo, filter or orthoimage stages make, and both ran
alone at the start of the assessment with every other core idle (on the full simulated
granule, 2 workers: the reference's read 0.45-0.6 s and the imports 0.43 s of an assessment
of 2.5-3.6 s); read ahead, they fill the cores the job's start, its loading and the stereo
stage's sparse part leave idle, and yield the cores to the workers otherwise
(:func:`stereodem.core.threads.lower_thread_priority`). On 2 cores at 2 workers the job is
as fast as without (its cores are seldom idle); a machine with more cores than the job's
serial parts use gains the assessment's start. The reference is held in memory from the
job's start (4 bytes a cell of the reference grid; the 15 m reference of the full granule:
181 MB; the peak over all processes at 2 workers 1.91-2.02 GB instead of 1.79-1.88 GB). A
read that fails stops the job at the next stage boundary (:meth:`AssessmentPrefetch.
raise_if_failed`), not after the orthoimages. A job of one worker keeps to one core: there
the assessment reads its inputs itself, as before.
"""

from __future__ import annotations

import importlib
import logging
import time
from concurrent.futures import ThreadPoolExecutor

from stereodem.core.dem import DEM
from stereodem.core.threads import lower_thread_priority

from ..config import Config

log = logging.getLogger(__name__)

#: modules the assessment imports on its way (its report and figures: matplotlib)
REPORT_MODULES = ("stereodem.post.report",)


def _read_ahead(cfg: Config) -> DEM:
    i = cfg.inputs
    ref = DEM.from_file(i.reference_dem, vertical=i.reference_vertical)
    for name in REPORT_MODULES:
        importlib.import_module(name)
    return ref


class AssessmentPrefetch:
    """The reference DEM of ``cfg`` read (and the report's modules imported) in a background
    thread from construction on, when ``threads`` (the job's thread budget) is 2 or more;
    :meth:`reference` waits for it (re-raising what the read raised: the same error the
    assessment's own read gives, at the same point of the job) or reads it then, with one
    thread. ``waited_s``: the seconds :meth:`reference` waited."""

    def __init__(self, cfg: Config, threads: int):
        self._cfg = cfg
        self._pool = self._future = None
        self.waited_s = 0.0
        if threads >= 2 and cfg.inputs.reference_dem:
            self._pool = ThreadPoolExecutor(
                max_workers=1,
                thread_name_prefix="stereodem-prefetch",
                initializer=lower_thread_priority,
            )
            self._future = self._pool.submit(_read_ahead, cfg)

    def reference(self) -> DEM:
        """The reference DEM (once: the prefetch keeps no reference to it after)."""
        if self._future is None:
            return _read_ahead(self._cfg)
        future, self._future = self._future, None
        t0 = time.perf_counter()
        try:
            return future.result()
        finally:
            self.waited_s = time.perf_counter() - t0
            log.debug("assessment inputs read ahead: waited %.2f s for them", self.waited_s)
            self.close()

    def raise_if_failed(self):
        """Re-raise, at once, what the read ahead raised if it has failed already (a reference
        whose first and last blocks read, which the input checks probe, but not a block in
        between): the job stops at the next stage instead of at the assessment, after the
        stereo stage and the orthoimages. Does not wait for a read under way."""
        f = self._future
        if f is not None and f.done() and not f.cancelled() and f.exception() is not None:
            self._future = None
            self.close()
            raise f.exception()

    def close(self):
        """Stop: a read not started is dropped, one under way ends in its thread (a failed
        job does not wait for it)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
