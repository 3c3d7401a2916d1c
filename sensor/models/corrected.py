"""Image-space corrections of any sensor model: the bias compensation of Grodecki & Dial (2003)
and Fraser & Hanley (2005), and s2p's relative pointing correction (its translation case).

The corrected model maps ground to the wrapped model's image coordinates ``(c, r)`` and then
adds an affine correction, in pixels::

    col = c + col_shift + col_drift_col * c + col_drift_row * r
    row = r + row_shift + row_drift_col * c + row_drift_row * r

``localize`` and ``rays`` invert the correction exactly (it is affine) before calling the
wrapped model. The six coefficients are the model's adjustable parameters.
"""

from __future__ import annotations

import numpy as np

from stereodem.core.errors import SensorModelError
from stereodem.sensor.io.sidecar import model_from_dict, model_to_dict
from stereodem.sensor.models.base import SensorModel
from stereodem.sensor.models.parameters import checked_parameters

#: adjustable parameters and their units
PARAMETERS = {
    "col_shift": "px",
    "row_shift": "px",
    "col_drift_col": "px/px",
    "col_drift_row": "px/px",
    "row_drift_col": "px/px",
    "row_drift_row": "px/px",
}


class ImageCorrectedModel(SensorModel):
    """A sensor model followed by an affine image-space correction (see the module docstring).

    Parameters
    ----------
    model : SensorModel
        The wrapped model (any model of the contract).
    **coefficients : float
        Any of :data:`PARAMETERS` (default 0): shifts in pixels, drifts in pixels per pixel.
    """

    MODEL_TYPE = "image_corrected"
    PARAMETERS = PARAMETERS
    #: central-difference steps (the model is linear in its parameters: any step is exact)
    PARAMETER_STEPS = {
        "col_shift": 1.0,
        "row_shift": 1.0,
        "col_drift_col": 1e-4,
        "col_drift_row": 1e-4,
        "row_drift_col": 1e-4,
        "row_drift_row": 1e-4,
    }

    def __init__(self, model: SensorModel, **coefficients):
        self.model = model
        self.width, self.height = model.width, model.height
        self._p = dict.fromkeys(PARAMETERS, 0.0)
        self._set(coefficients)

    def _set(self, values):
        self._p.update(checked_parameters(PARAMETERS, values, "image correction"))
        p = self._p
        self._A = np.array(
            [
                [1.0 + p["col_drift_col"], p["col_drift_row"]],
                [p["row_drift_col"], 1.0 + p["row_drift_row"]],
            ]
        )
        self._b = np.array([p["col_shift"], p["row_shift"]])
        det = np.linalg.det(self._A)
        if abs(det) < 1e-6:
            raise SensorModelError("image correction: the affine correction is singular")
        self._Ainv = np.linalg.inv(self._A)

    # ------------------------------------------------------------------ parameters
    def parameters(self) -> dict:
        """The six correction coefficients, ``{name: value}`` (units in :data:`PARAMETERS`)."""
        return dict(self._p)

    def with_parameters(self, **values) -> ImageCorrectedModel:
        """A copy with some coefficients changed."""
        return ImageCorrectedModel(self.model, **{**self._p, **values})

    def project_partials(self, lon, lat, h, names):
        """Analytic partials of ``(col, row)`` with respect to ``names``, shape (n, 2, u)."""
        if any(n not in ("col_shift", "row_shift") for n in names):  # drifts need (col, row)
            c, r = self.model.project(lon, lat, h)
            c, r = np.asarray(c, float), np.asarray(r, float)
        else:  # shifts: no projection
            c = r = np.zeros(np.broadcast(np.asarray(lon), np.asarray(lat), np.asarray(h)).shape)
        one, zero = np.ones_like(c), np.zeros_like(c)
        table = {
            "col_shift": (one, zero),
            "row_shift": (zero, one),
            "col_drift_col": (c, zero),
            "col_drift_row": (r, zero),
            "row_drift_col": (zero, c),
            "row_drift_row": (zero, r),
        }
        return np.stack([np.stack(table[n], -1) for n in names], -1)

    # ------------------------------------------------------------------ contract
    def _uncorrect(self, col, row):
        col = np.asarray(col, float) - self._b[0]
        row = np.asarray(row, float) - self._b[1]
        A = self._Ainv
        return A[0, 0] * col + A[0, 1] * row, A[1, 0] * col + A[1, 1] * row

    def project(self, lon, lat, h):
        c, r = self.model.project(lon, lat, h)
        A, b = self._A, self._b
        return A[0, 0] * c + A[0, 1] * r + b[0], A[1, 0] * c + A[1, 1] * r + b[1]

    def localize(self, col, row, h):
        return self.model.localize(*self._uncorrect(col, row), h)

    def rays(self, col, row):
        return self.model.rays(*self._uncorrect(col, row))

    def height_bounds(self):
        return self.model.height_bounds()

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        return {"model": model_to_dict(self.model), "parameters": self.parameters()}

    @classmethod
    def from_dict(cls, d: dict) -> ImageCorrectedModel:
        return cls(model_from_dict(d["model"]), **d.get("parameters", {}))

    def __repr__(self):
        set_ = ", ".join(f"{k}={v:.4g}" for k, v in self._p.items() if v)
        return f"ImageCorrectedModel({self.model!r}{', ' if set_ else ''}{set_})"
