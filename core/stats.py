"""Robust statistics shared by every package (issue #23: one NMAD)."""

from __future__ import annotations

import numpy as np

from stereodem.core.errors import InputError

#: NMAD scale: 1 / Φ⁻¹(3/4), so that the NMAD of normal errors estimates their σ
NMAD_FACTOR = 1.4826


def nanmedian(a, axis: int = 0) -> np.ndarray:
    """``np.nanmedian(a, axis=axis)`` (the same values), NaN where a slice has no non-NaN
    value, without the RuntimeWarning numpy gives for those slices: they are left out of the
    call instead of silenced with ``warnings.catch_warnings``, which saves and restores the
    whole process's filters and is not thread-safe before Python 3.14."""
    a = np.asarray(a)
    have = ~np.isnan(a).all(axis=axis)
    if have.all():
        return np.nanmedian(a, axis=axis)
    out = np.full(have.shape, np.nan, np.result_type(a.dtype, np.float16))
    if have.any():
        moved = np.moveaxis(a, axis, 0)
        out[have] = np.nanmedian(moved[:, have], axis=0)
    return out


def nmad(x, axis=None):
    """Normalised median absolute deviation ``1.4826 · median(|x − median(x)|)`` of the finite
    values of ``x`` (same unit as ``x``); NaN when none is finite.

    With ``axis`` (e.g. 0 for a layer-first stack of co-registered DEMs), the NMAD along that
    axis as a float64 array (NaN where a column has no finite value); otherwise a float."""
    if axis is not None:
        a = np.asarray(x, dtype=np.float64)
        med = np.expand_dims(nanmedian(a, axis=axis), axis)
        with np.errstate(invalid="ignore"):
            return NMAD_FACTOR * nanmedian(np.abs(a - med), axis=axis)
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return float("nan")
    return float(NMAD_FACTOR * np.median(np.abs(x - np.median(x))))


def generator(seed) -> np.random.Generator:
    """NumPy's random generator for ``seed`` (a whole number >= 0, or a generator), else
    :class:`~stereodem.core.errors.InputError` naming it: a negative seed ended
    ``simulate --seed -1`` and ``uncertainty --seed -1`` in NumPy's traceback ("expected
    non-negative integer"). The one rule for the commands' seeds."""
    try:
        return np.random.default_rng(seed)
    except (TypeError, ValueError):
        raise InputError(f"seed must be a whole number >= 0, got {seed}") from None


def check_sigma(value, what: str) -> float:
    """``value`` as a standard deviation: a finite number > 0, else
    :class:`~stereodem.core.errors.InputError` naming ``what``. NaN passed the ``<= 0`` checks
    and weighted every observation by NaN (``adjust --sigma-px nan``), and ``compare-models``
    took 0 as "not given" (1 px). The one rule for the a-priori sigmas."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a standard deviation > 0, got {value!r}") from None
    with np.errstate(over="ignore", divide="ignore"):
        # in NumPy: 1e-300 squared is 0, and Python's 1 / 0.0 was a ZeroDivisionError
        weight = np.float64(1.0) / np.float64(v * v) if v > 0 else 0.0
    if not (np.isfinite(v) and np.isfinite(weight) and weight > 0):
        # its weight 1/sigma^2 must exist in float64 too (1e308 made every weight 0)
        raise InputError(
            f"{what} must be a finite standard deviation > 0 whose weight 1/sigma^2 is a "
            f"finite number > 0, got {value}"
        )
    return v
