"""Option choices of the sensor-model commands, as the command line takes them (a light
module: no numpy, SciPy or rasterio, so that ``stereodem adjust``'s parser loads none).

The names are kept in step with the library by tests (``tests/app/test_choices.py``): the
fitted models' forms (:data:`stereodem.sensor.models.generic.MODEL_NAMES` is this module's
tuple) and the built-in parameter sets registered with
:data:`stereodem.sensor.estimation.adjust.MODEL_SETS` (a set registered at run time with
``register_model_set`` is the library's to use, not a command-line choice).
"""

#: built-in parameter sets (:mod:`stereodem.sensor.estimation.adjust.model_sets` and the
#: orbital sets of :func:`stereodem.sensor.models.orbital.register_sets`), sorted
MODEL_SET_NAMES: tuple[str, ...] = (
    "attitude-bias",
    "attitude-bias-drift",
    "attitude-bias-scale",
    "eop-(P_S A)_0",
    "eop-(P_S V_S A)_0",
    "eop-(P_S V_S)_0",
    "eop-(V_S A)_0",
    "eop-A",
    "eop-A_0",
    "eop-A_1",
    "eop-A_2",
    "eop-L",
    "eop-P_S",
    "eop-P_S A",
    "eop-P_S V_S",
    "eop-P_S0",
    "eop-P_S1",
    "eop-P_S2",
    "eop-V_S",
    "eop-V_S A",
    "eop-V_S0",
    "eop-V_S1",
    "eop-V_S2",
    "eop-poly2",
    "frame-eo",
    "frame-eo-io",
    "frame-self-calibration",
    "kratky",
    "kratky-full",
    "orun",
    "orun-full",
    "position-attitude",
    "pushbroom-time",
    "rpc-affine",
    "rpc-shift",
    "rpc-shift-drift",
    "toutin",
    "toutin-full",
)

#: fitted (generic) models, in the order of their forms (:mod:`stereodem.sensor.models.generic`)
GENERIC_MODEL_NAMES: tuple[str, ...] = (
    "poly2d-1",
    "poly2d-2",
    "poly2d-3",
    "poly3d-1",
    "poly3d-2",
    "poly3d-3",
    "relief-1",
    "relief-2",
    "projective",
    "projective-pushbroom",
    "dlt",
    "edlt",
    "rational-1",
    "rational-2",
    "rational-3",
)

#: ``stereodem adjust --model``: a parameter set, a fitted model, or ``bundle``
ADJUST_MODELS: tuple[str, ...] = (*MODEL_SET_NAMES, *GENERIC_MODEL_NAMES, "bundle")
