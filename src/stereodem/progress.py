"""Progress bars and log output on stderr for long jobs (tqdm).

Every bar is made by :func:`stage_bar` from the stage's entry in :data:`STAGES` (its
description and its unit of work: ``stereo  40%|####  | 12/30 tiles [00:07<00:10,
1.71tile/s]``). It shows the fraction done, the count, the rate, the elapsed time and the
ETA, and is drawn only when stderr is a terminal and the run is not quiet (``-q``); in logs
and pipes it is silent, and one summary line goes to the ``stereodem`` logger at INFO level
(shown with ``-v``). A bar whose total is not known yet is not drawn until the stage's first
``progress(done, total)``, and it never counts down: a stage that runs its loop several times
(N-view pairs, the jitter correction's second DEM) counts on through
:class:`stereodem.stereo.execution.ProgressPasses`. Log records are written through
:func:`tqdm.write` (:class:`TqdmLoggingHandler`), so warnings printed during a stage land
above the bar instead of on its line.
"""

from __future__ import annotations

import logging
import sys
import time
import warnings

from tqdm import tqdm

from stereodem.core import worker_logging

log = logging.getLogger("stereodem.progress")

#: stage -> (description shown before the bar, unit of work counted by the stage's callback)
STAGES = {
    "stereo": ("stereo", "tile"),
    "ortho": ("orthoimages", "row"),
    "mosaic": ("mosaic", "block"),
    "stack": ("stack", "DEM"),
    "compare": ("models", "adjustment"),
    "splits": ("GCP/ICP splits", "draw"),
}


def stage_bar(stage: str, *, enabled: bool = True, stream=None) -> Progress:
    """The progress bar of ``stage`` (a key of :data:`STAGES`), its total learnt from the
    stage's first ``progress(done, total)``; ``enabled`` False (``-q``) draws and logs
    nothing. The one place the command line makes its bars."""
    label, unit = STAGES[stage]
    return Progress(label, None, enabled=enabled, stream=stream, unit=unit)


class Progress:
    """A stage's progress bar: ``Progress("stereo", total, unit="tile")`` then
    ``update(n)``, or the callback form ``progress(done, total)`` that library functions
    call. Made by :func:`stage_bar` on the command line.

    Parameters
    ----------
    label : str
        Description shown before the bar.
    total : int or None
        Units of work; None until the callback's first ``total`` (nothing is drawn before).
    enabled : bool
        False for ``-q``: nothing is drawn or logged.
    stream : file, optional
        Where the bar goes (default ``sys.stderr``); drawn only if it is a terminal.
    unit : str
        Name of a unit of work, shown after the count (``12/30 tiles``) and in the rate
        (``1.71tile/s``).
    """

    def __init__(
        self,
        label: str,
        total: int | None = None,
        *,
        enabled: bool = True,
        stream=None,
        unit: str = "item",
    ):
        self.label, self.unit, self.enabled = label, unit, enabled
        self.total = None if total is None else max(int(total), 1)
        self.stream = stream or sys.stderr
        self.done = 0
        self.t0 = time.perf_counter()
        tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._draw = enabled and tty
        self._bar = None
        if self.total is not None:
            self._open()

    def _open(self):
        self._bar = tqdm(
            total=self.total,
            initial=self.done,
            desc=self.label,
            unit=self.unit,
            file=self.stream,
            leave=True,
            dynamic_ncols=True,
            disable=not self._draw,
            bar_format="{desc:<11} {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} "
            + self.unit
            + "s [{elapsed}<{remaining}, {rate_fmt}]",
        )

    def update(self, n: int = 1):
        """Advance by ``n`` units."""
        if self._bar is None:
            self._open()
        if self.total is not None:
            n = min(int(n), self.total - self.done)
        n = max(0, int(n))
        self.done += n
        self._bar.update(n)

    def __call__(self, done: int, total: int | None = None, *_):
        """Callback form ``progress(done, total)``: ``done`` units of ``total`` are finished
        (further arguments, such as a tile's summary, are ignored).

        The count never goes back: a ``done`` below the previous one is ignored (a stage
        that runs a loop again counts on, through
        :class:`~stereodem.stereo.execution.ProgressPasses`)."""
        if total and (self.total is None or int(total) != self.total):
            self.total = max(int(total), 1)
            if self._bar is None:
                self._open()
            else:
                self._bar.total = self.total
                self._bar.refresh()
        self.update(int(done) - self.done)

    def close(self):
        """End the bar (terminal) or log one summary line (logs, pipes)."""
        if self._draw and self._bar is not None:
            self._bar.close()
        elif self.enabled:
            log.info(
                "%s: %d/%s %ss in %.1f s",
                self.label,
                self.done,
                "?" if self.total is None else self.total,
                self.unit,
                time.perf_counter() - self.t0,
            )
        elif self._bar is not None:
            self._bar.close()
        self.enabled = self._draw = False  # closing twice logs once

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
    # the pool workers log as this process does (stereodem.core.worker_logging)
    worker_logging.register(setup_logging, verbose, quiet)
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
