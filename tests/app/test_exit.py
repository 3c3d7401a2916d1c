"""The ``stereodem`` program ends without finalising every module (:func:`stereodem.cli.exit_now`),
but only once nothing is left to do: exit handlers ran, streams and logs are flushed, and a
running non-daemon thread is waited for."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[2]


def _python(code, tmp_path):
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )


def test_the_program_entry_point_is_the_quick_exit():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["stereodem"] == "stereodem.cli:console_main"


def test_exit_handlers_run_and_streams_and_logs_are_flushed(tmp_path):
    p = _python(
        """
        import atexit, logging, sys, tempfile, pathlib
        from stereodem.cli import exit_now
        atexit.register(lambda: pathlib.Path("handler_ran").write_text("yes"))
        kept = tempfile.TemporaryDirectory(dir=".")  # removed by its weakref finalizer
        pathlib.Path("tmpdir_name").write_text(kept.name)
        log = logging.getLogger("x")
        h = logging.FileHandler("log.txt", delay=True)
        h.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(h)
        log.warning("last line of the log")
        sys.stdout.write("partial line without a newline")
        sys.stderr.write("and on stderr")
        exit_now(3)
        """,
        tmp_path,
    )
    assert p.returncode == 3, p.stderr
    assert p.stdout == "partial line without a newline"
    assert p.stderr == "and on stderr"
    assert (tmp_path / "handler_ran").read_text() == "yes"
    assert (tmp_path / "log.txt").read_text() == "last line of the log\n"
    assert not (tmp_path / (tmp_path / "tmpdir_name").read_text()).exists()


@pytest.mark.slow  # a subprocess importing the program
def test_a_running_thread_is_waited_for(tmp_path):
    # os._exit would end the thread before it writes; the normal exit waits for it
    p = _python(
        """
        import pathlib, threading, time
        from stereodem.cli import exit_now
        def late():
            time.sleep(0.5)
            pathlib.Path("thread_done").write_text("yes")
        threading.Thread(target=late).start()
        exit_now(0)
        """,
        tmp_path,
    )
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "thread_done").read_text() == "yes"


@pytest.mark.slow  # a subprocess importing the program
def test_the_programs_output_and_exit_code_survive_the_quick_exit(tmp_path):
    ok = subprocess.run(
        [sys.executable, "-m", "stereodem.cli", "--version"], capture_output=True, text=True
    )
    assert ok.returncode == 0 and ok.stdout.startswith("stereodem ")
    bad = subprocess.run(
        [sys.executable, "-m", "stereodem.cli", "info", str(tmp_path / "missing.hdf")],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 1
    assert "missing.hdf" in bad.stderr and "Traceback" not in bad.stderr


def test_a_deprecation_warning_of_an_exit_handler_is_not_shown(tmp_path):
    """An exit handler's DeprecationWarning (numcodecs 0.11's blosc ``_destroy`` at exit, on the
    declared minimum versions) is about a library's internals: the normal exit does not show
    it (no Python frame calls the handlers); run from ``exit_now``, it was attributed to
    ``stereodem.cli`` and printed as a WARNING under ``python -m stereodem.cli``."""
    p = _python(
        """
        import atexit, warnings
        from stereodem.cli import exit_now
        warnings.simplefilter("default")  # what __main__ gets under python -m stereodem.cli
        atexit.register(lambda: warnings.warn("old internals", DeprecationWarning, stacklevel=2))
        exit_now(0)
        """,
        tmp_path,
    )
    assert p.returncode == 0 and "old internals" not in p.stderr, p.stderr
