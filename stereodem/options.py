"""Command-line options shared by several commands, with one meaning everywhere.

``--res`` is the output posting in the output CRS's units in every command (metres for the
default UTM grids); ``--workers``, ``--overwrite`` and the DEM vertical-reference options are
spelled and checked once here.
"""
from __future__ import annotations

import logging

from stereodem.sensor.errors import InputError

from .progress import Progress

VERTICALS = ("geoid", "ellipsoid")


def add_res(p, default_text: str):
    p.add_argument("--res", type=float, metavar="RES",
                   help=f"output posting in the output CRS's units, metres for UTM (default: {default_text})")
    p.add_argument("--crs", help="output CRS, e.g. EPSG:32637 (default: the scene's UTM zone)")


def add_workers(p, what="worker processes for the stereo tiles"):
    p.add_argument("--workers", type=int, help=f"{what} (default: all cores)")


def add_overwrite(p):
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing outputs (default: refuse to touch them)")


def check_common(args):
    """Range checks of the shared options, before any work starts."""
    res = getattr(args, "res", None)
    if res is not None and not res > 0:
        raise InputError(f"--res must be positive, got {res:g}")
    workers = getattr(args, "workers", None)
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")


def progress_bar(label: str):
    """A progress callable for a stage, silent with -q."""
    return Progress(label, 1, enabled=logging.getLogger().getEffectiveLevel() <= logging.WARNING)


def say(message: str):
    """A result line for the user on standard output (what was written, headline figures),
    unless -q; logs and progress go to standard error."""
    if logging.getLogger().getEffectiveLevel() <= logging.WARNING:
        print(message)
