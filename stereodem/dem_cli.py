"""``stereodem dem``: a DEM from a stereo pair of GeoTIFFs with sensor models.

Writes ``DIR/dem.tif`` (float32, NaN nodata, ellipsoidal heights unless ``--geoid``) and the
companion layers ``score.tif`` (mean correlation), ``count.tif`` (points per cell) and
``raygap.tif`` (mean ray gap, m), plus ``dem_report.json`` (settings and per-tile QA).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  stereodem dem left.tif right.tif -o out --height-range 1400 3300
  stereodem dem img_01.tif img_02.tif -o dsm --res 0.5 --crs EPSG:32740 --height-range 2100 2600
  stereodem dem 3N.tif 3B.tif -o dem --seed-dem srtm.tif --matcher ncc --geoid --overwrite
  stereodem dem 3N.tif 3B.tif -o dem --height-range 0 2500 --workers 2 --tile-timeout 120
"""

OUTPUTS = ("dem.tif", "score.tif", "count.tif", "raygap.tif", "dem_report.json")


def add_parser(subparsers):
    """Register the ``dem`` sub-command on an ``argparse`` sub-parser set."""
    p = subparsers.add_parser(
        "dem", help="stereo DEM from two images with sensor models",
        description="Build a DEM from a stereo pair: per-tile epipolar resampling, dense "
                    "matching, space intersection with the exact sensor models, gridding. "
                    "LEFT/RIGHT are GeoTIFFs with RPC metadata (tags or .RPB sidecar) or a "
                    "physical-model sidecar <stem>.model.json.",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("left", help="left (reference) image GeoTIFF")
    p.add_argument("right", help="right image GeoTIFF")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument("--res", type=float, help="posting in CRS units (default: 2 x the left GSD)")
    p.add_argument("--crs", help="output CRS, e.g. EPSG:32637 (default: the scene's UTM zone)")
    rng = p.add_mutually_exclusive_group()
    rng.add_argument("--height-range", nargs=2, type=float, metavar=("MIN", "MAX"),
                     help="ellipsoidal height range of the terrain, metres")
    rng.add_argument("--seed-dem", help="coarse DEM giving each tile's height range")
    p.add_argument("--dem-vertical", choices=["geoid", "ellipsoid"],
                   help="vertical reference of the seed DEM when the file does not say")
    p.add_argument("--matcher", choices=["ncc", "sgm"], default="sgm", help="dense matcher (default sgm)")
    p.add_argument("--tile-size", type=int, default=512, help="tile side, pixels (default 512)")
    p.add_argument("--gridding", choices=["gaussian", "mean"], default="gaussian",
                   help="cell estimator (default gaussian)")
    p.add_argument("--no-pointing-correction", action="store_true",
                   help="do not estimate the relative pointing (right-image translation)")
    p.add_argument("--geoid", action="store_true", help="write EGM96 geoid heights")
    p.add_argument("--band", type=int, default=1, help="image band (default 1)")
    p.add_argument("--workers", type=int, help="worker processes for tiles (default: all cores)")
    p.add_argument("--tile-timeout", type=float, default=600.0,
                   help="seconds after which a tile is abandoned and reported (default 600)")
    p.add_argument("--dask", metavar="ADDRESS", help="dask.distributed scheduler (tcp://host:port)")
    p.add_argument("--overwrite", action="store_true", help="write into an existing non-empty folder")
    p.set_defaults(run=run)
    return p


def _load_model(path):
    from stereodem.sensor.errors import RPCError, SensorModelError
    try:
        from stereodem.sensor.io.sidecar import load_image_model
    except ImportError:                                   # pragma: no cover - partial builds
        load_image_model = None
    if load_image_model is not None:
        return load_image_model(path)
    from stereodem.sensor.models.rpc import RPCModel
    try:
        return RPCModel.from_file(path)
    except RPCError as exc:
        raise SensorModelError(f"{path}: no usable sensor model ({exc})") from None


def _read_image(path, band):
    import numpy as np
    import rasterio

    from stereodem.sensor.errors import InputError
    try:
        with rasterio.open(path) as ds:
            if not 1 <= band <= ds.count:
                raise InputError(f"{path}: no band {band} (the image has {ds.count})")
            arr = ds.read(band).astype(np.float32)
            if ds.nodata is not None and np.isfinite(ds.nodata):
                arr[arr == ds.nodata] = np.nan
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"{path}: cannot read the image ({exc})") from None
    return arr


