"""``stereodem filter DEM -o CLEAN``: blunder filters and hole filling of a stereo DEM.

Reads ``DEM`` (as written by ``stereodem dem``) and the ``score.tif`` / ``raygap.tif`` beside
it, runs the same filter chain and hole filling as ``stereodem run``, and writes ``CLEAN`` and
its edit mask ``<CLEAN stem>_edit_mask.tif`` (filter reason 1-8, 99 border rim, 100 filled by
IDW, 101 filled from the seed DEM, 0 kept).
"""
from __future__ import annotations

import argparse
import json

from . import options

EXAMPLES = """examples:
  stereodem filter out/dem.tif -o out/dem_clean.tif
  stereodem filter out/dem.tif -o clean.tif --thesis --max-hole-size 50
  stereodem filter out/dem.tif -o clean.tif --seed-dem srtm.tif --dem-vertical geoid --fill-from-seed
"""


def add_parser(sub):
    p = sub.add_parser("filter", help="blunder filters and hole filling of a stereo DEM",
                       description=__doc__, epilog=EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dem", help="stereo DEM GeoTIFF (score.tif and raygap.tif beside it are used)")
    p.add_argument("-o", "--out", required=True, help="clean DEM GeoTIFF to write")
    p.add_argument("--thesis", action="store_true", help="the Ok thesis's filter chain")
    p.add_argument("--erode", type=int, default=2,
                   help="cells removed along the border of the matched area (default 2)")
    p.add_argument("--no-filters", action="store_true", help="skip the blunder filters")
    p.add_argument("--no-fill", action="store_true", help="leave holes unfilled")
    p.add_argument("--max-hole-size", type=int, default=200,
                   help="largest hole filled by interpolation, cells (default 200)")
    p.add_argument("--seed-dem", help="DEM for --fill-from-seed")
    p.add_argument("--seed-vertical", choices=options.VERTICALS,
                   help="vertical reference of the seed DEM when the file does not say")
    p.add_argument("--fill-from-seed", action="store_true",
                   help="fill holes larger than --max-hole-size from --seed-dem")
    p.add_argument("--dem-vertical", choices=options.VERTICALS,
                   help="vertical reference of DEM when the file does not say")
    options.add_creation_options(p)
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def config_from_args(args):
    from .config import Config, FillSettings, FilterSettings, InputSettings, validate
    cfg = Config(inputs=InputSettings(dem=args.dem, dem_vertical=args.dem_vertical,
                                      seed_dem=args.seed_dem, seed_dem_vertical=args.seed_vertical),
                 output_dir=str(args.out),
                 filters=FilterSettings(enabled=not args.no_filters, thesis=args.thesis,
                                        erode=args.erode),
                 fill=FillSettings(enabled=not args.no_fill, max_hole_size=args.max_hole_size,
                                   fallback=args.fill_from_seed))
    validate(cfg, "command line")
    return cfg


def run(args) -> int:
    from stereodem.sensor.errors import InputError
    from stereodem.sensor.io.raster import check_writable

    from .pipeline import (edit_mask_path, load_seed_dem, post_stage, read_stereo_layers,
                           write_clean_dem)
    if args.fill_from_seed and not args.seed_dem:
        raise InputError("--fill-from-seed needs --seed-dem")
    cfg = config_from_args(args)
    from pathlib import Path

    from .outlock import check_not_an_input
    folder = Path(args.dem).parent
    check_not_an_input([args.out, edit_mask_path(args.out)],
                       [args.dem, args.seed_dem, folder / "score.tif", folder / "raygap.tif"])
    check_writable(args.out, args.overwrite)
    check_writable(edit_mask_path(args.out), args.overwrite)
    layers = read_stereo_layers(args.dem, vertical=args.dem_vertical)
    z, mask, report = post_stage(cfg, layers, load_seed_dem(cfg))
    write_clean_dem(args.out, z, mask, layers, overwrite=args.overwrite,
                    creation_options=options.creation_options(args))
    valid = float((z == z).mean())
    options.say(f"stereodem filter: {args.out}: {100 * valid:.1f} % of cells valid; "
                f"edits: {json.dumps(_summary(report))}")
    return 0


def _summary(report) -> dict:
    out = {}
    for step in report.get("filters", []):
        out[step["step"]] = step.get("removed", step.get("skipped"))
    if "erode" in report:
        out["border_rim"] = report["erode"]["removed"]
    if "fill" in report:
        out["filled"] = report["fill"].get("filled_idw")
    return out
