"""``stereodem dem LEFT RIGHT -o OUT``: a stereo DEM (before editing) from a pair.

Writes ``dem.tif`` (float32, NaN voids, ellipsoidal heights unless ``--geoid``), ``score.tif``
(mean correlation), ``count.tif`` (points per cell) and ``raygap.tif`` (mean ray gap, m), plus
``dem_report.json`` (settings and per-tile QA). ``stereodem filter OUT/dem.tif`` edits it.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from stereodem.core.vertical import VERTICALS
from stereodem.stereo.settings import FUSION_METHODS, GRIDDING_METHODS, JITTER_AXES, MATCHERS

from . import options
from .commands import help_line

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  stereodem dem left.tif right.tif -o out --height-range 1400 3300
  stereodem dem img_01.tif img_02.tif -o dsm --res 0.5 --crs EPSG:32740 --height-range 2100 2600
  stereodem dem 3N.tif 3B.tif -o dem --seed-dem srtm.tif --matcher ncc --geoid --overwrite
  stereodem dem 3N.tif 3B.tif -o dem --height-range 0 2500 --workers 2 --tile-timeout 120
  stereodem dem left.tif right.tif -o out --right-model right.adjusted.model.json
  stereodem dem AST_L1A_00307312017190728_20250708114426.hdf -o dem      # 3N/3B of a granule
  stereodem dem AST_L1A_004*.hdf -o strip_dem     # consecutive granules of one pass: one strip
"""


def add_parser(subparsers):
    """Register the ``dem`` sub-command on an ``argparse`` sub-parser set."""
    p = subparsers.add_parser(
        "dem",
        help=help_line("dem"),
        description="Build a DEM from a stereo pair: per-tile epipolar resampling, dense "
        "matching, space intersection with the exact sensor models, gridding. "
        "LEFT/RIGHT are GeoTIFFs with RPC metadata (tags or .RPB sidecar) or a "
        "physical-model sidecar <stem>.model.json.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "left",
        help="left (reference) image GeoTIFF, or an ASTER L1A granule (V004 "
        "AST_L1A_*.hdf, V003 zip or folder) whose 3N/3B bands are the pair; "
        "two or more consecutive granules of one pass (or a folder of "
        "them) make one strip and one DEM",
    )
    p.add_argument("right", nargs="?", help="right image GeoTIFF (omitted for an ASTER granule)")
    p.add_argument(
        "more",
        nargs="*",
        metavar="IMAGE",
        help="further images of the scene: three or more images make an N-view DEM "
        "(pairs chosen by overlap and base-to-height ratio, their DEMs fused per "
        "cell; count, nmad and sigma layers)",
    )
    p.add_argument("-o", "--out", required=True, help="output folder")
    options.add_res(p, "2 x the left image's GSD")
    rng = p.add_mutually_exclusive_group()
    rng.add_argument(
        "--height-range",
        nargs=2,
        type=float,
        metavar=("MIN", "MAX"),
        help="ellipsoidal height range of the terrain, metres",
    )
    rng.add_argument("--seed-dem", help="coarse DEM giving each tile's height range")
    p.add_argument(
        "--dem-vertical",
        choices=VERTICALS,
        help="vertical reference of the seed DEM when the file does not say",
    )
    p.add_argument("--left-model", help="sensor-model file for LEFT (default: its sidecar or RPCs)")
    p.add_argument(
        "--right-model", help="sensor-model file for RIGHT (default: its sidecar or RPCs)"
    )
    p.add_argument("--matcher", choices=MATCHERS, default="sgm", help="dense matcher (default sgm)")
    p.add_argument("--tile-size", type=int, default=512, help="tile side, pixels (default 512)")
    p.add_argument(
        "--gridding",
        choices=GRIDDING_METHODS,
        default="gaussian",
        help="cell estimator (default gaussian)",
    )
    p.add_argument(
        "--no-pointing-correction",
        action="store_true",
        help="do not estimate the relative pointing (right-image translation)",
    )
    p.add_argument(
        "--pointing-from-seed",
        action="store_true",
        help="also fix the pointing's component along the epipolar lines (a height "
        "offset, unobservable from two images) against --seed-dem",
    )
    p.add_argument("--geoid", action="store_true", help="write EGM96 geoid heights")
    p.add_argument(
        "--jitter-correction",
        nargs="?",
        const="pitch",
        choices=JITTER_AXES,
        help="estimate the right camera's attitude jitter (sum of sines), correct its "
        "attitude and make the DEM again (ASTER 3B): pitch (the default) against "
        "--seed-dem, roll from the matcher's residual vertical parallax (no "
        "reference DEM), or both",
    )
    options.add_band(p)
    p.add_argument(
        "--rpc-direct",
        action="store_true",
        help="localise RPCs with the file's direct model (DIMAP, rpcm JSON) instead of "
        "the exact inverse of the projection (the default)",
    )
    options.add_workers(p)
    p.add_argument(
        "--tile-timeout",
        type=float,
        default=600.0,
        help="seconds after which a tile is abandoned and reported (default 600)",
    )
    p.add_argument("--dask", metavar="ADDRESS", help="dask.distributed scheduler (tcp://host:port)")
    p.add_argument(
        "--point-cloud",
        choices=("las", "laz"),
        help="also write the intersected points as OUT/dem.las or dem.laz (x, y, z in "
        "the DEM's CRS; ray gap, score, source pair, classification); with several "
        "images one cloud of every pair's points, source_pair = pair_id in dem_report.json",
    )
    options.add_creation_options(p)
    options.add_overwrite(p)
    p.add_argument(
        "--fusion",
        choices=FUSION_METHODS,
        default="weighted",
        help="N-view DEMs: per cell, the σ-weighted mean of the pair heights that agree "
        "with their median (default), or their median",
    )
    p.add_argument(
        "--max-pairs", type=int, help="N-view DEMs: at most this many pairs (default all usable)"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="exit 0 with a result the sanity checks call suspect (still reported)",
    )
    # the tile pool's fork server starts before the job's modules load (cli._fork_server)
    p.set_defaults(run=run, pool_request=_pool_request)
    return p


