"""``stereodem run CONFIG.toml``: the whole job from a configuration file."""

from __future__ import annotations

import argparse
import sys

from . import options
from .commands import help_line
from .progress import stage_bar

EXAMPLES = """examples:
  stereodem run job.toml
  stereodem run job.toml --workers 2 --overwrite
  stereodem run job.toml --resume                 # skip what is already done
  stereodem run job.toml --dask tcp://scheduler:8786

The configuration keys and their defaults are listed in docs/configuration.md; 'stereodem demo'
writes one. Many scenes: one configuration per scene, one 'stereodem run' per job (e.g. a Slurm
job array indexing a list of configuration files); each run is independent and writes its own
folder.
"""


def add_parser(sub):
    p = sub.add_parser(
        "run",
        help=help_line("run"),
        description="Sensor models -> stereo DEM -> blunder filters and hole filling -> "
        "orthoimages -> accuracy report, into one output folder with run.json.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", help="TOML configuration")
    add_run_options(p)
    # the tile pool's fork server starts before the job's modules load (cli._fork_server)
    p.set_defaults(run=run, pool_request=_pool_request, co_float_products=True)
    return p


def add_run_options(p):
    p.add_argument("--workers", type=int, help="worker processes for tiles (default: all cores)")
    p.add_argument(
        "--tile-timeout", type=float, help="seconds before a tile is abandoned and logged"
    )
    p.add_argument("--dask", metavar="ADDRESS", help="dask.distributed scheduler (tcp://host:port)")
    p.add_argument("--resume", action="store_true", help="reuse an existing output folder")
    options.add_overwrite(p)
    p.add_argument(
        "--force",
        action="store_true",
        help="go on with a result the sanity checks call suspect (still reported)",
    )
    p.add_argument(
        "--clean-tiles",
        action="store_true",
        help="remove the tile cache OUT/tiles once the job has succeeded (it is kept for "
        "--resume otherwise; [run] keep_tiles)",
    )
    p.add_argument(
        "--co",
        action="append",
        metavar="KEY=VALUE",
        default=[],
        help="GDAL creation option of the GeoTIFF products, repeatable (overrides [run] "
        "creation_options)",
    )


def progress_factory(args):
    """The job's ``progress_factory(stage)``: :func:`stereodem.progress.stage_bar`, silent
    with -q."""
    quiet = getattr(args, "quiet", False)

    def make(stage):
        return stage_bar(stage, enabled=not quiet)

    return make


def summarize(info, stream=None):
    """The job's result lines (what was written, the headline figures, warnings) on ``stream``
    (standard output), unless -q (:func:`stereodem.options.quiet`)."""
    if options.quiet():
        return
    stream = stream or sys.stdout
    out = info["config"]["output"]["dir"]
    print(f"DEM:        {out}/dem.tif  (raw layers in {out}/raw/)", file=stream)
    for name in sorted(o for o in info.get("outputs", []) if o.startswith("ortho_")):
        print(f"orthoimage: {out}/{name}", file=stream)  # the left, and the right if asked
    if info.get("headline"):
        h = info["headline"]
        print(f"report:     {out}/assess/report.md", file=stream)
        print(
            f"accuracy vs reference: NMAD {h['nmad']:.2f} m, median {h['median']:+.2f} m, "
            f"RMSE {h['rmse']:.2f} m, LE90 {h['le90']:.2f} m, {h['valid_pct']:.1f} % valid",
            file=stream,
        )
    for w in info.get("warnings", []):
        print(f"warning: {w['message']}", file=stream)
    if info["failed_tiles"]:
        print(f"warning: {len(info['failed_tiles'])} tile(s) failed; see run.json", file=stream)
    print(f"total {info['seconds']:.1f} s; details in {out}/run.json", file=stream)


def _pool_request(args):
    """``(workers, dask)`` of the job, read before its modules load so that the tile pool's
    fork server starts meanwhile (:func:`stereodem.cli._fork_server`):
    the command line's, else the TOML's ``[run]`` values (workers absent: all cores). A file
    that cannot be read, or values of another type, give ``(1, None)``: no early start, and
    :func:`stereodem.config.load_config` then reports the problem."""
    import tomllib

    try:
        with open(args.config, "rb") as f:
            table = tomllib.load(f).get("run", {})
    except (OSError, ValueError):  # TOMLDecodeError and UnicodeDecodeError are ValueErrors
        return 1, None
    if not isinstance(table, dict):
        return 1, None
    workers = args.workers if args.workers is not None else table.get("workers")
    dask = args.dask if args.dask is not None else table.get("dask")
    if not isinstance(workers, int | None):
        return 1, None
    return workers, dask if isinstance(dask, str) else None


def run(args) -> int:
    """Run ``stereodem run``; the CLI starts the tile pool's fork server before this
    (``pool_request``: :func:`_pool_request`, :func:`stereodem.cli._fork_server`)."""
    from stereodem.core.raster import parse_creation_options

    from .config import load_config
    from .pipeline.job import run as run_pipeline

    cfg = load_config(
        args.config,
        workers=args.workers,
        tile_timeout=args.tile_timeout,
        dask=args.dask,
        resume=args.resume or None,
        overwrite=args.overwrite or None,
        force=args.force or None,
        creation_options=parse_creation_options(args.co) or None,
        keep_tiles=False if args.clean_tiles else None,
    )
    info = run_pipeline(cfg, progress_factory=progress_factory(args))
    summarize(info)
    return 0
