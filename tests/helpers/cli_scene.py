"""The small simulated ASTER-like scene the command-line tests run on, and their helpers
(test helper): ``stereodem`` in this process, the one-line error check, a job TOML."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from stereodem import cli
from stereodem.sensor.simulation.simulate import simulate_scene, write_scene

HR = ["--height-range", "1000", "3500"]  # the simulated terrain lies at ~1790..2870 m


def write_sim_scene(d: Path) -> Path:
    """The 300 x 300 simulated ASTER-like pair (seed 0, 20 check points) written to ``d``
    (``left.tif``, ``right.tif``, their model sidecars, ``truth_dem.tif``, ...).

    Simulated and written once per test session (into ``sim_master`` beside ``d``, in pytest's
    base temporary folder), then copied: the files hold no path, so every module gets the same
    bytes in a folder of its own that its tests may change."""
    master = d.parent / "sim_master"
    if not master.is_dir():  # renamed into place once complete
        tmp = d.parent / "sim_master.partial"
        shutil.rmtree(tmp, ignore_errors=True)
        scene = simulate_scene("aster", size=(300, 300), seed=0, n_points=20)
        write_scene(scene, tmp, overwrite=True)
        tmp.rename(master)
    shutil.copytree(master, d, dirs_exist_ok=True)
    return d


def run_cli(capsys, argv):
    """``stereodem ARGV`` in this process: (exit status, stdout, stderr)."""
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_clear_error(code, err, command, pattern):
    """Exit status 1 and exactly one ``stereodem COMMAND: error: ...`` line matching ``pattern``
    (case-insensitive), no traceback."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert code == 1, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"stereodem {command}: error: "), lines[0]
    assert re.search(pattern, lines[0], re.IGNORECASE), lines[0]


def job_toml(
    path: Path,
    sim: Path,
    out: Path,
    extra: str = "",
    rect: str = "tile_size = 300\nheight_range = [1000, 3500]",
    inputs: str = "",
) -> Path:
    """A job TOML at ``path`` on the scene in ``sim`` writing to ``out``: ``inputs`` added to
    ``[inputs]``, ``rect`` the ``[rectification]`` table, ``extra`` appended (more tables)."""
    path.write_text(f"""[inputs]
left = "{sim / "left.tif"}"
right = "{sim / "right.tif"}"
{inputs}
[output]
dir = "{out}"
[rectification]
{rect}
{extra}
""")
    return path
