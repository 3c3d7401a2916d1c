"""The ``stereodem`` command line: one sub-command per job.

Exit codes: 0 success, 1 the job failed (a one-line message says why), 2 bad usage.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

from stereodem.sensor.errors import StereodemError

from . import __version__

log = logging.getLogger("stereodem")

#: sub-commands implemented in their own modules: name -> module with add_parser/run
_SUBCOMMANDS = {
    "demo": "stereodem.demo_cli",
    "run": "stereodem.run_cli",
    "simulate": "stereodem.simulate_cli",
    "dem": "stereodem.dem_cli",
    "filter": "stereodem.filter_cli",
    "ortho": "stereodem.ortho_cli",
    "assess": "stereodem.assess_cli",
    "adjust": "stereodem.adjust_cli",
    "compare-models": "stereodem.compare_cli",
    "uncertainty": "stereodem.uncertainty_cli",
    "info": "stereodem.info_cli",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stereodem",
        description="Satellite stereo photogrammetry: stereo pairs in, DEMs and orthoimages out.",
        epilog="Run 'stereodem COMMAND --help' for the options and examples of each command.",
    )
    parser.add_argument("--version", action="version", version=f"stereodem {__version__}")
    verb = parser.add_mutually_exclusive_group()
    verb.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    verb.add_argument("-q", "--quiet", action="store_true", help="only errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for modname in _SUBCOMMANDS.values():
        importlib.import_module(modname).add_parser(sub)
    return parser


def _setup_logging(args):
    """Log lines on stderr through the progress bars' writer, UTC timestamps with ``-v``,
    Python warnings routed to logging (:func:`stereodem.progress.setup_logging`)."""
    from .progress import setup_logging
    setup_logging(verbose=args.verbose, quiet=args.quiet)


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help(sys.stderr)
        return 2
    _setup_logging(args)
    try:
        return int(args.run(args) or 0)
    except StereodemError as exc:
        print(f"stereodem {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"stereodem {args.command}: interrupted", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
