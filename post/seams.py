"""Is there a step where two granules meet? The DEM's error on either side of an image line.

A strip DEM (:mod:`stereodem.strip`) is made from granules joined at image lines (the seam
lines of :func:`stereodem.sensor.io.aster_strip.join_band`). A seam that is not right (a wrong
line offset, models that disagree) shows as a step in the height error across the ground
trace of that line. :func:`seam_step` measures it against a reference DEM: every DEM cell is
placed on an image line of the model (its centre, at the reference height, projected
through the model) and the median of the height error is taken in a band of lines on each
side.
"""

from __future__ import annotations

import numpy as np

from stereodem.core import geodesy
from stereodem.core.stats import nmad
from stereodem.post import warp


def seam_step(dem, reference, model, seam_line: float, *, half_width: float) -> dict:
    """Height error of ``dem`` against ``reference`` (both :class:`~stereodem.core.dem.DEM`,
    one vertical reference) on each side of image line ``seam_line`` of ``model``.

    Cells whose centre projects within ``half_width`` lines before the seam line make the
    ``before`` band, those within ``half_width`` lines after it the ``after`` band. Returns
    ``{"seam_line", "half_width_lines", "n_before", "n_after", "median_before_m",
    "median_after_m", "step_m" (after - before), "nmad_before_m", "nmad_after_m"}`` (metres).
    """
    ref = warp.to_grid(
        reference.heights, reference.transform, reference.crs, dem.transform, dem.crs, dem.shape
    )
    dh = dem.heights.astype(np.float64) - ref
    rows, cols = np.nonzero(np.isfinite(dh))
    x, y = dem.transform @ (cols + 0.5, rows + 0.5)
    lon, lat = geodesy.crs_to_lonlat(np.asarray(x), np.asarray(y), dem.crs)
    _, line = model.project(lon, lat, ref[rows, cols].astype(np.float64))
    e = dh[rows, cols]
    before = (line >= seam_line - half_width) & (line < seam_line)
    after = (line >= seam_line) & (line < seam_line + half_width)
    mb, ma = (float(np.median(e[s])) if s.any() else float("nan") for s in (before, after))
    return dict(
        seam_line=float(seam_line),
        half_width_lines=float(half_width),
        n_before=int(before.sum()),
        n_after=int(after.sum()),
        median_before_m=round(mb, 4),
        median_after_m=round(ma, 4),
        step_m=round(ma - mb, 4),
        nmad_before_m=round(nmad(e[before]), 4),
        nmad_after_m=round(nmad(e[after]), 4),
    )


__all__ = ["seam_step"]
