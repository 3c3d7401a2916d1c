"""Progress reporting on stderr for long jobs (no extra dependency)."""
from __future__ import annotations

import sys
import time


class Progress:
    """A one-line progress bar: ``Progress("matching", total)`` then ``update(n)``.

    Silent when ``enabled`` is false (``-q``); when stderr is not a terminal only the final
    summary line is written.
    """

    def __init__(self, label: str, total: int, *, enabled: bool = True, stream=None):
        self.label, self.total, self.enabled = label, max(int(total), 1), enabled
        self.stream = stream or sys.stderr
        self.done = 0
        self.t0 = time.perf_counter()
        self._tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def update(self, n: int = 1):
        self.done = min(self.total, self.done + n)
        if self.enabled and self._tty:
            frac = self.done / self.total
            bar = "#" * int(30 * frac)
            self.stream.write(f"\r{self.label:<14} [{bar:<30}] {100 * frac:5.1f}% "
                              f"{time.perf_counter() - self.t0:6.1f}s")
            self.stream.flush()

    def __call__(self, done: int, total: int | None = None):
        """Callback form ``progress(done, total)`` used by library functions."""
        if total:
            self.total = max(int(total), 1)
        self.update(done - self.done)

    def close(self):
        """End the bar (terminal) or write one summary line (logs, pipes)."""
        if not self.enabled:
            return
        if self._tty:
            self.stream.write("\n")
        else:
            self.stream.write(f"{self.label}: {self.done}/{self.total} in "
                              f"{time.perf_counter() - self.t0:.1f}s\n")
        self.stream.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
