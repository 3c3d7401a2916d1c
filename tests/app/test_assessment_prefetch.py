"""The assessment's inputs read ahead (``stereodem run``): the reference DEM is read in a
background thread of low priority when the job has a second core, on the caller's thread
otherwise, and a read that fails gives the error the assessment's own read gives."""

import threading

import numpy as np
import pytest
from helpers.damage import damage_a_middle_block

from stereodem.config import config_from_dict
from stereodem.core.dem import DEM
from stereodem.core.errors import DEMError
from stereodem.pipeline import prefetch as pf


def _cfg(ref, tmp_path):
    return config_from_dict(
        {
            "inputs": {
                "left": str(tmp_path / "left.tif"),
                "right": str(tmp_path / "right.tif"),
                "reference_dem": str(ref),
                "reference_vertical": "geoid",
            },
            "output": {"dir": str(tmp_path / "out")},
        }
    )


@pytest.fixture
def ref(tmp_path):
    path = tmp_path / "ref.tif"
    d = DEM.bundled()
    DEM(d.heights[:300, :600].copy(), d.transform, d.crs, d.vertical).write(path)
    return path


def _threads_reading(monkeypatch):
    """The names of the threads that read a DEM through :func:`DEM.from_file`."""
    names, original = [], DEM.from_file.__func__

    def spy(cls, *a, **k):
        names.append(threading.current_thread().name)
        return original(cls, *a, **k)

    monkeypatch.setattr(DEM, "from_file", classmethod(spy))
    return names


def test_with_two_threads_the_reference_is_read_in_a_background_thread(ref, tmp_path, monkeypatch):
    names = _threads_reading(monkeypatch)
    p = pf.AssessmentPrefetch(_cfg(ref, tmp_path), threads=2)
    got = p.reference()
    assert names and names[0].startswith("stereodem-prefetch")
    assert threading.current_thread().name not in names
    want = DEM.from_file(ref, vertical="geoid")
    np.testing.assert_array_equal(got.heights, want.heights)
    assert got.vertical == want.vertical == "geoid" and p.waited_s >= 0.0


def test_with_one_thread_the_reference_is_read_when_asked_on_the_callers_thread(
    ref, tmp_path, monkeypatch
):
    names = _threads_reading(monkeypatch)
    p = pf.AssessmentPrefetch(_cfg(ref, tmp_path), threads=1)
    assert names == []  # nothing read ahead: a job of one worker keeps to one core
    p.reference()
    assert names == [threading.current_thread().name]


@pytest.mark.parametrize("threads", [1, 2])
def test_a_reference_that_cannot_be_read_gives_the_assessments_own_error(tmp_path, threads):
    bad = tmp_path / "ref.tif"
    bad.write_bytes(b"II*\x00 not a GeoTIFF")
    with pytest.raises(DEMError) as own:
        DEM.from_file(bad, vertical="geoid")
    p = pf.AssessmentPrefetch(_cfg(bad, tmp_path), threads=threads)
    with pytest.raises(DEMError) as ahead:
        p.reference()
    assert str(ahead.value) == str(own.value) and str(bad) in str(ahead.value)


def test_a_failed_read_ahead_is_raised_at_the_next_check(ref, tmp_path, monkeypatch):
    """Once the read ahead has failed, :meth:`raise_if_failed` raises its error (and only
    then: not while it runs, not after it succeeded)."""
    bad = tmp_path / "bad.tif"
    started, release = threading.Event(), threading.Event()

    def damaged(cfg):
        started.set()
        release.wait(timeout=60)
        raise DEMError(f"{cfg.inputs.reference_dem}: cannot read the DEM (damaged)")

    monkeypatch.setattr(pf, "_read_ahead", damaged)
    p = pf.AssessmentPrefetch(_cfg(bad, tmp_path), threads=2)
    started.wait(timeout=60)
    p.raise_if_failed()  # still reading: nothing to raise yet
    release.set()
    p._future.exception(timeout=60)  # the read has failed (waited for here only)
    with pytest.raises(DEMError, match="bad.tif"):
        p.raise_if_failed()
    monkeypatch.undo()
    good = pf.AssessmentPrefetch(_cfg(ref, tmp_path), threads=2)
    good._future.result(timeout=60)
    good.raise_if_failed()  # a read that succeeded raises nothing
    assert good.reference().shape == (300, 600)


@pytest.mark.slow
def test_run_stops_before_the_orthoimages_when_the_reference_cannot_be_read(tmp_path, capsys):
    """A reference DEM damaged in a middle block passes the input checks; read ahead, its
    error stops ``stereodem run`` after the stereo stage, before the filters and orthoimages
    (before: at the assessment, after all of them), as one error line naming it."""
    from helpers.cli_scene import assert_clear_error, job_toml, run_cli, write_sim_scene

    from stereodem.core.threads import job_threads

    if job_threads(2) < 2:
        pytest.skip("one core: the assessment reads its reference itself, at its start")
    sim = write_sim_scene(tmp_path / "sim")
    bad = tmp_path / "ref_damaged.tif"
    assert damage_a_middle_block(sim / "truth_dem.tif", bad)
    out = tmp_path / "out"
    toml = job_toml(tmp_path / "job.toml", sim, out, inputs=f'reference_dem = "{bad}"')
    code, _, err = run_cli(capsys, ["run", toml, "--workers", "2"])
    assert_clear_error(code, err, "run", r"ref_damaged.tif: cannot read the DEM")
    assert (out / "raw" / "dem.tif").exists() or not out.exists()
    assert not list(tmp_path.rglob("ortho_*.tif")) and not (out / "dem.tif").exists()
