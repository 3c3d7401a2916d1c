"""How a co-registration reports its horizontal shift: the projection's scale factor at the
grid centre, the shift in ground metres where that differs from 1, and one wording of the
shift's axes for every report, summary and log line (the JSON fields keep their names).

Shifts are fitted and applied in the grid's units (:func:`stereodem.post.warp.metres_per_unit`:
ground metres on a geographic grid, grid metres, the CRS's units, on a projected one), as
xdem's; this module only says which metres they are."""

from __future__ import annotations

import logging
import threading

import numpy as np
from pyproj import CRS
from pyproj.exceptions import CRSError, ProjError

from . import terrain
from .warp import scale_factors

log = logging.getLogger(__name__)

#: |k - 1| above which a co-registration report adds the horizontal shift in ground metres
GROUND_SHIFT_REPORTED = 1e-3
#: |k - 1| above which a co-registration logs that its shifts are in grid metres
GROUND_SHIFT_WARNED = 1e-2
#: the CRSs (WKT) whose grid-metres warning this process has logged (:func:`ground_shift`):
#: once per CRS, not once per fit (a mosaic of 50 DEMs on one polar grid says it once)
_GROUND_SHIFT_WARNED_CRS: set[str] = set()
_GROUND_SHIFT_WARNED_LOCK = threading.Lock()


def ground_shift(transform, crs, shape, names, values, sigmas, *, what="shift") -> dict:
    """The report's record of a horizontal shift fitted on the grid ``transform, crs, shape``:
    ``values``/``sigmas`` (along x/y, grid east/north, metres per :func:`metres_per_unit`:
    grid metres on a projected grid) named ``names`` (e.g. ``("dx", "dy")``).

    Returns ``scale_factor`` (``[h, k]``, :func:`scale_factors` at the grid centre),
    ``horizontal_unit`` (a sentence) and, where ``|h - 1|`` or ``|k - 1|`` exceeds
    :data:`GROUND_SHIFT_REPORTED` (0.1 %), ``<name>_ground`` for each name: value and σ in
    ground metres (grid metres / h, / k). Logs one warning beyond :data:`GROUND_SHIFT_WARNED`
    (1 %), once per CRS in a process. A projection whose factors PROJ cannot give there has
    ``scale_factor`` None (the report never fails the fit)."""
    if terrain._is_geographic(crs):
        return {
            "scale_factor": [1.0, 1.0],
            "horizontal_unit": "ground metres east/north at the grid centre",
        }
    unit = (
        "grid metres (the CRS's units) along the grid's x/y axes; ground metres = grid "
        "metres / scale_factor (at the grid centre, [along x, along y])"
    )
    try:
        h, k = scale_factors(transform, crs, shape)
    except (ProjError, CRSError, ValueError) as exc:
        h = k = float("nan")
        log.info("%s: no projection scale factor at the grid centre: %s", what, exc)
    if not (np.isfinite(h) and np.isfinite(k) and h > 0 and k > 0):
        return {"scale_factor": None, "horizontal_unit": unit}
    rec = {"scale_factor": [h, k], "horizontal_unit": unit}
    dev = max(abs(h - 1.0), abs(k - 1.0))
    if dev > GROUND_SHIFT_REPORTED:
        for name, v, s, kk in zip(names, values, sigmas, (h, k)):
            rec[f"{name}_ground"] = {"value": float(v / kk), "sigma": float(s / kk), "unit": "m"}
    if dev > GROUND_SHIFT_WARNED and _first_warning(crs):
        log.warning(
            "%s: shifts are in CRS units; at this grid's centre the projection's scale factor "
            "is k = %s, ground metres = grid metres / k (said once per CRS; every report "
            "gives its own grid's k)",
            what,
            format_scale((h, k)),
        )
    return rec


def _first_warning(crs) -> bool:
    """Whether :func:`ground_shift`'s warning is the first for ``crs`` in this process (the
    CRS is then remembered, by its WKT)."""
    try:
        key = CRS.from_user_input(crs).to_wkt()
    except CRSError:
        key = str(crs)
    with _GROUND_SHIFT_WARNED_LOCK:
        if key in _GROUND_SHIFT_WARNED_CRS:
            return False
        _GROUND_SHIFT_WARNED_CRS.add(key)
        return True


#: How every report, summary and log line names the axes of a horizontal shift ``dx, dy``: the
#: grid's x and y axes (the JSON fields keep their names). True on both kinds of grid: on a
#: lon/lat grid they are east and north; on a projected one they are the grid's own east and
#: north, turned from true east/north away from the central meridian (by the longitude's
#: difference from it on a polar stereographic grid).
SHIFT_AXES = ("x (grid east)", "y (grid north)")


def shift_phrase(
    dx: float, dy: float, spec: str = ".2f", *, sigmas=None, names=("dx", "dy")
) -> str:
    """``"dx = 1.20 m along x (grid east), dy = -0.40 m along y (grid north)"``: a horizontal
    shift in the wording of :data:`SHIFT_AXES` (``spec`` formats the numbers, and the
    standard deviations ``sigmas`` when given: ``"dx = 1.20 ± 0.03 m along ..."``; ``names``
    the components', e.g. ``("tx", "ty")``)."""
    parts = []
    for name, v, s, axis in zip(names, (dx, dy), sigmas or (None, None), SHIFT_AXES):
        pm = f" ± {s:{spec.lstrip('+')}}" if _finite(s) else ""
        parts.append(f"{name} = {v:{spec}}{pm} m along {axis}")
    return ", ".join(parts)


def _finite(v) -> bool:
    return isinstance(v, int | float) and bool(np.isfinite(v))


def shift_units(co: dict, names=("dx", "dy")) -> str:
    """A sentence (with a leading space) on the metres of a co-registration summary's ``dx``,
    ``dy`` (:func:`~stereodem.post.assess.coregistration_summary`, a mosaic's correction
    record, or a step's parameters with :func:`ground_shift`'s keys; ``names`` the
    components', e.g. ``icp``'s ``("tx", "ty")``): on a projected grid they are grid metres
    (the CRS's units), with the projection's scale factor at the grid centre and, where that
    differs from 1 by over 0.1 %, the shift in ground metres. Empty on a geographic grid
    (ground metres) and for a summary without ``scale_factor``."""
    scale = co.get("scale_factor")
    if not scale or not str(co.get("horizontal_unit") or "").startswith("grid"):
        return ""
    k = format_scale(scale)
    nx, ny = names
    gx, gy = (_value(co.get(f"{n}_ground")) for n in names)
    if gx is None or gy is None:
        return (
            f" {nx}, {ny} are grid metres (the CRS's units; scale factor k = {k} at the grid "
            "centre)."
        )
    return (
        f" {nx}, {ny} are grid metres (the CRS's units); the projection's scale factor at the "
        f"grid centre is k = {k}: in ground metres (grid metres / k) {nx} = {gx:.2f} m, "
        f"{ny} = {gy:.2f} m."
    )


def _value(v):
    """A number of a summary (``1.2``) or of a step's parameters (``{"value": 1.2, ...}``)."""
    v = v.get("value") if isinstance(v, dict) else v
    try:
        return None if v is None else float(v)
    except (TypeError, ValueError):
        return None


def format_scale(scale) -> str:
    """``"1.02331"`` for a conformal projection's ``[h, k]`` (equal to 6 digits), else
    ``"0.98 (x), 1.02 (y)"``."""
    h, k = (f"{v:.6g}" for v in scale)
    return k if h == k else f"{h} (x), {k} (y)"
