"""How process-pool workers log: the main process's logging set-up, handed to each worker.

A spawned or fork-server worker starts with no log handler: Python's last-resort handler
prints a warning's message alone (no level, no logger), and info lines are lost at ``-v``. An
application that sets up logging registers how it did (:func:`register`: a picklable callable
and its arguments, e.g. the command line's ``setup_logging(verbose, quiet)``); every process
pool of the library (the stereo tiles, the stack's dates, the batch's scenes) passes
:func:`spec` to its workers, whose initializer calls :func:`apply`, so their lines read as
the main process's. With nothing registered (an embedding application's own logging, pytest)
the workers are left as they are.
"""

from __future__ import annotations

__all__ = ["register", "spec", "apply"]

_SPEC: tuple | None = None


def register(fn, *args) -> None:
    """Record ``fn(*args)`` (picklable: a module-level function and plain arguments) as what
    sets up a worker's logging."""
    global _SPEC
    _SPEC = (fn, args)


def spec() -> tuple | None:
    """What :func:`register` recorded, for a pool's ``initargs`` (None: nothing)."""
    return _SPEC


def apply(setup: tuple | None) -> None:
    """In a worker's initializer: set up logging as :func:`spec` says (None: nothing)."""
    if setup is not None:
        fn, args = setup
        fn(*args)
