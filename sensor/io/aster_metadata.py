"""What users look for in an ASTER granule's ODL metadata, and which product level it is.

Keys (ASTER notes §2.1; ECS/ASTER metadata as GDAL flattens it): acquisition time from
``CALENDARDATE`` + ``TIMEOFDAY``, else ``RANGEBEGINNINGDATE`` / ``RANGEBEGINNINGTIME``, else
``FIRSTPACKETTIME``, else the granule id (``AST_L1A_00xMMDDYYYYHHMMSS...``); sun azimuth and
elevation from ``SOLARDIRECTION``; cloud cover from ``SCENECLOUDCOVERAGE``; VNIR pointing from
``POINTINGANGLE.1``; geodetic corners from ``UPPERLEFT`` ... ``LOWERRIGHT``. The product level
comes from ``SHORTNAME`` (``ASTL1A``/``AST_L1A``, ``ASTL1B``, ``AST_L1T``), else
``PROCESSINGLEVELID``, else the file name. Every key is optional.
"""

from __future__ import annotations

import datetime as _dt
import re

from stereodem.sensor.io.odl import flatten_odl

_LEVEL_NAMES = {"1B": "L1B", "1T": "L1T", "L1B": "L1B", "L1T": "L1T"}


def product_level(flat: dict, name: str) -> str | None:
    """``"L1A"``, ``"L1B"``, ``"L1T"`` or None from the short name / processing level / file
    name."""
    short = str(flat.get("SHORTNAME", "")).upper().replace("_", "")
    if short.startswith("ASTL1A"):
        return "L1A"
    for key in ("ASTL1B", "ASTL1T"):
        if short.startswith(key):
            return "L" + key[-2:]
    lvl = str(flat.get("PROCESSINGLEVELID", "")).upper().strip()
    if lvl in ("1A", "L1A"):
        return "L1A"
    if lvl in _LEVEL_NAMES:
        return _LEVEL_NAMES[lvl]
    m = re.match(r"AST_?(L1[ABT])", name.upper())
    return m.group(1) if m else None


def not_l1a_message(path, level: str) -> str:
    return (
        f"{path}: this is an ASTER {level} product; stereodem needs AST_L1A (the raw image "
        f"lines with their lattice geometry: SightVector, SatellitePosition) to build the "
        f"3N/3B pushbroom models - {level} images are resampled and carry no sensor geometry"
    )


def first_key(flat: dict, *keys):
    """Value of the first of ``keys`` present in ``flat`` (case-insensitive), else None."""
    up = {k.upper(): v for k, v in flat.items()}
    for k in keys:
        if k.upper() in up:
            return up[k.upper()]
    return None


def _as_float(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _time_from_id(gid: str):
    m = re.match(r"AST_L1A_\d{3}(\d{2})(\d{2})(\d{4})(\d{2})(\d{2})(\d{2})", gid)
    if not m:
        return None
    mo, d, y, hh, mm, ss = (int(x) for x in m.groups())
    try:
        return _dt.datetime(y, mo, d, hh, mm, ss).isoformat() + "Z"
    except ValueError:
        return None


def _acquisition_time(flat: dict, gid: str):
    date, tod = first_key(flat, "CALENDARDATE"), first_key(flat, "TIMEOFDAY")
    if date is not None and tod is not None:
        ds, ts = re.sub(r"\D", "", str(date)), re.sub(r"\D", "", str(tod)).ljust(6, "0")
        if len(ds) == 8:
            return f"{ds[:4]}-{ds[4:6]}-{ds[6:8]}T{ts[:2]}:{ts[2:4]}:{ts[4:6]}Z"
    date, tod = first_key(flat, "RANGEBEGINNINGDATE"), first_key(flat, "RANGEBEGINNINGTIME")
    if date is not None and tod is not None:
        return f"{date}T{str(tod).rstrip('Z')}Z"
    first = first_key(flat, "FIRSTPACKETTIME", "FIRSTPACKETTIME.1")
    if first is not None:
        return str(first)
    return _time_from_id(gid)


def granule_metadata(odl: dict, gid: str) -> dict:
    """The metadata users look for, from the parsed ODL attributes (None where absent)."""
    flat: dict = {}
    for tree in odl.values():
        flat.update(flatten_odl(tree))
    sun = first_key(flat, "SOLARDIRECTION")
    sun = tuple(sun) if isinstance(sun, tuple) and len(sun) == 2 else (None, None)
    corners = {}
    for c in ("UPPERLEFT", "UPPERRIGHT", "LOWERLEFT", "LOWERRIGHT"):
        v = first_key(flat, c)
        if isinstance(v, tuple) and len(v) == 2:
            corners[c] = (float(v[0]), float(v[1]))
    return {
        "granule_id": gid,
        "acquisition_time": _acquisition_time(flat, gid),
        "sun_azimuth_deg": _as_float(sun[0]),
        "sun_elevation_deg": _as_float(sun[1]),
        "cloud_cover_pct": _as_float(first_key(flat, "SCENECLOUDCOVERAGE", "SceneCloudCoverage")),
        "pointing_angle_deg": _as_float(first_key(flat, "POINTINGANGLE.1", "POINTINGANGLE")),
        "corners": corners or None,
    }
