"""The post stage of a job (``stereodem run``, ``stereodem filter``): the border rim."""

import numpy as np
from affine import Affine
from pyproj import CRS

from stereodem.config import Config, FillSettings, InputSettings
from stereodem.core.dem import DEM
from stereodem.pipeline.stages import post_stage
from stereodem.post.filters import EditCode


def test_the_border_rim_is_the_matched_areas_not_the_filters_holes():
    """``[filters] erode`` removes the rim of the matched area (partial correlation windows):
    the stereo DEM's edges and its own voids. It also eroded around the holes the blunder
    filters had just made (a spike's hole grew from 1 to 25 cells; 20 % of the real Pleiades
    pair's cells went that way)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:60, 0:60]
    z = (1000 + 0.5 * xx + 0.3 * yy + rng.normal(0, 0.3, (60, 60))).astype(np.float32)
    z[20:26, 40:46] = np.nan  # a void of the matching
    z[40, 20] += 80.0  # a blunder: the spike filter removes it
    dem = DEM(z, Affine(30, 0, 500_000, 0, -30, 4_400_000), CRS.from_epsg(32637), "ellipsoid")
    cfg = Config(
        inputs=InputSettings(dem="dem.tif"), output_dir="out", fill=FillSettings(enabled=False)
    )
    clean, report = post_stage(cfg, dem)
    mask = clean.edit_mask
    assert np.isnan(clean.heights[40, 20]) and mask[40, 20] not in (0, EditCode.BORDER_RIM)
    # the blunder's neighbours stay; the rim of the edges and of the void goes
    assert np.isfinite(clean.heights[38:43, 18:23]).sum() == 24
    rim = mask == EditCode.BORDER_RIM
    assert rim[:2].all() and rim[-2:].all() and rim[:, :2].all() and rim[:, -2:].all()
    assert rim[18:28, 38:48].sum() == 100 - 36  # a 2-cell ring around the 6 x 6 void
    assert report["erode"]["removed"] == int(rim.sum()) == 60 * 60 - 56 * 56 + 64
