"""Will it fit? Memory checks made before an allocation that a hostile input could make absurd
(an image declaring 200 000 x 200 000 pixels, a posting of a millimetre).

The limit is the memory the system can give now (``MemAvailable`` of ``/proc/meminfo``, else
the physical memory), so a request that cannot succeed fails at once with a message naming
what was asked for, instead of a ``MemoryError`` or the OOM killer after minutes of work.
"""

from __future__ import annotations

import os

from stereodem.core.errors import InputError

__all__ = ["available_bytes", "check_allocation", "human_bytes"]


def available_bytes() -> int:
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``; elsewhere the
    physical memory; 2**63 when unknown)."""
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
    if nbytes > cap:
        raise InputError(
            f"{what} needs {human_bytes(nbytes)} of memory, more than the "
            f"{human_bytes(cap)} available"
        )
