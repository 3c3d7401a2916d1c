"""The job's configuration: paths and per-stage settings, from a TOML file or from the command
line, as the same objects (every command builds a :class:`Config` and calls the stages of
:mod:`stereodem.pipeline`).

Sections (every key optional except ``inputs.left``/``inputs.right`` and ``output.dir``;
``docs/configuration.md`` lists every key with its default)::

    [inputs]
    left = "left.tif"              # GeoTIFF with RPC tags/sidecar or <stem>.model.json
    right = "right.tif"
    model = "physical"             # "physical" (sidecar if present) or "rpc"
    seed_dem = "coarse.tif"        # optional: per-tile height ranges, fallback for large holes
    seed_dem_vertical = "geoid"    # when the seed file does not say (SRTM: geoid)
    reference_dem = "ref.tif"      # optional: accuracy assessment
    checkpoints = "points.csv"     # optional: lon,lat,h check points

    [output]
    dir = "out"

    [rectification]                # stereodem.stereo.settings.RectificationSettings
    tile_size = 512
    height_range = [1000, 3500]
    [matching]                     # ... MatchingSettings
    matcher = "ncc"
    [refinement]                   # ... RefinementSettings
    enabled = true
    [gridding]                     # ... GriddingSettings
    res = 30.0                     # output CRS units (metres for UTM)
    geoid = false

    [filters]
    thesis = false                 # the Ok thesis chain instead of the default one
    [fill]
    max_hole_size = 200
    [ortho]
    both = true                    # also the right image, on the same grid
    [assess]
    coregister = true
    [run]
    workers = 2                    # default: all cores
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import os
import typing
from dataclasses import dataclass, field
from pathlib import Path

import tomllib

from stereodem.core.errors import InputError, not_found
from stereodem.core.grid import map_crs
from stereodem.core.raster import as_path, check_creation_options
from stereodem.core.vertical import VERTICALS, Vertical
from stereodem.ortho.choices import RESAMPLINGS, UNCERTAINTY_METHODS, Resampling, UncertaintyMethod
from stereodem.stereo import settings as stereo_settings
from stereodem.stereo.fusion import FusionSettings
from stereodem.stereo.settings import (
    GRIDDING_METHODS,
    JITTER_AXES,
    MATCHERS,
    RECTIFICATION_METHODS,
    GriddingSettings,
    JitterAxes,
    MatchingSettings,
    RectificationSettings,
    RefinementSettings,
    StereoSettings,
)

__all__ = [
    "InputSettings",
    "JitterSettings",
    "UncertaintySettings",
    "FilterSettings",
    "FillSettings",
    "OrthoSettings",
    "AssessSettings",
    "RunSettings",
    "DemSettings",
    "Config",
    "load_config",
    "config_from_dict",
    "SECTIONS",
]


#: the longest per-tile timeout (s, ~31 years; infinity ended in a traceback from the
#: worker's alarm timer: "timestamp out of range for platform time_t")
MAX_TILE_TIMEOUT_S = 1e9

#: OpenCV's int: the whole-number options handed to it (SIFT's feature count, SGBM's
#: parameters) beyond it were "integer won't fit into a C int" in every tile
C_INT_MAX = 2**31 - 1
#: the widest correlation window, pixels (OpenCV's block matcher's bound; wider ones were
#: accepted and matched nothing: "no point was matched in any tile")
MAX_WINDOW = 255
#: the widest smoothing (refinement warp, px; hole-filled DEM, cells): 1e6 px took 10 GB and
#: minutes in one Gaussian kernel, 1e308 was a ValueError
MAX_SMOOTHING = 100.0
#: the largest height margin, m (more than the Earth's relief)
MAX_HEIGHT_MARGIN_M = 10_000.0


@dataclass
class InputSettings:
    """Input files.

    Attributes
    ----------
    left, right : str
        The stereo pair (left = reference image).
    images : list of str, optional
        Two or more images of one scene instead of ``left``/``right``: an N-view DEM, the
        pairs chosen by overlap and base, their DEMs fused ([fusion], :mod:`stereodem.multiview`).
    model : {"physical", "rpc"}
        Prefer the physical-model sidecar ``<stem>.model.json`` when present, or the RPCs.
    rpc_direct : bool
        Localise RPCs with their file's direct (image -> ground) model instead of the exact
        inverse of the projection (the default; see :mod:`stereodem.sensor.models.rpc_direct`).
    left_model, right_model : str, optional
        Sensor-model files overriding the images' own (e.g. from ``stereodem adjust``).
    band : int or str
        Image band used for matching and orthoimages (``"3N"``/``"3B"`` in an ASTER granule;
        a granule given alone is the pair 3N/3B).
    radiometric : bool
        ASTER granules: radiance by the radiometric correction table (L = A V / G + D), or
        the raw DNs.
    seed_dem : str, optional
        Coarse DEM setting each tile's height range (and filling large holes on request).
    seed_dem_vertical : {"geoid", "ellipsoid"}, optional
        Vertical reference of the seed DEM when its file does not say.
    reference_dem : str, optional
        Reference DEM of the accuracy assessment.
    reference_vertical : {"geoid", "ellipsoid"}, optional
    checkpoints : str, optional
        CSV of check points (lon,lat,h or x,y,z).
    checkpoints_crs : str, optional
        CRS of x,y check points.
    checkpoints_vertical : {"geoid", "ellipsoid"}, optional
        Vertical reference of the check-point heights (default: the DEM's).
    landcover : str, optional
        Raster of integer land-cover classes for the per-class statistics.
    dem : str, optional
        An existing DEM (the hand route: ``filter``, ``ortho`` and ``assess`` read it).
    dem_vertical : {"geoid", "ellipsoid"}, optional
        Vertical reference of ``dem`` when its file does not say.
    """

    left: str | None = None
    right: str | None = None
    images: list | None = None
    model: str = "physical"
    rpc_direct: bool = False
    left_model: str | None = None
    right_model: str | None = None
    band: int | str = 1
    radiometric: bool = True
    seed_dem: str | None = None
    seed_dem_vertical: Vertical | None = None
    reference_dem: str | None = None
    reference_vertical: Vertical | None = None
    checkpoints: str | None = None
    checkpoints_crs: str | None = None
    checkpoints_vertical: Vertical | None = None
    landcover: str | None = None
    dem: str | None = None
    dem_vertical: Vertical | None = None


@dataclass
class JitterSettings:
    """Attitude jitter of the right camera (ASTER 3B), MMASTER-style.

    Attributes
    ----------
    enabled : bool
        Estimate the right camera's attitude oscillation (a sum of sines in time) after a
        first DEM, correct the right model with that time-varying attitude and make the DEM
        again (:mod:`stereodem.stereo.jitter`). Needs a pushbroom/ASTER model.
    axes : {"pitch", "roll", "both"}
        ``pitch`` (along track): from the first DEM's residuals against the seed DEM, which
        is then required; ``roll`` (across track): from the matcher's residual vertical
        parallax, no reference DEM needed; ``both``.
    n_sines : int
        Sines in the fitted oscillation.
    min_frequency, max_frequency : float
        Frequency band searched, Hz.
    """

    enabled: bool = False
    axes: JitterAxes = "pitch"
    n_sines: int = 1
    min_frequency: float = 0.2
    max_frequency: float = 8.0

    @property
    def axis_names(self) -> tuple:
        """The estimated axes as a tuple (``("pitch", "roll")`` for ``both``)."""
        return ("pitch", "roll") if self.axes == "both" else (self.axes,)


@dataclass
class FilterSettings:
    """Blunder filters (:func:`stereodem.post.filters.default_chain`).

    Attributes
    ----------
    enabled : bool
    thesis : bool
        The Ok thesis's chain (2-sigma neighbourhood test) instead of the default one.
    erode : int
        Cells removed along the border of the matched area (partial correlation windows).
    """

    enabled: bool = True
    thesis: bool = False
    erode: int = 2


@dataclass
class FillSettings:
    """Hole filling (:func:`stereodem.post.fill.fill_holes`).

    Attributes
    ----------
    enabled : bool
    max_hole_size : int
        Largest hole (cells) filled by inverse-distance weighting.
    fallback : bool
        Fill larger holes from the seed DEM (blended seam).
    smooth_sigma : float
        Gaussian smoothing of the filled DEM, cells (0: none; at most 100).
    """

    enabled: bool = True
    max_hole_size: int = 200
    fallback: bool = False
    smooth_sigma: float = 0.0


@dataclass
class OrthoSettings:
    """Orthoimages (:func:`stereodem.ortho.drm.orthorectify`).

    Attributes
    ----------
    enabled : bool
    both : bool
        Also the right image, on the left image's grid.
    resampling : {"nearest", "bilinear", "cubic", "lanczos"}
    res : float, optional
        Posting in the output CRS's units (metres for UTM; default the image GSD).
    crs : str, optional
        Output CRS (default: the UTM zone of the image).
    fill_dem : str, optional
        A second DEM whose heights are used where the DEM has none (holes, partial coverage);
        ``fill_dem_vertical`` its vertical reference when the file does not say.
    """

    enabled: bool = True
    both: bool = True
    resampling: Resampling = "bilinear"
    res: float | None = None
    crs: str | None = None
    fill_dem: str | None = None
    fill_dem_vertical: Vertical | None = None


@dataclass
class AssessSettings:
    """Accuracy assessment (:func:`stereodem.post.assess.assess_dem`).

    Attributes
    ----------
    enabled : bool
        Assess when a reference DEM is given.
    coregister : bool
        Also after Nuth & Kääb co-registration.
    slope_bins : list of float, optional
        Slope class edges, degrees (default 0, 5, 10, 20, 30, 45, 90).
    elevation_bins : list of float, optional
        Elevation band edges, metres (default: five bands over the DEM's range).
    landcover_names : dict, optional
        Names of the land-cover classes, e.g. {"1" = "forest"}.
    exclude : list of str, optional
        Vector files (any format pyogrio reads, any CRS) whose polygons are left out of the
        stable terrain the co-registration is fitted on (glaciers, landslides, lakes); as
        ``stereodem assess --exclude``.
    """

    enabled: bool = True
    coregister: bool = True
    slope_bins: tuple | None = None
    elevation_bins: tuple | None = None
    landcover_names: dict | None = None
    exclude: list | None = None


@dataclass
class UncertaintySettings:
    """Per-cell uncertainty of the left orthoimage and of the DEM
    (:mod:`stereodem.ortho.uncertainty`).

    Attributes
    ----------
    enabled : bool
        Write ``uncertainty/`` (σ east/north/horizontal, CE90, dominant source, shares) for the
        left orthoimage and ``dem_sigma_vertical.tif`` beside ``dem.tif``.
    sigma : dict, optional
        Independent input σ by name, e.g. {col_shift = 0.5, row_shift = 0.5, dem_height = 5}
        (pixels, metres, or the model parameter's unit).
    covariance : str, optional
        An ``adjust_report.json`` whose parameter covariance is propagated.
    method : {"first-order", "monte-carlo", "fast"}
    samples : int
        Monte Carlo samples (or FAST points per curve), 10..100000.
    """

    enabled: bool = False
    sigma: dict | None = None
    covariance: str | None = None
    method: UncertaintyMethod = "first-order"
    samples: int = 1000


@dataclass
class RunSettings:
    """Execution.

    Attributes
    ----------
    workers : int, optional
        Worker processes for the stereo tiles, and the main process's threads (OpenCV,
        BLAS, GDAL, row blocks: post, ortho, assessment), at most the cores; default all cores.
    tile_timeout : float, optional
        Seconds after which a tile is abandoned and reported.
    resume : bool
        Reuse finished tiles of the same job in ``OUT/tiles``.
    dask : str, optional
        ``dask.distributed`` scheduler address.
    overwrite : bool
        Replace the products of a previous job in the output folder.
    force : bool
        Keep going with a result the sanity checks call suspect (:mod:`stereodem.stereo.sanity`);
        the findings are still reported.
    creation_options : dict, optional
        GDAL creation options of the GeoTIFF products (as ``-co``), e.g. {COMPRESS = "ZSTD"};
        checked against GDAL's COG driver when the configuration is read (an option or value
        GDAL does not know, or one it cannot write the float32 DEMs with, is an error).
    keep_tiles : bool
        Keep the tile cache ``OUT/tiles`` after a job that succeeded, for a later ``--resume``
        (e.g. with other filter, ortho or assessment settings); false removes it once the
        products are written (``--clean-tiles``; a full ASTER granule's cache is ~330 MB, more
        than its products). A failed, interrupted or suspect job keeps it either way.
    """

    workers: int | None = None
    tile_timeout: float | None = 600.0
    resume: bool = False
    dask: str | None = None
    overwrite: bool = False
    force: bool = False
    creation_options: dict | None = None
    keep_tiles: bool = True


@dataclass
class DemSettings:
    """Products of the stereo DEM beside its rasters.

    Attributes
    ----------
    point_cloud : {"las", "laz"}, optional
        Also write the intersected points as ``dem.las`` / ``dem.laz`` (laspy; LAZ through
        lazrs): x, y, z in the DEM's CRS and vertical reference, with ray gap, score, source
        pair and the filters' classification as extra dimensions. An N-view job writes one
        cloud of every matched pair's points (``source_pair`` = the pair's ``pair_id`` in the
        report; points whose pair height the fusion rejected are noise, edit code 98).
    """

    point_cloud: str | None = None


@dataclass
class Config:
    """Paths and settings of a job; nothing loaded (the stages load what they read)."""

    inputs: InputSettings
    output_dir: str
    stereo: StereoSettings = field(default_factory=StereoSettings)
    jitter: JitterSettings = field(default_factory=JitterSettings)
    filters: FilterSettings = field(default_factory=FilterSettings)
    fill: FillSettings = field(default_factory=FillSettings)
    ortho: OrthoSettings = field(default_factory=OrthoSettings)
    assess: AssessSettings = field(default_factory=AssessSettings)
    uncertainty: UncertaintySettings = field(default_factory=UncertaintySettings)
    run: RunSettings = field(default_factory=RunSettings)
    dem: DemSettings = field(default_factory=DemSettings)
    fusion: FusionSettings = field(default_factory=FusionSettings)

    def to_dict(self) -> dict:
        d = {"inputs": dataclasses.asdict(self.inputs), "output": {"dir": self.output_dir}}
        d.update(self.stereo.summary())
        for name in (
            "jitter",
            "filters",
            "fill",
            "ortho",
            "assess",
            "uncertainty",
            "run",
            "dem",
            "fusion",
        ):
            d[name] = dataclasses.asdict(getattr(self, name))
        return d


#: TOML section -> (settings class, where it lives in a Config)
SECTIONS = {
    "inputs": InputSettings,
    "rectification": RectificationSettings,
    "matching": MatchingSettings,
    "refinement": RefinementSettings,
    "gridding": GriddingSettings,
    "jitter": JitterSettings,
    "filters": FilterSettings,
    "fill": FillSettings,
    "ortho": OrthoSettings,
    "assess": AssessSettings,
    "uncertainty": UncertaintySettings,
    "run": RunSettings,
    "dem": DemSettings,
    "fusion": FusionSettings,
}
_STEREO = ("rectification", "matching", "refinement", "gridding")
_SECTION_PATHS = {
    "uncertainty": ("covariance",),
    "ortho": ("fill_dem",),
    "assess": ("exclude",),
}
_PATH_KEYS = (
    "left",
    "right",
    "left_model",
    "right_model",
    "seed_dem",
    "reference_dem",
    "checkpoints",
    "landcover",
    "dem",
)


# ----------------------------------------------------------------------------- checking

#: string-valued option choices (Literal aliases) annotating the settings classes
_CHOICE_TYPES = tuple(
    name
    for namespace in (dict(globals()), vars(stereo_settings))
    for name, value in namespace.items()
    if typing.get_origin(value) is typing.Literal
)


def _check_value(value, annotation: str, where: str):
    """``value`` converted to the annotated type, or :class:`InputError` naming ``where``."""
    ann = annotation.replace("typing.", "").replace(" ", "")
    optional = ann.startswith("Optional[") or ann.endswith("|None")
    base = (
        ann.removeprefix("Optional[").removesuffix("]")
        if ann.startswith("Optional[")
        else ann.removesuffix("|None")
    )
    if value is None:
        if optional or base == "Any":
            return None
        raise InputError(f"{where}: a value is required")
    if base == "Any":
        return value
    if base == "bool":
        if not isinstance(value, bool):
            raise InputError(f"{where}: expected true or false, got {value!r}")
        return value
    if base == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{where}: expected a whole number, got {value!r}")
        return value
    if base == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{where}: expected a number, got {value!r}")
        if value != value or value in (float("inf"), float("-inf")):
            raise InputError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if base == "str" or base in _CHOICE_TYPES:  # choices: checked by validate()
        if not isinstance(value, str):
            raise InputError(f"{where}: expected a string, got {value!r}")
        return value
    if base == "tuple":
        if not isinstance(value, (list, tuple)) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
        ):
            raise InputError(f"{where}: expected a list of numbers, got {value!r}")
        if not all(abs(v) < float("inf") for v in value):  # nan, inf: a traceback later
            raise InputError(f"{where}: expected a list of finite numbers, got {value!r}")
        return tuple(float(v) if isinstance(v, float) else v for v in value)
    if base == "list":  # of paths
        if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
            raise InputError(f"{where}: expected a list of paths, got {value!r}")
        return list(value)
    if base == "dict":
        if not isinstance(value, dict):
            raise InputError(f"{where}: expected a table, got {value!r}")
        return value
    return value  # pragma: no cover


def unknown_keys(given, known, where: str) -> str | None:
    """``"unknown key(s) in WHERE: windw (did you mean window?) (known: ...)"``, the keys of
    ``given`` that are not in ``known`` each with the closest known key when one is close, or
    None when every key is known."""
    known = list(known)
    unknown = sorted(set(given) - set(known))
    if not unknown:
        return None
    said = []
    for key in unknown:
        close = difflib.get_close_matches(key, known, n=1)
        said.append(f"{key} (did you mean {close[0]}?)" if close else key)
    return f"unknown key(s) in {where}: {', '.join(said)} (known: {', '.join(known)})"


def check_options(options: dict, function, where: str) -> dict:
    """``options``, a table of keyword options passed on to ``function``, with each value
    checked against (and converted to) the type of its parameter, or :class:`InputError`
    naming ``where``: a key that is not one of ``function``'s keyword-only parameters (the
    others are the caller's: passing one of them fails too) or a value of the wrong type.
    A parameter's type is its annotation, or its default's type."""
    params = {
        name: p
        for name, p in inspect.signature(function).parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    }
    unknown = unknown_keys(options, params, where)
    if unknown:
        raise InputError(unknown)
    checked = {}
    for key, value in options.items():
        p = params[key]
        if isinstance(p.annotation, str):
            annotation = p.annotation
        elif p.default is not None and p.default is not inspect.Parameter.empty:
            annotation = type(p.default).__name__
        else:
            annotation = "Any"
        checked[key] = _check_value(value, annotation, f"{where} {key}")
    return checked


def build_settings(cls, table: dict, section: str, source):
    """A settings object of ``cls`` from a TOML table: unknown keys and values of the wrong
    type are :class:`InputError`\\ s naming the file, section and key."""
    if not isinstance(table, dict):
        raise InputError(f"{source}: [{section}] must be a table")
    hints = {
        f.name: f.type if isinstance(f.type, str) else typing.get_type_hints(cls)[f.name].__name__
        for f in dataclasses.fields(cls)
        if f.init
    }
    unknown = unknown_keys(table, hints, f"[{section}]")
    if unknown:
        raise InputError(f"{source}: {unknown}")
    values = {k: _check_value(v, hints[k], f"{source}: [{section}] {k}") for k, v in table.items()}
    try:
        return cls(**values)
    except TypeError as exc:
        raise InputError(f"{source}: [{section}]: {exc}") from None


# ----------------------------------------------------------------------------- reading


def _path(value: str, base) -> str:
    """A configuration's path: ``~`` is the home folder; a relative path is relative to the
    configuration file (``base``). (``dir = "~/out"`` made a folder named ``~`` there.)"""
    value = os.path.expanduser(value)
    return value if os.path.isabs(value) else str(Path(base) / value)


def _is_granule(path, base) -> bool:
    # imported here: the ASTER reader brings SciPy's interpolation (0.3 s), which commands
    # that never read a granule (assess, change, ...) then do not import
    from stereodem.sensor.io.aster_l1a import is_aster_granule

    return isinstance(path, str) and is_aster_granule(_path(path, base))


def load_config(path, **overrides) -> Config:
    """Read a TOML configuration; relative input paths are relative to the file;
    ``overrides`` as :func:`config_from_dict`'s (``output_dir``, [run] keys)."""
    path = as_path(path, "configuration")
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(not_found(path, "configuration file")) from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, not a configuration file") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (expected a TOML configuration)") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None
    return config_from_dict(raw, base=path.parent, source=path, **overrides)


