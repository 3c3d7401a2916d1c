"""Command-line options shared by several commands, with one meaning everywhere.

``--res`` is the output posting in the output CRS's units in every command (metres for the
default UTM grids); ``--workers``, ``--overwrite`` and the DEM vertical-reference options are
spelled and checked once here.
"""

from __future__ import annotations

import argparse
import logging
import math

from stereodem.core.errors import InputError

from .progress import stage_bar


def add_res(p, default_text: str):
    p.add_argument(
        "--res",
        type=float,
        metavar="RES",
        help=f"output posting in the output CRS's units, metres for UTM (default: {default_text})",
    )
    p.add_argument("--crs", help="output CRS, e.g. EPSG:32637 (default: the scene's UTM zone)")


def band(text: str):
    """``--band``: a band number, or an ASTER band name (3N, 3B)."""
    t = text.strip()
    if t.isdigit():
        return int(t)
    if t.upper() in ("3N", "3B"):
        return t.upper()
    raise argparse.ArgumentTypeError(f"expected a band number or 3N/3B, got {text!r}")


def heading(text: str) -> float:
    """``--track-angle``: a ground-track heading, degrees clockwise from north (any finite
    number; NaN or infinity would turn the along/cross-track frame into NaN)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a heading in degrees, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(
            f"a heading must be a finite number of degrees, got {text}"
        )
    return value


def standard_deviation(text: str) -> float:
    """An a-priori standard deviation (``--sigma-px``, ``--sigma-tie-px``): the one rule of
    :func:`stereodem.core.stats.check_sigma` (a finite number > 0 whose weight 1/σ² is finite:
    NaN passed a ``<= 0`` check and weighted every observation by NaN, 1e-300 got past this
    type and failed in the adjustment), as a usage error."""
    from stereodem.core.stats import check_sigma

    try:
        float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    try:
        return check_sigma(text, "it")
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def add_track_angle(p, help_text: str):
    """``--track-angle DEG`` (:func:`heading`) of the commands with along/cross-track steps."""
    p.add_argument("--track-angle", type=heading, metavar="DEG", help=help_text)


def add_band(p, default_text="1; 3N/3B in an ASTER granule", *, radiometric: bool = True):
    """``--band`` (and ``--no-radiometric`` for the commands that read the pixels)."""
    p.add_argument("--band", type=band, default=1, help=f"image band (default {default_text})")
    if radiometric:
        p.add_argument(
            "--no-radiometric",
            action="store_true",
            help="ASTER granules: keep the DNs instead of radiance from the radiometric table",
        )


def add_image_model(p, generic_names):
    """``--model``, ``--gcps`` and ``--rpc-direct``: an image's sensor model, one meaning in
    every command that takes it (``ortho``, ``uncertainty``; the rule itself is
    :func:`stereodem.pipeline.inputs.chosen_model`). ``generic_names``: the fitted models'
    names (:data:`stereodem.sensor.choices.GENERIC_MODEL_NAMES`)."""
    p.add_argument(
        "--model",
        default="auto",
        metavar="MODEL",
        help="sensor model: auto (the image's physical sidecar, else its RPCs), rpc, "
        "physical, a model file (e.g. OUT.model.json from 'stereodem adjust'), or "
        f"a generic model fitted to --gcps: {', '.join(generic_names)} (default auto)",
    )
    p.add_argument("--gcps", help="GCP CSV (id,lon,lat,h,col,row[,role]) for the generic models")
    p.add_argument(
        "--rpc-direct",
        action="store_true",
        help="localise RPCs with the file's direct model instead of the exact inverse",
    )


def add_workers(p, what="worker processes for the stereo tiles"):
    """``--workers N``: the command's one thread budget (:mod:`stereodem.core.threads`):
    :func:`stereodem.cli.main` pins the process's OpenCV, BLAS/OpenMP and GDAL threads, and
    the row blocks of :mod:`stereodem.core.blocks`, to N (at most the cores) around the
    command; ``what`` says what else N counts in the command (its pool's processes)."""
    p.add_argument("--workers", type=int, help=f"{what} (default: all cores)")


def check_workers(args):
    """``--workers`` at least 1 (refused before any work: :func:`stereodem.cli.main`)."""
    workers = getattr(args, "workers", None)
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")


def add_creation_options(p, *, float_products: bool = True):
    """``--co KEY=VALUE``; ``float_products``: the command's products include float32 rasters
    (its options are then checked against them before any work:
    :func:`stereodem.core.raster.check_creation_options`)."""
    p.set_defaults(co_float_products=float_products)
    p.add_argument(
        "--co",
        action="append",
        metavar="KEY=VALUE",
        default=[],
        help="GDAL creation option of the GeoTIFF products, repeatable (as GDAL's -co), "
        "e.g. --co COMPRESS=ZSTD (default: COG, DEFLATE, predictor by data type)",
    )


def creation_options(args):
    """The ``--co`` options as a dict (None when none were given; :func:`stereodem.cli.main`
    has checked them against GDAL's COG driver before the command ran:
    :func:`stereodem.core.raster.check_creation_options`)."""
    from stereodem.core.raster import parse_creation_options

    return parse_creation_options(getattr(args, "co", None)) or None


#: the one help text of ``--overwrite`` (the policy: :func:`stereodem.outlock.check_output_folder`
#: for output folders, :func:`stereodem.core.raster.check_writable` for output files)
OVERWRITE_HELP = (
    "replace the outputs of a previous run (in an output folder only the command's own "
    "products: the folder's other files and the inputs are never touched; the previous "
    "outputs are kept until this run has written its own, and put back if it fails before; "
    "default: refuse an existing output and a non-empty output folder)"
)


def add_overwrite(p):
    """``--overwrite``, with one meaning and one help text in every command."""
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)


