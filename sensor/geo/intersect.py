"""Space intersection: matched image points of two sensor models -> 3-D ground points.

Each image point defines a line of sight through the exact model (``model.rays(col, row)``:
ECEF origin and unit direction; models without exact rays get them from two localisations).
The least-squares point of two lines is the midpoint of their common perpendicular, computed
here in closed form for all matches at once; the length of that perpendicular is the *ray
gap*, the distance (m) by which the two lines of sight miss each other. A ray gap much larger
than the matching precision times the GSD flags a blunder or a pointing error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereodem.core import geodesy

__all__ = ["Intersection", "intersect_rays", "intersect_matches"]


@dataclass
class Intersection:
    """Ground points from two rays per match.

    Attributes
    ----------
    ecef : ndarray (N, 3)
        Midpoints of the common perpendiculars, ECEF metres (NaN where the rays are parallel
        or a model failed).
    lon, lat, h : ndarray (N,)
        The same points, degrees and metres above the WGS84 ellipsoid.
    ray_gap : ndarray (N,)
        Closest-approach distance of the two rays, metres.
    """

    ecef: np.ndarray
    lon: np.ndarray
    lat: np.ndarray
    h: np.ndarray
    ray_gap: np.ndarray

    def __len__(self):
        return len(self.h)


def intersect_rays(o1, d1, o2, d2):
    """Closest points of pairs of lines ``o + s d`` (ECEF, any consistent units).

    Parameters
    ----------
    o1, d1, o2, d2 : array_like (..., 3)
        Origins and directions (need not be unit vectors).

    Returns
    -------
    point : ndarray (..., 3)
        Midpoint of the common perpendicular (NaN for parallel lines).
    gap : ndarray (...)
        Length of the common perpendicular.
    """
    o1, d1, o2, d2 = (np.asarray(a, np.float64) for a in (o1, d1, o2, d2))
    w = o1 - o2

    def dot(x, y):
        return np.einsum("...i,...i->...", x, y)

    a, b, c, d, e = dot(d1, d1), dot(d1, d2), dot(d2, d2), dot(d1, w), dot(d2, w)
    den = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        den = np.where(den > 1e-15 * a * c, den, np.nan)
        s = (b * e - c * d) / den
        t = (a * e - b * d) / den
    p1 = o1 + s[..., None] * d1
    p2 = o2 + t[..., None] * d2
    gap = p1 - p2
    return 0.5 * (p1 + p2), np.sqrt(dot(gap, gap))


def intersect_matches(
    left, right, col1, row1, col2, row2, *, tolerance_m: float | None = None
) -> Intersection:
    """Intersect the lines of sight of matched pixels of two sensor models.

    Parameters
    ----------
    left, right : stereodem.sensor.models.base.SensorModel
        Exact models of the two images.
    col1, row1, col2, row2 : array_like (N,)
        Matched pixel coordinates in the left and right images (pixel centres at integers).
    tolerance_m : float, optional
        Geodetic coordinates of many points in a small extent may come from a polynomial
        checked against PROJ within this many metres
        (:func:`stereodem.core.geodesy.ecef_to_geodetic`); None: PROJ for every point.

    Returns
    -------
    Intersection
    """
    col1, row1, col2, row2 = (np.asarray(a, np.float64).ravel() for a in (col1, row1, col2, row2))
    o1, d1 = left.rays(col1, row1)
    o2, d2 = right.rays(col2, row2)
    p, gap = intersect_rays(o1, d1, o2, d2)
    if len(p):
        lon, lat, h = geodesy.ecef_to_geodetic(p[:, 0], p[:, 1], p[:, 2], tolerance_m=tolerance_m)
    else:
        lon = lat = h = p[:, 0]
    return Intersection(p, np.asarray(lon), np.asarray(lat), np.asarray(h), gap)
