"""Stopping a process pool at once (an interrupted run, a failed job): the one rule for every
``concurrent.futures.ProcessPoolExecutor`` of the project (tiles, scenes of a batch, dates of
a stack)."""

from __future__ import annotations

import sys
import time

#: the ``-W`` filter for multiprocessing's resource tracker's own reports
_TRACKER_FILTER = "ignore::UserWarning:multiprocessing.resource_tracker"


def stop_pool(ex, grace: float = 2.0):
    """Stop the process pool ``ex`` at once: cancel its queued tasks and end its workers
    (SIGTERM, then SIGKILL after ``grace`` seconds), so no worker outlives an interrupted job
    and the interpreter can exit."""
    procs = list((getattr(ex, "_processes", None) or {}).values())  # the pool's workers
    # the result pipe's write end (shutdown() drops the executor's reference to it)
    writer = getattr(getattr(ex, "_result_queue", None), "_writer", None)
    ex.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + grace
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(1.0)
    # A worker ended while it was sending a result leaves half a message in the result pipe,
    # and the pool's manager thread then waits in recv() for the rest for ever: the
    # interpreter, which joins that thread at exit, never exits. With every worker gone the
    # parent holds the pipe's last write end; closing it turns that wait into end-of-file,
    # which the manager handles as a broken pool and ends.
    if writer is not None and not any(p.is_alive() for p in procs):
        try:
            writer.close()
        except OSError:
            pass


def quiet_resource_tracker() -> None:
    """Keep multiprocessing's resource tracker from printing on the command's stderr.

    The tracker is a helper process that unlinks the named semaphores of a pool (its queues'
    locks) whose owner exited without unlinking them, as after an interrupted job whose
    finalisers did not all run. It reports each as a ``UserWarning`` on the shared stderr, and
    it does so after the command has ended, below the command's own last line (the
    ``--resume`` hint): Python internals a user can do nothing about. The tracker still
    unlinks them; only its report is silenced.

    The tracker is started with the parent's interpreter flags, ``sys.warnoptions`` included
    (``multiprocessing.util._args_from_interpreter_flags``), so the filter is added there; it
    applies to the helper processes started after this call (the tracker, spawned workers)
    and leaves this process's own warning filters as they are."""
    if _TRACKER_FILTER not in sys.warnoptions:
        sys.warnoptions.append(_TRACKER_FILTER)
