"""``stereodem adjust``: estimate sensor-model corrections from GCPs (one image) or by bundle
adjustment of a pair, with a statistics report."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from stereodem.core.vertical import VERTICALS
from stereodem.sensor.choices import ADJUST_MODELS

from . import options
from .commands import help_line

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  stereodem adjust img.tif --gcps points.csv --model rpc-shift -o img_adj.model.json --report adj/
  stereodem adjust img.tif --gcps points.csv --model rpc-affine --sigma-px 0.5 -o out.model.json
  stereodem adjust aster_3n.tif --gcps pts.csv --vertical geoid --model attitude-bias \\
      -o 3n.model.json
  stereodem adjust img.tif --gcps points.csv --model rational-1 -o fitted.model.json --report rep/
  stereodem adjust left.tif right.tif --model bundle --set rpc-shift --gcps left.csv \\
      --gcps2 right.csv -o left.model.json --out2 right.model.json --report ba/
  stereodem adjust left.tif right.tif --model bundle --ties ties.csv -o l.model.json \\
      --out2 r.model.json
  stereodem adjust img_01.tif img_02.tif img_03.tif --model bundle --image-gcps 3=pts3.csv \\
      -o adjusted/
  stereodem adjust 3N.tif 3B.tif --model bundle --match run-3N__3B.match -o 3n.model.json \\
      --out2 3b.model.json

GCP CSV: id,lon,lat,h,col,row[,sigma_px][,sigma_ground_m][,role]  (role gcp or check; lon/lat
degrees WGS84, h ellipsoidal metres unless --vertical geoid, col/row pixels with the centre of
the top-left pixel at 0,0). Tie CSV: col1,row1,col2,row2 (header required).
"""


#: the bundle-only options' defaults (None in the parser, so that a single-image adjustment
#: can tell them given and refuse them instead of ignoring them)
BUNDLE_DEFAULTS = {"param_set": "rpc-shift", "sigma_tie_px": 0.5}

#: options that only a bundle adjustment reads (dest: spelling); the ones only an N-image
#: bundle reads; the one only a pair reads
BUNDLE_ONLY = {
    "image2": "IMAGE2",
    "gcps2": "--gcps2",
    "ties": "--ties",
    "match": "--match",
    "image_gcps": "--image-gcps",
    "fix": "--fix",
    "out2": "--out2",
    "param_set": "--set",
    "sigma_tie_px": "--sigma-tie-px",
}
IMAGES_ONLY = {"image_gcps": "--image-gcps", "fix": "--fix"}
PAIR_ONLY = {"out2": "--out2"}


def _applicable(args, n_images) -> None:
    """Refuse an option the chosen adjustment would not read (``--ties`` with a single-image
    model was ignored without a word), then fill the bundle's defaults."""
    from stereodem.core.errors import InputError

    if args.model != "bundle":
        given = [flag for dest, flag in BUNDLE_ONLY.items() if getattr(args, dest) is not None]
        if given:
            raise InputError(
                f"{', '.join(given)}: only --model bundle reads "
                f"{'it' if len(given) == 1 else 'them'} (--model {args.model} adjusts one "
                "image from its --gcps)"
            )
        return
    unread = PAIR_ONLY if n_images else IMAGES_ONLY
    given = [flag for dest, flag in unread.items() if getattr(args, dest) is not None]
    if given:
        kind = "a pair (IMAGE IMAGE2)" if n_images else "three or more images"
        raise InputError(f"{', '.join(given)}: only a bundle of {kind} reads it")
    for dest, value in BUNDLE_DEFAULTS.items():
        if getattr(args, dest) is None:
            setattr(args, dest, value)


