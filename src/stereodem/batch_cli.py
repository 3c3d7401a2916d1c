"""``stereodem batch SCENES... -o OUTDIR``: one job per scene, on a process pool or Dask."""

from __future__ import annotations

import argparse

from . import options
from .commands import help_line

EXAMPLES = """examples:
  stereodem batch a.toml b.toml c.toml -o out                    # configurations
  stereodem batch AST_L1A_*.hdf -o out --template job.toml        # granules, one template
  stereodem batch scenes.txt -o out --workers 4                   # a list file, 4 scenes at once
  stereodem batch scenes.txt -o out --dask local                  # a dask LocalCluster
  stereodem batch scenes.txt -o out --dask tcp://scheduler:8786   # a running cluster
  stereodem batch scenes.txt -o out                               # again: done scenes are skipped

Each scene writes OUTDIR/<name>/ (its file's stem) as 'stereodem run' does; OUTDIR/batch.json
lists every scene in OUTDIR as done, failed (with its one-line reason) or skipped: a batch run
again in OUTDIR adds its scenes' rows to those of the batches before (a scene run again gets
its new row). A scene already done is skipped (one whose configuration changed since fails
until --overwrite); a failed or interrupted one runs again, reusing its finished tiles
(--overwrite: recompute the scenes given). OUTDIR must be new, empty or a batch's (its
batch.json); a folder holding other files needs --overwrite, and the batch then writes
beside them (never over a batch.json of the user's). A Slurm/PBS cluster through
dask-jobqueue: docs/batch.md.
Exit status 1 when a scene of this run failed (the others are done).
"""


def add_parser(sub):
    p = sub.add_parser(
        "batch",
        help=help_line("batch"),
        description=__doc__,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "scenes",
        nargs="+",
        metavar="SCENE",
        help="TOML configurations, ASTER L1A granules, or list files (.txt/.lst) of them",
    )
    p.add_argument("-o", "--out", required=True, help="output folder (one sub-folder per scene)")
    p.add_argument(
        "--template",
        metavar="TOML",
        help="configuration for granules (its [inputs] left/right and [output] are replaced)",
    )
    p.add_argument(
        "--workers",
        type=int,
        help="scenes at once: pool processes or LocalCluster workers (default: all cores)",
    )
    p.add_argument(
        "--dask",
        metavar="ADDRESS",
        help="'local' for a dask LocalCluster, or a scheduler address tcp://host:port",
    )
    p.add_argument(
        "--clean-tiles",
        action="store_true",
        help="remove each scene's tile cache once it is done (a failed scene keeps its tiles "
        "for the next run)",
    )
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from .batch import expand_inputs, run_batch, status_text, summary_lines

    options.check_common(args)

    def progress(row):
        options.say(f"  {row.name}: {status_text(row.status, row.reason, row.seconds)}")

    result = run_batch(
        expand_inputs(args.scenes, args.template),
        args.out,
        workers=args.workers,
        dask=args.dask,
        overwrite=args.overwrite,
        keep_tiles=False if args.clean_tiles else None,
        progress=progress,
    )
    for line in summary_lines(result):
        options.say(line)
    return 1 if result["this_run"]["failed"] else 0
