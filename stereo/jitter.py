"""Stereo DEM with along-track jitter correction of the second camera against a reference DEM.

One round of the MMASTER-style correction (ASTER notes §7 item 12): a first DEM with the
nominal models, its residuals against ``reference`` turned into a pitch oscillation of the
second camera (:func:`stereodem.sensor.estimation.jitter.estimate_pitch_jitter`: sum of sines
fitted to the along-track profile), the second model corrected by that time-varying attitude,
and the DEM made again.
"""
from __future__ import annotations

import dataclasses

from stereodem.sensor.estimation.jitter import estimate_pitch_jitter, with_attitude_sines
from stereodem.sensor.geo.dem import DEM, ELLIPSOID, as_dem
from stereodem.stereo.pipeline import make_dem
from stereodem.stereo.settings import StereoSettings


def products_dem(products) -> DEM:
    """The :class:`~stereodem.sensor.geo.dem.DEM` of :func:`make_dem` products."""
    g = products.dem
    return DEM(g.heights, g.transform, g.crs, g.vertical, None)


def dem_with_jitter_correction(left_image, right_image, left_model, right_model, reference,
                               settings: StereoSettings | None = None, *, seed_dem=None,
                               n_sines: int = 1, f_range=(0.2, 8.0), runner=None):
    """``(products, corrected_right_model, fit, first_products)``; ``runner`` as
    :func:`~stereodem.stereo.pipeline.make_dem`'s.

    ``reference`` is a DEM (or path) covering the scene; ``fit`` is the
    :class:`~stereodem.sensor.estimation.jitter.SineSeries` of the right camera's pitch (rad).
    The first DEM is made on ellipsoidal heights whatever ``settings.gridding.geoid`` says;
    without a height range or ``seed_dem`` the reference sets the tiles' height ranges.
    """
    settings = settings or StereoSettings()
    ref = as_dem(reference)
    seed = seed_dem if seed_dem is not None or settings.rectification.height_range else ref
    first_settings = dataclasses.replace(
        settings, gridding=dataclasses.replace(settings.gridding, geoid=False))
    first = make_dem(left_image, right_image, left_model, right_model, first_settings, seed_dem=seed,
                     runner=runner)
    d0 = products_dem(first)
    if d0.vertical != ELLIPSOID:          # pragma: no cover - geoid=False above
        raise AssertionError("first DEM must be ellipsoidal")
    fit, diag = estimate_pitch_jitter(d0, ref, left_model, right_model, n_sines=n_sines,
                                      f_range=f_range)
    corrected = with_attitude_sines(right_model, fit)
    final = make_dem(left_image, right_image, left_model, corrected, settings, seed_dem=seed,
                     runner=runner)
    final.info["jitter"] = {**fit.to_dict(), "sensitivity_m_per_rad": diag["sensitivity_m_per_rad"]}
    return final, corrected, fit, first
