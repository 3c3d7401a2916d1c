"""Adjustable parameters of sensor models: named vectors and their partial derivatives.

A model that can be estimated or whose uncertainty can be propagated offers two methods:

* ``parameters() -> dict``: the adjustable parameters as an ordered ``{name: value}`` mapping
  (units in the class's ``PARAMETERS`` table);
* ``with_parameters(**values) -> model``: a copy with some of them changed.

Frame cameras, pushbroom/ASTER models and image-space corrections
(:class:`stereodem.sensor.models.corrected.ImageCorrectedModel`) implement them. Estimation
(:mod:`stereodem.sensor.estimation`) and error propagation use :func:`project_jacobian`: the
model's own analytic partials when it has a ``project_partials(lon, lat, h, names)`` method,
otherwise central differences with a per-parameter step (the model's ``PARAMETER_STEPS``, else
:func:`default_step`).
"""

from __future__ import annotations

import numpy as np

from stereodem.core.errors import SensorModelError


def is_adjustable(model) -> bool:
    """Whether ``model`` exposes named adjustable parameters."""
    return callable(getattr(model, "parameters", None)) and callable(
        getattr(model, "with_parameters", None)
    )


def parameter_names(model) -> list[str]:
    """Names of the model's adjustable parameters, in order."""
    if not is_adjustable(model):
        raise SensorModelError(f"{type(model).__name__} has no adjustable parameters")
    return list(model.parameters())


def default_step(name: str, value: float) -> float:
    """Central-difference step for a parameter: relative to its size, never below an absolute
    floor chosen for the units the project uses (radians, metres, seconds, pixels, 1)."""
    return 1e-6 * max(1.0, abs(float(value)))


def checked_parameters(known, values, owner: str, *, listing: str | None = None) -> dict:
    """Parameter values checked against a model's names, as floats.

    Parameters
    ----------
    known : Mapping or collection of str
        The names the model accepts.
    values : Mapping
        ``{name: value}`` to check (values in the parameters' own units).
    owner : str
        The model's name, for the messages.
    listing : str, optional
        How the messages list the accepted names (default: all of ``known``, comma-separated).

    Returns
    -------
    dict
        ``{name: float(value)}`` in the order of ``values``.

    Raises
    ------
    SensorModelError
        For a name not in ``known`` (the message lists the known names) or a non-finite value.
    """
    out = {}
    for k, v in values.items():
        if k not in known:
            raise SensorModelError(
                f"{owner}: unknown parameter {k!r} "
                f"(known: {listing if listing is not None else ', '.join(known)})"
            )
        v = float(v)
        if not np.isfinite(v):
            raise SensorModelError(f"{owner}: parameter {k} must be finite, got {v}")
        out[k] = v
    return out


def _steps(model, names, steps):
    table = dict(getattr(model, "PARAMETER_STEPS", {}) or {})
    if steps:
        table.update(steps)
    values = model.parameters()
    return np.array([table.get(n, default_step(n, values[n])) for n in names], dtype=np.float64)


def project_jacobian(model, lon, lat, h, names=None, *, steps: dict | None = None):
    """Image coordinates and their partial derivatives with respect to named parameters.

    Parameters
    ----------
    model : adjustable sensor model (see the module docstring)
    lon, lat, h : array_like
        Ground points: degrees, degrees, metres above the WGS84 ellipsoid.
    names : list of str, optional
        Parameters to differentiate against (default: all of them).
    steps : dict, optional
        Central-difference steps overriding the model's ``PARAMETER_STEPS``.

    Returns
    -------
    col, row : ndarray (n,)
        The model's projection.
    J : ndarray (n, 2, u)
        ``J[i, 0, k] = d col_i / d p_k`` and ``J[i, 1, k] = d row_i / d p_k`` in pixels per the
        parameter's unit.
    """
    lon, lat, h = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (lon, lat, h))
    lon, lat, h = np.broadcast_arrays(lon, lat, h)
    names = parameter_names(model) if names is None else list(names)
    known = model.parameters()
    unknown = [n for n in names if n not in known]
    if unknown:
        raise SensorModelError(
            f"{type(model).__name__}: unknown parameter(s) {', '.join(unknown)} "
            f"(known: {', '.join(known)})"
        )
    col, row = model.project(lon, lat, h)
    if hasattr(model, "project_partials"):
        return col, row, np.asarray(model.project_partials(lon, lat, h, names), dtype=np.float64)
    J = np.empty(lon.shape + (2, len(names)), dtype=np.float64)
    for k, (name, step) in enumerate(zip(names, _steps(model, names, steps))):
        v = known[name]
        cp, rp = model.with_parameters(**{name: v + step}).project(lon, lat, h)
        cm, rm = model.with_parameters(**{name: v - step}).project(lon, lat, h)
        J[..., 0, k] = (cp - cm) / (2 * step)
        J[..., 1, k] = (rp - rm) / (2 * step)
    return col, row, J