def run(args) -> int:
    """Run ``stereodem dem``; returns the exit status (0 ok, 1 failure with a one-line message)."""
    from stereodem.sensor.errors import StereodemError
    try:
        return _run(args)
    except StereodemError as exc:
        print(f"stereodem dem: error: {exc}", file=sys.stderr)
        return 1


def _run(args) -> int:
    from stereodem.sensor.geo.dem import DEM
    from stereodem.sensor.errors import InputError, OutputExistsError
    from stereodem.sensor.io.raster import write_text_atomic
    from stereodem.stereo.pipeline import DEMSettings, make_dem

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise OutputExistsError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not args.overwrite:
        raise OutputExistsError(f"{out}: folder is not empty; pass --overwrite to write into it")
    if args.res is not None and not args.res > 0:
        raise InputError(f"--res must be positive, got {args.res}")
    if args.height_range is not None:
        lo, hi = args.height_range
        if not (lo == lo and hi == hi) or hi < lo:
            raise InputError(f"--height-range {lo:g} {hi:g} is unusable (need MIN <= MAX)")
    left_model, right_model = _load_model(args.left), _load_model(args.right)
    left, right = _read_image(args.left, args.band), _read_image(args.right, args.band)
    for path, img, mdl in ((args.left, left, left_model), (args.right, right, right_model)):
        if img.shape != (mdl.height, mdl.width):
            raise InputError(f"{path}: image is {img.shape[1]}x{img.shape[0]} but its model "
                             f"describes {mdl.width}x{mdl.height}")
    seed = DEM.from_file(args.seed_dem, vertical=args.dem_vertical) if args.seed_dem else None
    settings = DEMSettings(tile_size=args.tile_size, height_range=args.height_range, seed_dem=seed,
                           matcher=args.matcher, posting=args.res, crs=args.crs, geoid=args.geoid,
                           gridding=args.gridding, pointing_correction=not args.no_pointing_correction)
    quiet = logging.getLogger().getEffectiveLevel() > logging.WARNING

    tty = sys.stderr.isatty()

    def progress(done, total):
        # a live line on a terminal, one line per tile in logs and pipes
        if not quiet:
            print(f"{chr(13) if tty else ''}stereodem dem: tile {done}/{total}", end="" if tty else "\n",
                  file=sys.stderr, flush=True)

    from .config import RunSettings
    from .pipeline import tile_runner
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be at least 1, got {args.workers}")
    runner = tile_runner(RunSettings(workers=args.workers, tile_timeout=args.tile_timeout,
                                      dask=args.dask), progress)
    prod = make_dem(left, right, left_model, right_model, settings, runner=runner)
    if not quiet:
        print(file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    prod.write(out, overwrite=True)
    failed = [f.to_dict() for f in runner.failures]
    if failed:
        log.warning("%d tile(s) failed (listed in dem_report.json); the DEM has holes there", len(failed))
    report = dict(left=str(args.left), right=str(args.right), settings=prod.settings,
                  info=prod.info, n_points=prod.n_points, seconds=prod.seconds, tiles=prod.tiles,
                  failed_tiles=failed)
    write_text_atomic(out / "dem_report.json", json.dumps(report, indent=2, default=str) + "\n",
                      overwrite=True)
    g = prod.grid
    if not quiet:
        print(f"stereodem dem: {out / 'dem.tif'}: {g.height.shape[1]}x{g.height.shape[0]} cells at "
              f"{g.posting:g}, {100 * prod.info['valid_cells']:.1f} % valid, {prod.seconds:.1f} s",
              file=sys.stderr)
    return 0
