"""Progress bars (tqdm, ETA, silent off a terminal or with -q), warnings through logging,
UTC timestamps with -v, and the provenance record (issue #19)."""

from __future__ import annotations

import io
import logging
import re
import subprocess
import sys

import pytest

from stereodem import __version__, options
from stereodem.progress import STAGES, Progress, TqdmLoggingHandler, UTCFormatter, stage_bar
from stereodem.provenance import git_commit, provenance, utc_now
from stereodem.run_cli import progress_factory
from stereodem.stereo.execution import ProgressPasses


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_bar_on_a_terminal_shows_eta_and_callback_total():
    s = _Tty()
    p = Progress("stereo", 1, stream=s)
    for k in range(1, 5):
        p(k, 4)  # the pipeline's callback form, total learnt late
    p.close()
    out = s.getvalue()
    assert "stereo" in out and "100%" in out and "4/4" in out
    assert "<" in out  # tqdm's [elapsed<remaining] field: the ETA
    assert p.done == 4 and p.total == 4


@pytest.mark.parametrize("tty,enabled", [(False, True), (True, False)])
def test_silent_off_a_terminal_or_quiet(tty, enabled, caplog):
    s = _Tty() if tty else io.StringIO()
    with caplog.at_level(logging.INFO, logger="stereodem.progress"):
        with stage_bar("ortho", stream=s, enabled=enabled) as p:
            p(10, 10)
    assert s.getvalue() == ""
    summary = [r.getMessage() for r in caplog.records if r.name == "stereodem.progress"]
    expected = ["orthoimages: 10/10 rows in " + summary[0].split(" in ")[1]] if enabled else []
    assert summary == expected


def test_log_lines_go_above_the_bar(monkeypatch):
    s = _Tty()
    monkeypatch.setattr(sys, "stderr", s)
    lg = logging.getLogger("stereodem.test_bar")
    h = TqdmLoggingHandler()
    h.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
    lg.addHandler(h)
    lg.propagate = False
    try:
        p = Progress("stereo", 4, stream=s)
        p(1, 4)
        lg.warning("tile 2 failed")
        p(4, 4)
        p.close()
    finally:
        lg.removeHandler(h)
        lg.propagate = True
    out = s.getvalue()
    # the warning is on a line of its own: tqdm cleared the bar before writing it
    line = [ln for ln in re.split(r"[\r\n]", out) if "tile 2 failed" in ln]
    assert line and line[0].strip() == "WARNING tile 2 failed"


def test_utc_timestamps_and_captured_warnings():
    rec = logging.LogRecord("stereodem", logging.INFO, __file__, 1, "hello", None, None)
    rec.created = 0.0
    rec.msecs = 0.0
    assert UTCFormatter("%(asctime)s %(message)s").format(rec) == "1970-01-01T00:00:00.000Z hello"


