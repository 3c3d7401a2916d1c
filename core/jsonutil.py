"""JSON of the project's records: every JSON file stereodem writes goes through :func:`dumps`,
strict JSON (no ``NaN``/``Infinity``, which Python's ``json`` writes by default and which jq,
JavaScript's ``JSON.parse`` and most parsers refuse), numpy values as plain numbers."""

from __future__ import annotations

import json
import math

import numpy as np

__all__ = ["dumps", "json_default", "json_ready"]


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
