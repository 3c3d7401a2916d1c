"""Inputs of every command: images (GeoTIFF + RPCs/sidecar, or an ASTER L1A granule's band)
with their sensor models through one layer (:func:`open_image`), the seed DEM, a stereo DEM
with its layers, and the cheap checks of the assessment inputs."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereodem.core.dem import DEM, ELLIPSOID
from stereodem.core.errors import InputError
from stereodem.core.raster import image_dtype, read_image
from stereodem.post.assess import check_checkpoints
from stereodem.sensor.io.aster_l1a import is_aster_granule, open_aster_granule
from stereodem.sensor.io.sidecar import load_image_model, load_model
from stereodem.stereo import sanity

from ..config import Config

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


def open_image(
    path,
    *,
    band=1,
    prefer: str = "physical",
    model_file=None,
    rpc_direct: bool = False,
    radiometric: bool = True,
    granules: dict | None = None,
) -> InputImage:
    """The one input layer: a GeoTIFF (with RPCs or a model sidecar) or an ASTER L1A granule
    (V004 ``.hdf``, V003 ``.zip`` or folder; ``band`` ``"3N"``/``"3B"``, radiance by the
    granule's radiometric table unless ``radiometric`` is false), with its model (or the
    ``model_file``), checked against each other. ``granules`` caches opened granules by path."""
    if is_aster_granule(path):
        key = str(Path(path).resolve())
        g = (granules or {}).get(key) or open_aster_granule(path)
        if granules is not None:
            granules[key] = g
        name = band if isinstance(band, str) else ASTER_STEREO_BANDS[0]
        img = g.read_image(name, radiometric=radiometric)
        model = load_model(model_file) if model_file else g.model(name)
        dtype = np.dtype("float32") if radiometric else g.band(name).dn.dtype
        tags = {
            **g.tags(),
            "ASTER_BAND": str(name).upper(),
            "ASTER_RADIOMETRIC": str(bool(radiometric)),
        }
    else:
        if isinstance(band, str):
            raise InputError(
                f"{path}: band {band!r} names an ASTER band, but this is not an ASTER "
                "granule (give a band number)"
            )
        model = (
            load_model(model_file, rpc_direct=rpc_direct)
            if model_file
            else load_image_model(path, prefer=prefer, rpc_direct=rpc_direct)
        )
        img, dtype, tags = read_image(path, band), image_dtype(path, band), {}
    if img.shape != (model.height, model.width):
        raise InputError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]} but its model "
            f"describes {model.width}x{model.height}"
        )
    sanity.check_texture(img, f"{path}" + (f" band {band}" if isinstance(band, str) else ""))
    return InputImage(img, model, dtype, tags)


def image_model(path, *, band=1, prefer: str = "physical"):
    """The sensor model of an input (the image's sidecar or RPCs, or band ``band`` of an ASTER
    granule), without reading the pixels."""
    if is_aster_granule(path):
        return open_aster_granule(path).model(
            band if isinstance(band, str) else ASTER_STEREO_BANDS[0]
        )
    return load_image_model(path, prefer=prefer)


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
        return tuple(f"{left} ({b})" for b in ASTER_STEREO_BANDS)
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
        )
        if p
    ]
