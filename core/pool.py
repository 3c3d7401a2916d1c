"""Stopping a process pool at once (an interrupted run, a failed job): the one rule for every
``concurrent.futures.ProcessPoolExecutor`` of the project (tiles, scenes of a batch, dates of
a stack)."""

from __future__ import annotations

import time


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
