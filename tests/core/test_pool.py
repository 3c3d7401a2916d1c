"""stereodem.core.pool: stopping a process pool at once."""

import pytest

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
    import subprocess
    import sys

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
