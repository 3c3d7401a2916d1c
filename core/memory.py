"""Will it fit? Memory checks made before an allocation that a hostile input could make absurd
(an image declaring 200 000 x 200 000 pixels, a posting of a millimetre).

The limit is the memory the system can give now (``MemAvailable`` of ``/proc/meminfo``, else
the physical memory), within what the process's control groups still allow (a container's or a
batch job's memory limit), so a request that cannot succeed fails at once with a message naming
what was asked for, instead of a ``MemoryError`` or the OOM killer after minutes of work.
"""

from __future__ import annotations

import os

from stereodem.core import cgroup
from stereodem.core.errors import InputError

__all__ = ["available_bytes", "check_allocation", "human_bytes", "keep_freed_memory"]

#: glibc's ``mallopt`` parameters (``malloc.h``) and the values set by
#: :func:`keep_freed_memory`: freed memory is kept for reuse (trimmed back to the system only
#: above 512 MB) and blocks up to glibc's largest threshold (32 MB on 64-bit) come from the
#: heap instead of fresh maps
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_KEEP_TRIM_BYTES, _KEEP_MMAP_BYTES = 512 << 20, 32 << 20


def keep_freed_memory() -> bool:
    """Let this process's allocator keep the memory it frees (glibc ``mallopt``), for the
    whole process and from now on.

    The work here allocates and frees arrays of a few to a few tens of MB again and again (a
    tile, a row block, a filter pass). By default glibc returns such blocks to the system
    (each is a fresh map, or the freed top of the heap is trimmed beyond a threshold that
    grows only to 2 x 32 MB), so the next one faults its pages in afresh, each zero-filled by
    the kernel. With this the pages are reused instead; the peak is the same, since a
    working set is reused, not added to. Set in the tile pool's worker processes, and by
    :func:`stereodem.stereo.runner.run_tiles` when it runs the tiles in its own process (one
    worker: that process then works like a pool worker for the rest of the job). Not set
    for a main process that runs its stages on several threads (each thread's arena would
    keep its own freed memory; at 2 workers it measured no faster). Returns whether it
    applied (False where the C library is not glibc)."""
    try:
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(_M_TRIM_THRESHOLD, _KEEP_TRIM_BYTES) == 1
    return mallopt(_M_MMAP_THRESHOLD, _KEEP_MMAP_BYTES) == 1 and ok


def available_bytes() -> int:
    """Bytes of memory available to a new allocation: the system's (Linux ``MemAvailable``;
    elsewhere the physical memory; 2**63 when unknown), and no more than what this process's
    control groups still allow (:func:`stereodem.core.cgroup.memory_available`: a
    container's ``--memory``, a pod's or a batch job's memory limit, which ``/proc/meminfo``
    does not show)."""
    group = cgroup.memory_available()
    system = _system_available_bytes()
    return system if group is None else min(system, group)


def _system_available_bytes() -> int:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover
        return 2**63


def human_bytes(n: float) -> str:
    """``n`` bytes as text (``"5.2 TB"``)."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1000.0
    return f"{n:.3g} PB"  # pragma: no cover


def check_allocation(
    nbytes: float, what: str, *, fraction: float = 0.8, limit: float | None = None
):
    """Raise :class:`InputError` if ``nbytes`` exceed ``fraction`` of the available memory
    (or ``limit`` bytes when given); ``what`` names the request in the message."""
    cap = limit if limit is not None else fraction * available_bytes()
    if not nbytes <= cap:  # NaN too: a size from an extent of inf / inf cells
        raise InputError(
            f"{what} needs {human_bytes(nbytes)} of memory, more than the "
            f"{human_bytes(cap)} available"
        )
