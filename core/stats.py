"""Robust statistics shared by every package (issue #23: one NMAD)."""

from __future__ import annotations

import warnings

import numpy as np

#: NMAD scale: 1 / Φ⁻¹(3/4), so that the NMAD of normal errors estimates their σ
NMAD_FACTOR = 1.4826


def nmad(x, axis=None):
    """Normalised median absolute deviation ``1.4826 · median(|x − median(x)|)`` of the finite
    values of ``x`` (same unit as ``x``); NaN when none is finite.

    With ``axis`` (e.g. 0 for a layer-first stack of co-registered DEMs), the NMAD along that
    axis as a float64 array (NaN where a column has no finite value); otherwise a float."""
    if axis is not None:
        a = np.asarray(x, dtype=np.float64)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns -> NaN
            med = np.nanmedian(a, axis=axis, keepdims=True)
            return NMAD_FACTOR * np.nanmedian(np.abs(a - med), axis=axis)
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return float("nan")
    return float(NMAD_FACTOR * np.median(np.abs(x - np.median(x))))
