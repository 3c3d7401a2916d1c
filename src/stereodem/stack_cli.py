"""``stereodem stack``: many DEMs of the same terrain in time -> a co-registered, cloud-masked
stack (``OUT/stack.zarr``), elevation-change rates with σ (``rate.tif``, ``rate_sigma.tif``,
``n_obs.tif``; quick looks ``rate_map.png``, ``rate_sigma_map.png``, ``n_obs_map.png``) and,
with ``--outlines``, volume change rates per polygon (``volumes.json``)."""

from __future__ import annotations

import argparse
import contextlib
import logging
import time
from pathlib import Path

from stereodem.core.vertical import VERTICALS
from stereodem.post.choices import STACK_FIGURES

from . import options
from .commands import help_line
from .outlock import Products

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  stereodem stack dems/*.tif --ref srtm.tif --ref-vertical geoid -o stack_out
  stereodem stack a.tif b.tif c.tif --dates 2002-07-01,2010-08-12,2018-07-30 --ref ref.tif \\
      --exclude glaciers.gpkg --outlines glaciers.gpkg -o out
  stereodem stack run*/dem.tif --dates dates.csv --ref ref.tif --chain nuth_kaab,deramp:1 -o out

A stack that failed or was interrupted says so in OUT/stack.json, with its input files: the
same command run again replaces what it left, without --overwrite.
"""

#: reference grids of at least this many cells are built with --workers processes
PARALLEL_BUILD_CELLS = 1_000_000
#: the rasters of the rate fit
RATE_FILES = {
    "rate": "rate.tif",
    "rate_sigma": "rate_sigma.tif",
    "n_obs": "n_obs.tif",
    "n_rejected": "n_rejected.tif",
}
#: what ``stereodem stack`` writes into its output folder
PRODUCTS = Products(
    ("stack.json", "stack.zarr", *RATE_FILES.values(), *STACK_FIGURES.values(), "volumes.json"),
    markers=("stack.json",),
)


def add_cloud_options(p):
    """The cloud-mask thresholds (``stack``)."""
    p.add_argument(
        "--cloud-max-dev",
        type=float,
        default=50.0,
        metavar="M",
        help="cells deviating from the reference by more than M metres (median "
        "difference removed) are cloud/blunder (default 50; 0 = off)",
    )
    p.add_argument(
        "--cloud-min-score",
        type=float,
        metavar="S",
        help="also cells whose matcher score (score.tif beside the DEM) is below S",
    )
    p.add_argument(
        "--cloud-max-radiance",
        type=float,
        metavar="L",
        help="also cells whose 3N radiance (ortho_left.tif beside the DEM, "
        "W m-2 sr-1 um-1) exceeds L",
    )
    options.add_cloud_grow(p)


def cloud_settings(args):
    from stereodem.post.clouds import CloudSettings

    return CloudSettings(
        max_deviation=args.cloud_max_dev or None,
        min_score=args.cloud_min_score,
        max_radiance=args.cloud_max_radiance,
        grow=args.cloud_grow,
    )


def add_parser(sub):
    p = sub.add_parser(
        "stack",
        help=help_line("stack"),
        description="Co-register every DEM to the reference with the correction chain, mask "
        "clouds, put all on the reference grid as OUT/stack.zarr (xarray/Zarr), fit "
        "per-cell elevation-change rates by weighted least squares with outlier "
        "rejection in time (rate.tif, rate_sigma.tif, n_obs.tif; quick looks rate_map.png, "
        "rate_sigma_map.png, n_obs_map.png) and, with "
        "--outlines, volume change rates per polygon (volumes.json).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dems", nargs="+", metavar="DEM", help="DEM GeoTIFFs (at least 2)")
    p.add_argument("--ref", required=True, help="reference DEM (its grid is the stack's grid)")
    p.add_argument(
        "--ref-vertical",
        choices=VERTICALS,
        help="vertical reference of --ref when the file does not say",
    )
    p.add_argument(
        "--dates",
        help="D1,D2,... (one per DEM, YYYY-MM-DD) or a CSV of path,date "
        "(default: read from each DEM's metadata, as stereodem writes it)",
    )
    p.add_argument(
        "--chain",
        default=None,
        help="co-registration chain (default nuth_kaab,deramp:1,along_track where the "
        "DEM's track heading is known: --track-angle or the STEREODEM_TRACK_HEADING "
        "tag of a stereodem DEM; nuth_kaab,deramp:1 where it is not)",
    )
    p.add_argument(
        "--exclude",
        action="append",
        default=[],
        metavar="VECTOR",
        help="unstable terrain (glaciers, water...), any vector format and CRS; repeatable",
    )
    options.add_track_angle(
        p,
        "ground-track heading (deg clockwise from north) for along/cross-track steps",
    )
    add_cloud_options(p)
    p.add_argument(
        "--k",
        type=float,
        default=4.0,
        help="outlier rejection in time: studentised residual threshold (default 4)",
    )
    p.add_argument(
        "--max-deviation",
        type=float,
        default=150.0,
        metavar="M",
        help="drop observations farther than M metres from the cell's temporal median "
        "before fitting (default 150)",
    )
    p.add_argument(
        "--outlines",
        metavar="VECTOR",
        help="polygons for elevation and volume change rates (volumes.json)",
    )
    p.add_argument(
        "--band-width",
        type=float,
        default=50.0,
        metavar="M",
        help="elevation band of the hypsometric void fill (default 50 m)",
    )
    p.add_argument(
        "--chunk", type=int, default=256, help="chunk edge of the stack, cells (default 256)"
    )
    options.add_workers(
        p,
        "processes building the stack (one DEM each) and threads of the rate fit",
    )
    options.add_creation_options(p)
    p.add_argument("-o", "--out", required=True, help="output folder")
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def _check(args):
    from stereodem.core.errors import InputError

    options.check_common(args)
    if args.chunk < 16:
        raise InputError(f"--chunk must be at least 16 cells, got {args.chunk}")
    if not args.band_width > 0:
        raise InputError(f"--band-width must be positive, got {args.band_width}")
    if args.cloud_max_dev < 0:
        raise InputError(f"--cloud-max-dev must be >= 0, got {args.cloud_max_dev}")


@contextlib.contextmanager
def _status_if_stopped(path, record):
    """``stack.json`` says ``running`` while the job runs, then ``failed`` (with the one-line
    reason) or ``interrupted`` when it stops (a DEM refused while the stack is built): not
    ``running`` for ever (the store is built under a hidden name and removed when the build
    stops: :func:`stereodem.outlock.staged`). ``record`` (the job's ``inputs``,
    :func:`stereodem.outlock.job_inputs`) goes into each: a rerun of the same inputs then
    replaces what the job left without ``--overwrite`` (:func:`stereodem.outlock.output_folder`),
    a run of other inputs is still refused without it."""
    from stereodem.core import jsonutil
    from stereodem.core.raster import write_text_atomic

    def status(**what):
        write_text_atomic(
            path, jsonutil.dumps(jsonutil.stamped({**what, **record})), overwrite=True
        )

    status(status="running")
    try:
        yield
    except BaseException as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        status(
            status="interrupted" if isinstance(exc, KeyboardInterrupt) else "failed",
            error=reason,
        )
        raise


def run(args) -> int:
    import numpy as np

    from stereodem.core import jsonutil
    from stereodem.core.dem import DEM
    from stereodem.core.raster import write_geotiff, write_text_atomic
    from stereodem.post.dates import dem_dates
    from stereodem.post.rates import RateSettings
    from stereodem.post.stack import open_stack, stack_grid, stack_rates
    from stereodem.post.stack_build import BuildSettings, build_stack, check_inputs

    from .outlock import check_output_folder, job_inputs, output_folder, staged

    t0 = time.perf_counter()
    _check(args)
    rate_settings = RateSettings(k=args.k, max_deviation=args.max_deviation)
    settings = BuildSettings(
        chain=args.chain,
        exclude=list(args.exclude),
        track_angle_deg=args.track_angle,
        cloud=cloud_settings(args),
        chunk=args.chunk,
    )
    # every refusal before the output folder is touched
    inputs = (
        list(args.dems)
        + [args.ref]
        + list(args.exclude)
        + ([args.outlines] if args.outlines else [])
    )
    check_output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs)
    if len(args.dems) < 2:
        check_inputs(args.dems, None)
    ref = DEM.from_file(args.ref, vertical=args.ref_vertical)
    dates = dem_dates(args.dems, args.dates)
    check_inputs(args.dems, ref)
    if args.chain:
        from stereodem.post.coreg import parse_chain

        parse_chain(args.chain)
    outlines = _read_outlines(args.outlines, ref) if args.outlines else None
    for path in args.exclude:
        from stereodem.post.stack_build import exclude_mask

        exclude_mask([path], ref)
    from stereodem.core.threads import job_threads, pool_size

    workers = pool_size(args.workers)  # processes of the build (the cores, by default)
    with (
        output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs) as out,
        _status_if_stopped(out / "stack.json", {"inputs": job_inputs(inputs)}),
    ):
        # processes pay off on scene-sized DEMs only (each starts a Python: ~1-2 s)
        build_workers = workers if ref.heights.size >= PARALLEL_BUILD_CELLS else 1
        # built under a hidden name, moved into place once complete: a build that fails
        # leaves no half-built store, and the previous stack (--overwrite) comes back whole
        with options.progress_bar("stack") as bar, staged(out / "stack.zarr") as store:
            records = build_stack(
                args.dems,
                dates,
                ref,
                store,
                settings,
                progress=bar,
                workers=build_workers,
            )
        t_build = time.perf_counter() - t0
        ds = open_stack(out / "stack.zarr", chunk=args.chunk)
        res = stack_rates(ds, settings=rate_settings, workers=job_threads(args.workers))
        g = stack_grid(ds)
        co = options.creation_options(args)
        for key, name in RATE_FILES.items():
            data = res[key]
            integer = np.issubdtype(data.dtype, np.integer)
            write_geotiff(
                out / name,
                data,
                g.transform,
                g.crs,
                None if integer else np.nan,
                overwrite=True,
                creation_options=co,
                descriptions=key,
                units=None if integer else "metre per year",
            )
        from stereodem.post.product_figures import stack_figures  # matplotlib: when used

        days = ds["time"].values.astype("datetime64[D]")
        figs = stack_figures(
            res,
            g.transform,
            g.crs,
            out,
            what=f"{len(records)} DEMs, {days[0]} to {days[-1]}",
            overwrite=True,
        )
        summary = dict(
            status="ok",
            figures={k: Path(v).name for k, v in figs.items()},
            dems=records,
            chain=sorted({r["chain"] for r in records}),
            rate_settings=rate_settings.__dict__,
            cloud_settings=settings.cloud.__dict__,
            dates=[str(d) for d in ds["time"].values.astype("datetime64[s]")],
            sigma=ds["sigma"].values.tolist(),
            rate_cells=int(np.isfinite(res["rate"]).sum()),
            rejected_observations=int(res["n_rejected"].sum()),
            seconds=dict(build=round(t_build, 2), total=round(time.perf_counter() - t0, 2)),
            workers=workers,
        )
        stable = ds["stable"].values.astype(bool)
        from stereodem.post.stats import error_stats

        summary["rate_stable"] = error_stats(res["rate"][stable])
        if outlines is not None:
            from stereodem.post.volumes import outline_changes, rate_error_model

            model, _emp, znmad = rate_error_model(res["rate"], res["rate_sigma"], stable, g)
            vols = outline_changes(
                res["rate"],
                res["rate_sigma"],
                ds["reference"].values,
                outlines,
                g,
                model,
                band_width=args.band_width,
            )
            write_text_atomic(
                out / "volumes.json",
                jsonutil.dumps(
                    dict(
                        outlines=str(args.outlines),
                        variogram=model.to_dict(),
                        standardised_rate_nmad_stable=znmad,
                        polygons=vols,
                    )
                ),
                overwrite=True,
            )
            summary["volumes"] = [
                {k: v for k, v in r.items() if k != "hypsometric_bands"} for r in vols
            ]
        write_text_atomic(
            out / "stack.json", jsonutil.dumps(jsonutil.stamped(summary)), overwrite=True
        )
    s = summary["rate_stable"]
    options.say(
        f"stereodem stack: {len(records)} DEMs -> {out}/stack.zarr, rate.tif "
        f"({summary['rate_cells']} cells; stable-terrain rate median {s['median']:.3f}, "
        f"NMAD {s['nmad']:.3f} m/yr; {summary['rejected_observations']} observations "
        "rejected in time)"
    )
    return 0


def _read_outlines(path, ref):
    """The polygons of ``path`` (labelled: ``post.masks.read_outlines``) in the reference's
    CRS, refused when none touches its grid."""
    from stereodem.post.masks import rasterize, read_outlines

    outlines = read_outlines(path, ref.crs)
    rasterize([o.geom for o in outlines], ref, path=str(path))
    return outlines
