"""A seed DEM is judged on the scene it covers, not on the whole file (real-data audit of
the Pleiades pair over La Réunion): the pair's RPCs are valid for -20..2610 m, and a 1 degree
SRTM tile around the scene holds Piton des Neiges (3070 m) 20 km away. The whole file's
heights used to be checked against the models, so such a tile was refused as "wrong units
(feet?)"; a seed DEM of another place (the bundled Turkish SRTM tile) got the same message
instead of "not the DEM of this scene"."""

from __future__ import annotations

import numpy as np
import pytest
from affine import Affine
from pyproj import CRS

from stereodem.config import Config, InputSettings
from stereodem.core.dem import DEM
from stereodem.core.errors import DEMCoverageError, DEMError
from stereodem.multiview import reference_height
from stereodem.sensor.models.rpc import RPCModel
from stereodem.stereo.plan import seed_height_range
from stereodem.stereo.sanity import check_seed_dem


@pytest.fixture(scope="module")
def pair(data_dir):
    return tuple(RPCModel.from_file(data_dir / "pleiades" / f"img_0{i}_rpc.tif") for i in (1, 2))


def _seed(west, north, shape=(800, 800), step=0.001, base=2320.0):
    """An ellipsoidal lon/lat seed DEM: ``base`` m with a 3070 m summit in its north-west
    corner (20+ km from the scene at 55.65 E, 21.23 S when it spans the island)."""
    h = np.full(shape, base, np.float32)
    h[50:150, 50:150] = 3070.0
    return DEM(
        h,
        Affine(step, 0.0, west, 0.0, -step, north),
        CRS.from_epsg(4326),
        vertical="ellipsoid",
        path="seed.tif",
    )


def test_a_seed_dem_larger_than_the_scene_is_judged_on_the_scene(pair):
    left, right = pair
    seed = _seed(55.25, -20.83)  # 55.25..56.05 E, 21.63..20.83 S: the scene and the summit
    assert seed.height_range() == (2320.0, 3070.0)  # the whole file
    assert seed_height_range(seed, left, right) == (2320.0, 2320.0)  # under the scene
    assert check_seed_dem(seed, left, right) == 1.0  # was a DEMError: "feet?"


def test_a_seed_dem_of_another_place_is_named_as_such(pair):
    left, right = pair
    seed = _seed(40.0, 40.0)  # eastern Turkey
    with pytest.raises(DEMCoverageError, match=r"does not cover the scene.*this scene"):
        check_seed_dem(seed, left, right)


def test_a_seed_dem_in_feet_under_the_scene_is_still_refused(pair):
    left, right = pair
    seed = _seed(55.25, -20.83, base=2320.0 * 3.28084)
    with pytest.raises(DEMError, match=r"implausible for the sensor models.*feet"):
        check_seed_dem(seed, left, right)


def test_an_n_view_job_plans_at_the_seeds_height_under_the_scene(pair):
    """The N-view route planned footprints, bases and the lattice at the middle of the whole
    seed file's heights (2695 m with the summit 20 km away; 2320 m under the scene)."""
    cfg = Config(inputs=InputSettings(left="a.tif", right="b.tif"), output_dir="out")
    assert reference_height(cfg, pair, _seed(55.25, -20.83)) == 2320.0
    # a seed elsewhere: planned on the models (its own check names it)
    assert reference_height(cfg, pair, _seed(40.0, 40.0)) == reference_height(cfg, pair)