def config_from_dict(
    raw: dict, *, base=".", source="configuration", output_dir=None, **overrides
) -> Config:
    """A :class:`Config` from a parsed TOML mapping (see the module docstring).

    ``output_dir``: the folder the job writes into, whatever ``[output] dir`` says, which is
    then optional (``stereodem batch``: ``OUT/<scene>``). ``overrides`` (``workers``,
    ``resume``, ...) replace [run] keys when not None.
    """
    if "stereo" in raw:
        raise InputError(
            f"{source}: the [stereo] section was split into [rectification], "
            "[matching], [refinement] and [gridding] (see docs/configuration.md)"
        )
    unknown = set(raw) - set(SECTIONS) - {"output"}
    if unknown:
        raise InputError(f"{source}: unknown section(s) {', '.join(sorted(unknown))}")
    inp = dict(raw.get("inputs", {}))
    if "images" in inp:
        imgs = inp["images"]
        if not (
            isinstance(imgs, list)
            and len(imgs) >= 2
            and all(isinstance(v, str) and v for v in imgs)
        ):
            raise InputError(
                f"{source}: [inputs] images must be a list of two or more paths, got {imgs!r}"
            )
        if "left" in inp or "right" in inp:
            raise InputError(f"{source}: [inputs] takes either images or left/right, not both")
        inp["images"] = [_path(v, base) for v in imgs]
    elif "left" not in inp:
        raise InputError(f"{source}: [inputs] needs 'left' (or 'images')")
    elif "right" not in inp and not _is_granule(inp["left"], base):
        raise InputError(
            f"{source}: [inputs] needs 'right' (only an ASTER granule is a pair alone)"
        )
    for key in _PATH_KEYS:
        if isinstance(inp.get(key), str) and inp[key]:
            inp[key] = _path(inp[key], base)
    out = raw.get("output", {}).get("dir") if isinstance(raw.get("output"), dict) else None
    if output_dir is not None:
        out = str(output_dir)
    elif not out or not isinstance(out, str):
        raise InputError(f"{source}: [output] needs 'dir'")
    section = raw.get("output", {})
    unknown = unknown_keys(section if isinstance(section, dict) else {}, ("dir",), "[output]")
    if unknown:  # a typo was ignored
        raise InputError(f"{source}: {unknown}")
    tables = {name: dict(inp if name == "inputs" else raw.get(name, {})) for name in SECTIONS}
    for name, keys in _SECTION_PATHS.items():
        for key in keys:
            v = tables[name].get(key)
            if isinstance(v, str) and v:
                tables[name][key] = _path(v, base)
            elif isinstance(v, list):  # a list of paths ([assess] exclude)
                tables[name][key] = [_path(x, base) if isinstance(x, str) and x else x for x in v]
    parts = {
        name: build_settings(cls, tables[name], name, source) for name, cls in SECTIONS.items()
    }
    run = parts["run"]
    for k, v in overrides.items():
        if v is not None:
            setattr(run, k, v)
    cfg = Config(
        inputs=parts["inputs"],
        output_dir=_path(out, base),
        stereo=StereoSettings(**{k: parts[k] for k in _STEREO}),
        jitter=parts["jitter"],
        filters=parts["filters"],
        fill=parts["fill"],
        ortho=parts["ortho"],
        assess=parts["assess"],
        uncertainty=parts["uncertainty"],
        run=run,
        dem=parts["dem"],
        fusion=parts["fusion"],
    )
    validate(cfg, source)
    return cfg


