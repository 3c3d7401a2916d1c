"""A stop request that is not lost.

The command line's SIGINT/SIGTERM handler raises ``KeyboardInterrupt`` at once and also records
the request here. Python cannot raise an exception everywhere: one raised inside a finaliser
(``__del__``, a weakref callback) or a C callback is printed or dropped and the job would run
on to the end. Long loops (the tile pool's results) and stage boundaries therefore call
:func:`check`, which raises ``KeyboardInterrupt`` again while a request is pending, so a job
stops at the next of them at the latest.
"""

from __future__ import annotations

_requested: list[int] = []


def request(signum: int) -> None:
    """Record a stop request (the signal's number)."""
    _requested.append(int(signum))


def requested() -> int | None:
    """The first pending request's signal number, or None."""
    return _requested[0] if _requested else None


def check() -> None:
    """Raise ``KeyboardInterrupt`` if a stop was requested."""
    if _requested:
        raise KeyboardInterrupt


def clear() -> None:
    """Forget the pending requests (the command that handled them has ended)."""
    _requested.clear()