def add_parser(sub):
    p = sub.add_parser(
        "adjust",
        help=help_line("adjust"),
        description="Estimate the parameters of IMAGE's sensor model from ground "
        "control points (or of a pair's two models from tie points and "
        "GCPs with --model bundle), write the adjusted model as a JSON "
        "sidecar readable by ortho/dem (--model), and a report: "
        "adjust_report.json, adjust_report.md and the residual figure.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "image",
        help="image (GeoTIFF with RPCs or a <stem>.model.json sidecar), or an "
        "ASTER L1A granule (its --band; with --model bundle and no IMAGE2, "
        "the 3N/3B pair)",
    )
    p.add_argument("image2", nargs="?", help="second image of a pair (--model bundle)")
    p.add_argument(
        "more",
        nargs="*",
        metavar="IMAGE",
        help="further images (--model bundle of three or more images: -o is then the "
        "folder of their adjusted models <stem>.model.json)",
    )
    p.add_argument(
        "--band",
        type=options.band,
        default=1,
        help="band of an ASTER granule (3N or 3B; default 3N)",
    )
    p.add_argument("--gcps", help="GCP / check-point CSV measured in IMAGE")
    p.add_argument("--gcps2", help="GCP / check-point CSV measured in IMAGE2 (bundle)")
    p.add_argument(
        "--ties",
        help="tie-point CSV col1,row1,col2,row2, or point,image,col,row for "
        "three or more images (bundle; default: automatic SIFT matches "
        "checked through the models, when available)",
    )
    p.add_argument(
        "--match",
        action="append",
        metavar="FILE",
        help="ASP binary match file <prefix>-<stem1>__<stem2>.match as tie points "
        "(bundle; repeatable; refused when it belongs to other images)",
    )
    p.add_argument(
        "--image-gcps",
        action="append",
        metavar="K=CSV",
        help="GCP / check-point CSV measured in the K-th image (bundle; repeatable)",
    )
    p.add_argument(
        "--fix",
        action="append",
        type=int,
        metavar="K",
        help="hold the K-th image's model fixed (bundle; repeatable; default: the "
        "first image when no GCP is given)",
    )
    p.add_argument(
        "--model",
        required=True,
        choices=ADJUST_MODELS,
        metavar="MODEL",
        help="parameter set (" + ", ".join(ADJUST_MODELS) + ")",
    )
    p.add_argument(
        "--set",
        dest="param_set",
        help="parameter set of each image in a bundle adjustment (default rpc-shift)",
    )
    p.add_argument("-o", "--out", required=True, help="adjusted model (JSON sidecar) of IMAGE")
    p.add_argument("--out2", help="adjusted model of IMAGE2 (bundle)")
    p.add_argument("--report", help="directory for adjust_report.json/.md and the residual figure")
    p.add_argument(
        "--vertical",
        choices=VERTICALS,
        default="ellipsoid",
        help="reference of the CSV heights (geoid: EGM96)",
    )
    p.add_argument(
        "--sigma-px",
        type=options.standard_deviation,
        help="a-priori sigma of GCP image coordinates (px) "
        "where the CSV has none; without either sigma is estimated (Pope's tau test)",
    )
    p.add_argument(
        "--sigma-tie-px",
        type=options.standard_deviation,
        help="a-priori sigma of tie points (px; bundle; default "
        f"{BUNDLE_DEFAULTS['sigma_tie_px']})",
    )
    p.add_argument("--alpha", type=float, default=0.001, help="significance level of data snooping")
    p.add_argument("--no-snooping", action="store_true", help="no outlier rejection")
    p.add_argument(
        "--max-iterations",
        type=int,
        default=20,
        help="iterations of the least-squares adjustment at most (default 20; 0: the "
        "initial model's residuals and statistics, nothing estimated)",
    )
    p.add_argument(
        "--regularization", help="lcurve, gcv or a weight: Tikhonov for rank-deficient sets"
    )
    options.add_workers(p, "threads of the tie matching (SIFT) and the least squares (BLAS)")
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def _read_ties(path):
    import numpy as np

    from stereodem.core.errors import InputError

    from .adjust_images import tie_csv_rows

    ix, rows = tie_csv_rows(path, ["col1", "row1", "col2", "row2"])
    try:
        t = np.array([[float(r[k]) for k in ix] for r in rows])
    except (ValueError, IndexError):
        raise InputError(f"{path}: non-numeric or missing tie-point value") from None
    return t.reshape(-1, 4)


def _auto_ties(args, left, right):
    from stereodem.core.errors import InputError

    try:
        from stereodem.stereo.sparse import sparse_matches
    except ImportError:
        raise InputError(
            "--model bundle needs --ties CSV (automatic tie points need stereodem.stereo.sparse)"
        ) from None

    from .pipeline.inputs import open_image

    imgs = [open_image(path, band=b).image for path, b in _pair_inputs(args)]
    m = sparse_matches(imgs[0], imgs[1], left, right)
    log.info("adjust: %d automatic tie points", len(m))
    return m


