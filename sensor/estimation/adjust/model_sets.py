"""Named parameter sets: which adjustable model to build and which of its parameters to free.

A :class:`ModelSet` turns a delivered sensor model into the model to adjust (``build``, e.g.
an RPC wrapped in an :class:`~stereodem.sensor.models.corrected.ImageCorrectedModel`) and names
the parameters to estimate, optionally with a-priori standard deviations that enter the
adjustment as fictitious observations about the initial values (``priors``).

Extend with :func:`register_model_set` (e.g. Topan's ``eop-poly2``, registered by the orbital
module); :func:`model_set` looks a name up.

Units of the parameters are those of the model's ``PARAMETERS`` table (:func:`parameter_unit`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from stereodem.core.errors import InputError, SensorModelError
from stereodem.sensor.models.corrected import ImageCorrectedModel
from stereodem.sensor.models.frame import FrameCamera
from stereodem.sensor.models.orbital import register_sets
from stereodem.sensor.models.parameters import is_adjustable
from stereodem.sensor.models.pushbroom import PushbroomModel

__all__ = [
    "ModelSet",
    "MODEL_SETS",
    "register_model_set",
    "model_set",
    "free_parameters",
    "parameter_unit",
    "image_corrected",
]


@dataclass(frozen=True)
class ModelSet:
    """How to adjust a model.

    Attributes
    ----------
    name : str
    description : str
    build : callable ``model -> model``
        The adjustable model to start from (same protocol: ``parameters``/``with_parameters``).
    names : tuple of str
        Parameters to free.
    priors : dict
        ``{name: sigma}`` a-priori standard deviations (parameter units) about the initial
        values, entered as fictitious observations; empty for none.
    applies_to : tuple of type
        Model classes the set is meant for (checked by ``build``; empty: any).
    """

    name: str
    description: str
    build: Callable
    names: tuple
    priors: dict = field(default_factory=dict)
    applies_to: tuple = ()

    def prepare(self, model):
        """``(adjustable model, names, priors)`` for ``model``."""
        if (
            self.applies_to
            and not isinstance(model, self.applies_to)
            and not (isinstance(model, ImageCorrectedModel) and self.build is image_corrected)
        ):
            kinds = ", ".join(t.__name__ for t in self.applies_to)
            raise SensorModelError(
                f"model set '{self.name}' applies to {kinds}, not to {type(model).__name__}"
            )
        return self.build(model), list(self.names), dict(self.priors)


#: registry name -> ModelSet
MODEL_SETS: dict[str, ModelSet] = {}


def register_model_set(
    name, build, names, *, description="", priors=None, applies_to=(), replace=False
) -> ModelSet:
    """Register a named parameter set (see :class:`ModelSet`); returns it."""
    if name in MODEL_SETS and not replace:
        raise InputError(f"model set '{name}' is already registered")
    ms = ModelSet(name, description, build, tuple(names), dict(priors or {}), tuple(applies_to))
    MODEL_SETS[name] = ms
    return ms


def model_set(name: str) -> ModelSet:
    """The registered set ``name``; :class:`InputError` listing the known ones otherwise."""
    try:
        return MODEL_SETS[name]
    except KeyError:
        raise InputError(
            f"unknown model set '{name}' (known: {', '.join(sorted(MODEL_SETS))})"
        ) from None


def free_parameters(model, names, priors=None, *, what: str, side: str = ""):
    """The model to adjust and its free parameters.

    ``names``: a model set's name (:func:`model_set`: the model is built by the set, its priors
    come first, ``priors`` override them) or the names of ``model``'s own parameters.
    ``priors``: name -> a-priori standard deviation, in the parameter's unit
    (:func:`parameter_unit`). Errors name ``what`` (the caller) and ``side`` (which image of a
    bundle, e.g. ``"left"``). Returns ``(model, names, priors, set name or None)``.

    Raises
    ------
    SensorModelError
        The model has no adjustable parameters.
    InputError
        An unknown set or parameter name, or no parameter named.
    """
    whose = f"{side} " if side else ""
    set_name = None
    priors = dict(priors or {})
    if isinstance(names, str):
        ms = model_set(names)
        model, names, set_priors = ms.prepare(model)
        priors = {**set_priors, **priors}
        set_name = ms.name
    names = list(names)
    if not is_adjustable(model):
        raise SensorModelError(
            f"{what}: the {whose}model ({type(model).__name__}) has no adjustable parameters "
            "(wrap it, e.g. with the 'rpc-shift' model set)"
        )
    known = model.parameters()
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise InputError(
            f"{what}: unknown {whose}parameter(s) {', '.join(unknown) or '(none given)'} "
            f"of {type(model).__name__} (known: {', '.join(known)})"
        )
    return model, names, priors, set_name


def parameter_unit(model, name: str) -> str:
    """Unit of parameter ``name`` from the model's ``PARAMETERS``/``PARAMETER_UNITS`` tables."""
    table = getattr(model, "PARAMETER_UNITS", None) or getattr(model, "PARAMETERS", None)
    if isinstance(table, dict) and name in table:
        text = str(table[name])
        return text.rsplit(", ", 1)[-1] if ", " in text else text
    return FrameCamera.PARAMETER_UNITS.get(name, "")


