"""``stereodem uncertainty``: per-cell horizontal σ maps and sensitivity shares of an orthoimage."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from stereodem.core.vertical import VERTICALS
from stereodem.ortho.choices import UNCERTAINTY_METHODS
from stereodem.sensor.choices import GENERIC_MODEL_NAMES

from . import options
from .commands import help_line
from .outlock import Products

#: what ``stereodem uncertainty`` writes into its output folder
#: (:meth:`stereodem.ortho.uncertainty.maps.UncertaintyMaps.write` and the figure)
PRODUCTS = Products(
    (
        "sigma_horizontal.tif",
        "sigma_east.tif",
        "sigma_north.tif",
        "ce90.tif",
        "dominant_source.tif",
        "share_*.tif",
        "sensitivity.json",
        "uncertainty.png",
    ),
    markers=("sensitivity.json",),
)

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  stereodem uncertainty img.tif --dem dem.tif --sigma col_shift=0.5 --sigma row_shift=0.5 \\
      --sigma dem_height=5 -o unc
  stereodem uncertainty left.tif --dem dem.tif --covariance adjust_report.json \\
      --sigma dem_height=3 -o unc
  stereodem uncertainty left.tif --dem dem.tif --sigma roll_bias=2e-5 --method monte-carlo \\
      --samples 500 -o unc
  stereodem uncertainty left.tif --dem dem.tif --model rpc --sigma col_shift=0.5 -o unc

inputs (--sigma NAME=VALUE, 1-sigma in the input's unit):
  every model: col_shift, row_shift (px), col_drift_col ... (px/px): the image-space
    correction adjust's rpc-* sets estimate (a physical model is wrapped in it), dem_height (m)
  physical models: their own parameter names (see the error message for the list),
    imaging_time (s) for frame cameras (pushbroom models: time_offset); not together with
    the image-space ones
"""


