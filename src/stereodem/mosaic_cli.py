"""``stereodem mosaic DEM... -o OUT``: one DEM from many (ASP ``dem_mosaic``), block by block.

The DEMs are brought to one CRS (the first DEM's unless ``--crs``; others are warped,
bilinear) and one vertical reference (the first DEM's unless ``--vertical``; EGM96 converts
geoid <-> ellipsoid heights; a DEM whose reference is unknown among DEMs that say theirs is
refused unless ``--dem-vertical`` says it). Seams are blended with distance-to-edge weights
(``--method blend``, the default), σ-weighted where every DEM carries a σ layer; other methods:
first, last, min, max, mean, median, count, stddev, nmad. With ``--ref REF --coregister`` every
DEM is first co-registered to REF (Nuth & Kääb; ``--coreg-chain`` names the chain).

Writes ``OUT`` (a Cloud-Optimised GeoTIFF: heights, count, σ or stddev; the statistic alone
for count/stddev/nmad), ``OUT`` with ``.json`` (DEMs used and skipped, conversions,
co-registration shifts, memory bound and peak) and quick looks beside it: ``OUT_hillshade.png``
(shaded relief) and ``OUT_count.png`` (DEMs contributing per cell), or ``OUT_<method>.png``
for count/stddev/nmad. Memory is bounded by the block size and the
number of DEMs overlapping one block, not by the mosaic's size (``--block``).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from stereodem.core.vertical import VERTICALS

from . import options
from .commands import help_line

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  stereodem mosaic dem_*.tif -o mosaic.tif
  stereodem mosaic a/dem.tif b/dem.tif --method median -o median.tif --res 30
  stereodem mosaic tiles/*.tif -o m.tif --crs EPSG:32637 --vertical ellipsoid --dask local \\
      --workers 2
  stereodem mosaic dem_*.tif --ref srtm.tif --coregister -o m.tif --dem-vertical geoid
"""


def add_parser(sub):
    from stereodem.post.choices import MOSAIC_METHODS as METHODS

    p = sub.add_parser(
        "mosaic",
        help=help_line("mosaic"),
        description=__doc__,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "dems", nargs="+", metavar="DEM", help="DEM GeoTIFFs, in priority order (first/last)"
    )
    p.add_argument("-o", "--out", required=True, help="mosaic GeoTIFF to write")
    p.add_argument(
        "--method",
        choices=METHODS,
        default="blend",
        help="value per cell (default blend: distance-to-edge weighted mean)",
    )
    p.add_argument(
        "--res",
        type=float,
        metavar="RES",
        help="output posting in the output CRS's units (default: the first DEM's)",
    )
    p.add_argument("--crs", help="output CRS, e.g. EPSG:32637 (default: the first DEM's)")
    p.add_argument(
        "--bounds",
        type=float,
        nargs=4,
        metavar=("W", "S", "E", "N"),
        help="output extent in the output CRS (default: all DEMs); DEMs outside are skipped",
    )
    p.add_argument(
        "--vertical",
        choices=VERTICALS,
        help="vertical reference of the mosaic (default: the first DEM's)",
    )
    p.add_argument(
        "--dem-vertical",
        choices=VERTICALS,
        help="vertical reference of DEMs whose file does not say",
    )
    p.add_argument(
        "--blend-length",
        type=int,
        default=50,
        help="cells over which a DEM's weight rises from its edge (default 50)",
    )
    p.add_argument(
        "--weights-exponent",
        type=float,
        default=2.0,
        help="exponent of the distance weight (default 2, as dem_mosaic)",
    )
    p.add_argument("--no-sigma", action="store_true", help="ignore the DEMs' σ layers")
    p.add_argument("--ref", help="reference DEM for --coregister")
    p.add_argument(
        "--coregister",
        action="store_true",
        help="co-register every DEM to --ref first (DEMs that miss it are skipped)",
    )
    p.add_argument(
        "--coreg-chain",
        help="co-registration chain, steps comma separated: nuth_kaab, vshift "
        "(default nuth_kaab; see stereodem coregister)",
    )
    p.add_argument("--block", type=int, default=512, help="output block size, cells (default 512)")
    p.add_argument(
        "--dask",
        metavar="ADDRESS",
        help="compute blocks on a dask.distributed scheduler (tcp://host:port, or "
        "'local' for a local cluster of --workers processes)",
    )
    options.add_workers(
        p,
        "threads of this process (the blocks' reads and weights without --dask, the COG's "
        "compression); with --dask local also the cluster's worker processes, each pinned to "
        "its share of the cores",
    )
    options.add_creation_options(p)
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def report_path(out) -> Path:
    """The mosaic's JSON report: ``OUT`` with ``.json``."""
    return Path(out).with_suffix(".json")


def run(args) -> int:
    from stereodem.core import jsonutil
    from stereodem.core.errors import InputError
    from stereodem.core.raster import check_writable, write_text_atomic
    from stereodem.post.mosaic import plan_mosaic, run_mosaic
    from stereodem.post.product_figures import mosaic_figure_paths, mosaic_figures
    from stereodem.stereo.runner import process_peak_rss_mb, reset_peak_rss

    from .outlock import check_not_an_input
    from .provenance import begin, provenance

    started = begin()
    options.check_common(args)
    if args.coregister and not args.ref:
        raise InputError("--coregister needs --ref REF")
    if args.ref and not args.coregister:
        raise InputError("--ref is used with --coregister")
    if args.coreg_chain is not None and not args.coregister:  # it would be ignored
        raise InputError("--coreg-chain is used with --coregister")
    out = options.geotiff_output(args.out, "mosaic")
    rep = report_path(out)
    pngs = list(mosaic_figure_paths(out, args.method).values())
    check_not_an_input([out, rep, *pngs], [*args.dems, args.ref])
    for path in (out, rep, *pngs):
        check_writable(path, args.overwrite)
    reset_peak_rss()
    plan = plan_mosaic(
        args.dems,
        method=args.method,
        crs=args.crs,
        res=args.res,
        bounds=args.bounds,
        vertical=args.vertical,
        dem_vertical=args.dem_vertical,
        block=args.block,
        blend_length=args.blend_length,
        weights_exponent=args.weights_exponent,
        use_sigma=not args.no_sigma,
        reference=args.ref if args.coregister else None,
        coreg_chain="nuth_kaab" if args.coreg_chain is None else args.coreg_chain,
    )
    bar = options.progress_bar("mosaic")
    report = run_mosaic(
        plan,
        out,
        overwrite=args.overwrite,
        creation_options=options.creation_options(args),
        dask=args.dask,
        workers=args.workers,
        progress=bar,
    )
    bar.close()
    figs = mosaic_figures(out, args.method, n_dems=report["n_used"], overwrite=args.overwrite)
    report.update(
        figures={k: Path(v).name for k, v in figs.items()},
        peak_rss_mb=process_peak_rss_mb(),
        provenance=provenance(started=started),
        inputs=[str(p) for p in args.dems],
        reference=args.ref,
    )
    write_text_atomic(rep, jsonutil.dumps(report, indent=2), overwrite=args.overwrite)
    g = plan.grid
    options.say(
        f"stereodem mosaic: {out}: {report['n_used']} of {report['n_inputs']} DEMs, "
        f"{g.width}x{g.height} cells at {options.posting(g)}, "
        f"{100 * report['valid_share']:.1f} % valid, {report['seconds']:.1f} s ({args.method})"
    )
    for s in report["skipped"]:
        options.say(f"  skipped {s['path']}: {s['reason']}")
    return 0
