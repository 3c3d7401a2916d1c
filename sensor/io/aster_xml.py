"""ASTER product geometry from ASP ``aster2asp`` camera XML (``out-Band3N.xml``,
``out-Band3B.xml``), and the bundled real granule's geometry.

ASP's XML (``<isd>``) holds ``LATTICE_POINT``, ``SIGHT_VECTOR`` (orbital frame, as in the
product), ``WORLD_SIGHT_VECTOR`` (ECEF, from the product's latitude/longitude),
``SAT_POS``, ``IMAGE_COLS``/``IMAGE_ROWS`` and ASP's fitted RPC in ``<RPB>``.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from importlib import resources

import numpy as np

from stereodem.core.errors import RPCError, SensorModelError, not_found
from stereodem.sensor.io.tables import TableError, numeric_blocks
from stereodem.sensor.models.aster import _RPB_COEFS, AsterGeometry

_RPB_SCALARS = (
    "LINEOFFSET",
    "SAMPOFFSET",
    "LATOFFSET",
    "LONGOFFSET",
    "HEIGHTOFFSET",
    "LINESCALE",
    "SAMPSCALE",
    "LATSCALE",
    "LONGSCALE",
    "HEIGHTSCALE",
)


def _numbers(root, tag, path, *, required=True):
    el = root.find(tag)
    if el is None:
        if required:
            raise SensorModelError(f"{path}: missing <{tag}> element")
        return None
    try:
        vals = np.array([float(x) for x in (el.text or "").split()], dtype=np.float64)
    except ValueError:
        raise SensorModelError(f"{path}: <{tag}> holds non-numeric text") from None
    if vals.size == 0:
        raise SensorModelError(f"{path}: <{tag}> is empty")
    if not np.all(np.isfinite(vals)):
        raise SensorModelError(f"{path}: <{tag}> holds non-finite values")
    return vals


def _blocks(root, tag, path):
    """Blank-line separated blocks of numeric rows -> list of (rows, width) arrays."""
    el = root.find(tag)
    if el is None:
        raise SensorModelError(f"{path}: missing <{tag}> element")
    try:
        blocks = numeric_blocks(el.text or "")
    except TableError:
        raise SensorModelError(f"{path}: <{tag}> holds non-numeric text") from None
    if not blocks:
        raise SensorModelError(f"{path}: <{tag}> is empty")
    try:
        arr = np.array(blocks, dtype=np.float64)
    except ValueError:
        raise SensorModelError(f"{path}: <{tag}> blocks have unequal sizes") from None
    if not np.all(np.isfinite(arr)):
        raise SensorModelError(f"{path}: <{tag}> holds non-finite values")
    return arr


def _read_rpb(root, path):
    rpb = root.find("RPB")
    if rpb is None:
        return None
    img = rpb.find("IMAGE")
    if img is None:
        raise RPCError(f"{path}: <RPB> has no <IMAGE> block")
    out = {"SATID": (rpb.findtext("SATID") or "").strip()}
    for key in _RPB_SCALARS:
        txt = img.findtext(key)
        try:
            out[key] = float(txt)
        except (TypeError, ValueError):
            raise RPCError(f"{path}: RPC key {key} missing or not a number") from None
    for key in _RPB_COEFS:
        el = img.find(f"{key}List/{key}")
        if el is None:
            el = img.find(key)
        try:
            c = np.array([float(x) for x in (el.text or "").split()]) if el is not None else None
        except ValueError:
            c = None
        if c is None or c.size != 20 or not np.all(np.isfinite(c)):
            raise RPCError(f"{path}: RPC key {key} must hold 20 numbers")
        out[key] = c
    return out


def read_asp_aster_xml(path) -> AsterGeometry:
    """Read an ASP ``aster2asp`` camera XML (``out-Band3N.xml`` / ``out-Band3B.xml``).

    Raises
    ------
    SensorModelError
        Unreadable XML, a missing element, non-numeric or inconsistent contents.
    RPCError
        A garbled ``<RPB>`` block.
    """
    path = str(path)
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise SensorModelError(not_found(path, "ASTER XML file")) from None
    except ET.ParseError as exc:
        raise SensorModelError(f"{path}: not valid XML ({exc})") from None
    lattice = _blocks(root, "LATTICE_POINT", path)
    sight = _blocks(root, "SIGHT_VECTOR", path)
    world = _blocks(root, "WORLD_SIGHT_VECTOR", path)
    pos = _numbers(root, "SAT_POS", path)
    if pos.size % 3:
        raise SensorModelError(f"{path}: <SAT_POS> does not hold triplets")
    cols = _numbers(root, "IMAGE_COLS", path)
    rows = _numbers(root, "IMAGE_ROWS", path)
    for name, arr in (("SIGHT_VECTOR", sight), ("WORLD_SIGHT_VECTOR", world)):
        norm = np.linalg.norm(arr, axis=-1)
        if np.any(norm < 0.5):
            raise SensorModelError(f"{path}: <{name}> holds zero-length vectors")
    sight = sight / np.linalg.norm(sight, axis=-1, keepdims=True)
    world = world / np.linalg.norm(world, axis=-1, keepdims=True)
    return AsterGeometry(
        lattice=lattice,
        sight_vectors=sight,
        world_sight_vectors=world,
        satellite_positions=pos.reshape(-1, 3),
        image_cols=int(cols[0]),
        image_rows=int(rows[0]),
        rpc=_read_rpb(root, path),
        path=path,
    )


def bundled_xml(band: str):
    """Path of the bundled real ASTER geometry (ASP ``aster2asp`` XML) of band ``3N`` or ``3B``.

    One V003 granule over Mt Rainier, 2017-07-31 (uw-cryo/asp_plot test data, BSD-3-Clause).
    """
    if band not in ("3N", "3B"):
        raise SensorModelError(f"ASTER band must be '3N' or '3B', got {band!r}")
    return resources.files("stereodem.sensor") / "data" / "aster" / f"out-Band{band}.xml"