def add_parser(sub):
    p = sub.add_parser(
        "uncertainty",
        help=help_line("uncertainty"),
        description="First-order (J D J^T), Monte Carlo (Latin hypercube) or FAST "
        "propagation of sensor-model, DEM-height and imaging-time errors "
        "to the orthoimage grid: sigma_east/north/horizontal, CE90, the "
        "dominant source per cell and each source's share.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "image",
        help="image GeoTIFF (with RPCs or a <stem>.model.json sidecar), or an ASTER L1A "
        "granule (choose the band with --band 3N|3B)",
    )
    options.add_image_model(p, GENERIC_MODEL_NAMES)
    options.add_band(p, "1; 3N in an ASTER granule", radiometric=False)
    p.add_argument("--dem", required=True, help="DEM GeoTIFF")
    p.add_argument(
        "--dem-vertical",
        choices=VERTICALS,
        help="vertical reference of --dem when the file does not say",
    )
    options.add_res(p, "the image GSD")
    p.add_argument(
        "--sigma",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="1-sigma of an input (repeatable)",
    )
    p.add_argument(
        "--covariance", metavar="REPORT", help="adjust_report.json with a full covariance"
    )
    p.add_argument(
        "--method",
        choices=UNCERTAINTY_METHODS,
        default="first-order",
        help="propagation: first-order (Jacobians of the ground position, full covariance), "
        "monte-carlo (--samples Latin hypercube draws) or fast (FAST and Sobol sensitivity "
        "indices, SALib) (default first-order)",
    )
    p.add_argument(
        "--samples",
        type=int,
        default=1000,
        help="Monte Carlo samples or FAST points per curve, 10..100000 (default 1000)",
    )
    p.add_argument(
        "--seed", type=int, default=0, help="random seed of the sampled methods (default 0)"
    )
    p.add_argument(
        "--source-maps", action="store_true", help="also write share_<source>.tif per source"
    )
    options.add_workers(
        p,
        "threads of the maps' row blocks and the GeoTIFF compression, written while the "
        "figure is drawn",
    )
    p.add_argument("-o", "--out", required=True, help="output folder")
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from stereodem.core.dem import DEM
    from stereodem.core.errors import AccuracyError
    from stereodem.core.threads import job_threads
    from stereodem.ortho.choices import check_samples
    from stereodem.ortho.drm import dem_gaps, no_height_message
    from stereodem.ortho.grid import footprint_height_range, grid_for_model
    from stereodem.ortho.uncertainty.covariance import (
        assemble,
        parse_sigma_pairs,
        read_adjust_report,
    )
    from stereodem.ortho.uncertainty.maps import ortho_uncertainty_maps
    from stereodem.sensor.io.sidecar import sidecar_path

    from . import options
    from .pipeline.inputs import check_image, chosen_model

    options.check_common(args)
    check_samples(args.samples, "--samples")
    from .outlock import check_output_folder, output_folder

    # an input named like a map in the output folder was replaced with --overwrite
    model_file = args.model if Path(args.model).is_file() else None
    inputs = [
        args.image,
        args.dem,
        args.covariance,
        args.gcps,
        model_file,
        sidecar_path(args.image),
    ]
    check_output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs)
    sigmas = parse_sigma_pairs(args.sigma)
    report = read_adjust_report(args.covariance) if args.covariance else None
    chosen = chosen_model(
        args.image, args.model, band=args.band, rpc_direct=args.rpc_direct, gcps=args.gcps
    )
    # the image itself, not only its model (a sidecar beside a zero-byte image passed)
    check_image(args.image, band=args.band)
    if chosen.note:
        options.say(chosen.note)
    model, names, D = assemble(chosen.model, sigmas=sigmas, report=report, image=args.image)
    dem = DEM.from_file(args.dem, vertical=args.dem_vertical)
    h_range = footprint_height_range(model, dem)
    grid = grid_for_model(model, dem, res=args.res, crs=args.crs, h_range=h_range)
    # the maps are nodata there, as the orthoimage on this grid: the figure ortho reports
    missing = dem_gaps(model, dem, grid)
    if missing["n_no_height"]:
        log.warning(
            "%s", no_height_message(args.dem, missing, "the uncertainty maps are nodata there")
        )
    threads = job_threads(args.workers)
    try:
        maps = ortho_uncertainty_maps(
            model,
            dem,
            grid,
            D,
            names,
            args.method,
            samples=args.samples,
            seed=args.seed,
            source_maps=args.source_maps,
            threads=threads,
        )
    except AccuracyError as exc:  # no maps known to be wrong: the files it concerns named
        raise AccuracyError(f"{args.image} over the DEM {args.dem}: {exc}") from exc
    with output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs) as out:
        _write_and_plot(maps, out, args, threads)
    s = maps.summary()
    top = max(maps.shares, key=lambda k: maps.shares[k])
    options.say(
        f"wrote {out}/sigma_horizontal.tif (+ east, north, ce90, dominant_source, "
        f"sensitivity.json, uncertainty.png): {grid.width}x{grid.height} cells of "
        f"{options.posting(grid)}; sigma_horizontal median "
        f"{s['sigma_horizontal_m']['median']:.3g} m (max {s['sigma_horizontal_m']['max']:.3g}); "
        f"largest share {top} {maps.shares[top]:.3f}; "
        f"interpolation error {maps.interpolation_error:.2g} (relative, measured)"
    )
    return 0


def _write_and_plot(maps, out, args, threads: int):
    """The maps' GeoTIFFs and the figure: with more than one thread the GeoTIFFs are written
    (GDAL compresses without the GIL) on a thread of their own while the figure is drawn
    (matplotlib, which holds it); the same files either way."""
    from concurrent.futures import ThreadPoolExecutor

    from stereodem.ortho.uncertainty.figure import plot_uncertainty

    def write():
        maps.write(out, overwrite=True, source_maps=args.source_maps)

    def plot():
        plot_uncertainty(maps, out / "uncertainty.png", title=Path(args.image).name, overwrite=True)

    if threads <= 1:
        write()
        plot()
        return
    with ThreadPoolExecutor(1, thread_name_prefix="stereodem-maps-write") as ex:
        written = ex.submit(write)
        try:
            plot()
        finally:
            written.result()  # the GeoTIFFs waited for whatever the figure did
