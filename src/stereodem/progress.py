"""Progress bars and log output on stderr for long jobs (tqdm).

A stage's bar (``Progress("stereo", total)``) shows the fraction done, the rate, the elapsed
time and the ETA. It is drawn only when stderr is a terminal and the run is not quiet
(``-q``); in logs and pipes it is silent, and one summary line goes to the ``stereodem``
logger at INFO level (shown with ``-v``). Log records are written through :func:`tqdm.write`
(:class:`TqdmLoggingHandler`), so warnings printed during a stage land above the bar
instead of on its line.
"""

from __future__ import annotations

import logging
import sys
import time
import warnings

from tqdm import tqdm

log = logging.getLogger("stereodem.progress")


class Progress:
    """A stage's progress bar: ``Progress("matching", total)`` then ``update(n)``, or the
    callback form ``progress(done, total)`` that library functions call.

    Parameters
    ----------
    label : str
        Stage name shown before the bar.
    total : int
        Units of work (tiles, rows); may be changed later by the callback's ``total``.
    enabled : bool
        False for ``-q``: nothing is drawn or logged.
    stream : file, optional
        Where the bar goes (default ``sys.stderr``); drawn only if it is a terminal.
    unit : str
        Name of a unit of work, shown in the rate (``tiles/s``).
    """

    def __init__(
        self, label: str, total: int, *, enabled: bool = True, stream=None, unit: str = "it"
    ):
        self.label, self.total, self.enabled = label, max(int(total), 1), enabled
        self.stream = stream or sys.stderr
        self.done = 0
        self.t0 = time.perf_counter()
        self._tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._bar = tqdm(
            total=self.total,
            desc=label,
            unit=unit,
            file=self.stream,
            leave=True,
            dynamic_ncols=True,
            disable=not (enabled and self._tty),
            bar_format="{desc:<10} {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} "
            "[{elapsed}<{remaining}, {rate_fmt}]",
        )

    def update(self, n: int = 1):
        """Advance by ``n`` units."""
        n = max(0, min(int(n), self.total - self.done))
        self.done += n
        self._bar.update(n)

    def __call__(self, done: int, total: int | None = None):
        """Callback form ``progress(done, total)``: ``done`` units of ``total`` are finished.

        A ``done`` below the previous one starts the count again (a stage that runs the
        same loop twice, e.g. the left then the right orthoimage)."""
        if int(done) < self.done:
            self.done = 0
            self._bar.reset(total=self.total)
        if total and int(total) != self.total:
            self.total = max(int(total), 1)
            self._bar.total = self.total
            self._bar.refresh()
        self.update(int(done) - self.done)

    def close(self):
        """End the bar (terminal) or log one summary line (logs, pipes)."""
        if not self._bar.disable:
            self._bar.close()
        elif self.enabled:
            log.info(
                "%s: %d/%d in %.1f s",
                self.label,
                self.done,
                self.total,
                time.perf_counter() - self.t0,
            )
        self.enabled = False  # closing twice logs once

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class TqdmLoggingHandler(logging.StreamHandler):
    """A log handler writing through :func:`tqdm.write`, which clears and redraws any active
    bar, to the *current* ``sys.stderr`` (so redirections made after set-up are followed)."""

    def __init__(self):
        super().__init__(stream=sys.stderr)

    def emit(self, record):
        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:  # pragma: no cover - logging must never raise
            self.handleError(record)


class UTCFormatter(logging.Formatter):
    """Log lines stamped in UTC, ISO 8601 (``2026-11-24T05:23:13.123Z``)."""

    converter = time.gmtime
    default_time_format = "%Y-%m-%dT%H:%M:%S"
    default_msec_format = "%s.%03dZ"


def setup_logging(verbose: int = 0, quiet: bool = False):
    """Configure the root logger for the command line.

    ``quiet``: errors only; default: warnings; ``verbose=1``: info; ``verbose>=2``: debug.
    With ``-v`` lines carry a UTC timestamp. Python warnings (``warnings.warn``) are routed
    to logging (logger ``py.warnings``), and every line goes through
    :class:`TqdmLoggingHandler` so a progress bar is not broken. Like
    :func:`logging.basicConfig`, this does nothing when the root logger already has handlers
    (an embedding application's, pytest's).
    """
    level = (
        logging.ERROR
        if quiet
        else (logging.DEBUG if verbose > 1 else logging.INFO if verbose == 1 else logging.WARNING)
    )
    handler = TqdmLoggingHandler()
    fmt = (
        "%(asctime)s %(levelname)s %(name)s: %(message)s"
        if verbose
        else "%(levelname)s %(name)s: %(message)s"
    )
    handler.setFormatter(UTCFormatter(fmt))
    logging.basicConfig(level=level, handlers=[handler])
    logging.captureWarnings(True)
    # rasterio's NotGeoreferencedWarning on opening a raster without a geotransform: images
    # in sensor geometry have none by nature (their sensor models place them), and a raster
    # that must be on the map (DEM, land cover, masks, σ maps) is refused with a message that
    # says so (core.dem.check_georeferenced, core.raster.check_map_raster); the warning was
    # a two-line traceback-like noise before that error. By message: rasterio is not loaded
    # here (stereodem --help stays light).
    warnings.filterwarnings(
        "ignore", message="Dataset has no geotransform, gcps, or rpcs", module="rasterio"
    )
    return level