def run(args) -> int:
    from stereodem.core.errors import InputError
    from stereodem.core.raster import check_writable
    from stereodem.sensor.estimation.adjust import (
        adjust_generic,
        adjust_model,
        bundle_adjust,
        write_report,
    )
    from stereodem.sensor.io.gcps import read_gcps
    from stereodem.sensor.io.sidecar import save_model
    from stereodem.sensor.models.generic import MODEL_NAMES

    from .pipeline.inputs import check_image, image_model

    options.check_common(args)
    n_images = args.model == "bundle" and args.more
    if args.more and args.model != "bundle":
        raise InputError(
            f"--model {args.model} adjusts one image; several images need --model bundle"
        )
    _applicable(args, n_images)
    _check_outputs(args, n_images)
    if not n_images:  # N images: -o is a folder, each model checked by run_bundle_images
        check_writable(args.out, args.overwrite)
    if args.report:
        from .outlock import check_output_folder

        check_output_folder(
            args.report,
            report_products(args, n_images),
            overwrite=args.overwrite,
            inputs=_inputs(args),
        )
    reg = args.regularization
    if reg is not None and reg not in ("lcurve", "gcv"):
        try:
            reg = float(reg)
        except ValueError:
            raise InputError(
                f"--regularization must be lcurve, gcv or a number, got {reg!r}"
            ) from None
    common = dict(
        sigma_px=args.sigma_px,
        snooping=not args.no_snooping,
        alpha=args.alpha,
        max_iterations=args.max_iterations,
    )
    if n_images:
        from .adjust_images import run_bundle_images

        options.say(run_bundle_images(args))
        return 0
    if args.model == "bundle":
        from stereodem.sensor.io.aster_l1a import is_aster_granule

        if reg is not None:
            raise InputError(
                "--regularization is not available for --model bundle: fix its rank "
                "defects with GCPs, or free fewer parameters (--set)"
            )
        if not (args.image2 or is_aster_granule(args.image)) or not args.out2:
            raise InputError("--model bundle needs IMAGE2 (or an ASTER granule) and --out2")
        check_writable(args.out2, args.overwrite)
        left, right = (image_model(path, band=b) for path, b in _pair_inputs(args))
        gcps = tuple(
            read_gcps(p, vertical=args.vertical) if p else None for p in (args.gcps, args.gcps2)
        )
        if args.match:
            from .adjust_images import match_ties

            paths = [p for p, _ in _pair_inputs(args)]
            if paths[0] == paths[1]:
                raise InputError("--match needs two image files (not one ASTER granule)")
            got = match_ties(args.match, paths, [left, right])
            ties = got[(0, 1)]
        else:
            ties = _read_ties(args.ties) if args.ties else _auto_ties(args, left, right)
        res = bundle_adjust(
            left,
            right,
            ties,
            names=(args.param_set, args.param_set),
            gcps=gcps,
            sigma_tie_px=args.sigma_tie_px,
            **common,
        )
        saves = [(res.left, args.out), (res.right, args.out2)]
        summary = (
            f"bundle ({args.param_set}): {len(res.tie_rejected)} ties "
            f"({int(res.tie_rejected.sum())} rejected), tie RMSE {res.tie_rmse_px:.3f} px, "
            f"ray gap {res.parallax_before.get('ray_gap_rms_m', float('nan')):.2f} -> "
            f"{res.parallax_after.get('ray_gap_rms_m', float('nan')):.2f} m RMS"
        )
    else:
        if not args.gcps:
            raise InputError(f"--model {args.model} needs --gcps CSV")
        pts = read_gcps(args.gcps, vertical=args.vertical)
        if args.model in MODEL_NAMES:
            model = _model_if_any(args.image, args.band)
            # the fitted model describes the image's pixels: without a model, its header's
            # size (not the GCPs' extent, which ortho then refused as the image's model)
            size = (
                (model.width, model.height)
                if model is not None
                else check_image(args.image, band=args.band)
            )
            res = adjust_generic(
                args.model,
                pts,
                image_size=size,
                regularization="auto" if reg is None else reg,
                **common,
            )
        else:
            res = adjust_model(
                image_model(args.image, band=args.band),
                pts,
                args.model,
                regularization=reg,
                **common,
            )
        saves = [(res.model, args.out)]
        summary = (
            f"{args.model}: sigma0 {res.sigma0:.3f}, GCP RMSE {options.rmse_px(res.gcp_rmse_px)}, "
            f"check RMSE {options.rmse_px(res.check_rmse_px, 'n/a (no check point)')}, outliers: "
            f"{', '.join(o['id'] for o in res.outliers) or 'none'}; {res.parameters_text()}"
        )
    with report_folder(args, n_images) as rep:
        for model, path in saves:
            save_model(model, path, overwrite=args.overwrite)
        if rep is not None:
            write_report(res, rep, overwrite=True)
    options.say(summary)
    return 0


