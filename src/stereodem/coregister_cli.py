"""``stereodem coregister``: co-register a DEM to a reference DEM or altimetry points with a
chain of corrections (:mod:`stereodem.post.coreg`), on stable terrain."""

from __future__ import annotations

import argparse

from stereodem.core.vertical import VERTICALS

from . import options
from .commands import help_line
from .outlock import Products

EXAMPLES = """examples:
  stereodem coregister aster_dem.tif --ref srtm.tif -o coreg
  stereodem coregister dem.tif --ref ref.tif --chain nuth_kaab,deramp:2,along_track \\
      --track-angle 192 --exclude glaciers.gpkg -o coreg
  stereodem coregister dem.tif --ref atl06.csv --ref-vertical ellipsoid --chain nuth_kaab,vshift \\
      -o coreg

steps (--chain, comma separated, applied in order; ':N' = order or number of sines):
  nuth_kaab (horizontal + vertical shift), vshift, deramp[:1-3], along_track[:N sines],
  cross_track[:1-3], curvature[:1-3], icp
"""


def add_parser(sub):
    p = sub.add_parser(
        "coregister",
        help=help_line("coregister"),
        description="Fit a chain of corrections (shift, ramp, along/cross-track "
        "biases, curvature) of DEM against REF on stable terrain and "
        "write the corrected DEM, a JSON report (parameters with "
        "standard deviations, statistics before/after each step) and "
        "figures.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dem", help="DEM GeoTIFF to correct")
    p.add_argument(
        "--ref",
        required=True,
        help="reference DEM GeoTIFF (any grid/CRS), or altimetry "
        "points: CSV/GeoParquet with lon, lat, h[, time]",
    )
    p.add_argument(
        "--chain", default="nuth_kaab", help="steps, comma separated (default nuth_kaab)"
    )
    options.add_track_angle(
        p,
        "ground-track heading, degrees clockwise from north, for a straight "
        "track (default: the DEM's own track: its STEREODEM_TRACK_FRAME tag from "
        "the sensor model, else its STEREODEM_TRACK_HEADING tag)",
    )
    p.add_argument(
        "--exclude",
        action="append",
        default=[],
        metavar="VECTOR",
        help="polygons left out of the stable terrain (any CRS; repeatable)",
    )
    p.add_argument(
        "--include",
        action="append",
        default=[],
        metavar="VECTOR",
        help="polygons that are the only stable terrain (repeatable)",
    )
    p.add_argument("--stable-mask", metavar="RASTER", help="raster, non-zero = stable terrain")
    p.add_argument("--min-slope", type=float, help="stable terrain: least slope (deg)")
    p.add_argument("--max-slope", type=float, help="stable terrain: largest slope (deg)")
    p.add_argument(
        "--outlier-nmad",
        type=float,
        default=5.0,
        help="cells with |dh - median| beyond this many NMADs leave the stable terrain "
        "(default 5; 0: off)",
    )
    p.add_argument(
        "--dem-vertical",
        choices=VERTICALS,
        help="vertical reference of DEM when the file does not say",
    )
    p.add_argument(
        "--ref-vertical",
        choices=VERTICALS,
        help="vertical reference of REF when the file does not say (a DEM's CRS or tag, a "
        "points file's h_ellipsoid/h_geoid column; a file that says wins, with a warning); "
        "required for points whose column does not say",
    )
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("-o", "--output", required=True, help="output folder")
    options.add_workers(p, "threads of the warps, the slopes and the GeoTIFF compression")
    options.add_creation_options(p)
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


#: what ``stereodem coregister`` writes into its output folder (:mod:`stereodem.post.coreg_run`)
PRODUCTS = Products(
    ("dem_coregistered.tif", "coregistration.json", "coreg_*.png"), markers=("coregistration.json",)
)


def run(args) -> int:
    from stereodem.post.coreg import step_line
    from stereodem.post.coreg_run import CoregJob
    from stereodem.post.coreg_run import run as run_job

    from .options import check_common, creation_options, say
    from .outlock import check_output_folder, output_folder

    check_common(args)
    products = PRODUCTS
    inputs = [args.dem, args.ref, *args.exclude, *args.include, args.stable_mask]
    check_output_folder(args.output, products, overwrite=args.overwrite, inputs=inputs)
    job = CoregJob(
        dem=args.dem,
        ref=args.ref,
        chain=args.chain,
        dem_vertical=args.dem_vertical,
        ref_vertical=args.ref_vertical,
        track_angle=args.track_angle,
        exclude=args.exclude,
        include=args.include,
        stable_mask=args.stable_mask,
        min_slope=args.min_slope,
        max_slope=args.max_slope,
        outlier_nmad=args.outlier_nmad or None,
    )
    job.check()  # limits that cannot be honoured fail before any reading
    with output_folder(args.output, products, overwrite=args.overwrite, inputs=inputs) as out:
        rep = run_job(
            job,
            out,
            overwrite=True,
            figures=not args.no_figures,
            creation_options=creation_options(args),
        )
    for r in rep["steps"]:
        say(step_line(r))
    say(f"-> {rep['files']['dem']}")
    return 0
