"""``stereodem info``: what is in an ASTER L1A granule (V004 .hdf, V003 .zip or folder)."""

from __future__ import annotations

import argparse

from .commands import help_line

EXAMPLES = """examples:
  stereodem info AST_L1A_00407312017190728_20250822173530.hdf
  stereodem info AST_L1A_00307312017190728_20160404141337_21031.zip --json
"""


def add_parser(sub):
    p = sub.add_parser(
        "info",
        help=help_line("info"),
        description="Print the bands, image sizes, acquisition time, corner "
        "coordinates and lattice of an ASTER L1A granule.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("granule", help="AST_L1A V004 .hdf, or V003 .zip / unzipped folder")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(run=run)
    return p


def granule_summary(g) -> dict:
    """Plain summary of an :class:`~stereodem.sensor.io.aster_l1a.AsterGranule`."""
    bands = {}
    for name, b in g.bands.items():
        lat = b.fields.lattice
        rows, cols = b.shape
        lon, la = b.model.localize(
            [0.0, cols - 1.0, 0.0, cols - 1.0], [0.0, 0.0, rows - 1.0, rows - 1.0], [0.0] * 4
        )
        bands[name] = {
            "cols": cols,
            "rows": rows,
            "lattice": {
                "rows": int(lat.shape[0]),
                "cols": int(lat.shape[1]),
                "first_row": int(lat[0, 0, 1]),
                "row_step": int(lat[1, 0, 1] - lat[0, 0, 1]),
                "col_step": int(lat[0, 1, 0] - lat[0, 0, 0]),
            },
            "velocity": b.velocity_convention,
            "lattice_check_urad": None
            if b.lattice_error_rad is None
            else [round(1e6 * x, 3) for x in b.lattice_error_rad],
            "corners_lonlat": [[round(float(x), 6), round(float(y), 6)] for x, y in zip(lon, la)],
        }
    return {"granule": g.path, "product": g.product, "metadata": g.metadata, "bands": bands}


def run(args) -> int:
    from stereodem.sensor.io.aster_l1a import open_aster_granule

    s = granule_summary(open_aster_granule(args.granule, bands=()))
    if args.json:
        from stereodem.core import jsonutil

        print(jsonutil.dumps(s, indent=2), end="")
        return 0
    md = s["metadata"]
    print(f"{s['granule']}: {s['product']}, granule {md['granule_id']}")
    print(
        f"  acquired {md['acquisition_time'] or 'unknown'}; sun azimuth/elevation "
        f"{md['sun_azimuth_deg']}/{md['sun_elevation_deg']} deg; cloud cover "
        f"{md['cloud_cover_pct']} %; VNIR pointing {md['pointing_angle_deg']} deg"
    )
    for k, (la, lo) in (md["corners"] or {}).items():
        print(f"  {k.lower():11s} lat {la:.6f} lon {lo:.6f}")
    for name, b in s["bands"].items():
        lt = b["lattice"]
        chk = (
            ""
            if b["lattice_check_urad"] is None
            else f", model vs product lat/lon {b['lattice_check_urad'][0]} urad mean"
        )
        print(
            f"  band {name}: {b['cols']} x {b['rows']} px, lattice {lt['rows']} x {lt['cols']} "
            f"(first row {lt['first_row']}, steps {lt['row_step']} lines / {lt['col_step']} px), "
            f"velocity {b['velocity']}{chk}"
        )
        print(
            "    corners (lon, lat) at h=0: "
            + "; ".join(f"{x:.5f}, {y:.5f}" for x, y in b["corners_lonlat"])
        )
    return 0
