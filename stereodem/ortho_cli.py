"""``stereodem ortho``: orthorectify an image onto a DEM (backward DRM projection)."""
from __future__ import annotations

import argparse
import logging
import sys

log = logging.getLogger(__name__)

GENERIC = ["poly2d-1", "poly2d-2", "poly2d-3", "poly3d-1", "poly3d-2", "poly3d-3", "relief-1",
           "relief-2", "projective", "projective-pushbroom", "dlt", "edlt", "rational-1",
           "rational-2", "rational-3"]

EXAMPLES = """examples:
  stereodem ortho left.tif --dem dem.tif -o left_ortho.tif
  stereodem ortho img.tif --dem srtm.tif --dem-vertical geoid --res 0.5 --resampling cubic -o ortho.tif
  stereodem ortho img.tif --dem dem.tif --model rational-2 --gcps points.csv -o ortho.tif
  stereodem ortho img.tif --dem dem.tif --layers incidence,occlusion -o ortho.tif
"""


def add_parser(sub):
    p = sub.add_parser("ortho", help="orthorectify an image onto a DEM",
                       description="Orthorectify IMAGE by backward projection of a north-up map grid "
                                   "through its sensor model onto the DEM (UTM and the image GSD by "
                                   "default). Optional layers are written beside the output as "
                                   "<output stem>_<layer>.tif.",
                       epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", help="image GeoTIFF (with RPCs or a <stem>.model.json sidecar)")
    p.add_argument("--dem", required=True, help="DEM GeoTIFF")
    p.add_argument("-o", "--out", required=True, help="output orthoimage GeoTIFF")
    p.add_argument("--res", type=float, help="posting in metres (default: the image GSD)")
    p.add_argument("--crs", help="output CRS, e.g. EPSG:32637 (default: the UTM zone of the image)")
    from stereodem.ortho.drm import RESAMPLING
    p.add_argument("--resampling", choices=sorted(RESAMPLING), default="bilinear",
                   help="interpolation kernel (lanczos: 8x8 Lanczos, closest to the band-limited signal)")
    p.add_argument("--dem-vertical", choices=["geoid", "ellipsoid"],
                   help="vertical reference of the DEM heights when the file does not say")
    p.add_argument("--model", default="auto", choices=["auto", "rpc", "physical"] + GENERIC,
                   help="sensor model: the image's physical sidecar or RPC (auto), or a generic "
                        "model fitted to --gcps")
    p.add_argument("--gcps", help="GCP CSV (id,lon,lat,h,col,row[,role]) for the generic models")
    p.add_argument("--layers", default="", help="comma-separated extra layers: incidence,occlusion")
    p.add_argument("--band", type=int, default=1, help="image band (default 1)")
    p.add_argument("--workers", type=int, help="threads for the row blocks (default: all cores)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.set_defaults(run=run)
    return p


def _load_model(args):
    from stereodem.sensor.errors import InputError, SensorModelError
    if args.model in GENERIC:
        if not args.gcps:
            raise InputError(f"--model {args.model} needs --gcps CSV")
        from stereodem.sensor.io.gcps import read_gcps
        from stereodem.sensor.models.generic import fit_model
        pts = read_gcps(args.gcps)
        gcp = pts.select("gcp") if "gcp" in set(pts.role) else pts
        chk = pts.select("check")
        model, report = fit_model(args.model, *gcp.arrays(),
                                  check=chk.arrays() if len(chk) else None)
        print(f"{args.model}: {report.n_gcp} GCPs, {report.n_check} check points; GCP RMSE "
              f"{report.gcp_rmse:.3f} px, check RMSE {report.check_rmse:.3f} px", file=sys.stderr)
        return model
    if args.gcps:
        raise InputError("--gcps is only used with a generic --model (poly2d-1 ... rational-3)")
    try:
        from stereodem.sensor.io.sidecar import load_image_model
    except ImportError:                                   # pragma: no cover - partial builds
        load_image_model = None
    if args.model == "rpc" or load_image_model is None:
        from stereodem.sensor.errors import RPCError
        from stereodem.sensor.models.rpc import RPCModel
        try:
            return RPCModel.from_file(args.image)
        except RPCError as exc:
            raise SensorModelError(f"{args.image}: no RPC model ({exc})") from None
    model = load_image_model(args.image, prefer="physical")
    if args.model == "physical" and type(model).__name__ == "RPCModel":
        raise SensorModelError(f"{args.image}: no physical model sidecar (<stem>.model.json)")
    return model


def _read_image(path, band):
    import numpy as np
    import rasterio
    from stereodem.sensor.errors import InputError
    try:
        with rasterio.open(path) as ds:
            if band < 1 or band > ds.count:
                raise InputError(f"{path}: no band {band} (the image has {ds.count})")
            arr = ds.read(band, masked=True)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"{path}: cannot read the image ({exc})") from None
    return np.ma.asarray(arr)


def run(args) -> int:
    from pathlib import Path

    from stereodem.ortho.drm import orthorectify
    from stereodem.sensor.geo.dem import DEM
    from stereodem.sensor.errors import InputError
    from stereodem.sensor.io.raster import check_writable, write_geotiff

    layers = [s.strip() for s in args.layers.split(",") if s.strip()]
    bad = set(layers) - {"incidence", "occlusion"}
    if bad:
        raise InputError(f"unknown layer(s) {', '.join(sorted(bad))}; choose incidence, occlusion")
    out = Path(args.out)
    check_writable(out, args.overwrite)
    layer_paths = {name: out.with_name(f"{out.stem}_{name}.tif") for name in layers}
    for p in layer_paths.values():
        check_writable(p, args.overwrite)
    model = _load_model(args)
    image = _read_image(args.image, args.band)
    dem = DEM.from_file(args.dem, vertical=args.dem_vertical)
    try:
        from stereodem.progress import Progress
        bar = Progress("ortho", 1, enabled=log.getEffectiveLevel() <= logging.WARNING)
    except ImportError:                                   # pragma: no cover
        bar = None
    import os
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be at least 1, got {args.workers}")
    ortho = orthorectify(image, model, dem, res=args.res, crs=args.crs, resampling=args.resampling,
                         strict_dem=True, progress=bar, threads=args.workers or os.cpu_count() or 1)
    if bar is not None:
        bar.close()
    ortho.write(out, overwrite=args.overwrite)
    rep = ortho.report()
    print(f"wrote {out}: {rep['width']}x{rep['height']} cells of {rep['res_m']:g} m in {rep['crs']}, "
          f"{100 * rep['valid_fraction']:.1f}% valid; map interpolation error "
          f"{rep['interpolation_error_px']:.2g} px (measured)")
    if "incidence" in layers:
        from stereodem.ortho.layers import incidence_angle
        write_geotiff(layer_paths["incidence"], incidence_angle(ortho, model), ortho.transform,
                      ortho.crs, float("nan"), overwrite=args.overwrite)
        print(f"wrote {layer_paths['incidence']}: local incidence angle (deg)")
    if "occlusion" in layers:
        from stereodem.ortho.layers import occlusion_mask
        occ = occlusion_mask(ortho, model)
        write_geotiff(layer_paths["occlusion"], occ.astype("uint8"), ortho.transform, ortho.crs, 255,
                      overwrite=args.overwrite)
        print(f"wrote {layer_paths['occlusion']}: occlusion mask (1 = hidden, {100 * occ.mean():.2f}%)")
    return 0
