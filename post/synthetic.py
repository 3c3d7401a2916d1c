"""Known errors injected into a real DEM, for the co-registration tests and benchmark.

:func:`inject_errors` returns the DEM with (in this order) a horizontal shift, a vertical
offset, a planar ramp, an along-track sum of sines, spatially correlated noise and a real
change inside a polygon, plus the truth: every injected parameter, the noise field alone and
the change mask. Frames as in :mod:`stereodem.post.coreg` (metres east/north from the grid
centre; heading in degrees clockwise from north).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stereodem.core.dem import DEM

from . import warp
from .coreg import local_metric_coords, track_coords
from .spatialstats import VariogramModel, simulate_field


@dataclass
class InjectedErrors:
    """What :func:`inject_errors` put in (metres unless said; ``dx``/``dy`` in the grid's
    metres, :func:`~stereodem.post.warp.translated`'s)."""

    dx: float = 0.0  #: displacement east of the DEM relative to the truth
    dy: float = 0.0  #: displacement north
    dz: float = 0.0  #: vertical offset
    ramp_e: float = 0.0  #: m per 10 km east
    ramp_n: float = 0.0  #: m per 10 km north
    heading_deg: float = 0.0  #: ground-track heading
    along_sines: list = field(default_factory=list)  #: [(amplitude m, wavelength m, phase rad)]
    noise: VariogramModel | None = None
    change_m: float = 0.0  #: height change inside the change polygon
    change_centre_px: tuple = (0.5, 0.5)  #: (row, col) fractions of the grid
    change_radius_m: float = 0.0
    seed: int = 0


def change_mask(shape, transform, crs, centre_px, radius_m):
    """Bool disc of ``radius_m`` metres around (row, col) fractions ``centre_px``."""
    e, n = local_metric_coords(transform, crs, shape)
    r0, c0 = centre_px
    ec, nc = e[0, int(c0 * (shape[1] - 1))], n[int(r0 * (shape[0] - 1)), 0]
    return np.hypot(e - ec, n - nc) <= radius_m


def inject_errors(truth: DEM, spec: InjectedErrors):
    """The erroneous DEM (same grid) and a dict: ``noise`` (the noise field alone, m),
    ``change`` (bool mask), ``along`` (the along-track signal, m), ``spec``."""
    rng = np.random.default_rng(spec.seed)
    z = truth.heights.astype(np.float64)
    if spec.dx or spec.dy:
        t = warp.translated(truth.transform, truth.crs, truth.shape, spec.dx, spec.dy)
        z = warp.to_grid(
            z, t, truth.crs, truth.transform, truth.crs, truth.shape, resampling="cubic"
        ).astype(np.float64)
    e, n = local_metric_coords(truth.transform, truth.crs, truth.shape)
    z = z + spec.dz + spec.ramp_e * e / 1e4 + spec.ramp_n * n / 1e4
    a, _ = track_coords(e, n, spec.heading_deg)
    along = np.zeros(truth.shape)
    for amp, wl, ph in spec.along_sines:
        along += amp * np.sin(2 * np.pi * a / wl + ph)
    z = z + along
    noise = np.zeros(truth.shape)
    if spec.noise is not None:
        fx, fy = warp.metres_per_unit(truth.transform, truth.crs, truth.shape)
        px = (abs(truth.transform.a) * fx, abs(truth.transform.e) * fy)
        noise = simulate_field(spec.noise, truth.shape, px, rng=rng)[0]
        z = z + noise
    chg = np.zeros(truth.shape, bool)
    if spec.change_radius_m > 0:
        chg = change_mask(
            truth.shape, truth.transform, truth.crs, spec.change_centre_px, spec.change_radius_m
        )
        z = z + np.where(chg, spec.change_m, 0.0)
    out = DEM(z.astype(np.float32), truth.transform, truth.crs, truth.vertical, None)
    return out, {"noise": noise, "change": chg, "along": along, "spec": spec}