def validate(cfg: Config, source="configuration"):
    """Ranges and choices of the settings, checked before any work starts."""

    def bad(msg):
        raise InputError(f"{source}: {msg}")

    def choice(section, key, value, choices):
        if value not in choices:
            said = " or ".join([", ".join(repr(c) for c in choices[:-1]), repr(choices[-1])])
            bad(f"[{section}] {key} must be {said}, got {value!r}")

    rect, match, ref, gs = (
        cfg.stereo.rectification,
        cfg.stereo.matching,
        cfg.stereo.refinement,
        cfg.stereo.gridding,
    )
    if cfg.inputs.model not in ("physical", "rpc"):
        bad(f"[inputs] model must be 'physical' or 'rpc', got {cfg.inputs.model!r}")
    for key in ("seed_dem_vertical", "reference_vertical", "checkpoints_vertical", "dem_vertical"):
        v = getattr(cfg.inputs, key)
        if v is not None:
            choice("inputs", key, v, VERTICALS)
    band = cfg.inputs.band
    if isinstance(band, bool) or not (
        isinstance(band, int)
        and band >= 1
        or isinstance(band, str)
        and band.upper() in ("3N", "3B")
    ):
        bad(f"[inputs] band must be a band number >= 1 or an ASTER band 3N/3B, got {band!r}")
    if not 64 <= rect.tile_size <= 16384:
        bad(f"[rectification] tile_size must be 64..16384 px, got {rect.tile_size}")
    if rect.height_range is not None:
        hr = rect.height_range
        if len(hr) != 2 or not hr[0] <= hr[1]:
            bad(f"[rectification] height_range must be [MIN, MAX] with MIN <= MAX, got {list(hr)}")
    if not 0 <= rect.height_margin <= MAX_HEIGHT_MARGIN_M:
        bad(
            f"[rectification] height_margin must be 0..{MAX_HEIGHT_MARGIN_M:g} m (more than "
            f"the Earth's relief), got {rect.height_margin}"
        )
    # the next ones failed in every tile ("no point was matched") or with a traceback
    halo = rect.halo
    # at most a tile: a wider halo rectified and matched void around every tile (1000 px on
    # the 300 px test scene: minutes), a wider disparity margin searched where no pixel of the
    # tile can be (1e6 px: minutes, then nothing matched)
    if len(halo) != 2 or not all(isinstance(v, int) and 0 <= v <= rect.tile_size for v in halo):
        bad(
            f"[rectification] halo must be [COLUMNS, ROWS], whole numbers 0..tile_size "
            f"({rect.tile_size}), got {list(halo)}"
        )
    if not 0 <= rect.disparity_margin <= rect.tile_size:
        bad(
            f"[rectification] disparity_margin must be 0..tile_size ({rect.tile_size}) px, "
            f"got {rect.disparity_margin}"
        )
    if not 0 < ref.sigma <= MAX_SMOOTHING:
        bad(f"[refinement] sigma must be in (0, {MAX_SMOOTHING:g}] px, got {ref.sigma}")
    for key in ("gaussian_sigma", "max_ray_gap"):
        v = getattr(gs, key)
        if v is not None and not v > 0:
            bad(f"[gridding] {key} must be positive, got {v}")
    b = gs.bounds
    if b is not None and (len(b) != 4 or not (b[0] < b[2] and b[1] < b[3])):
        bad(f"[gridding] bounds must be [XMIN, YMIN, XMAX, YMAX] with MIN < MAX, got {list(b)}")
    choice("rectification", "method", rect.method, RECTIFICATION_METHODS)
    choice("matching", "matcher", match.matcher, MATCHERS)
    _check_stereo_options(rect, match, source, bad, choice)
    if not 3 <= ref.window <= MAX_WINDOW or ref.window % 2 == 0:
        bad(f"[refinement] window must be an odd number 3..{MAX_WINDOW}, got {ref.window}")
    # accepted before: a score threshold no ZNCC reaches (every refined match dropped) or a
    # gain outside the share of the first pass's detail kept (0..1), a distorted DEM
    if ref.min_score is not None and not -1 <= ref.min_score <= 1:
        bad(f"[refinement] min_score is a ZNCC, -1..1, got {ref.min_score}")
    if ref.detail_gain is not None and not 0 <= ref.detail_gain <= 1:
        bad(f"[refinement] detail_gain must be 0..1, got {ref.detail_gain}")
    if gs.res is not None and not gs.res > 0:
        bad(f"[gridding] res must be positive, got {gs.res}")

    for key, value in (
        ("[gridding] crs", gs.crs),
        ("[ortho] crs", cfg.ortho.crs),
        ("[inputs] checkpoints_crs", cfg.inputs.checkpoints_crs),
    ):
        if value is not None:
            map_crs(value, f"{source}: {key}")
    choice("gridding", "method", gs.method, GRIDDING_METHODS)
    if rect.pointing_uses_seed and not cfg.inputs.seed_dem:
        bad(
            "[rectification] pointing_uses_seed needs a seed DEM ([inputs] seed_dem, --seed-dem) "
            "to fix the pointing along the epipolar lines"
        )
    j = cfg.jitter
    choice("jitter", "axes", j.axes, JITTER_AXES)
    if j.enabled and "pitch" in j.axis_names and not cfg.inputs.seed_dem:
        bad(
            "[jitter] enabled needs a seed DEM ([inputs] seed_dem, --seed-dem) as the reference "
            "for the pitch jitter (axes = 'roll' needs none)"
        )
    if j.n_sines < 1 or not 0 < j.min_frequency < j.max_frequency:
        bad(
            f"[jitter] needs n_sines >= 1 and 0 < min_frequency < max_frequency, got "
            f"{j.n_sines}, {j.min_frequency}, {j.max_frequency}"
        )
    if cfg.filters.erode < 0:
        bad(f"[filters] erode must be >= 0, got {cfg.filters.erode}")
    if cfg.fill.max_hole_size < 0:
        bad(f"[fill] max_hole_size must be >= 0, got {cfg.fill.max_hole_size}")
    if not 0 <= cfg.fill.smooth_sigma <= MAX_SMOOTHING:
        bad(f"[fill] smooth_sigma must be 0..{MAX_SMOOTHING:g} cells, got {cfg.fill.smooth_sigma}")
    for key in ("slope_bins", "elevation_bins"):
        v = getattr(cfg.assess, key)
        if v is not None and (len(v) < 2 or any(b >= c for b, c in zip(v, v[1:]))):
            bad(f"[assess] {key} must be at least two increasing edges, got {list(v)}")
    if cfg.assess.exclude and not cfg.assess.coregister:
        bad(
            "[assess] exclude leaves polygons out of the stable terrain the co-registration is "
            "fitted on: it needs coregister = true"
        )
    if cfg.ortho.fill_dem_vertical is not None:
        choice("ortho", "fill_dem_vertical", cfg.ortho.fill_dem_vertical, VERTICALS)
    if cfg.ortho.res is not None and not cfg.ortho.res > 0:
        bad(f"[ortho] res must be positive, got {cfg.ortho.res}")
    choice("ortho", "resampling", cfg.ortho.resampling, RESAMPLINGS)
    u = cfg.uncertainty
    choice("uncertainty", "method", u.method, UNCERTAINTY_METHODS)
    if u.enabled and not cfg.ortho.enabled:
        bad("[uncertainty] maps are on the orthoimage's grid: enable [ortho]")
    if u.enabled and not (u.sigma or u.covariance):
        bad(
            "[uncertainty] enabled needs sigma = {name = value, ...} or covariance = "
            "adjust_report.json"
        )
    from stereodem.ortho.choices import check_input_sigma, check_samples  # the CLI's rules

    try:
        for name, v in (u.sigma or {}).items():
            check_input_sigma(v, f"[uncertainty] sigma {name}")
        check_samples(u.samples, "[uncertainty] samples")
    except InputError as err:
        bad(str(err))
    if cfg.dem.point_cloud not in (None, "las", "laz"):
        bad(f"[dem] point_cloud must be 'las' or 'laz', got {cfg.dem.point_cloud!r}")
    for msg in cfg.fusion.problems():
        bad(f"[fusion] {msg}")
    run = cfg.run
    if run.workers is not None and run.workers < 1:
        bad(f"[run] workers must be at least 1, got {run.workers}")
    if run.tile_timeout is not None and not 0 < run.tile_timeout < MAX_TILE_TIMEOUT_S:
        bad(
            f"[run] tile_timeout must be a positive number of seconds below "
            f"{MAX_TILE_TIMEOUT_S:.0e}, got {run.tile_timeout}"
        )
    if run.creation_options:
        # the [run] table's, or --co on the command line over them
        run.creation_options = check_creation_options(
            run.creation_options,
            source=f"{source}: [run] creation_options (or --co)",
            float_products=True,  # a job's DEMs
        )


