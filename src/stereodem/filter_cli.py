"""``stereodem filter DEM -o CLEAN``: blunder filters and hole filling of a stereo DEM.

Reads ``DEM`` (as written by ``stereodem dem``) and the ``score.tif`` / ``raygap.tif`` beside
it, runs the same filter chain and hole filling as ``stereodem run``, and writes ``CLEAN`` and
its edit mask ``<CLEAN stem>_edit_mask.tif`` (filter reason 1-9, 9 = cloud, 99 border rim, 100
filled by IDW, 101 filled from the seed DEM, 0 kept).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from stereodem.core.vertical import VERTICALS

from . import options
from .commands import help_line

EXAMPLES = """examples:
  stereodem filter out/dem.tif -o out/dem_clean.tif
  stereodem filter out/dem.tif -o clean.tif --thesis --max-hole-size 50
  stereodem filter out/dem.tif -o clean.tif --seed-dem srtm.tif --seed-vertical geoid \\
      --fill-from-seed
"""


def add_parser(sub):
    p = sub.add_parser(
        "filter",
        help=help_line("filter"),
        description=__doc__,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dem", help="stereo DEM GeoTIFF (score.tif and raygap.tif beside it are used)")
    p.add_argument("-o", "--out", required=True, help="clean DEM GeoTIFF to write")
    p.add_argument("--thesis", action="store_true", help="the Ok thesis's filter chain")
    p.add_argument(
        "--erode",
        type=int,
        default=2,
        help="cells removed along the border of the matched area (default 2)",
    )
    p.add_argument("--no-filters", action="store_true", help="skip the blunder filters")
    p.add_argument("--no-fill", action="store_true", help="leave holes unfilled")
    p.add_argument(
        "--max-hole-size",
        type=int,
        default=200,
        help="largest hole filled by interpolation, cells (default 200)",
    )
    p.add_argument("--seed-dem", help="DEM for --fill-from-seed")
    p.add_argument(
        "--seed-vertical",
        choices=VERTICALS,
        help="vertical reference of the seed DEM when the file does not say",
    )
    p.add_argument(
        "--fill-from-seed",
        action="store_true",
        help="fill holes larger than --max-hole-size from --seed-dem",
    )
    p.add_argument(
        "--dem-vertical",
        choices=VERTICALS,
        help="vertical reference of DEM when the file does not say",
    )
    p.add_argument(
        "--cloud-max-dev",
        type=float,
        metavar="M",
        help="cloud mask: remove cells deviating from --seed-dem by more than M metres "
        "(median difference removed), grown by --cloud-grow (edit code 9)",
    )
    p.add_argument(
        "--cloud-min-score",
        type=float,
        metavar="S",
        help="cloud mask: also cells whose matcher score is below S",
    )
    options.add_cloud_grow(p)
    options.add_workers(
        p, "threads of the filters' and the hole filling's row bands and the GeoTIFF compression"
    )
    options.add_creation_options(p)
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def _cloud_mask(args, layers, seed):
    """The cloud mask of the DEM (None when no --cloud-* option is given); refused without the
    seed DEM for --cloud-max-dev."""
    from stereodem.core.errors import InputError
    from stereodem.post.clouds import CloudSettings, cloud_mask

    # checked whether or not a mask is made (--cloud-grow -1 alone was taken without a word)
    settings = CloudSettings(
        max_deviation=args.cloud_max_dev, min_score=args.cloud_min_score, grow=args.cloud_grow
    )
    if args.cloud_max_dev is None and args.cloud_min_score is None:
        return None

    ref = None
    if args.cloud_max_dev is not None:
        if seed is None:
            raise InputError(
                "--cloud-max-dev needs --seed-dem (the reference the deviation is taken from)"
            )
        from stereodem.post import warp

        s = seed.to_reference(layers.vertical) if seed.vertical and layers.vertical else seed
        ref = warp.to_grid(
            s.heights, s.transform, s.crs, layers.transform, layers.crs, layers.shape
        )
    m, _ = cloud_mask(
        layers.heights,
        reference=ref,
        score=layers.score,
        settings=settings,
    )
    return m


def config_from_args(args):
    from .config import (
        Config,
        FillSettings,
        FilterSettings,
        InputSettings,
        RunSettings,
        validate,
    )

    cfg = Config(
        inputs=InputSettings(
            dem=args.dem,
            dem_vertical=args.dem_vertical,
            seed_dem=args.seed_dem,
            seed_dem_vertical=args.seed_vertical,
        ),
        output_dir=str(args.out),
        filters=FilterSettings(enabled=not args.no_filters, thesis=args.thesis, erode=args.erode),
        fill=FillSettings(
            enabled=not args.no_fill, max_hole_size=args.max_hole_size, fallback=args.fill_from_seed
        ),
        run=RunSettings(workers=args.workers),  # the budget (cli.main), as `dem` sets it
    )
    validate(cfg, "command line")
    return cfg


def run(args) -> int:
    import numpy as np

    from stereodem.core.dem import edit_mask_path
    from stereodem.core.errors import InputError
    from stereodem.core.raster import check_writable
    from stereodem.core.threads import job_threads
    from stereodem.post.coreg_run import carried_tags

    from .pipeline.inputs import load_seed_dem, read_stereo_dem
    from .pipeline.stages import post_stage

    options.check_common(args)
    options.geotiff_output(args.out, "clean DEM")
    if args.fill_from_seed and not args.seed_dem:
        raise InputError("--fill-from-seed needs --seed-dem")
    cfg = config_from_args(args)

    from .outlock import check_not_an_input

    folder = Path(args.dem).parent
    check_not_an_input(
        [args.out, edit_mask_path(args.out)],
        [args.dem, args.seed_dem, folder / "score.tif", folder / "raygap.tif"],
    )
    check_writable(args.out, args.overwrite)
    check_writable(edit_mask_path(args.out), args.overwrite)
    raw = read_stereo_dem(args.dem, vertical=args.dem_vertical)
    seed = load_seed_dem(cfg)
    cloud = _cloud_mask(args, raw, seed)
    if cloud is not None:
        raw.heights[cloud] = np.nan
    clean, report = post_stage(cfg, raw, seed, path=args.out)
    if cloud is not None:
        from stereodem.post.filters import Reason

        clean.edit_mask[cloud & ~np.isfinite(clean.heights)] = Reason.CLOUD
        report["cloud"] = {"removed": int(cloud.sum())}
    clean.write(
        args.out,
        overwrite=args.overwrite,
        creation_options=options.creation_options(args),
        tags=carried_tags(args.dem),  # the track and date that coregister and stack read
        threads=job_threads(cfg.run.workers),
    )
    valid = float((clean.heights == clean.heights).mean())
    options.say(
        f"stereodem filter: {args.out}: {100 * valid:.1f} % of cells valid; "
        f"edits: {json.dumps(_summary(report))}"
    )
    return 0


def _summary(report) -> dict:
    out = {}
    for step in report.get("filters", []):
        out[step["step"]] = step.get("removed", step.get("skipped"))
    if "erode" in report:
        out["border_rim"] = report["erode"]["removed"]
    if "fill" in report:
        out["filled"] = report["fill"].get("filled_idw")
        if report["fill"].get("filled_fallback"):  # --fill-from-seed
            out["filled_from_seed"] = report["fill"]["filled_fallback"]
    if "cloud" in report:
        out["cloud"] = report["cloud"]["removed"]
    return out
