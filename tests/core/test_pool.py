"""stereodem.core.pool: stopping a process pool at once."""

import subprocess
import sys

import pytest

from stereodem.cli import main
from stereodem.core.pool import _TRACKER_FILTER

_HALF_SENT_RESULT = """
import os, struct, sys, time
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from stereodem.core.pool import stop_pool

if __name__ == "__main__":
    ex = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
    fut = ex.submit(time.sleep, 60)
    while not fut.running():
        time.sleep(0.05)
    time.sleep(0.5)
    # what a worker ended in the middle of sending a result leaves in the pipe: a header
    # announcing 1000 bytes, and 10 of them
    os.write(ex._result_queue._writer.fileno(), struct.pack("!i", 1000) + bytes(10))
    time.sleep(0.5)
    stop_pool(ex)
    print("stopped", flush=True)
"""


@pytest.mark.slow
def test_stopped_pool_exits_even_with_half_a_result_in_its_pipe(tmp_path):
    """A worker killed while sending its tile leaves a partial message in the result pipe;
    the pool's manager thread then blocks in recv() and the interpreter, which joins it at
    exit, hung for ever after an interrupted run (seen with SIGTERM in CI). stop_pool ends
    that wait: the process exits."""
    script = tmp_path / "half_sent.py"
    script.write_text(_HALF_SENT_RESULT)
    try:
        r = subprocess.run(
            [sys.executable, str(script)], capture_output=True, text=True, timeout=120
        )
    except subprocess.TimeoutExpired:
        pytest.fail("the interpreter did not exit after stop_pool (manager thread blocked)")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "stopped"


_TRACKER_REPORT = """
import sys
import multiprocessing
from multiprocessing import resource_tracker
from stereodem.core.pool import quiet_resource_tracker

if __name__ == "__main__":
    if sys.argv[1] == "quiet":
        quiet_resource_tracker()
    lock = multiprocessing.get_context("forkserver").Lock()  # a named, tracked semaphore
    # what an interrupted job leaves: a semaphore its owner never unregistered, and which
    # is already gone when the tracker tries to unlink it (the report seen in CI)
    resource_tracker.register("/mp-stereodem-test-never-made", "semaphore")
    print("done", flush=True)
"""


@pytest.mark.skipif(sys.platform == "win32", reason="the resource tracker is POSIX only")
@pytest.mark.parametrize("mode", ["quiet", "default"])
def test_resource_tracker_reports_nothing_on_the_commands_stderr(tmp_path, mode):
    """After an interrupted job, multiprocessing's resource tracker printed two UserWarning
    lines (leaked semaphores, one 'No such file') after the command's own last line.
    quiet_resource_tracker silences the tracker's reports; "default" shows that this script
    does provoke them (the test can fail)."""
    script = tmp_path / "tracker.py"
    script.write_text(_TRACKER_REPORT)
    # captured output waits for the end of the pipes: the tracker's too, which exits last
    r = subprocess.run(
        [sys.executable, str(script), mode], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "done"
    if mode == "quiet":
        assert r.stderr == ""
    else:
        assert "resource_tracker" in r.stderr and "leaked semaphore" in r.stderr


def test_command_line_quiets_the_tracker_before_any_pool(monkeypatch, tmp_path, capsys):
    """``stereodem.cli.main`` adds the tracker's filter to ``sys.warnoptions`` (the flags the
    tracker is started with) for every command, once."""
    monkeypatch.setattr(sys, "warnoptions", [])
    missing = str(tmp_path / "missing.tif")
    assert main(["change", missing, missing, "-o", str(tmp_path / "out")]) != 0
    assert main(["change", missing, missing, "-o", str(tmp_path / "out")]) != 0
    assert sys.warnoptions == [_TRACKER_FILTER]
