"""``stereodem change DEM_A DEM_B``: elevation change ``B − A`` on A's grid after
co-registering B to A (``dh.tif``), its σ map (``dh_sigma.tif``), their quick looks
(``dh_map.png``, ``dh_sigma_map.png``) and, when both dates are known, the rate and its σ
(``change.json``)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from stereodem.core.vertical import VERTICALS
from stereodem.post.choices import CHANGE_FIGURES

from . import options
from .commands import help_line
from .outlock import Products

#: what ``stereodem change`` writes into its output folder
PRODUCTS = Products(
    ("dh.tif", "dh_sigma.tif", "change.json", *CHANGE_FIGURES.values()),
    markers=("change.json",),
)

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  stereodem change dem_2004.tif dem_2019.tif --exclude glaciers.gpkg -o change
  stereodem change a.tif b.tif --dates 2004-08-01,2019-07-20 --chain nuth_kaab,deramp:1 -o change
"""


def add_parser(sub):
    p = sub.add_parser(
        "change",
        help=help_line("change"),
        description="Co-register DEM_B to DEM_A on stable terrain (outside --exclude), write "
        "dh = B - A on A's grid (dh.tif) and its per-cell sigma from the dispersion "
        "of dh on stable terrain against slope and curvature (dh_sigma.tif), with "
        "change.json (co-registration, statistics, the rate when the dates are known) and "
        "quick looks of both maps (dh_map.png, dh_sigma_map.png).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dem_a", metavar="DEM_A", help="earlier DEM (its grid is the output grid)")
    p.add_argument("dem_b", metavar="DEM_B", help="later DEM")
    p.add_argument(
        "--a-vertical",
        choices=VERTICALS,
        help="vertical reference of DEM_A when the file does not say",
    )
    p.add_argument(
        "--b-vertical",
        choices=VERTICALS,
        help="vertical reference of DEM_B when the file does not say",
    )
    p.add_argument(
        "--dates", help="DA,DB (default: from the DEMs' metadata when stereodem made them)"
    )
    p.add_argument(
        "--chain",
        default="nuth_kaab,deramp:1",
        help="co-registration chain (default nuth_kaab,deramp:1)",
    )
    p.add_argument(
        "--exclude",
        action="append",
        default=[],
        metavar="VECTOR",
        help="unstable terrain, any vector format and CRS; repeatable",
    )
    options.add_track_angle(
        p,
        "ground-track heading for along/cross-track steps",
    )
    options.add_workers(
        p,
        "threads of the warps, the curvature, the sigma map's bins and cells and the "
        "GeoTIFF compression",
    )
    options.add_creation_options(p)
    p.add_argument("-o", "--out", required=True, help="output folder")
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    import numpy as np

    from stereodem.core import jsonutil
    from stereodem.core.dem import DEM
    from stereodem.core.errors import InputError
    from stereodem.core.raster import write_geotiff, write_text_atomic
    from stereodem.core.threads import job_threads
    from stereodem.post.change import dem_change
    from stereodem.post.coreg import parse_chain
    from stereodem.post.dates import dem_dates
    from stereodem.post.stack_build import check_inputs, exclude_mask
    from stereodem.sensor.simulation.multidate import decimal_year

    from .outlock import check_output_folder, output_folder

    options.check_common(args)
    # an -o that cannot be a folder is refused before the DEMs are compared
    inputs = [args.dem_a, args.dem_b] + list(args.exclude)
    check_output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs)
    a = DEM.from_file(args.dem_a, vertical=args.a_vertical)
    b = DEM.from_file(args.dem_b, vertical=args.b_vertical)
    check_inputs([args.dem_a, args.dem_b], a, reference_name=f"DEM_A {args.dem_a}")
    parse_chain(args.chain)
    for path in args.exclude:
        exclude_mask([path], a)
    dates = None
    if args.dates:
        dates = dem_dates([args.dem_a, args.dem_b], args.dates)
    else:
        try:
            dates = dem_dates([args.dem_a, args.dem_b])
        except InputError as exc:  # dates are optional here: no rate then
            log.info("no rate: %s", exc)
    if dates is not None and not dates[1] > dates[0]:
        raise InputError(f"{args.dem_b}: its date {dates[1]} is not after DEM_A's {dates[0]}")
    res = dem_change(
        a,
        b,
        chain=args.chain,
        exclude=args.exclude,
        track_angle_deg=args.track_angle,
        threads=job_threads(args.workers),
    )
    info = dict(
        dem_a=args.dem_a,
        dem_b=args.dem_b,
        chain=args.chain,
        vertical=res["vertical"],
        coregistration=res["coregistration"],
        stats_stable=res["stats_stable"],
        heteroscedasticity=res["heteroscedasticity"],
    )
    st = res["stable"] & np.isfinite(res["dh"])
    if dates is not None:
        dt = decimal_year(dates[1]) - decimal_year(dates[0])
        info.update(dates=[str(d) for d in dates], years=dt)
        info["rate_note"] = "rate = dh / years; its sigma = dh_sigma / years"
    co = options.creation_options(args)
    with output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs) as out:
        write_geotiff(
            out / "dh.tif",
            res["dh"],
            a.transform,
            a.crs,
            np.nan,
            overwrite=True,
            descriptions="dh = B - A",
            units="metre",
            creation_options=co,
        )
        write_geotiff(
            out / "dh_sigma.tif",
            res["sigma"],
            a.transform,
            a.crs,
            np.nan,
            overwrite=True,
            descriptions="sigma of dh",
            units="metre",
            creation_options=co,
        )
        from stereodem.post.product_figures import change_figures  # matplotlib: when used

        figs = change_figures(
            res["dh"],
            res["sigma"],
            a.transform,
            a.crs,
            out,
            names=(Path(args.dem_a).name, Path(args.dem_b).name),
            overwrite=True,
        )
        info["figures"] = {k: Path(v).name for k, v in figs.items()}
        write_text_atomic(
            out / "change.json", jsonutil.dumps(jsonutil.stamped(info)), overwrite=True
        )
    s = res["stats_stable"]
    options.say(
        f"stereodem change: {out}/dh.tif, dh_sigma.tif, dh_map.png, dh_sigma_map.png; "
        "stable terrain median "
        f"{s['median']:.3f} m, NMAD {s['nmad']:.3f} m over {int(st.sum())} cells"
    )
    return 0
