"""A GeoTIFF damaged in a block the input checks do not probe is refused when read, whatever
the thread budget: GDAL 3.6 (rasterio 1.3.8's wheels, the declared minimum) decoded such a
block into zeros without an error when its blocks were decoded on several threads
(``GDAL_NUM_THREADS`` 2 or ``ALL_CPUS``), so heights of 0 m were read as data; GDAL 3.8 and
later raise. Below 3.8 stereodem decodes on one thread (``core.threads.gdal_threads``)."""

import contextlib

import pytest
import rasterio
from helpers.damage import damage_a_middle_block

from stereodem.core import threads
from stereodem.core.dem import DEM
from stereodem.core.errors import DEMError
from stereodem.core.raster import reading_env

#: a failed read (RasterioIOError is an OSError, not a RasterioError, before rasterio 1.4)
GDAL_READ_ERRORS = (rasterio.errors.RasterioError, rasterio.errors.RasterioIOError)


@pytest.fixture
def damaged(tmp_path):
    d = DEM.bundled()
    DEM(d.heights[:300, :600].copy(), d.transform, d.crs, d.vertical).write(tmp_path / "ok.tif")
    return tmp_path / "ok.tif", tmp_path / "damaged.tif"


@pytest.mark.parametrize("budget", [None, 1, 2])
def test_a_dem_damaged_in_a_middle_block_is_refused_whatever_the_budget(damaged, budget):
    ok, bad = damaged
    with threads.thread_budget(budget) if budget else contextlib.nullcontext():
        assert damage_a_middle_block(ok, bad)  # DEM.from_file refuses it
        with pytest.raises(DEMError, match=r"damaged\.tif"):
            DEM.from_file(bad)
        with reading_env(), rasterio.open(bad) as ds, pytest.raises(GDAL_READ_ERRORS):
            ds.read(1)
        assert DEM.from_file(ok).heights.shape == (300, 600)


def test_gdal_threads_is_the_budget_from_gdal_3_8(monkeypatch):
    monkeypatch.setattr(rasterio, "__gdal_version__", "3.6.4")
    assert threads.gdal_threads(4) == "1" and threads.gdal_threads("ALL_CPUS") == "1"
    monkeypatch.setattr(rasterio, "__gdal_version__", "3.8.4")
    assert threads.gdal_threads(4) == "4" and threads.gdal_threads("ALL_CPUS") == "ALL_CPUS"


def test_an_error_raised_from_gdals_crosses_to_the_dask_client_as_itself(damaged):
    """Dask ships a task's error with its chain: GDAL's error (rasterio's ``CPLE_*``) in it does
    not unpickle, and the client got a bare ``Exception``; :func:`portable` drops the chain."""
    core = pytest.importorskip("distributed.core")
    from stereodem.core.errors import portable

    ok, bad = damaged
    damage_a_middle_block(ok, bad)

    def read_error():
        try:
            DEM.from_file(bad)
        except DEMError as exc:
            return exc

    def through_dask(exc):  # what a worker sends for a task's error, as the client loads it
        from distributed.protocol.pickle import loads

        sent = core.error_message(exc)["exception"]
        return loads(getattr(sent, "data", sent))

    chained = read_error()
    assert chained.__context__ is not None  # GDAL's error, the message says what it said
    assert type(through_dask(chained)) is Exception  # what the client got
    got = through_dask(portable(read_error()))
    assert type(got) is DEMError and str(got) == str(chained)