def config_from_args(args):
    """The :class:`~stereodem.config.Config` of a ``stereodem dem`` command line."""
    from stereodem.core.errors import InputError
    from stereodem.stereo.fusion import FusionSettings
    from stereodem.stereo.settings import (
        GriddingSettings,
        MatchingSettings,
        RectificationSettings,
        StereoSettings,
    )

    from .config import Config, DemSettings, InputSettings, JitterSettings, RunSettings, validate

    hr = tuple(args.height_range) if args.height_range is not None else None
    images = [args.left, args.right, *args.more] if args.more else None
    if images and (args.left_model or args.right_model):
        raise InputError(
            "--left-model/--right-model name a pair's models; with three or more "
            "images give each image its <stem>.model.json sidecar"
        )
    cfg = Config(
        inputs=InputSettings(
            left=None if images else args.left,
            right=None if images else args.right,
            images=images,
            band=args.band,
            radiometric=not args.no_radiometric,
            left_model=args.left_model,
            right_model=args.right_model,
            rpc_direct=args.rpc_direct,
            seed_dem=args.seed_dem,
            seed_dem_vertical=args.dem_vertical,
        ),
        output_dir=args.out,
        stereo=StereoSettings(
            rectification=RectificationSettings(
                tile_size=args.tile_size,
                height_range=hr,
                pointing_correction=not args.no_pointing_correction,
                pointing_uses_seed=args.pointing_from_seed,
            ),
            matching=MatchingSettings(matcher=args.matcher),
            gridding=GriddingSettings(
                res=args.res, crs=args.crs, geoid=args.geoid, method=args.gridding
            ),
        ),
        jitter=JitterSettings(
            enabled=bool(args.jitter_correction), axes=args.jitter_correction or "pitch"
        ),
        run=RunSettings(
            workers=args.workers,
            tile_timeout=args.tile_timeout,
            dask=args.dask,
            overwrite=args.overwrite,
            force=args.force,
            creation_options=options.creation_options(args),
        ),
        dem=DemSettings(point_cloud=args.point_cloud),
        fusion=FusionSettings(method=args.fusion, max_pairs=args.max_pairs),
    )
    validate(cfg, "command line")
    return cfg


def _pool_request(args):
    """``(workers, dask)`` of the job, for the CLI's early start of the tile pool's fork server
    (:func:`stereodem.cli._fork_server`)."""
    return args.workers, args.dask


def run(args) -> int:
    """Run ``stereodem dem``; returns the exit status (0 ok; errors propagate to the CLI).

    The output folder is locked for the job; a suspect result (:mod:`stereodem.stereo.sanity`) is
    written with its findings in ``dem_report.json`` and fails the command unless ``--force``.
    The CLI starts the tile pool's fork server before this (``pool_request``,
    :func:`stereodem.cli._fork_server`), while the job's modules load.
    """
    from . import point_cloud
    from .outlock import output_folder
    from .pipeline.inputs import input_paths, load_pair, pair_names
    from .pipeline.stages import check_dem_result, stereo_stage, write_dem_report
    from .provenance import begin

    started = begin()
    options.check_common(args)
    from .strip import strip_granules

    granules = strip_granules([args.left, args.right, *args.more], args.band)
    if granules:
        return _run_strip(args, granules, started)
    cfg = config_from_args(args)
    from stereodem.core.threads import job_threads, thread_budget

    if cfg.inputs.images:
        with thread_budget(cfg.run.workers):
            return _run_multiview(cfg, started)
    with (
        output_folder(
            cfg.output_dir,
            overwrite=args.overwrite,
            inputs=input_paths(cfg),
        ) as out,
        thread_budget(cfg.run.workers),
    ):
        pair = load_pair(cfg)
        bar = options.progress_bar("stereo")
        pts = point_cloud.prepare(out) if cfg.dem.point_cloud else None
        prod, failed = stereo_stage(cfg, pair, progress=bar, points_dir=pts)
        bar.close()
        from stereodem.post.coreg_run import track_tags  # the track for coregister's along_track

        prod.write(  # the job waits for these: its files side by side on its threads
            out,
            overwrite=True,
            creation_options=cfg.run.creation_options,
            tags=track_tags(pair.left_model, pair.left_image.shape, prod.dem.crs, prod.dem.heights),
            threads=job_threads(cfg.run.workers),
        )
        left, right = pair_names(args.left, args.right)
        cloud = None
        if pts is not None:
            cloud = point_cloud.point_cloud_stage(cfg, out, prod, pairs={0: (left, right)})
        write_dem_report(out, prod, failed, pair, started, cloud, left=left, right=right)
    check_dem_result(cfg, prod, failed, out / "dem_report.json")
    g = prod.dem.grid
    options.say(
        f"stereodem dem: {out / 'dem.tif'}: {g.width}x{g.height} cells at {options.posting(g)}, "
        f"{100 * prod.info.valid_cells:.1f} % valid, {prod.seconds:.1f} s"
    )
    options.say(sparse_line(prod.info.to_dict()))
    if cloud is not None:
        options.say(f"  point cloud {cloud['path']}: {cloud['n_points']} points")
    return 0


