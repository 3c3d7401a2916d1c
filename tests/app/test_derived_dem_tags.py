"""A DEM made from a stereodem DEM on its own grid keeps what stereodem stored with it: the
clean DEM of ``stereodem filter`` and the corrected one of ``stereodem coregister`` carry the
ground track (``STEREODEM_TRACK_HEADING`` / ``STEREODEM_TRACK_FRAME``, which ``coregister
--chain ...,along_track`` and ``stack``'s default chain read) and the acquisition date
(``stack``). Both dropped them: README's ``dem`` -> ``filter`` -> ``coregister --chain
nuth_kaab,deramp:1,along_track`` stopped with "the DEM carries none: give --track-angle"."""

from __future__ import annotations

import json

import numpy as np
import rasterio

from stereodem import cli
from stereodem.core.dem import DEM
from stereodem.post.coreg_run import TRACK_HEADING_TAG, carried_tags, track_heading_of
from stereodem.post.dates import date_from_metadata


def _dem(tmp_path, tags=None, name="dem.tif"):
    full = DEM.bundled()
    ref = DEM(full.heights[:80, :80].copy(), full.transform, full.crs, "geoid")
    d = tmp_path / "in"
    d.mkdir(exist_ok=True)
    ref.write(d / "ref.tif")
    noisy = ref.heights + np.random.default_rng(0).normal(0, 1.0, ref.shape).astype(np.float32)
    DEM(noisy, ref.transform, ref.crs, "geoid").write(d / name, tags=tags)
    return d


def _tags(path):
    with rasterio.open(path) as ds:
        return ds.tags()


def test_filter_and_coregister_keep_the_track_and_the_date(tmp_path):
    d = _dem(tmp_path, {TRACK_HEADING_TAG: "192.0000", "ACQUISITION_DATE": "2017-07-31"})
    clean = tmp_path / "clean.tif"
    assert cli.main(["-q", "filter", str(d / "dem.tif"), "-o", str(clean), "--workers", "1"]) == 0
    assert track_heading_of(clean) == 192.0
    assert _tags(clean)["ACQUISITION_DATE"] == "2017-07-31"
    # the filtered DEM goes on to a chain that needs the track, without --track-angle
    co = tmp_path / "co"
    argv = ["-q", "coregister", str(clean), "--ref", str(d / "ref.tif"), "-o", str(co)]
    assert cli.main([*argv, "--chain", "vshift", "--no-figures", "--workers", "1"]) == 0
    assert track_heading_of(co / "dem_coregistered.tif") == 192.0
    assert str(date_from_metadata(co / "dem_coregistered.tif")) == "2017-07-31T00:00:00"
    assert json.loads((co / "coregistration.json").read_text())["track_heading_deg"] == 192.0


def test_a_date_beside_the_dem_goes_into_the_tags(tmp_path):
    """A DEM dated by the ``dem_report.json`` beside it (``stereodem dem`` of a granule) keeps
    its date when the filtered DEM is written into another folder."""
    d = _dem(tmp_path)
    (d / "dem_report.json").write_text(
        json.dumps({"input_metadata": {"ASTER_ACQUISITION_TIME": "2017-07-31T19:07:28Z"}})
    )
    assert carried_tags(d / "dem.tif") == {"ACQUISITION_DATE": "2017-07-31T19:07:28"}
    clean = tmp_path / "elsewhere" / "clean.tif"
    clean.parent.mkdir()
    assert cli.main(["-q", "filter", str(d / "dem.tif"), "-o", str(clean), "--workers", "1"]) == 0
    assert str(date_from_metadata(clean)) == "2017-07-31T19:07:28"
    assert carried_tags(tmp_path / "missing.tif") == {}