def add_cloud_grow(p):
    """``--cloud-grow N``: how many cells the cloud mask is grown by (``filter``, ``stack``)."""
    p.add_argument(
        "--cloud-grow",
        type=int,
        default=3,
        metavar="N",
        help="grow the cloud mask by N cells (default 3)",
    )


def geotiff_output(path, what: str):
    """``path`` as the GeoTIFF file a command writes (``-o`` of ``filter``, ``ortho``,
    ``mosaic``): named ``.tif``/``.tiff``, else an :class:`InputError` (a file named ``o3413``
    was written as a GeoTIFF nothing recognises by its name; the side-cars, e.g. the edit
    mask ``NAME_edit_mask.tif``, are named from it)."""
    from pathlib import Path

    out = Path(path)
    # an existing folder is left to the overwrite policy's check, which says what it is
    if out.suffix.lower() not in (".tif", ".tiff") and not out.is_dir():
        raise InputError(f"{out}: the {what} is a GeoTIFF; name it .tif")
    return out


def check_common(args):
    """Range checks of the shared options, before any work starts."""
    res = getattr(args, "res", None)
    if res is not None and not res > 0:
        raise InputError(f"--res must be positive, got {res:g}")
    check_workers(args)
    from stereodem.core.grid import map_crs

    for key in ("crs", "checkpoints_crs"):
        if getattr(args, key, None) is not None:
            map_crs(getattr(args, key), "--" + key.replace("_", "-"))


def progress_bar(stage: str):
    """The progress bar of ``stage`` (:data:`stereodem.progress.STAGES`), silent with -q."""
    return stage_bar(stage, enabled=not quiet())


def quiet() -> bool:
    """Whether -q asked for errors only (the root logger above WARNING): result lines too
    are left out."""
    return logging.getLogger().getEffectiveLevel() > logging.WARNING


def say(message: str):
    """A result line for the user on standard output (what was written, headline figures),
    unless -q; logs and progress go to standard error."""
    if not quiet():
        print(message)


def posting(grid) -> str:
    """A result line's cell size with its CRS's unit (:attr:`stereodem.core.grid.MapGrid.
    posting_text`): ``"30 m"``, ``"0.000833°"``."""
    return grid.posting_text


def rmse_px(value, none: str = "n/a") -> str:
    """A result line's RMSE in pixels, ``"1.234 px"``, or ``none`` where there is no figure
    (NaN: no check point, no redundancy), rather than "nan px"."""
    import math

    return f"{value:.3f} px" if value is not None and math.isfinite(value) else none
