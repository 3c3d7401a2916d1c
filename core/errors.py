"""Exception hierarchy shared by every stereodem package.

Each error names the file (when there is one) and the problem in one line, so that the
command-line front end can print ``str(error)`` and exit with status 1 without a traceback.
"""

from __future__ import annotations


class StereodemError(Exception):
    """Base class of all errors raised deliberately by stereodem."""


class InputError(StereodemError, ValueError):
    """An input file or array is unusable (garbled, NaN, wrong shape, wrong units)."""


class RPCError(InputError):
    """Missing or garbled RPC00B metadata."""


class SensorModelError(InputError):
    """A sensor model cannot be built or evaluated (missing metadata, no convergence)."""


class CRSError(InputError):
    """A raster or point set has no CRS, or one that cannot be used."""


class DEMError(InputError):
    """A DEM cannot be read or used (no CRS, all voids, unknown vertical reference)."""


class DEMCoverageError(DEMError):
    """Points fall outside the DEM or on its voids where heights are required."""


class VerticalReferenceError(DEMError):
    """Two height sets cannot be reconciled (geoid vs ellipsoid unknown)."""


class NoOverlapError(InputError):
    """Two images, or an image and a DEM, do not overlap."""


class OutputExistsError(StereodemError, FileExistsError):
    """An output exists and overwriting was not allowed."""


class OutputWriteError(StereodemError, OSError):
    """An output could not be written (GDAL refused the creation options for its data, the
    disk is full, ...)."""


class ConvergenceError(StereodemError, RuntimeError):
    """An iterative solution did not converge."""


def where(path) -> str:
    """Prefix for messages about ``path`` (empty when there is no file)."""
    return f"{path}: " if path else ""
