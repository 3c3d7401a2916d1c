"""Co-registration of a DEM to a reference DEM: Nuth & Kääb (2011), iterated.

Nuth & Kääb relate the height difference to a horizontal shift through the terrain's slope α
and aspect ψ: ``dh = a · cos(b − ψ) · tan α + dz``. Since ``tan α · sin ψ`` and
``tan α · cos ψ`` are the downhill east/north gradient components, this is the linear model

    dh = −(∂z/∂E · Δe + ∂z/∂N · Δn) + dz

which is solved here by least squares on stable cells (slope between ``min_slope`` and
``max_slope``, |dh − median| < ``outlier_nmad`` NMADs), the DEM re-warped with the shift
found so far, until the shift increment is below ``tolerance_px`` (xdem ``NuthKaab``,
demcoreg ``dem_align.py``). Gradients are in metres even on lon/lat grids.

Sign convention: ``dx, dy, dz`` is the displacement of the DEM relative to the reference, in
metres east, north and up (a DEM whose features sit 50 m east of the reference's has
``dx = +50``); :meth:`NuthKaab.apply` removes it.
"""
from __future__ import annotations

import logging

import numpy as np

from stereodem.sensor.geo.dem import DEM
from stereodem.sensor.errors import ConvergenceError, DEMError

from . import terrain, warp
from .stats import nmad

log = logging.getLogger(__name__)


class NuthKaab:
    """Iterated Nuth & Kääb horizontal + vertical shift (xdem-style ``fit`` / ``apply``).

    Parameters
    ----------
    max_iterations : int
    tolerance_px : float
        Stop when the shift increment is below this fraction of a reference pixel.
    min_slope, max_slope : float
        Degrees; cells outside are not used (flat cells carry no horizontal information).
    outlier_nmad : float
        Cells with |dh − median| above this many NMADs are left out of each fit.
    resampling : str
        Resampling of the DEM onto the reference grid at each iteration.

    Attributes
    ----------
    params : dict
        After :meth:`fit`: ``dx``, ``dy``, ``dz`` (m east/north/up), ``dx_px``, ``dy_px``
        (reference pixels), ``iterations``, ``converged``, ``nmad_before``, ``nmad_after``
        and ``log`` (one entry per iteration).
    """

    def __init__(self, *, max_iterations: int = 10, tolerance_px: float = 0.01,
                 min_slope: float = 1.0, max_slope: float = 70.0, outlier_nmad: float = 3.0,
                 resampling: str = "cubic"):
        self.max_iterations = int(max_iterations)
        self.tolerance_px = float(tolerance_px)
        self.min_slope, self.max_slope = float(min_slope), float(max_slope)
        self.outlier_nmad = float(outlier_nmad)
        self.resampling = resampling
        self.params: dict = {}

    def _warp(self, dem: DEM, reference: DEM, east, north):
        t = warp.translated(dem.transform, dem.crs, dem.shape, -east, -north)
        return warp.to_grid(dem.heights, t, dem.crs, reference.transform, reference.crs,
                            reference.shape, resampling=self.resampling).astype(np.float64)

    def fit(self, reference: DEM, dem: DEM) -> "NuthKaab":
        """Estimate the shift of ``dem`` relative to ``reference`` (same vertical reference)."""
        ref = reference.heights.astype(np.float64)
        ge, gn = terrain.gradient(ref, reference.transform, reference.crs)
        slope = np.degrees(np.arctan(np.hypot(ge, gn)))
        px_e, px_n = terrain.pixel_size_m(reference.transform, reference.crs, reference.shape)
        pe = float(np.abs(px_e[px_e.shape[0] // 2, 0]))
        pn = float(np.abs(px_n[px_n.shape[0] // 2, 0]))
        usable = np.isfinite(ref) & np.isfinite(slope) & (slope >= self.min_slope) & (slope <= self.max_slope)
        east = north = 0.0
        history, converged = [], False
        nmad0 = None
        for it in range(1, self.max_iterations + 1):
            dh = self._warp(dem, reference, east, north) - ref
            ok = usable & np.isfinite(dh)
            if ok.sum() < 50:
                raise DEMError(f"{dem.path or 'DEM'}: only {int(ok.sum())} overlapping cells with "
                               "usable slope; cannot co-register")
            med, sc = float(np.median(dh[ok])), nmad(dh[ok])
            if nmad0 is None:
                nmad0 = sc
            ok &= np.abs(dh - med) <= max(self.outlier_nmad * sc, 1e-6)
            a = np.column_stack([-ge[ok], -gn[ok], np.ones(int(ok.sum()))])
            sol, *_ = np.linalg.lstsq(a, dh[ok], rcond=None)
            de, dn = float(sol[0]), float(sol[1])
            east, north = east + de, north + dn
            step_px = float(np.hypot(de / pe, dn / pn))
            history.append({"iteration": it, "dx": east, "dy": north, "step_px": step_px,
                            "nmad": sc, "n": int(ok.sum())})
            log.info("Nuth-Kaab iteration %d: dx=%.3f m dy=%.3f m (step %.4f px, NMAD %.3f m)",
                     it, east, north, step_px, sc)
            if step_px < self.tolerance_px:
                converged = True
                break
        dh = self._warp(dem, reference, east, north) - ref
        ok = np.isfinite(dh)
        if not ok.any():
            raise ConvergenceError(f"{dem.path or 'DEM'}: co-registration shifted the DEM off the reference")
        dz = float(np.median(dh[ok & usable])) if (ok & usable).any() else float(np.median(dh[ok]))
        if not converged:
            log.warning("Nuth-Kaab did not converge in %d iterations (last step %.3f px)",
                        self.max_iterations, history[-1]["step_px"])
        self.params = {"method": "nuth_kaab", "dx": east, "dy": north, "dz": dz,
                       "dx_px": east / pe, "dy_px": north / pn, "pixel_size_m": [pe, pn],
                       "iterations": len(history), "converged": converged,
                       "nmad_before": nmad0, "nmad_after": nmad(dh[ok] - dz),
                       "frame": "metres east/north/up; displacement of the DEM relative to the reference",
                       "log": history}
        return self

    def apply(self, dem: DEM) -> DEM:
        """``dem`` with the fitted shift removed: its transform moved by (−dx, −dy) metres and
        ``dz`` subtracted from its heights."""
        if not self.params:
            raise DEMError("NuthKaab.apply called before fit")
        t = warp.translated(dem.transform, dem.crs, dem.shape, -self.params["dx"], -self.params["dy"])
        return DEM((dem.heights - np.float32(self.params["dz"])).astype(np.float32), t, dem.crs,
                   dem.vertical, dem.path)
