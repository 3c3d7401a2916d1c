"""The ``stereodem`` command line: one sub-command per job.

Exit codes: 0 success, 1 the job failed (a one-line message says why), 2 bad usage.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import importlib
import logging
import os
import signal
import sys
import threading
import warnings

from stereodem.core import interrupt
from stereodem.core.errors import StereodemError, one_line
from stereodem.core.pool import quiet_resource_tracker

from . import __version__
from .commands import COMMANDS

log = logging.getLogger("stereodem")


def _named_command(argv) -> str | None:
    """The sub-command ``argv`` names (its first word that is not an option), if known."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def build_parser(only: str | None = None, *, listing: bool = False) -> argparse.ArgumentParser:
    """The command-line parser; with ``only``, just that sub-command's (the others' modules,
    some of them slow to import, are then not loaded: a job starts about a second sooner).
    ``listing``: the sub-commands by name and summary only (:data:`COMMANDS`), none of their
    modules imported: what ``stereodem``, ``stereodem --help`` and a misspelt command need."""
    parser = argparse.ArgumentParser(
        prog="stereodem",
        description="Satellite stereo photogrammetry: stereo pairs in, DEMs and orthoimages out.",
        epilog="Run 'stereodem COMMAND --help' for the options and examples of each command.",
    )
    parser.add_argument("--version", action="version", version=f"stereodem {__version__}")
    verb = parser.add_mutually_exclusive_group()
    verb.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)"
    )
    verb.add_argument("-q", "--quiet", action="store_true", help="only errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (modname, summary) in COMMANDS.items():
        if listing:
            sub.add_parser(name, help=summary)
        elif only is None or name == only:
            importlib.import_module(modname).add_parser(sub)
    return parser


def _setup_logging(args):
    """Log lines on stderr through the progress bars' writer, UTC timestamps with ``-v``,
    Python warnings routed to logging (:func:`stereodem.progress.setup_logging`)."""
    from .progress import setup_logging

    setup_logging(verbose=args.verbose, quiet=args.quiet)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    named = _named_command(argv)
    parser = build_parser(named, listing=named is None)
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help(sys.stderr)
        return 2
    _setup_logging(args)
    quiet_resource_tracker()  # before any pool starts the tracker

    def on_signal(signum, frame):  # SIGTERM stops like Ctrl-C (pool stopped, lock released)
        interrupt.request(signum)  # and stays requested: stereodem.core.interrupt
        raise KeyboardInterrupt

    previous = _install(signal.SIGTERM, on_signal)
    previous_int = (
        _install(signal.SIGINT, on_signal)
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler
        else None
    )
    try:
        if hasattr(args, "workers"):  # one thread budget for the command (stereodem.core.threads)
            from stereodem.core.threads import thread_budget

            from .options import check_workers

            check_workers(args)  # --workers 0 refused before any work, in every command
            # the tile pool's fork server first: its imports then run on another core while
            # the budget's (OpenCV, rasterio) and the command's modules load here
            with _fork_server(args), thread_budget(args.workers):
                _check_creation_options(args)
                return int(args.run(args) or 0)
        _check_creation_options(args)
        return int(args.run(args) or 0)
    except StereodemError as exc:
        print(f"stereodem {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        sig = interrupt.requested() or signal.SIGINT
        name = signal.Signals(sig).name
        print(
            f"stereodem {args.command}: interrupted ({name}); {_resume_hint(args)}", file=sys.stderr
        )
        return 128 + sig
    except MemoryError:
        print(
            f"stereodem {args.command}: error: out of memory (try fewer --workers or a smaller "
            "--tile-size)",
            file=sys.stderr,
        )
        return 1
    finally:
        _install(signal.SIGTERM, previous)
        if previous_int is not None:
            _install(signal.SIGINT, previous_int)
        interrupt.clear()


def _check_creation_options(args):
    """A command's ``--co`` GDAL creation options, checked before it does any work
    (:func:`stereodem.core.raster.check_creation_options`: GDAL would ignore an option it
    does not know, or a value it does not accept, and write the products without it)."""
    if getattr(args, "co", None):
        from stereodem.core.raster import check_creation_options

        check_creation_options(
            args.co, source="--co", float_products=getattr(args, "co_float_products", False)
        )


def _fork_server(args):
    """The job's tile-pool fork server (:func:`stereodem.stereo.fork_server.fork_server_for_job`)
    for a command that declares its pool (``pool_request(args) -> (workers, dask)`` among the
    parser's defaults: ``run``, ``dem``), started before anything heavy is imported: started
    after the thread budget, it waited ~1 s for OpenCV, threadpoolctl and rasterio to load on
    one core, and its own imports then ran beside the job's first stages (load, sparse
    matching) instead of beside this process's imports."""
    request = getattr(args, "pool_request", None)
    if request is None:
        return contextlib.nullcontext()
    from stereodem.stereo.fork_server import fork_server_for_job

    return fork_server_for_job(*request(args))


def _install(signum, handler):
    """Set a signal handler where that is possible (the main thread); returns the old one."""
    try:
        return signal.signal(signum, handler)
    except (ValueError, TypeError):  # not the main thread, or no previous Python handler
        return None


def _one_line(exc) -> str:
    """An error message on one line (messages relayed from GDAL may carry newlines), in the
    command line's words ("pass --overwrite", not the library's "overwrite=True":
    :func:`stereodem.core.errors.error_message`)."""
    return one_line(exc, "command line")


def _resume_hint(args) -> str:
    """What the user can do after an interruption."""
    if args.command == "run":
        return (
            "finished tiles are kept in the output folder's tiles/; run the same command "
            "with --resume to continue"
        )
    if args.command == "demo":
        return "run it again with --overwrite"
    if args.command == "batch":
        # batch resumes in its folder; --overwrite would recompute the scenes already done
        return (
            "the scenes done are kept (batch.json lists them); run the same command again to "
            "continue: done scenes are skipped, the others reuse their finished tiles"
        )
    if args.command == "stack":
        # stack.json says interrupted, with the inputs: the same command replaces its files
        return "run the same command again: it replaces what the interrupted job left"
    return "no product was written; run the command again (--overwrite if the folder is not empty)"


def console_main() -> None:
    """The ``stereodem`` program: :func:`main`, then :func:`exit_now` with its exit code."""
    exit_now(main())


def exit_now(code: int) -> None:
    """End the process with ``code`` without tearing down each imported module.

    After a job, the interpreter's normal exit spends about 0.2 s finalising the thousands of
    modules that NumPy, SciPy, OpenCV, rasterio, pyproj and matplotlib bring in (measured on
    2 cores; the same at any ``--workers``, so a serial piece of every run). Here the exit
    handlers run first (:mod:`atexit`: multiprocessing's children, weakref finalizers such
    as temporary folders), then the log handlers and the standard streams are flushed, and
    the process ends (``os._exit``). Every product is already closed and renamed into place
    by then (:func:`stereodem.core.raster.atomic_path`). While a non-daemon thread other than
    this one still runs, the normal exit, which waits for it, is taken instead."""
    me = threading.current_thread()
    if any(t is not me and not t.daemon and t.is_alive() for t in threading.enumerate()):
        sys.exit(code)
    with warnings.catch_warnings():
        # a handler's DeprecationWarning (a library's internals: numcodecs 0.11's blosc at
        # exit) would be attributed to this module, shown under ``python -m stereodem.cli``;
        # the normal exit, with no Python frame calling the handlers, does not show it
        warnings.simplefilter("ignore", DeprecationWarning)
        atexit._run_exitfuncs()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more can be said
            pass
    os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    console_main()
