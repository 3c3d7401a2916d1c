"""JSON of the project's records: every JSON file stereodem writes goes through :func:`dumps`,
strict JSON (no ``NaN``/``Infinity``, which Python's ``json`` writes by default and which jq,
JavaScript's ``JSON.parse`` and most parsers refuse), numpy values as plain numbers."""

from __future__ import annotations

import functools
import json
import math
from importlib.metadata import PackageNotFoundError, version

import numpy as np

__all__ = ["dumps", "json_default", "json_ready", "STAMP", "stamped", "is_stamped"]

#: the key of the records that mark a folder as a stereodem command's output (``run.json``,
#: ``report.json``, ...: :data:`stereodem.outlock.MARKERS`); its value is the version that
#: wrote the record. A file of the user's with a marker's name lacks it, so ``--overwrite``
#: does not take the folder for a previous run's (:func:`stereodem.outlock.is_stereodem_output`)
STAMP = "stereodem_version"


@functools.lru_cache(maxsize=1)
def stereodem_version() -> str:
    """The installed stereodem's version (``0+unknown`` in a source tree without one)."""
    try:
        return version("stereodem")
    except PackageNotFoundError:
        return "0+unknown"


def stamped(record: dict) -> dict:
    """``record`` with :data:`STAMP` first: what every output-folder marker is written as."""
    return {STAMP: stereodem_version(), **{k: v for k, v in record.items() if k != STAMP}}


def is_stamped(obj) -> bool:
    """Whether a parsed record is one stereodem wrote: :data:`STAMP` at its top level or in
    its ``provenance`` section (``run.json``, ``dem_report.json``), a version string; a list
    (``compare.json``) when every item is."""
    if isinstance(obj, list):
        return bool(obj) and all(is_stamped(o) for o in obj)
    if not isinstance(obj, dict):
        return False
    prov = obj.get("provenance")
    found = obj.get(STAMP, prov.get(STAMP) if isinstance(prov, dict) else None)
    return isinstance(found, str) and bool(found)


def json_default(o):
    """numpy scalars -> Python numbers, arrays -> lists, anything else -> ``str`` (the
    ``default=`` hook of :func:`dumps`)."""
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def json_ready(obj):
    """A copy of ``obj`` that strict JSON can hold: a non-finite number (a statistic of no
    cell, an undefined ratio) becomes ``None`` (``null``), numpy scalars and arrays plain
    numbers and lists, tuples lists, dictionary keys strings; other objects are returned as
    they are (:func:`json_default` then writes them as text)."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def dumps(obj, *, indent: int | None = 1) -> str:
    """Strict JSON text of ``obj`` (:func:`json_ready`; ``allow_nan=False`` guards the rule),
    ending with a newline."""
    return json.dumps(json_ready(obj), indent=indent, allow_nan=False, default=json_default) + "\n"
