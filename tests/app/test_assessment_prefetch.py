"""The assessment's inputs read ahead (``stereodem run``): the reference DEM is read in a
background thread of low priority when the job has a second core, on the caller's thread
otherwise, and a read that fails gives the error the assessment's own read gives."""

import threading

import numpy as np
import pytest

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
    DEM(d.heights[:200, :300].copy(), d.transform, d.crs, d.vertical).write(path)
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