def _run_strip(args, granules, started) -> int:
    """``stereodem dem G1.hdf G2.hdf ...`` (or a folder): consecutive ASTER granules of one
    pass as one strip (:func:`stereodem.strip.run_strip_dem`)."""
    from stereodem.core.errors import InputError

    from .strip import run_strip_dem

    if args.left_model or args.right_model:
        raise InputError(
            "--left-model/--right-model name a pair's models; a strip of ASTER "
            "granules takes its models from the granules"
        )
    one = argparse.Namespace(**{**vars(args), "left": granules[0], "right": None, "more": []})
    cfg = config_from_args(one)
    bar = options.progress_bar("stereo")
    prod, out, strip, cloud = run_strip_dem(cfg, granules, started=started, progress=bar)
    bar.close()
    g = prod.dem.grid
    seams = strip.report["seams"]["3N"]
    options.say(
        f"stereodem dem: {out / 'dem.tif'}: strip of {len(granules)} granules "
        f"({', '.join(Path(p).name for p in granules)}), {g.width}x{g.height} cells at "
        f"{options.posting(g)}, {100 * prod.info.valid_cells:.1f} % valid, {prod.seconds:.1f} s"
    )
    options.say(
        "  3N line offsets "
        + ", ".join(str(s["offset_lines"]) for s in seams)
        + "; overlaps "
        + ", ".join(f"{s['overlap_lines']} lines" for s in seams)
    )
    options.say(sparse_line(prod.info.to_dict()))
    if cloud is not None:  # as the pair and N-view routes say it
        options.say(f"  point cloud {cloud['path']}: {cloud['n_points']} points")
    return 0


def _run_multiview(cfg, started) -> int:
    """``stereodem dem IMG1 IMG2 IMG3 ...``: the N-view DEM
    (:func:`stereodem.multiview.run_dem`)."""
    from .multiview import run_dem

    bar = options.progress_bar("stereo")
    prod, out = run_dem(cfg, started=started, progress=bar)
    bar.close()
    f, mv = prod.fused, prod.report
    pairs = ", ".join(
        f"{r['left'] + 1}+{r['right'] + 1} (B/H {r['base_to_height']:.2f})" for r in mv["pair_runs"]
    )
    options.say(
        f"stereodem dem: {out / 'dem.tif'}: {f.grid.width}x{f.grid.height} cells at "
        f"{options.posting(f.grid)}, {100 * mv['fusion']['valid_cells']:.1f} % valid, fused from "
        f"{len(mv['pair_runs'])} pair(s): {pairs}; {prod.seconds:.1f} s"
    )
    for s in mv["skipped_images"]:
        options.say(f"  skipped {s['name']}: {s['reason']}")
    cloud = prod.point_cloud
    if cloud is not None:
        options.say(
            f"  point cloud {cloud['path']}: {cloud['n_points']} points of "
            f"{len(cloud['pairs'])} pair(s) (source_pair: pair_id in dem_report.json)"
        )
    return 0


def sparse_line(info: dict) -> str:
    """One line on the heights searched and the relative pointing correction."""
    lo, hi = info["height_range"]
    text = f"  heights {lo:.0f}..{hi:.0f} m ({info.get('height_source', '?')}"
    if info.get("height_margin_m"):  # the range asked for (or the seed's) and its margin
        text += f" +/- {info['height_margin_m']:g} m, within the models' validity"
    terrain = (info.get("sparse") or {}).get("terrain")
    if terrain:
        text += f", {terrain['n_points']} points"
    text += ")"
    p = info.get("pointing") or {}
    if p.get("parameters"):
        pp = p["parameters"]
        text += (
            f"; pointing {p['kind']} {pp['col_shift']:+.2f}/{pp['row_shift']:+.2f} px (col/row), "
            f"residual across the epipolar lines: median {p['residual_before_px']['median']:+.2f} "
            f"-> {p['residual_after_px']['median']:+.2f} px, NMAD "
            f"{p['residual_after_px']['nmad']:.2f} px"
        )
    if info.get("suspect"):
        text += "; SUSPECT: heights pile up at a bound of the search range"
    return text