def _check_stereo_options(rect, match, source, bad, choice):
    """[matching] options and [rectification] sparse_options: keys and types against the
    signatures of the functions they are passed to, then the ranges of those whose meaning is
    clear. (An unknown key or a bad value failed in every tile, ending in "no point was
    matched in any tile", or at the sparse stage with a traceback.)"""
    from stereodem.stereo.match import SGM_MODES, SUBPIXELS, match_rectified
    from stereodem.stereo.sparse import sparse_matches

    where = f"{source}: [matching] options"
    o = match.options = check_options(match.options, match_rectified, where)

    def in_range(section, key, value, low, high=C_INT_MAX):
        if value is not None and not low <= value <= high:
            say = f"OpenCV's int ({high})" if high == C_INT_MAX else f"{high}"
            bad(f"{section} {key} must be {low}..{say}, got {value}")

    w = o.get("window")
    if w is not None and (not 3 <= w <= MAX_WINDOW or w % 2 == 0):
        bad(f"[matching] options window must be an odd number 3..{MAX_WINDOW}, got {w}")
    if o.get("min_score") is not None and not -1 <= o["min_score"] <= 1:
        bad(f"[matching] options min_score is a ZNCC, -1..1, got {o['min_score']}")
    in_range("[matching] options", "min_std", o.get("min_std"), 0, float("inf"))
    # whole pixels to OpenCV (SGBM's disp12MaxDiff, the pyramid's sizes)
    for key in ("lr_tolerance", "levels", "margin", "vertical_search"):
        in_range("[matching] options", key, o.get(key), 0)
    for key in ("sgm_p1", "sgm_p2", "sgm_speckle_window"):
        in_range("[matching] options", key, o.get(key), 0)
    # a percentage; OpenCV scales the speckle range by 16 (its disparities' fixed point)
    in_range("[matching] options", "sgm_uniqueness", o.get("sgm_uniqueness"), 0, 100)
    in_range(
        "[matching] options", "sgm_speckle_range", o.get("sgm_speckle_range"), 0, C_INT_MAX // 16
    )
    if "subpixel" in o:
        choice("matching", "options subpixel", o["subpixel"], SUBPIXELS)
    if "sgm_mode" in o:
        choice("matching", "options sgm_mode", o["sgm_mode"], SGM_MODES)
    if o.get("vertical_search") and match.matcher != "ncc":
        bad("[matching] options vertical_search needs matcher = 'ncc'")

    where = f"{source}: [rectification] sparse_options"
    o = rect.sparse_options = check_options(rect.sparse_options, sparse_matches, where)
    if "ratio" in o and not 0 < o["ratio"] <= 1:
        bad(
            f"[rectification] sparse_options ratio (Lowe's test) must be in (0, 1], "
            f"got {o['ratio']}"
        )
    if "tolerance" in o and not o["tolerance"] > 0:
        bad(f"[rectification] sparse_options tolerance must be positive, got {o['tolerance']}")
    for key, low in (("max_offset", 0), ("max_size", 1), ("n_features", 0), ("threads", 1)):
        in_range("[rectification] sparse_options", key, o.get(key), low)
    # the heights of the model check's grid: 99999999999 was "out of memory"
    in_range("[rectification] sparse_options", "n_heights", o.get("n_heights"), 2, 1000)
    lw = o.get("left_window")
    if lw is not None and (len(lw) != 4 or not (lw[0] < lw[2] and lw[1] < lw[3])):
        bad(
            "[rectification] sparse_options left_window must be [COL0, ROW0, COL1, ROW1] with "
            f"COL0 < COL1 and ROW0 < ROW1, got {list(lw)}"
        )
