"""`run` and `dem` start the tile pool's fork server before they import their pipeline
(its imports then use a core the command's start leaves idle), and no server outlives a job
that did not use it."""

import subprocess
import sys
import textwrap
from types import SimpleNamespace

import pytest

from stereodem.run_cli import _pool_request

needs_fork_server = pytest.mark.skipif(
    "forkserver" not in __import__("multiprocessing").get_all_start_methods(),
    reason="no fork server on this platform",
)


def _args(config, workers=None, dask=None):
    return SimpleNamespace(config=str(config), workers=workers, dask=dask)


def test_the_pool_request_is_the_command_lines_else_the_run_tables(tmp_path):
    cfg = tmp_path / "job.toml"
    cfg.write_text('[run]\nworkers = 3\ndask = "tcp://h:8786"\n')
    assert _pool_request(_args(cfg)) == (3, "tcp://h:8786")
    assert _pool_request(_args(cfg, workers=2, dask="tcp://x:1")) == (2, "tcp://x:1")
    cfg.write_text("[output]\ndir = 'o'\n")
    assert _pool_request(_args(cfg)) == (None, None)  # no [run]: all cores, no Dask
    # unreadable or ill-typed: no early start (load_config reports the problem)
    assert _pool_request(_args(tmp_path / "missing.toml")) == (1, None)
    cfg.write_text("[run\n")
    assert _pool_request(_args(cfg)) == (1, None)
    cfg.write_text('[run]\nworkers = "two"\n')
    assert _pool_request(_args(cfg)) == (1, None)
    cfg.write_text("run = 3\n")
    assert _pool_request(_args(cfg)) == (1, None)
    cfg.write_bytes(b"[run]\nworkers = 2\n\x80\xff")
    assert _pool_request(_args(cfg)) == (1, None)


_PROBE = """
import sys
from multiprocessing import forkserver
import stereodem.stereo.fork_server as fs
seen = []
real = fs._start_fork_server
def probe():
    heavy = ("stereodem.stereo.pipeline", "cv2", "rasterio", "threadpoolctl", "scipy")
    seen.append(any(m in sys.modules for m in heavy))
    return real()
fs._start_fork_server = probe
from stereodem.cli import main
rc = main({argv!r})
print(rc, seen, forkserver._forkserver._forkserver_pid)
"""


@pytest.mark.slow  # a subprocess importing the whole program (~1 s each)
@needs_fork_server
@pytest.mark.parametrize("command", ["run", "dem"])
def test_the_server_starts_before_the_pipeline_loads_and_ends_with_a_failed_job(tmp_path, command):
    if command == "run":
        cfg = tmp_path / "job.toml"
        missing = tmp_path / "missing.hdf"
        cfg.write_text(
            f'[inputs]\nleft = "{missing}"\nright = "{missing}"\n'
            f'[output]\ndir = "{tmp_path / "out"}"\n[run]\nworkers = 2\n'
        )
        argv = ["-q", "run", str(cfg)]
    else:
        missing = str(tmp_path / "missing.hdf")
        argv = ["-q", "dem", missing, missing, "-o", str(tmp_path / "out"), "--workers", "2"]
    p = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(_PROBE.format(argv=argv))],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    rc, rest = p.stdout.split(maxsplit=1)
    seen, pid = rest.rsplit(maxsplit=1)
    assert rc == "1" and "missing.hdf" in p.stderr  # the job failed, with a clear message
    # started before the tile code, OpenCV or rasterio was imported here (the thread budget
    # imports the last two: the server used to wait ~1 s for them on one core)
    assert seen.startswith("[False")
    assert pid == "None"  # and stopped: no server outlives the job


@pytest.mark.slow
@needs_fork_server
def test_one_worker_starts_no_server(tmp_path):
    cfg = tmp_path / "job.toml"
    cfg.write_text(
        f'[inputs]\nleft = "{tmp_path / "missing.hdf"}"\n'
        f'[output]\ndir = "{tmp_path / "out"}"\n[run]\nworkers = 1\n'
    )
    p = subprocess.run(
        [
            sys.executable,
            "-c",
            textwrap.dedent(_PROBE.format(argv=["-q", "run", str(cfg)])),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["1", "[]", "None"]


def test_the_servers_first_preload_makes_it_ignore_ctrl_c():
    """A Ctrl-C in a job's first second reached the fork server while it imported the tile
    code (CPython ignores SIGINT there only after its preload imports): its 30-line
    KeyboardInterrupt traceback came out above the command's one-line message. The server's
    first preload module now makes it ignore SIGINT, before the heavy imports."""
    from stereodem.stereo import fork_server

    assert fork_server._PRELOAD[0] == "stereodem.core.ignore_interrupt"
    script = (
        "import signal, sys; import stereodem.core.ignore_interrupt; "
        "print(signal.getsignal(signal.SIGINT) is signal.SIG_IGN, "
        "'numpy' in sys.modules, 'cv2' in sys.modules)"
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert r.stdout.split() == ["True", "False", "False"], r.stderr  # ignored, nothing heavy


@pytest.mark.slow
@needs_fork_server
def test_a_ctrl_c_to_the_starting_server_prints_no_traceback():
    """The fork server, once it ignores SIGINT (its status says so), takes a Ctrl-C while its
    imports go on without a traceback and keeps running."""
    script = textwrap.dedent(
        """
        import os, signal, time
        from multiprocessing import forkserver
        from stereodem.stereo import fork_server
        assert fork_server.warm_fork_server(2)
        pid = forkserver._forkserver._forkserver_pid
        mask = 0
        for _ in range(1000):  # until the server ignores SIGINT (bit 2 of SigIgn)
            with open(f"/proc/{pid}/status") as f:
                line = next(x for x in f if x.startswith("SigIgn:"))
            mask = int(line.split()[1], 16)
            if mask & (1 << (signal.SIGINT - 1)):
                break
            time.sleep(0.005)
        os.kill(pid, signal.SIGINT)
        time.sleep(1.0)
        done, status = os.waitpid(pid, os.WNOHANG)
        print("alive" if done == 0 else f"ended {status}")
        fork_server.stop_idle_fork_server()
        """
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "alive"
    assert "Traceback" not in r.stderr and "KeyboardInterrupt" not in r.stderr
