"""Provenance of a run: when, how it was invoked, which version and which commit.

:func:`provenance` returns a JSON-ready dict for ``run.json`` and each command's report::

    t0 = begin()                          # the start time; the commit looked up now
    ...                                   # the work
    info["provenance"] = provenance(started=t0)
"""

from __future__ import annotations

import datetime as _dt
import functools
import shlex
import subprocess
import sys
from pathlib import Path

from . import __version__

#: the package's source folder: the commit is looked up from here, not from the caller's cwd
_PACKAGE_DIR = Path(__file__).resolve().parent


def utc_now() -> str:
    """The current time, UTC, ISO 8601 with seconds and a ``Z`` (``2026-11-24T05:23:13Z``)."""
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def git_commit(where=_PACKAGE_DIR) -> dict | None:
    """The commit of the git work tree holding ``where`` (default: the installed package).

    Returns ``{"commit": sha, "dirty": bool}``, or ``None`` when ``where`` is not in a git
    work tree (an installed wheel, a source archive) or git is not available.
    """

    def git(*args):
        return subprocess.run(
            ["git", "-C", str(where), *args], capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()

    try:
        if git("rev-parse", "--is-inside-work-tree") != "true":
            return None
        sha = git("rev-parse", "HEAD")
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": sha, "dirty": dirty}


@functools.lru_cache(maxsize=1)
def package_commit() -> dict | None:
    """:func:`git_commit` of the installed package, looked up once per process (the code
    that runs does not change while it runs); :func:`begin` makes the lookup at a run's
    start."""
    return git_commit()


def begin() -> str:
    """A run's start: the time (:func:`utc_now`), and the package's commit looked up now
    (:func:`package_commit`), while the process is small: the kernel counts a child started
    from a process of several gigabytes (``git``) as a child of that size in the largest
    resident set of the waited-for children (``RUSAGE_CHILDREN``: run.json's
    ``peak_worker_rss_mb``), and looked up at the end of a full-granule run it made that
    figure 1.5 GB where the tile workers peaked at 0.37 GB."""
    package_commit()
    return utc_now()


def provenance(*, started: str | None = None, ended: str | None = None, argv=None) -> dict:
    """Who-made-this record of a run.

    Parameters
    ----------
    started : str, optional
        Start time from :func:`utc_now` taken when the run began; default now.
    ended : str, optional
        End time; default now (call this at the end of the run).
    argv : list of str, optional
        The command line; default ``sys.argv`` (the program name shortened to ``stereodem``
        when it is the console script).

    Returns
    -------
    dict
        ``started_utc``, ``ended_utc`` (ISO 8601, UTC), ``command_line`` (one shell-quoted
        string), ``argv`` (list), ``stereodem_version`` and, from a git checkout only,
        ``git_commit`` and ``git_dirty`` (uncommitted changes to tracked files).
    """
    argv = list(sys.argv if argv is None else argv)
    if argv and Path(argv[0]).name in ("stereodem", "__main__.py", "cli.py"):
        argv[0] = "stereodem"
    now = utc_now()
    out = {
        "started_utc": started or now,
        "ended_utc": ended or now,
        "command_line": shlex.join(argv),
        "argv": argv,
        "stereodem_version": __version__,
    }
    git = package_commit()
    if git:
        out["git_commit"], out["git_dirty"] = git["commit"], git["dirty"]
    return out
