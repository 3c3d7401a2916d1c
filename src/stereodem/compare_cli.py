"""``stereodem compare-models``: fit many sensor models to the same GCPs and compare them at
the same independent check points (:mod:`stereodem.sensor.estimation.compare`)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from . import options
from .commands import help_line
from .outlock import Products

#: what ``stereodem compare-models`` writes into its output folder
PRODUCTS = Products(
    ("compare.json", "compare.md", "compare.png", "splits.json", "splits.md"),
    markers=("compare.json",),
)

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  stereodem compare-models left.tif --gcps points.csv --models all -o cmp
  stereodem compare-models AST_L1A_....hdf --band 3B --gcps points_3b.csv -o cmp_3b
"""


def add_parser(subparsers):
    p = subparsers.add_parser(
        "compare-models",
        help=help_line("compare-models"),
        description="Fit every model with the same GCP/ICP split and GCP counts from small to "
        "large; write compare.json, compare.md and compare.png to DIR.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "image",
        help="image GeoTIFF (with RPCs or a <stem>.model.json sidecar), or an ASTER L1A "
        "granule (choose the band with --band 3N|3B; the GCPs' col,row in that band)",
    )
    options.add_band(p, "1; 3N in an ASTER granule", radiometric=False)
    p.add_argument("--gcps", required=True, help="CSV id,lon,lat,h,col,row[,role,...]")
    p.add_argument(
        "--models",
        default="all",
        help="comma-separated model names or 'all' (generic, physical sets, orbital)",
    )
    p.add_argument(
        "--counts",
        default="6,10,15,20,30,40",
        help="GCP counts (default 6,10,15,20,30,40; those above the pool are dropped)",
    )
    p.add_argument(
        "--n-check",
        type=int,
        default=20,
        help="check points drawn when the CSV has no 'check' roles (default 20)",
    )
    p.add_argument(
        "--sigma-px", type=options.standard_deviation, default=None, help="a-priori image sigma, px"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the split")
    p.add_argument(
        "--splits",
        type=int,
        default=0,
        help="also repeat the comparison over this many random GCP/ICP splits (the "
        "CSV's roles ignored, --n-check check points each) and write "
        "splits.json / splits.md: per model and count the median and largest "
        "ratio of ICP RMSE to the --reference model's (default 0: off)",
    )
    p.add_argument(
        "--reference",
        default="attitude-bias-drift",
        help="model the split ratios are taken against (default attitude-bias-drift, "
        "the rigorous pushbroom model's attitude biases and drifts)",
    )
    p.add_argument("-o", "--output", required=True, help="output folder")
    options.add_workers(p, "threads of the least-squares fits (BLAS)")
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from stereodem.core.errors import InputError
    from stereodem.sensor.estimation.compare import (
        compare,
        compare_splits,
        expand_models,
        split_summary,
    )
    from stereodem.sensor.io.gcps import read_gcps
    from stereodem.sensor.io.sidecar import sidecar_path

    from .outlock import check_output_folder, output_folder
    from .pipeline.inputs import image_model, image_name

    try:
        counts = [int(v) for v in args.counts.split(",") if v.strip()]
    except ValueError:
        raise InputError(
            f"--counts: expected comma-separated integers, got {args.counts!r}"
        ) from None
    if args.splits < 0:
        raise InputError(f"--splits: expected a count >= 0, got {args.splits}")
    inputs = [args.image, sidecar_path(args.image), args.gcps]
    check_output_folder(args.output, PRODUCTS, overwrite=args.overwrite, inputs=inputs)
    # the image's model (a GeoTIFF's sidecar or RPCs, the image itself checked readable; an
    # ASTER granule's --band), as adjust and uncertainty take it
    base = image_model(args.image, band=args.band)
    points = read_gcps(args.gcps)
    models = expand_models([m.strip() for m in args.models.split(",") if m.strip()], base)
    expand_models([args.reference], base)  # an unknown --reference refused, splits or not
    # the same fits, the same check points' rule and weights in both comparisons
    common = dict(n_check=args.n_check, seed=args.seed, sigma_px=args.sigma_px)
    with options.progress_bar("compare") as bar:
        names = (str(args.gcps), image_name(args.image, args.band))
        records = compare(base, points, models, counts, names=names, progress=bar, **common)
    splits = None
    if args.splits:
        with options.progress_bar("splits") as bar:
            recs = compare_splits(
                base,
                points,
                models,
                counts,
                reference=args.reference,
                n_splits=args.splits,
                progress=bar,
                **common,
            )
        splits = {
            "reference": args.reference,
            "splits": args.splits,
            "summary": split_summary(recs),
            "records": recs,
        }
    with output_folder(args.output, PRODUCTS, overwrite=args.overwrite, inputs=inputs) as out:
        name = image_name(args.image, args.band, name=Path(args.image).name)
        _write(out, records, splits, image=name)
    ok = [r for r in records if not r.get("error")]
    options.say(
        f"{len(models)} model(s), {len(records)} fit(s), {len(records) - len(ok)} refused -> {out}"
    )
    return 0


def _write(out, records, splits, *, image=None):
    """The products, into the locked output folder ``out`` (a previous run's removed)."""
    from stereodem.core import jsonutil
    from stereodem.core.raster import write_text_atomic
    from stereodem.sensor.estimation.compare import figure, markdown, split_markdown

    write_text_atomic(
        out / "compare.json", jsonutil.dumps([jsonutil.stamped(r) for r in records]), overwrite=True
    )
    write_text_atomic(out / "compare.md", markdown(records), overwrite=True)
    figure(records, out / "compare.png", overwrite=True, image=image)
    if splits is not None:
        write_text_atomic(out / "splits.json", jsonutil.dumps(splits), overwrite=True)
        write_text_atomic(
            out / "splits.md",
            split_markdown(splits["summary"], splits["reference"]),
            overwrite=True,
        )
