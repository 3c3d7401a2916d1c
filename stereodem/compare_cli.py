"""``stereodem compare-models``: fit many sensor models to the same GCPs and compare them at
the same independent check points (:mod:`stereodem.sensor.estimation.compare`)."""
from __future__ import annotations

import json
import logging

log = logging.getLogger(__name__)


def add_parser(subparsers):
    p = subparsers.add_parser(
        "compare-models", help="compare sensor models fitted to the same GCPs",
        description="Fit every model with the same GCP/ICP split and GCP counts from small to "
                    "large; write compare.json, compare.md and compare.png to DIR.",
        epilog="example: stereodem compare-models left.tif --gcps points.csv --models all -o cmp")
    p.add_argument("image", help="image with a <stem>.model.json sidecar or RPC metadata")
    p.add_argument("--gcps", required=True, help="CSV id,lon,lat,h,col,row[,role,...]")
    p.add_argument("--models", default="all",
                   help="comma-separated model names or 'all' (generic, physical sets, orbital)")
    p.add_argument("--counts", default="6,10,15,20,30,40",
                   help="GCP counts (default 6,10,15,20,30,40; those above the pool are dropped)")
    p.add_argument("--n-check", type=int, default=20,
                   help="check points drawn when the CSV has no 'check' roles (default 20)")
    p.add_argument("--sigma-px", type=float, default=None, help="a-priori image sigma, px")
    p.add_argument("--seed", type=int, default=0, help="seed of the split")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from stereodem.sensor.errors import InputError
    from stereodem.sensor.estimation.compare import compare, expand_models, figure, markdown
    from stereodem.sensor.io.gcps import read_gcps
    from stereodem.sensor.io.raster import prepare_output_dir, write_text_atomic
    from stereodem.sensor.io.sidecar import load_image_model

    try:
        counts = [int(v) for v in args.counts.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--counts: expected comma-separated integers, got {args.counts!r}") from None
    out = prepare_output_dir(args.output, overwrite=args.overwrite)
    base = load_image_model(args.image)
    points = read_gcps(args.gcps)
    models = expand_models([m.strip() for m in args.models.split(",") if m.strip()], base)
    records = compare(base, points, models, counts, n_check=args.n_check, seed=args.seed,
                      sigma_px=args.sigma_px)
    write_text_atomic(out / "compare.json", json.dumps(records, indent=1, default=float),
                      overwrite=args.overwrite)
    write_text_atomic(out / "compare.md", markdown(records), overwrite=args.overwrite)
    figure(records, out / "compare.png")
    ok = [r for r in records if not r.get("error")]
    print(f"{len(models)} model(s), {len(records)} fit(s), {len(records) - len(ok)} refused -> {out}")
    return 0
