"""``stereodem assess``: DEM accuracy against a reference DEM and check points.

The lead wires :func:`add_parser` into the ``stereodem`` command; :func:`run` returns the exit
status (0 ok, 1 on a stereodem error, whose one-line message is logged).
"""
from __future__ import annotations

import argparse
import logging

from stereodem.sensor.errors import InputError, StereodemError

log = logging.getLogger(__name__)


def _floats(text):
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


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
        "assess", help="accuracy of a DEM against a reference DEM and check points",
        description="Warp DEM onto the reference grid, difference it (DEM - reference) and "
                    "report statistics overall, per slope class, land cover and elevation band, "
                    "optionally before and after Nuth & Kaab co-registration.",
        epilog="examples:\n"
               "  stereodem assess out/dem.tif --ref srtm.tif --ref-vertical geoid -o report\n"
               "  stereodem assess dem.tif --ref lidar.tif --checkpoints gps.csv --coregister -o report\n"
               "  stereodem assess dem.tif --ref ref.tif --landcover lc.tif --landcover-names 1=forest,2=urban -o r\n",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dem", help="DEM GeoTIFF to assess")
    p.add_argument("--ref", required=True, help="reference DEM GeoTIFF (any CRS/resolution)")
    p.add_argument("--checkpoints", help="CSV of check points: lon,lat,height or x,y,z")
    p.add_argument("--checkpoints-crs", help="CRS of x,y check points (e.g. EPSG:32636)")
    p.add_argument("--checkpoints-vertical", choices=("geoid", "ellipsoid"),
                   help="vertical reference of the check-point heights (default: the DEM's)")
    p.add_argument("--landcover", help="land-cover raster of integer classes")
    p.add_argument("--landcover-names", type=_names, help="class names, e.g. 1=water,2=urban")
    p.add_argument("--slope-bins", type=_floats, help="slope class edges in degrees "
                   "(default 0,5,10,20,30,45,90)")
    p.add_argument("--elevation-bins", type=_floats, help="elevation band edges in metres")
    p.add_argument("--coregister", action="store_true", help="Nuth & Kaab co-registration; "
                   "report before and after")
    p.add_argument("--dem-vertical", choices=("geoid", "ellipsoid"),
                   help="vertical reference of DEM (overrides the file)")
    p.add_argument("--ref-vertical", choices=("geoid", "ellipsoid"),
                   help="vertical reference of the reference (overrides the file)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty folder")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    """Run ``stereodem assess`` from parsed arguments; returns the exit status."""
    from stereodem.post.assess import assess_dem
    from stereodem.post.report import prepare_output_dir, write_report
    from stereodem.post.stats import DEFAULT_SLOPE_BINS
    from stereodem.sensor.geo.dem import DEM

    try:
        prepare_output_dir(args.output, overwrite=args.overwrite)
        dem = DEM.from_file(args.dem, vertical=args.dem_vertical)
        ref = DEM.from_file(args.ref, vertical=args.ref_vertical)
        slope_bins = args.slope_bins or DEFAULT_SLOPE_BINS
        if len(slope_bins) < 2:
            raise InputError("--slope-bins needs at least two edges")
        result = assess_dem(dem, ref, coregister=args.coregister, landcover=args.landcover,
                            landcover_names=args.landcover_names, slope_bins=slope_bins,
                            elevation_bins=args.elevation_bins, checkpoints=args.checkpoints,
                            checkpoint_crs=args.checkpoints_crs,
                            checkpoint_vertical=args.checkpoints_vertical)
        files = write_report(result, args.output, dem_heights=dem.heights,
                             dem_transform=dem.transform, dem_crs=dem.crs, overwrite=True)
    except StereodemError as exc:
        log.error("%s", exc)
        return 1
    s = result.report["stats"]
    print(f"n={s['n']} mean={s['mean']:.3f} rmse={s['rmse']:.3f} nmad={s['nmad']:.3f} "
          f"le90={s['le90']:.3f} m -> {files['json']}")
    co = result.report.get("coregistration")
    if co:
        print(f"co-registration: dx={co['dx']:.3f} m dy={co['dy']:.3f} m dz={co['dz']:.3f} m")
    return 0