def _report_names(args, n_images) -> list[str]:
    """The files ``--report`` writes (:func:`stereodem.sensor.estimation.adjust.write_report`):
    the report and one residual figure per image."""
    if n_images:
        figures = [f"adjust_residuals_image{k}.png" for k in range(2 + len(args.more))]
    elif args.model == "bundle":
        figures = ["adjust_residuals_left.png", "adjust_residuals_right.png"]
    else:
        figures = ["adjust_residuals.png"]
    return ["adjust_report.json", "adjust_report.md", *figures]


def _model_outputs(args, n_images) -> list:
    """The adjusted models' files (``-o``, ``--out2``; N images: one per image in ``-o``)."""
    if n_images:
        images = [p for p in (args.image, args.image2, *(args.more or [])) if p]
        return [Path(args.out) / f"{Path(p).stem}.model.json" for p in images]
    return [p for p in (args.out, args.out2 if args.model == "bundle" else None) if p]


def _inputs(args) -> list:
    """The input files: images, their model sidecars, GCP, tie and match files."""
    from stereodem.sensor.io.sidecar import sidecar_path

    images = [p for p in (args.image, args.image2, *(args.more or [])) if p]
    sidecars = [s for s in map(sidecar_path, images) if s.exists()]
    tables = [args.gcps, args.gcps2, args.ties, *(args.match or [])]
    tables += [t.partition("=")[2] for t in args.image_gcps or []]
    return [*images, *sidecars, *tables]


def report_products(args, n_images):
    """What ``--report`` writes into its folder (:func:`_report_names`; the report marks the
    folder as an adjustment's), and the adjusted models that ``-o`` puts there too."""
    from .outlock import Products

    report = Path(args.report).resolve()
    models = [
        Path(p).name for p in _model_outputs(args, n_images) if Path(p).resolve().parent == report
    ]
    return Products((*_report_names(args, n_images), *models), markers=("adjust_report.json",))


def report_folder(args, n_images):
    """The ``--report`` folder, locked while the models and the report are written (their
    previous versions removed with ``--overwrite``): yields its path, or None without
    ``--report``."""
    import contextlib

    from .outlock import output_folder

    if not args.report:
        return contextlib.nullcontext()
    return output_folder(
        args.report,
        report_products(args, n_images),
        overwrite=args.overwrite,
        inputs=_inputs(args),
    )


def _check_outputs(args, n_images):
    """Before any work: no output is one of the inputs (an image, its model sidecar, a GCP,
    tie or match file), even with --overwrite, and no two outputs are one file (-o and
    --out2: the second model replaced the first)."""
    from stereodem.core.errors import InputError

    from .outlock import check_not_an_input

    outputs = _model_outputs(args, n_images)
    if args.report:
        outputs += [Path(args.report) / n for n in _report_names(args, n_images)]
    check_not_an_input(outputs, _inputs(args))
    seen = {}
    for out in [] if n_images else outputs:  # N images: two with one stem are refused later
        key = Path(out).resolve()
        if key in seen:
            raise InputError(f"{out}: given twice as an output (also as {seen[key]})")
        seen[key] = out


def _pair_inputs(args):
    """(path, band) of the two images of a bundle: IMAGE and IMAGE2, or a granule's 3N and 3B."""
    if args.image2:
        return [(args.image, args.band), (args.image2, args.band)]
    return [(args.image, "3N"), (args.image, "3B")]


def _model_if_any(image, band):
    """IMAGE's own sensor model (:func:`stereodem.pipeline.inputs.image_model`: the image
    checked readable), or None when it has none at all (a generic model needs none). A model
    it has but that cannot be read (a garbled ``<stem>.model.json``, bad RPC tags) and a
    missing image are the errors every other command gives: only
    :class:`~stereodem.core.errors.NoSensorModelError` is passed over (before, every
    :class:`SensorModelError` was: a garbled sidecar was ignored without a word)."""
    from stereodem.core.errors import NoSensorModelError

    from .pipeline.inputs import image_model

    try:
        return image_model(image, band=band)
    except NoSensorModelError:
        return None
