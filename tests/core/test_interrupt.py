"""stereodem.core.interrupt: a stop request stops the job at the next check even when the
KeyboardInterrupt raised by the signal handler was lost (a finaliser, a C callback)."""

import signal

import pytest

from stereodem import cli
from stereodem.core import interrupt
from stereodem.pipeline.record import StageLog
from stereodem.stereo.runner import run_tiles
from stereodem.stereo.tiling import tile_grid


@pytest.fixture(autouse=True)
def _clean():
    interrupt.clear()
    yield
    interrupt.clear()


def test_a_pending_request_stops_at_the_next_stage():
    log = StageLog()
    log.record("load", log.start())  # nothing requested: the stage runs
    interrupt.request(signal.SIGTERM)
    assert interrupt.requested() == signal.SIGTERM
    with pytest.raises(KeyboardInterrupt):
        log.start()
    interrupt.clear()
    log.start()


def test_a_pending_request_stops_the_tile_loop():
    seen = []

    def fn(tile, ctx):
        seen.append(tile.index)
        if len(seen) == 2:
            interrupt.request(signal.SIGINT)  # as if a lost KeyboardInterrupt had been asked for
        return None

    tiles = tile_grid(64, 64, 16)
    with pytest.raises(KeyboardInterrupt):
        run_tiles(fn, tiles, None, workers=1)
    assert len(seen) == 2 < len(tiles)


def test_the_command_line_reports_the_signal_and_forgets_it(monkeypatch, capsys):
    def interrupted(args):
        interrupt.request(signal.SIGTERM)
        raise KeyboardInterrupt

    monkeypatch.setattr("stereodem.info_cli.run", interrupted)
    before = signal.getsignal(signal.SIGINT)  # SIG_IGN where the suite runs in the background
    rc = cli.main(["info", "whatever.tif"])
    assert rc == 128 + signal.SIGTERM
    assert "interrupted (SIGTERM)" in capsys.readouterr().err
    assert interrupt.requested() is None
    assert signal.getsignal(signal.SIGINT) == before
