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


class NoSensorModelError(RPCError, SensorModelError):
    """A file carries no sensor model of the kind looked for: no RPCs in any format stereodem
    reads (:func:`~stereodem.sensor.io.rpc_formats.read_rpc`), or an image neither a
    ``<stem>.model.json`` sidecar nor RPCs
    (:func:`~stereodem.sensor.io.sidecar.load_image_model`). A model that is there but garbled
    (invalid JSON, bad RPC tags) is another :class:`SensorModelError` or :class:`RPCError`:
    only this one may be passed over by what can do without the image's model (a generic
    model fitted to GCPs)."""


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


class AccuracyError(StereodemError):
    """A result would miss its stated accuracy (measured, not assumed), so it is not made."""


#: what lets a write replace an existing output, in each caller's words: the library's keyword
#: argument and the command line's flag (:meth:`OutputExistsError.needs_overwrite`)
OVERWRITE_WORDS = {"library": "overwrite=True", "command line": "--overwrite"}


class OutputExistsError(StereodemError, FileExistsError):
    """An output exists and overwriting was not allowed.

    Made by :meth:`needs_overwrite`, it carries its advice in both vocabularies
    (:data:`OVERWRITE_WORDS`): ``str(error)`` is the library's ("pass overwrite=True to
    replace it"), ``error.message("command line")`` the command line's ("pass --overwrite to
    replace it"), which ``stereodem`` prints (:func:`error_message`).
    """

    def __init__(self, message, *, advice: str | None = None):
        self.problem = str(message)
        self.advice = advice
        super().__init__(self.message("library"))

    @classmethod
    def needs_overwrite(cls, problem: str, advice: str = "to replace it"):
        """``"<problem>; pass overwrite=True <advice>"`` (``--overwrite`` on the command
        line): the one way an output refused for want of overwriting is worded."""
        return cls(problem, advice=advice)

    def message(self, words: str = "library") -> str:
        """The message in ``words`` (a key of :data:`OVERWRITE_WORDS`)."""
        if self.advice is None:
            return self.problem
        return f"{self.problem}; pass {OVERWRITE_WORDS[words]} {self.advice}"

    def __reduce__(self):  # across processes (batch, dask) with both wordings
        return (_rebuild_output_exists, (type(self), self.problem, self.advice))


def _rebuild_output_exists(cls, problem, advice):
    return cls(problem, advice=advice)


def portable(exc: BaseException) -> BaseException:
    """``exc`` without the chain of errors it was raised from (``__cause__``, ``__context__``),
    returned: what an error raised on a Dask worker must be to reach the client as itself.
    Dask ships a task's error with its chain (tblib), and a GDAL error in the chain
    (rasterio's ``CPLE_*``, whose ``args`` cannot be set) does not unpickle: the client got a
    bare ``Exception`` holding the error's repr, and the command printed a traceback instead
    of its one-line error (``mosaic --dask`` with a damaged DEM). The messages already say
    what the chain said (GDAL's words: :func:`unreadable`)."""
    exc.__cause__ = None
    exc.__context__ = None
    exc.__suppress_context__ = True
    return exc


def one_line(exc: BaseException, words: str = "library") -> str:
    """:func:`error_message` on one line (messages relayed from GDAL or Dask may carry
    newlines), or the exception's type name when it has no message."""
    return " ".join(error_message(exc, words).split()) or type(exc).__name__


def error_message(exc: BaseException, words: str = "library") -> str:
    """``str(exc)``, or for an :class:`OutputExistsError` its message in ``words``
    (``"command line"``: the ``stereodem`` program's vocabulary)."""
    if isinstance(exc, OutputExistsError):
        return exc.message(words)
    return str(exc)


class OutputWriteError(StereodemError, OSError):
    """An output could not be written (GDAL refused the creation options for its data, the
    disk is full, ...)."""


class ConvergenceError(StereodemError, RuntimeError):
    """An iterative solution did not converge."""


def where(path) -> str:
    """Prefix for messages about ``path`` (empty when there is no file)."""
    return f"{path}: " if path else ""


#: the reason :func:`not_found` gives (the system's own words, as ``OSError.strerror`` says it)
NOT_FOUND = "No such file or directory"


def not_found(path, what: str) -> str:
    """The one wording of a missing input file, in every reader of every command: ``"PATH:
    cannot read the WHAT (No such file or directory)"`` (``what``: "image", "DEM", "GCP
    file", ...), the wording of every reader that cannot read its file ("PATH: cannot read
    the WHAT (REASON)": :func:`stereodem.core.raster.unreadable`, the CSV readers). Before,
    a missing file read "PATH: image not found", "PATH: match file not found", "PATH: no
    such file", "PATH: no such file or folder" or "PATH: cannot read the DEM (PATH: No such
    file or directory)" depending on the reader."""
    return f"{path}: cannot read the {what} ({NOT_FOUND})"
