"""``stereodem ortho``: orthorectify an image onto a DEM (backward DRM projection)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from stereodem.core.vertical import VERTICALS
from stereodem.ortho.choices import RESAMPLINGS
from stereodem.sensor.choices import GENERIC_MODEL_NAMES

from . import options
from .commands import help_line

log = logging.getLogger(__name__)

#: the generic models `ortho --model` fits to --gcps (the library's names)
GENERIC = GENERIC_MODEL_NAMES

EXAMPLES = """examples:
  stereodem ortho left.tif --dem dem.tif -o left_ortho.tif
  stereodem ortho img.tif --dem srtm.tif --dem-vertical geoid --res 0.5 --resampling cubic \\
      -o ortho.tif
  stereodem ortho img.tif --dem dem.tif --model rational-2 --gcps points.csv -o ortho.tif
  stereodem ortho img.tif --dem dem.tif --layers incidence,occlusion -o ortho.tif
  stereodem ortho AST_L1A_00307312017190728_20250708114426.hdf --band 3B --dem dem.tif -o 3B.tif
"""


def add_parser(sub):
    p = sub.add_parser(
        "ortho",
        help=help_line("ortho"),
        description="Orthorectify IMAGE by backward projection of a north-up map grid "
        "through its sensor model onto the DEM (UTM and the image GSD by "
        "default). Optional layers are written beside the output as "
        "<output stem>_<layer>.tif.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "image",
        help="image GeoTIFF (with RPCs or a <stem>.model.json sidecar), or an "
        "ASTER L1A granule (choose the band with --band 3N|3B)",
    )
    p.add_argument("--dem", required=True, help="DEM GeoTIFF")
    p.add_argument("-o", "--out", required=True, help="output orthoimage GeoTIFF")
    options.add_res(p, "the image GSD")
    p.add_argument(
        "--resampling",
        choices=RESAMPLINGS,
        default="bilinear",
        help="interpolation kernel (lanczos: 8x8 Lanczos, closest to the band-limited signal)",
    )
    p.add_argument(
        "--dem-vertical",
        choices=VERTICALS,
        help="vertical reference of the DEM heights when the file does not say",
    )
    options.add_image_model(p, GENERIC)
    p.add_argument("--layers", default="", help="comma-separated extra layers: incidence,occlusion")
    options.add_band(p, "1; 3N in an ASTER granule")
    p.add_argument(
        "--fill-dem",
        metavar="OTHER.tif",
        help="second DEM for the cells the DEM has no height for (holes, partial coverage)",
    )
    p.add_argument(
        "--fill-dem-vertical",
        choices=VERTICALS,
        help="vertical reference of --fill-dem when the file does not say",
    )
    options.add_workers(p, "threads for the row blocks")
    p.add_argument(
        "--float",
        action="store_true",
        help="write float32 values instead of the image's own data type",
    )
    options.add_creation_options(p, float_products=False)  # the image's type, unless --float
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def _open(args):
    """The image and its model as ``--model`` chooses it
    (:func:`stereodem.pipeline.inputs.chosen_model`, the rule ``uncertainty`` shares); returns
    an :class:`stereodem.pipeline.inputs.InputImage`."""
    from .pipeline.inputs import chosen_model, open_image

    chosen = chosen_model(
        args.image, args.model, band=args.band, rpc_direct=args.rpc_direct, gcps=args.gcps
    )
    if chosen.note:
        options.say(chosen.note)
    return open_image(
        args.image,
        band=args.band,
        model=chosen.model,
        radiometric=not args.no_radiometric,
    )


def config_from_args(args):
    from .config import Config, InputSettings, OrthoSettings, RunSettings, validate

    cfg = Config(
        inputs=InputSettings(
            left=args.image, band=args.band, dem=args.dem, dem_vertical=args.dem_vertical
        ),
        output_dir=str(args.out),
        ortho=OrthoSettings(
            resampling=args.resampling,
            res=args.res,
            crs=args.crs,
            fill_dem=args.fill_dem,
            fill_dem_vertical=args.fill_dem_vertical,
        ),
        run=RunSettings(workers=args.workers, overwrite=args.overwrite),
    )
    validate(cfg, "command line")
    return cfg


def run(args) -> int:
    from stereodem.core.dem import DEM
    from stereodem.core.errors import InputError
    from stereodem.core.raster import check_writable, write_geotiff

    from .pipeline.stages import ortho_stage

    options.check_common(args)
    layers = [s.strip() for s in args.layers.split(",") if s.strip()]
    bad = set(layers) - {"incidence", "occlusion"}
    if bad:
        raise InputError(f"unknown layer(s) {', '.join(sorted(bad))}; choose incidence, occlusion")
    out = options.geotiff_output(args.out, "orthoimage")
    cfg = config_from_args(args)
    from stereodem.ortho.layers import LAYERS, layer_path, remove_stale_layers

    layer_paths = {name: layer_path(out, name) for name in layers}
    from stereodem.sensor.io.sidecar import sidecar_path

    from .outlock import check_not_an_input

    model_file = args.model if args.model not in GENERIC and Path(args.model).is_file() else None
    check_not_an_input(
        [out, *layer_paths.values()],
        [args.image, args.dem, args.gcps, model_file, sidecar_path(args.image)],
    )
    check_writable(out, args.overwrite)
    for p in layer_paths.values():
        check_writable(p, args.overwrite)
    src = _open(args)
    image, model = src.image, src.model
    dem = DEM.from_file(args.dem, vertical=args.dem_vertical)
    bar = options.progress_bar("ortho")
    ortho = ortho_stage(cfg, [("image", image, model)], dem, progress=bar)["image"]
    bar.close()
    co = options.creation_options(args)
    ortho.write(
        out,
        overwrite=args.overwrite,
        creation_options=co,
        tags=src.tags,
        dtype=None if args.float else src.dtype,
    )
    if args.overwrite:  # an earlier run's layers not made now would pass for this one's
        for p in remove_stale_layers(out, keep=layers):
            options.say(f"removed {p}: a layer of the orthoimage {out} replaced")
    rep = ortho.report()
    options.say(
        f"wrote {out}: {rep['width']}x{rep['height']} cells of {options.posting(ortho.grid)} in "
        f"{rep['crs']}, {100 * rep['valid_fraction']:.1f}% valid; map interpolation error "
        f"{rep['interpolation_error_px']:.2g} px (measured)"
    )
    if "incidence" in layers:
        from stereodem.ortho.layers import incidence_angle

        write_geotiff(
            layer_paths["incidence"],
            incidence_angle(ortho, model),
            ortho.transform,
            ortho.crs,
            float("nan"),
            overwrite=args.overwrite,
            creation_options=co,
            descriptions=[LAYERS["incidence"]],
            units=["degree"],
        )
        options.say(f"wrote {layer_paths['incidence']}: local incidence angle (deg)")
    if "occlusion" in layers:
        from stereodem.ortho.layers import occlusion_mask

        occ = occlusion_mask(ortho, model)
        write_geotiff(
            layer_paths["occlusion"],
            occ.astype("uint8"),
            ortho.transform,
            ortho.crs,
            255,
            overwrite=args.overwrite,
            creation_options=co,
            descriptions=[LAYERS["occlusion"]],
            units=["1"],
        )
        options.say(
            f"wrote {layer_paths['occlusion']}: occlusion mask (1 = hidden, "
            f"{100 * occ.mean():.2f}%)"
        )
    return 0
