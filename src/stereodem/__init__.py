"""stereodem: satellite stereo photogrammetry — sensor models, stereo DEMs, blunder filtering,
accuracy assessment and DRM orthoimages.

The public API is here, in one place (issue #23)::

    from stereodem import DEM, make_dem, orthorectify, assess_dem, simulate_scene
    from stereodem import NuthKaab, Deramp  # (NuthKaab() + Deramp(1)).fit(ref, dem)

Names are resolved on first use (PEP 562 ``__getattr__``), so ``import stereodem`` and
``stereodem --help`` do not load numpy, OpenCV or rasterio. Where each name lives:
:data:`_API`; docs/api.md describes them.
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("stereodem")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0+unknown"

#: public name -> defining module
_API = {
    # core: errors, rasters, grids, the DEM type
    # (every StereodemError subclass: what the public functions raise can be caught by its
    # own name from here)
    "StereodemError": "stereodem.core.errors",
    "InputError": "stereodem.core.errors",
    "RPCError": "stereodem.core.errors",
    "SensorModelError": "stereodem.core.errors",
    "NoSensorModelError": "stereodem.core.errors",
    "CRSError": "stereodem.core.errors",
    "DEMError": "stereodem.core.errors",
    "DEMCoverageError": "stereodem.core.errors",
    "VerticalReferenceError": "stereodem.core.errors",
    "NoOverlapError": "stereodem.core.errors",
    "OutputExistsError": "stereodem.core.errors",
    "OutputWriteError": "stereodem.core.errors",
    "ConvergenceError": "stereodem.core.errors",
    "AccuracyError": "stereodem.core.errors",
    # ... and those defined beside what raises them (make_dem, run)
    "SparseMatchError": "stereodem.stereo.sparse",
    "SuspectResultError": "stereodem.stereo.sanity",
    "OtherJobTilesError": "stereodem.stereo.execution",
    "OutputLockedError": "stereodem.outlock",
    "DEM": "stereodem.core.dem",
    "MapGrid": "stereodem.core.grid",
    "read_image": "stereodem.core.raster",
    "write_geotiff": "stereodem.core.raster",
    # sensor models and their files
    "SensorModel": "stereodem.sensor.models.base",
    "RPCModel": "stereodem.sensor.models.rpc",
    "load_model": "stereodem.sensor.io.sidecar",
    "save_model": "stereodem.sensor.io.sidecar",
    "load_image_model": "stereodem.sensor.io.sidecar",
    "open_aster_granule": "stereodem.sensor.io.aster_l1a",
    "simulate_scene": "stereodem.sensor.simulation.simulate",
    # stereo
    "make_dem": "stereodem.stereo.pipeline",
    "DEMProducts": "stereodem.stereo.pipeline",
    "StereoInfo": "stereodem.stereo.pipeline",
    "StereoSettings": "stereodem.stereo.settings",
    "RectificationSettings": "stereodem.stereo.settings",
    "MatchingSettings": "stereodem.stereo.settings",
    "RefinementSettings": "stereodem.stereo.settings",
    "GriddingSettings": "stereodem.stereo.settings",
    # post-processing and assessment
    "assess_dem": "stereodem.post.assess",
    "write_report": "stereodem.post.report",
    # co-registration and bias correction (xdem's pattern: fit/apply steps composed with +)
    "Coreg": "stereodem.post.coreg",
    "CoregChain": "stereodem.post.coreg",
    "parse_chain": "stereodem.post.coreg",
    "NuthKaab": "stereodem.post.biascorr",
    "VerticalShift": "stereodem.post.biascorr",
    "Deramp": "stereodem.post.biascorr",
    "AlongTrack": "stereodem.post.biascorr",
    "CrossTrack": "stereodem.post.biascorr",
    "Curvature": "stereodem.post.biascorr",
    "ICP": "stereodem.post.biascorr",
    "StableMask": "stereodem.post.masks",
    "AltimetryPoints": "stereodem.post.altimetry",
    "read_points": "stereodem.post.altimetry",
    # orthoimages
    "orthorectify": "stereodem.ortho.drm",
    "Ortho": "stereodem.ortho.drm",
    # whole jobs
    "load_config": "stereodem.config",
    "run": "stereodem.pipeline.job",
}

__all__ = ["__version__", *_API]


def __getattr__(name):
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'stereodem' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # next time without __getattr__
    return value


def __dir__():
    return sorted(set(globals()) | set(_API))
