"""Run configuration: a TOML file read with the standard library, mapped onto the settings
objects of each stage (the same objects the Python API takes).

Example (every key optional except ``inputs.left``/``inputs.right`` and ``output.dir``)::

    [inputs]
    left = "left.tif"              # GeoTIFF with RPC tags/sidecar or <stem>.model.json
    right = "right.tif"
    model = "physical"             # "physical" (sidecar if present) or "rpc"
    seed_dem = "coarse.tif"        # optional: per-tile height ranges, fallback for large holes
    seed_dem_vertical = "geoid"    # when the seed file does not say (SRTM: geoid)
    reference_dem = "ref.tif"      # optional: accuracy assessment
    reference_vertical = "geoid"   # when the reference file does not say
    checkpoints = "points.csv"     # optional: lon,lat,h check points
    landcover = "lc.tif"           # optional: integer classes

    [output]
    dir = "out"

    [stereo]                       # stereo.pipeline.DEMSettings
    tile_size = 512
    height_range = [1000, 3500]
    matcher = "ncc"
    posting = 30.0
    geoid = false

    [filters]
    enabled = true
    thesis = false                 # the Ok thesis chain instead of the default one

    [fill]
    max_hole_size = 200
    fallback = false               # true: large holes from the seed DEM
    smooth_sigma = 0.0

    [ortho]
    enabled = true
    both = true                    # also the right image, on the same grid
    resampling = "bilinear"
    res = 15.0

    [assess]
    coregister = true

    [run]
    workers = 2                    # default: all cores
    tile_timeout = 600
"""
from __future__ import annotations

import dataclasses
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from stereodem.sensor.errors import InputError
from stereodem.stereo.pipeline import DEMSettings


@dataclass
class InputSettings:
    left: str
    right: str
    model: str = "physical"
    seed_dem: str | None = None
    seed_dem_vertical: str | None = None
    reference_dem: str | None = None
    reference_vertical: str | None = None
    checkpoints: str | None = None
    landcover: str | None = None


@dataclass
class FilterSettings:
    enabled: bool = True
    thesis: bool = False
    erode: int = 2                  # cells removed along the border of the matched area


@dataclass
class FillSettings:
    enabled: bool = True
    max_hole_size: int = 200
    fallback: bool = False          # fill large holes from the seed DEM (blended seam)
    smooth_sigma: float = 0.0


@dataclass
class OrthoSettings:
    enabled: bool = True
    both: bool = True
    resampling: str = "bilinear"
    res: float | None = None


@dataclass
class AssessSettings:
    enabled: bool = True
    coregister: bool = True


@dataclass
class RunSettings:
    workers: int | None = None
    tile_timeout: float | None = 600.0
    resume: bool = False
    dask: str | None = None
    overwrite: bool = False


@dataclass
class Config:
    inputs: InputSettings
    output_dir: str
    stereo: DEMSettings = field(default_factory=DEMSettings)
    filters: FilterSettings = field(default_factory=FilterSettings)
    fill: FillSettings = field(default_factory=FillSettings)
    ortho: OrthoSettings = field(default_factory=OrthoSettings)
    assess: AssessSettings = field(default_factory=AssessSettings)
    run: RunSettings = field(default_factory=RunSettings)

    def to_dict(self) -> dict:
        d = {"inputs": dataclasses.asdict(self.inputs), "output": {"dir": self.output_dir},
             "stereo": self.stereo.summary()}
        for name in ("filters", "fill", "ortho", "assess", "run"):
            d[name] = dataclasses.asdict(getattr(self, name))
        return d


def _build(cls, table: dict, section: str, path):
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = set(table) - names
    if unknown:
        raise InputError(f"{path}: unknown key(s) in [{section}]: {', '.join(sorted(unknown))}")
    try:
        return cls(**table)
    except TypeError as exc:
        raise InputError(f"{path}: [{section}]: {exc}") from None


def load_config(path, **overrides) -> Config:
    """Read a TOML run configuration; relative input paths are relative to the file."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: configuration file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None
    return config_from_dict(raw, base=path.parent, source=path, **overrides)


def config_from_dict(raw: dict, *, base=".", source="configuration", **overrides) -> Config:
    unknown = set(raw) - {"inputs", "output", "stereo", "filters", "fill", "ortho", "assess", "run"}
    if unknown:
        raise InputError(f"{source}: unknown section(s) {', '.join(sorted(unknown))}")
    inp = dict(raw.get("inputs", {}))
    for key in ("left", "right"):
        if key not in inp:
            raise InputError(f"{source}: [inputs] needs '{key}'")
    for key in ("left", "right", "seed_dem", "reference_dem", "checkpoints", "landcover"):
        if inp.get(key):
            inp[key] = str((Path(base) / inp[key]) if not os.path.isabs(inp[key]) else inp[key])
    out = raw.get("output", {}).get("dir")
    if not out:
        raise InputError(f"{source}: [output] needs 'dir'")
    stereo = dict(raw.get("stereo", {}))
    if "height_range" in stereo and stereo["height_range"] is not None:
        stereo["height_range"] = tuple(float(v) for v in stereo["height_range"])
    if "halo" in stereo:
        stereo["halo"] = tuple(stereo["halo"])
    cfg = Config(
        inputs=_build(InputSettings, inp, "inputs", source),
        output_dir=str(Path(base) / out) if not os.path.isabs(out) else out,
        stereo=_build(DEMSettings, stereo, "stereo", source),
        filters=_build(FilterSettings, raw.get("filters", {}), "filters", source),
        fill=_build(FillSettings, raw.get("fill", {}), "fill", source),
        ortho=_build(OrthoSettings, raw.get("ortho", {}), "ortho", source),
        assess=_build(AssessSettings, raw.get("assess", {}), "assess", source),
        run=_build(RunSettings, raw.get("run", {}), "run", source),
    )
    for k, v in overrides.items():
        if v is not None:
            setattr(cfg.run, k, v)
    if cfg.inputs.seed_dem and cfg.stereo.seed_dem is None:
        from stereodem.sensor.geo.dem import DEM
        cfg.stereo.seed_dem = DEM.from_file(cfg.inputs.seed_dem, vertical=cfg.inputs.seed_dem_vertical)
    return cfg
