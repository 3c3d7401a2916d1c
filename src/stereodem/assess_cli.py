"""``stereodem assess``: DEM accuracy against a reference DEM and check points
(:func:`stereodem.pipeline.assessment.assess_stage`, the same stage as ``stereodem run``)."""

from __future__ import annotations

import argparse
import logging

from stereodem.core.errors import InputError
from stereodem.core.vertical import VERTICALS

from . import options
from .commands import help_line
from .outlock import Products

#: what ``stereodem assess`` writes into its output folder (:func:`stereodem.post.report.
#: write_report`: the reports, its figures, :data:`stereodem.post.report.FIGURES`, and those of
#: the error analysis)
PRODUCTS = Products(
    (
        "report.json",
        "report.md",
        "report.html",
        "hillshade.png",
        "difference_map.png",
        "histogram.png",
        "error_vs_slope.png",
        "error_vs_terrain.png",
        "variogram.png",
    ),
    markers=("report.json",),
)

log = logging.getLogger(__name__)


def _floats(text):
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None


def _names(text):
    out = {}
    for item in text.split(","):
        if not item.strip():
            continue
        k, sep, v = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"expected VALUE=NAME pairs, got {item!r}")
        out[int(k)] = v.strip()
    return out


def add_parser(subparsers):
    """Add the ``assess`` sub-command to an ``argparse`` sub-parsers object."""
    p = subparsers.add_parser(
        "assess",
        help=help_line("assess"),
        description="Warp DEM onto the reference grid, difference it (DEM - reference) and "
        "report statistics overall, per slope class, land cover and elevation band, "
        "optionally before and after Nuth & Kaab co-registration.",
        epilog="examples:\n"
        "  stereodem assess out/dem.tif --ref srtm.tif --ref-vertical geoid -o report\n"
        "  stereodem assess dem.tif --ref lidar.tif --checkpoints gps.csv --coregister -o report\n"
        "  stereodem assess dem.tif --ref ref.tif --landcover lc.tif --landcover-names "
        "1=forest,2=urban -o r\n",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dem", help="DEM GeoTIFF to assess")
    p.add_argument("--ref", required=True, help="reference DEM GeoTIFF (any CRS/resolution)")
    p.add_argument(
        "--checkpoints",
        help="CSV of check points: lon,lat,height or x,y,z (with a role column, as in "
        "adjust's GCP CSV: the role=check rows only)",
    )
    p.add_argument("--checkpoints-crs", help="CRS of x,y check points (e.g. EPSG:32636)")
    p.add_argument(
        "--checkpoints-vertical",
        choices=VERTICALS,
        help="vertical reference of the check-point heights (default: the DEM's)",
    )
    p.add_argument("--landcover", help="land-cover raster of integer classes")
    p.add_argument("--landcover-names", type=_names, help="class names, e.g. 1=water,2=urban")
    p.add_argument(
        "--slope-bins",
        type=_floats,
        help="slope class edges in degrees (default 0,5,10,20,30,45,90)",
    )
    p.add_argument("--elevation-bins", type=_floats, help="elevation band edges in metres")
    p.add_argument(
        "--coregister",
        action="store_true",
        help="co-register the DEM (Nuth & Kaab, or the --chain) and report each step and "
        "the statistics before and after the whole chain",
    )
    p.add_argument(
        "--dem-vertical",
        choices=VERTICALS,
        help="vertical reference of DEM when the file does not say",
    )
    p.add_argument(
        "--ref-vertical",
        choices=VERTICALS,
        help="vertical reference of the reference when the file does not say",
    )
    ea = p.add_argument_group("error analysis on stable terrain (Hugonnet et al. 2022)")
    ea.add_argument(
        "--error-analysis",
        action="store_true",
        help="dispersion vs slope/curvature, variogram of the standardised dh, "
        "sigma of area means (figures and a report section)",
    )
    ea.add_argument(
        "--outlines",
        action="append",
        default=[],
        metavar="VECTOR",
        help="polygons whose mean dh gets a sigma from the variogram (repeatable)",
    )
    ea.add_argument(
        "--exclude",
        action="append",
        default=[],
        metavar="VECTOR",
        help="polygons left out of the stable terrain, where the co-registration is fitted "
        "and the error analysis measured (repeatable; e.g. glaciers)",
    )
    ea.add_argument(
        "--sigma-map",
        metavar="RASTER",
        help="per-cell sigma (m) of the sensor models: the share it explains is reported",
    )
    ea.add_argument(
        "--chain",
        help="co-registration chain, e.g. nuth_kaab,deramp:1 (see stereodem coregister); "
        "implies --coregister: fitted once on the stable terrain, reported step by step "
        "(parameters with units), the before/after tables and the analysis of the DEM after "
        "the whole chain",
    )
    options.add_track_angle(
        ea,
        "ground-track heading for --chain (default: the DEM's own track tags)",
    )
    p.add_argument("-o", "--output", required=True, help="output folder")
    options.add_workers(p, "threads of the comparison's row blocks and of GDAL's reads")
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def config_from_args(args):
    from .config import AssessSettings, Config, InputSettings, RunSettings, validate

    cfg = Config(
        inputs=InputSettings(
            dem=args.dem,
            dem_vertical=args.dem_vertical,
            reference_dem=args.ref,
            reference_vertical=args.ref_vertical,
            checkpoints=args.checkpoints,
            checkpoints_crs=args.checkpoints_crs,
            checkpoints_vertical=args.checkpoints_vertical,
            landcover=args.landcover,
        ),
        output_dir=str(args.output),
        assess=AssessSettings(
            coregister=args.coregister,
            slope_bins=tuple(args.slope_bins) if args.slope_bins else None,
            elevation_bins=tuple(args.elevation_bins) if args.elevation_bins else None,
            landcover_names=args.landcover_names,
        ),
        run=RunSettings(workers=args.workers),  # the budget (cli.main), as `dem` sets it
    )
    validate(cfg, "command line")
    return cfg


def run(args) -> int:
    """Run ``stereodem assess`` from parsed arguments; returns the exit status."""
    from .outlock import check_output_folder, output_folder
    from .pipeline.assessment import assess_stage

    options.check_common(args)
    cfg = config_from_args(args)
    products = PRODUCTS
    inputs = [
        args.dem,
        args.ref,
        args.checkpoints,
        args.landcover,
        args.sigma_map,
        *(args.exclude or []),
        *(args.outlines or []),
    ]
    check_output_folder(args.output, products, overwrite=args.overwrite, inputs=inputs)
    if args.checkpoints:  # a bad file fails before the assessment runs
        from stereodem.post.assess import check_checkpoints

        check_checkpoints(args.checkpoints, crs=args.checkpoints_crs)
    job = None
    analysis = bool(args.error_analysis or args.outlines or args.sigma_map or args.chain)
    if args.exclude and not (analysis or args.coregister):
        raise InputError(
            "--exclude leaves polygons out of the stable terrain, which only the "
            "co-registration (--coregister, --chain) and the error analysis use; add one"
        )
    if analysis or args.exclude:
        from stereodem.post.error_analysis import ErrorAnalysisJob

        if args.chain:  # a bad chain fails before any work
            from stereodem.post.coreg import parse_chain

            parse_chain(args.chain)
        job = ErrorAnalysisJob(
            chain=args.chain,
            track_angle=args.track_angle,
            exclude=args.exclude,
            outlines=args.outlines,
            sigma_map=args.sigma_map,
        )
    with output_folder(args.output, products, overwrite=args.overwrite, inputs=inputs) as out:
        result, files = assess_stage(
            cfg, args.dem, out, overwrite=True, error_analysis=job, analysis=analysis
        )
    s = result.report["stats"]
    options.say(
        f"n={s['n']} mean={s['mean']:.3f} rmse={s['rmse']:.3f} nmad={s['nmad']:.3f} "
        f"le90={s['le90']:.3f} m -> {files['json']}"
    )
    co = result.report.get("coregistration")
    if co:
        for line in coregistration_lines(co, result.report["after_coregistration"]["stats"]):
            options.say(line)
    return 0


def coregistration_lines(co: dict, after: dict) -> list[str]:
    """The result lines of the co-registration: the chain with the NMAD before/after the
    whole chain (stable samples; all compared cells), then each step's line
    (:func:`stereodem.post.coreg.step_line`, as ``coregister`` prints it)."""
    from stereodem.post.coreg import step_line

    steps = co.get("steps") or []
    lines = [
        f"co-registration {' + '.join(r['step'] for r in steps)}: stable NMAD "
        f"{co['nmad_before']:.3f} -> {co['nmad_after']:.3f} m; all cells after the chain: "
        f"NMAD {after['nmad']:.3f} m, median {after['median']:+.3f} m, n={after['n']}"
    ]
    return lines + [f"  {step_line(r)}" for r in steps]