def test_cli_verbose_has_timestamps_and_warnings_are_logged(tmp_path):
    code = (
        "import warnings, logging; from stereodem.progress import setup_logging;"
        "setup_logging(verbose=1); logging.getLogger('stereodem').info('info line');"
        "warnings.warn('careful')"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    lines = r.stderr.strip().splitlines()
    assert re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z INFO stereodem: info line$", lines[0])
    assert re.match(r".*Z WARNING py\.warnings: .*UserWarning: careful", lines[1])
    r = subprocess.run(
        [sys.executable, "-c", code.replace("verbose=1", "quiet=True")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.stderr == ""


def test_cli_logging_drops_rasterios_not_georeferenced_warning():
    """Before, opening a raster without a geotransform printed rasterio's warning as a
    two-line ``WARNING py.warnings: .../rasterio/__init__.py:356: NotGeoreferencedWarning``
    with a source line, before the DEM's own one-line refusal (or for every image in sensor
    geometry, which has no geotransform by nature); other warnings are still logged."""
    code = (
        "import warnings; from rasterio.errors import NotGeoreferencedWarning;"
        "from stereodem.progress import setup_logging; setup_logging();"
        "msg = 'Dataset has no geotransform, gcps, or rpcs. The identity matrix will be "
        "returned.';"
        "warnings.warn_explicit(msg, NotGeoreferencedWarning, 'x/rasterio/__init__.py', 356,"
        " module='rasterio'); warnings.warn('careful')"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert "NotGeoreferenced" not in r.stderr
    assert re.fullmatch(r"WARNING py\.warnings: .*UserWarning: careful\n.*\n?", r.stderr, re.S)


def test_provenance_fields():
    t0 = utc_now()
    p = provenance(started=t0, argv=["/usr/bin/stereodem", "run", "job toml"])
    assert p["started_utc"] == t0 and p["ended_utc"] >= t0
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", p["ended_utc"])
    assert p["command_line"] == "stereodem run 'job toml'"

    assert p["stereodem_version"] == __version__
    git = git_commit()
    if git is None:
        assert "git_commit" not in p
    else:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            cwd=__file__.rsplit("/", 2)[0],
        ).stdout.strip()
        assert p["git_commit"] == head and isinstance(p["git_dirty"], bool)


def test_the_commit_is_looked_up_once_when_the_run_begins(monkeypatch):
    """The commit was looked up (``git``) for every provenance record, the last ones at the
    end of a run, from a process of gigabytes: the kernel counted that child as one of that
    size (run.json's ``peak_worker_rss_mb`` of the assessment 1.5 GB on a full granule, the
    tile workers' 0.37 GB). It is looked up once per process, when the run begins."""
    import stereodem.provenance as prov

    calls = []

    def commit():
        calls.append(1)
        return {"commit": "abc", "dirty": False}

    monkeypatch.setattr(prov, "git_commit", commit)
    prov.package_commit.cache_clear()
    try:
        t0 = prov.begin()
        assert calls == [1]
        records = [prov.provenance(started=t0) for _ in range(2)]
        assert calls == [1]
        assert [r["git_commit"] for r in records] == ["abc", "abc"]
        assert records[0]["started_utc"] == t0
    finally:
        prov.package_commit.cache_clear()


def test_no_commit_outside_a_work_tree(tmp_path):
    assert git_commit(tmp_path) is None


def test_every_bar_has_its_stages_description_and_unit():
    """Before, the bars were made in two places with the stage's name only: tqdm's default
    ``it/s`` rate and a bare ``12/30`` count."""
    for stage, (label, unit) in STAGES.items():
        s = _Tty()
        with stage_bar(stage, stream=s) as p:
            p(3, 7)
        out = s.getvalue()
        assert p.label == label and p.unit == unit
        assert f"3/7 {unit}s" in out and f"{unit}/s" in out and "it/s" not in out, out
        assert out.lstrip("\r").startswith(label)
    assert STAGES["stereo"][1] == "tile" and STAGES["ortho"][1] == "row"
    assert STAGES["mosaic"][1] == "block" and STAGES["stack"][1] == "DEM"
    with pytest.raises(KeyError):
        stage_bar("no such stage")


def test_the_command_lines_bars_come_from_stage_bar():
    """:func:`stage_bar` is the one place bars are made: the options' and the job's."""

    class Args:
        quiet = False

    for p in (options.progress_bar("ortho"), progress_factory(Args())("ortho")):
        assert (p.label, p.unit) == STAGES["ortho"]
        p.close()
    assert progress_factory(type("A", (), {"quiet": True})())("stereo").enabled is False


def test_a_bar_is_drawn_from_its_first_total_and_never_counts_down():
    """Before, the orthoimage stage's bar was drawn at 0/1 (its total unknown), then again at
    0/675, and a count below the last one started it again from 0."""
    s = _Tty()
    p = stage_bar("ortho", stream=s)
    assert s.getvalue() == ""  # nothing drawn before the stage says its total
    p(600, 675)
    p(675, 675)
    p(100, 675)  # a count below the last one: ignored, not a restart
    assert p.done == 675 and p._bar.n == 675
    p.close()
    out = s.getvalue()
    assert "| 0/1 " not in out and out.count("| 0/675 ") == 1, out  # drawn empty once
    assert "675/675 rows" in out


def test_passes_count_on_in_one_bar():
    """The jitter correction's second DEM, or an N-view stage's next pair, counts on after
    the tiles of the passes before it (it started the stereo bar again from 0 before)."""
    seen = []
    passes = ProgressPasses(lambda done, total: seen.append((done, total)))
    passes.next_pass()
    for k in (1, 2, 3):
        passes(k, 3, {"tile": k})  # the serial runner's third argument, a tile's summary
    passes.next_pass()
    for k in (1, 2):
        passes(k, 2)
    assert seen == [(1, 3), (2, 3), (3, 3), (4, 5), (5, 5)]
    s = _Tty()
    with stage_bar("stereo", stream=s) as bar:
        passes = ProgressPasses(bar)
        for n in (3, 2):
            passes.next_pass()
            for k in range(1, n + 1):
                passes(k, n)
    assert bar.done == 5 and bar.total == 5 and "5/5 tiles" in s.getvalue()


@pytest.mark.slow
def test_quiet_leaves_out_every_commands_result_lines(tmp_path):
    """``-q`` ("only errors") silenced the result lines of ``dem`` and ``mosaic`` but not those
    of ``simulate``, ``assess``, ``run``, ``demo``, ``adjust``, ``compare-models`` and
    ``uncertainty``, which printed straight to standard output."""

    def cli(*argv):
        return subprocess.run(
            [sys.executable, "-m", "stereodem.cli", *map(str, argv)],
            capture_output=True,
            text=True,
            timeout=120,
        )

    sim = tmp_path / "sim"
    r = cli("-q", "simulate", "--size", "64", "64", "-o", sim)
    assert r.returncode == 0 and r.stdout == "" and r.stderr == "", r.stdout + r.stderr
    dem = sim / "truth_dem.tif"
    r = cli("-q", "assess", dem, "--ref", dem, "-o", tmp_path / "a")
    assert r.returncode == 0 and r.stdout == "" and r.stderr == "", r.stdout + r.stderr
    # without -q the same command says what it wrote
    r = cli("assess", dem, "--ref", dem, "-o", tmp_path / "b")
    assert r.returncode == 0 and "nmad=" in r.stdout