# ------------------------------------------------------------------------------ builders
def image_corrected(model):
    """``model`` inside an image-space affine correction (kept when it already is one)."""
    return model if isinstance(model, ImageCorrectedModel) else ImageCorrectedModel(model)


def _identity(model):
    return model


def _register_defaults():
    # RPC (or any model) bias compensation in image space: Grodecki & Dial 2003, Fraser &
    # Hanley 2005. "shift-drift": shifts plus a drift of both coordinates with the line (time)
    register_model_set(
        "rpc-shift",
        image_corrected,
        ("col_shift", "row_shift"),
        description="image-space shift (bias compensation, 2 parameters)",
    )
    register_model_set(
        "rpc-shift-drift",
        image_corrected,
        ("col_shift", "row_shift", "col_drift_row", "row_drift_row"),
        description="image-space shift and along-track drift (4 parameters)",
    )
    register_model_set(
        "rpc-affine",
        image_corrected,
        (
            "col_shift",
            "row_shift",
            "col_drift_col",
            "col_drift_row",
            "row_drift_col",
            "row_drift_row",
        ),
        description="image-space affine correction (6 parameters)",
    )
    eo = ("roll", "pitch", "yaw", "x", "y", "z")
    register_model_set(
        "frame-eo",
        _identity,
        eo,
        applies_to=(FrameCamera,),
        description="frame camera space resection: exterior orientation (6)",
    )
    # a satellite frame camera cannot separate focal length from range (Bettemir 2006 §5.2:
    # f, c and the altitude are correlated; he fixed the altitude): with interior orientation
    # free, the telemetry position is a prior (15 m, the GPS sigma of the thesis)
    gps = dict.fromkeys(("x", "y", "z"), 15.0)
    register_model_set(
        "frame-eo-io",
        _identity,
        eo + ("focal_mm", "dx_mm", "dy_mm"),
        applies_to=(FrameCamera,),
        priors=gps,
        description="exterior + interior orientation, position prior 15 m (9)",
    )
    register_model_set(
        "frame-self-calibration",
        _identity,
        eo + ("focal_mm", "dx_mm", "dy_mm", "k1", "k2", "p1", "p2"),
        applies_to=(FrameCamera,),
        priors=gps,
        description="exterior + interior orientation + Brown distortion, position prior 15 m (13)",
    )
    att = ("roll_bias", "pitch_bias", "yaw_bias")
    drift = ("roll_drift", "pitch_drift", "yaw_drift")
    pos = ("position_offset_x", "position_offset_y", "position_offset_z")
    register_model_set(
        "attitude-bias",
        _identity,
        att,
        applies_to=(PushbroomModel,),
        description="pushbroom attitude biases roll/pitch/yaw (3)",
    )
    register_model_set(
        "attitude-bias-drift",
        _identity,
        att + drift,
        applies_to=(PushbroomModel,),
        description="pushbroom attitude biases and drifts (6)",
    )
    register_model_set(
        "attitude-bias-scale",
        _identity,
        att + ("look_scale",),
        applies_to=(PushbroomModel,),
        description="attitude biases and the cross-track look scale (4)",
    )
    # position offsets and attitude biases are nearly interchangeable over a narrow field of
    # view; 50 m a-priori position sigma (fictitious observations) keeps them apart
    register_model_set(
        "position-attitude",
        _identity,
        pos + att,
        applies_to=(PushbroomModel,),
        priors=dict.fromkeys(pos, 50.0),
        description="position offsets (prior 50 m) and attitude biases (6)",
    )
    register_model_set(
        "pushbroom-time",
        _identity,
        ("time_offset",) + att[:1] + att[2:],
        applies_to=(PushbroomModel,),
        description="time offset with roll and yaw biases (3)",
    )


_register_defaults()


def _register_orbital():
    # orbital models of Topan (2009) / Ok (2005): eop-poly2, eop-<Table 4.2 set>, orun, toutin,
    # kratky
    register_sets(register_model_set)


_register_orbital()
