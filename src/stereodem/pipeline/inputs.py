"""Inputs of every command: images (GeoTIFF + RPCs/sidecar, or an ASTER L1A granule's band)
with their sensor models through one layer (:func:`open_image`), the seed DEM, a stereo DEM
with its layers, and the cheap checks of the assessment inputs."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereodem.core import raster
from stereodem.core.dem import DEM, ELLIPSOID
from stereodem.core.errors import InputError, not_found
from stereodem.core.raster import image_dtype, image_shape, read_image
from stereodem.post.assess import check_checkpoints
from stereodem.sensor.io.aster_l1a import is_aster_granule, open_aster_granule
from stereodem.sensor.io.sidecar import load_image_model, load_model, sidecar_path
from stereodem.stereo import sanity

from ..config import Config
from ..options import rmse_px

log = logging.getLogger(__name__)


@dataclass
class Pair:
    """The loaded stereo pair: images (float32, NaN = no data), their models, the seed DEM."""

    left_image: np.ndarray
    right_image: np.ndarray
    left_model: object
    right_model: object
    seed_dem: DEM | None = None
    left_dtype: np.dtype = np.dtype("float32")
    right_dtype: np.dtype = np.dtype("float32")
    tags: dict = field(default_factory=dict)


@dataclass
class InputImage:
    """One input image as every stage sees it: float32 values (NaN = no data), its sensor
    model, the stored data type and metadata tags (an ASTER granule's acquisition time, ...)."""

    image: np.ndarray
    model: object
    dtype: np.dtype
    tags: dict = field(default_factory=dict)


ASTER_STEREO_BANDS = ("3N", "3B")


def aster_band(band) -> str:
    """The band of an ASTER granule that ``band`` (a ``--band``) names: ``"3N"``/``"3B"``, or
    for a band number (the GeoTIFF default, 1) the granule's first stereo band, 3N."""
    return band if isinstance(band, str) else ASTER_STEREO_BANDS[0]


def image_name(path, band=1, *, name=None) -> str:
    """An input image as named to the user (reports, figures): ``name`` (default: the path)
    and, for an ASTER granule, the band read from it (:func:`aster_band`): ``"G.hdf (3N)"``."""
    label = str(path) if name is None else str(name)
    return f"{label} ({aster_band(band)})" if is_aster_granule(path) else label


def open_image(
    path,
    *,
    band=1,
    prefer: str = "physical",
    model_file=None,
    rpc_direct: bool = False,
    radiometric: bool = True,
    granules: dict | None = None,
    model=None,
) -> InputImage:
    """The one input layer: a GeoTIFF (with RPCs or a model sidecar) or an ASTER L1A granule
    (V004 ``.hdf``, V003 ``.zip`` or folder; ``band`` ``"3N"``/``"3B"``, radiance by the
    granule's radiometric table unless ``radiometric`` is false), with its model (or the
    ``model_file``, or ``model`` itself, e.g. :func:`chosen_model`'s), checked against each
    other. ``granules`` caches opened granules by path."""
    if is_aster_granule(path):
        key = str(Path(path).resolve())
        g = (granules or {}).get(key) or open_aster_granule(path)
        if granules is not None:
            granules[key] = g
        name = aster_band(band)
        img = g.read_image(name, radiometric=radiometric)
        if model is None:
            model = load_model(model_file) if model_file else g.model(name)
        dtype = np.dtype("float32") if radiometric else g.band(name).dn.dtype
        tags = {
            **g.tags(),
            "ASTER_BAND": str(name).upper(),
            "ASTER_RADIOMETRIC": str(bool(radiometric)),
        }
    else:
        _check_band_number(path, band)
        if model is None:
            model = (
                load_model(model_file, rpc_direct=rpc_direct)
                if model_file
                else load_image_model(path, prefer=prefer, rpc_direct=rpc_direct)
            )
        img, dtype, tags = read_image(path, band), image_dtype(path, band), {}
    check_model_size(path, (img.shape[1], img.shape[0]), model)
    sanity.check_texture(img, f"{path}" + (f" band {band}" if isinstance(band, str) else ""))
    return InputImage(img, model, dtype, tags)


def _check_band_number(path, band):
    """A GeoTIFF's band is a number: an ASTER band name is refused (the image is no granule)."""
    if isinstance(band, str):
        raise InputError(
            f"{path}: band {band!r} names an ASTER band, but this is not an ASTER "
            "granule (give a band number)"
        )


def check_image(path, *, band=1) -> tuple[int, int] | None:
    """Before any work, the input checks of :func:`open_image` that need no pixel read, for
    the commands that use an image's sensor model only (``adjust``, ``compare-models``,
    ``uncertainty``): the GeoTIFF opens with its band and its first and last blocks decode
    (:func:`stereodem.core.raster.check_image`, worded as every image and DEM reader words a
    file it cannot read: "PATH: cannot read the image (...)"). Without it a zero-byte or
    text file beside a model sidecar passed: those commands read the sidecar alone. Its size
    is not checked against the model (an image stand-in carrying only RPCs may be smaller).
    An ASTER granule is checked by its reader when its band's model is read from it (not
    opened a second time here): None. Returns the GeoTIFF's ``(width, height)``."""
    if is_aster_granule(path):
        return None
    _check_band_number(path, band)
    return raster.check_image(path, band)


def check_model_size(path, size, model):
    """An image of ``size`` (width, height) and its model must describe the same pixels."""
    if tuple(size) != (model.width, model.height):
        raise InputError(
            f"{path}: image is {size[0]}x{size[1]} but its model "
            f"describes {model.width}x{model.height}"
        )


@dataclass
class ChosenModel:
    """An image's sensor model as a command's ``--model`` chose it (:func:`chosen_model`):
    the model, the model file it was read from (None: the image's own), and a result line
    for the user (a fitted model's residuals; None otherwise)."""

    model: object
    model_file: str | None = None
    note: str | None = None


def chosen_model(
    path, choice: str = "auto", *, band=1, rpc_direct: bool = False, gcps=None
) -> ChosenModel:
    """The one rule of the commands that take an image's model by ``--model`` (``ortho``,
    ``uncertainty``): ``auto`` (the image's ``<stem>.model.json`` sidecar, else its RPCs; an
    ASTER granule's band model), ``rpc`` (the RPCs, even beside a sidecar), ``physical`` (the
    sidecar, refused without one), a model file (e.g. ``stereodem adjust``'s ``-o``), or a
    generic model (:data:`stereodem.sensor.choices.GENERIC_MODEL_NAMES`) fitted to the GCPs
    of ``gcps``; ``rpc_direct`` localises RPCs with their file's direct model. Errors are
    one-line :class:`InputError`/:class:`SensorModelError` naming the file or the option."""
    from stereodem.core.errors import SensorModelError
    from stereodem.sensor.choices import GENERIC_MODEL_NAMES
    from stereodem.sensor.models.rpc import RPCModel

    choice = str(choice)
    if choice in GENERIC_MODEL_NAMES:
        return _fitted_model(path, choice, band=band, gcps=gcps)
    if gcps:
        raise InputError(
            f"--gcps is only used with a generic --model ({GENERIC_MODEL_NAMES[0]} ... "
            f"{GENERIC_MODEL_NAMES[-1]})"
        )
    if choice in ("auto", "physical", "rpc"):
        if is_aster_granule(path):
            if choice == "rpc":
                raise InputError(f"{path}: an ASTER granule has no RPCs (--model auto)")
            return ChosenModel(image_model(path, band=band))
        if not Path(path).exists():
            raise SensorModelError(not_found(path, "image"))
        if choice == "physical" and not sidecar_path(path).exists():
            raise SensorModelError(f"{path}: no physical model sidecar ({sidecar_path(path).name})")
        model = load_image_model(
            path, prefer="rpc" if choice == "rpc" else "physical", rpc_direct=rpc_direct
        )
        if choice == "physical" and isinstance(model, RPCModel):
            raise SensorModelError(f"{path}: no physical model sidecar (<stem>.model.json)")
        return ChosenModel(model)
    if Path(choice).is_file():
        return ChosenModel(load_model(choice, rpc_direct=rpc_direct), model_file=choice)
    raise InputError(
        f"--model {choice!r}: not auto, rpc, physical, a generic model name or an existing "
        "model file"
    )


def _fitted_model(path, name, *, band, gcps) -> ChosenModel:
    """A generic model fitted to the GCPs of ``gcps`` over the image's size."""
    from stereodem.sensor.io.gcps import read_gcps
    from stereodem.sensor.models.generic import fit_model

    if not gcps:
        raise InputError(f"--model {name} needs --gcps CSV")
    pts = read_gcps(gcps)
    gcp, chk = pts.select("gcp"), pts.select("check")
    if not len(gcp):
        # fitting the check points instead made them GCPs and check points at once (the
        # "check RMSE" was the GCP RMSE): as adjust, refuse
        raise InputError(
            f"{gcps}: no GCP to fit --model {name}: all {len(pts)} point(s) have role 'check'"
        )
    model, report = fit_model(
        name,
        *gcp.arrays(),
        check=chk.arrays() if len(chk) else None,
        # the image's size (without it the model took the GCPs' extent, and the image's
        # rows and columns beyond the outermost GCPs were left out of the products)
        image_size=image_size(path, band),
    )
    note = (
        f"{name}: {report.n_gcp} GCPs, {report.n_check} check points; GCP RMSE "
        f"{rmse_px(report.gcp_rmse)}, check RMSE "
        f"{rmse_px(report.check_rmse, 'n/a (no check point)')}"
    )
    return ChosenModel(model, note=note)


def image_size(path, band=1) -> tuple[int, int]:
    """``(width, height)`` of an input image (a GeoTIFF's header, or an ASTER granule's
    band), without reading the pixels."""
    if is_aster_granule(path):
        m = open_aster_granule(path).model(aster_band(band))
        return int(m.width), int(m.height)
    return image_shape(path)


def image_model(path, *, band=1, prefer: str = "physical"):
    """The sensor model of an input (the image's sidecar or RPCs, or band ``band`` of an ASTER
    granule), without reading the pixels; a GeoTIFF is checked by :func:`check_image` (the
    image must be readable, not only its model)."""
    if is_aster_granule(path):
        return open_aster_granule(path).model(aster_band(band))
    model = load_image_model(path, prefer=prefer)
    check_image(path, band=band)
    return model


def load_seed_dem(cfg: Config) -> DEM | None:
    """The seed DEM of the configuration (loaded once per job), or None."""
    if not cfg.inputs.seed_dem:
        return None
    return DEM.from_file(cfg.inputs.seed_dem, vertical=cfg.inputs.seed_dem_vertical)


def load_pair(cfg: Config) -> Pair:
    """Both images with their models, and the seed DEM. An ASTER granule given alone (or as
    both images) is its own pair: 3N left, 3B right."""
    i = cfg.inputs
    if not i.left:
        raise InputError("a stereo DEM needs two images ([inputs] left and right)")

    granule = is_aster_granule(i.left)
    right = i.right or (i.left if granule else None)
    if not right:
        raise InputError(f"{i.left}: a stereo DEM needs a second image (or an ASTER granule)")
    same = granule and Path(right).resolve() == Path(i.left).resolve()
    bands = ASTER_STEREO_BANDS if same else (i.band, i.band)
    cache: dict = {}
    kw = dict(prefer=i.model, rpc_direct=i.rpc_direct, radiometric=i.radiometric, granules=cache)
    left = open_image(i.left, band=bands[0], model_file=i.left_model, **kw)
    right = open_image(right, band=bands[1], model_file=i.right_model, **kw)
    seed = load_seed_dem(cfg)
    return Pair(
        left.image,
        right.image,
        left.model,
        right.model,
        seed,
        left.dtype,
        right.dtype,
        {**left.tags, **{f"RIGHT_{k}": v for k, v in right.tags.items()}},
    )


def pair_names(left, right) -> tuple[str, str]:
    """The pair's two images as named to the user (reports, the point cloud's pair list): an
    ASTER granule given alone (or as both images) is its bands, ``"G.hdf (3N)"`` and
    ``"G.hdf (3B)"`` (:func:`load_pair`), not the granule and ``"None"``."""
    if (
        left
        and is_aster_granule(left)
        and (not right or Path(right).resolve() == Path(left).resolve())
    ):
        return tuple(image_name(left, b) for b in ASTER_STEREO_BANDS)
    return str(left), str(right)


def read_stereo_dem(dem_path, *, vertical=None) -> DEM:
    """A stereo DEM written by ``stereodem dem`` with its ``score.tif`` and ``raygap.tif``
    beside it (missing layers are NaN: the filters that need them then keep every cell); an
    unstated vertical reference is stereodem's own, the ellipsoid."""
    dem = DEM.from_file(dem_path, vertical=vertical, layers=("score", "ray_gap"))
    void = np.full(dem.shape, np.nan, np.float32)
    return dataclasses.replace(
        dem,
        vertical=dem.vertical or ELLIPSOID,
        score=void if dem.score is None else dem.score,
        ray_gap=void if dem.ray_gap is None else dem.ray_gap,
    )


def check_inputs(cfg: Config):
    """Cheap checks of the assessment inputs, so that a bad reference DEM or check-point file
    fails the job before the stereo work rather than after it: the reference DEM's header and
    first block (:meth:`DEM.check_file`; the assessment reads it, once, when it needs it: a
    full read here cost ~0.7 s on a 45 M-cell reference, or held it in memory through the
    stereo and ortho stages), the check points read."""
    i = cfg.inputs
    if cfg.assess.enabled and i.reference_dem:
        DEM.check_file(i.reference_dem, vertical=i.reference_vertical)
        if i.checkpoints:
            check_checkpoints(i.checkpoints, crs=i.checkpoints_crs)
        for path in cfg.assess.exclude or ():  # read when the co-registration is fitted
            if not Path(path).is_file():
                raise InputError(not_found(path, "[assess] exclude outlines"))


def input_paths(cfg: Config) -> list:
    """Every input file of a job (none may be among its outputs)."""
    i = cfg.inputs
    return [
        p
        for p in (
            i.left,
            i.right,
            *(i.images or ()),
            i.left_model,
            i.right_model,
            i.seed_dem,
            i.reference_dem,
            i.checkpoints,
            i.landcover,
            i.dem,
            *(cfg.assess.exclude or ()),
        )
        if p
    ]
