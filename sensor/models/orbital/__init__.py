"""Parametric orbital models of linear-array images (Topan 2009 survey, Ok 2005 Ch. 6).

* :mod:`.topan_los` — Topan's line-of-sight model with quadratic EOP polynomials (Eq. 3.71),
  the 19 EOP sets of his Table 4.2, pre-adjustment types 1 and 2, the look-vector sign switch
  that reproduces his Table 4.3 column L;
* :mod:`.orun_natarajan` — Orun & Natarajan (1994);
* :mod:`.toutin` — a Toutin-type rigorous model from Toutin's published equations;
* :mod:`.kratky` — Kratky's polynomial exterior orientation along the strip;
* :mod:`.linecam` — the collinearity line camera the last two share; :mod:`._common` —
  normalised line variable, initial fits to a metadata model, GCP-count and image checks.

Every model implements the sensor-model contract (``project``, ``localize``, ``width``,
``height``, ``height_bounds``) and the adjustable-parameter protocol
(:mod:`stereodem.sensor.models.parameters`), and is built from a model of the image
(``from_model``: a pushbroom/ASTER/DIMAP physical model, or an RPC for the ENU models). Named
parameter sets: :data:`PARAMETER_SETS`.

Models of Topan's survey (§3.2.2) left out, and why
---------------------------------------------------
* Salamonowicz (1986): written for scanners, not linear arrays; its thirteen steps name the
  quantities but the scan-rate correction and the GCP-longitude Earth-rotation step are not
  given as equations.
* Gugan (1987): Eq. 3.10-3.18 are complete for the orbit, but the attitude drift rotation
  ``R_A`` and its rates are not specified; with them fixed it is Orun & Natarajan's position
  polynomial with a Keplerian arc, which :mod:`.orun_natarajan` and :mod:`.topan_los` cover.
* Konecny et al. (1987) / BINGO: the 8 sets of additional parameters are not published.
* Jacobsen BLASPO / CORIKON: program descriptions, not equations ("two additional parameters
  for image and angular affinity" are not defined).
* Westin (1990): needs the on-board angular-rate integration (relative attitude) the
  products used here do not carry; with a constant relative attitude it is Topan's set
  (P_S V_S A)_0 on a circular orbit.
* Radhadevi & Ramachandran (1994): 3rd-order attitude polynomials plus osculating elements —
  expressible with :mod:`.topan_los` orders raised, but its weighting (cofactor matrices) is
  not published.
* El-Manadili & Novak (1996): a DLT with image corrections, i.e. the generic ``dlt``/``edlt``
  of :mod:`stereodem.sensor.models.generic` plus three terms; not an orbital model.
* Poli (2005, 2007): piecewise polynomials over trajectory segments; with one segment it is
  Topan's model with offsets added to the measured EOPs.
* Jung et al. (2007): LOS bias terms linear in line and pixel — the same correction as the
  ``L`` set of :mod:`.topan_los` at first order and as
  :class:`stereodem.sensor.models.corrected.ImageCorrectedModel` in image space.
"""

from stereodem.core.errors import InputError
from stereodem.sensor.models.orbital.kratky import KratkyModel
from stereodem.sensor.models.orbital.orun_natarajan import OrunNatarajanModel
from stereodem.sensor.models.orbital.topan_los import EOP_SETS, SET_ORDER, TopanLOSModel
from stereodem.sensor.models.orbital.toutin import ToutinModel

#: Named parameter sets of the orbital models: name -> (model class, parameter names).
PARAMETER_SETS = {
    **{f"eop-{k}": (TopanLOSModel, list(EOP_SETS[k])) for k in (*SET_ORDER, "L")},
    **{k: (OrunNatarajanModel, v) for k, v in OrunNatarajanModel.ADJUST_SETS.items()},
    **{k: (ToutinModel, v) for k, v in ToutinModel.ADJUST_SETS.items()},
    **{k: (KratkyModel, v) for k, v in KratkyModel.ADJUST_SETS.items()},
}
#: The default orbital model sets of a comparison (``eop-poly2`` = Topan set A).
DEFAULT_SETS = {
    "eop-poly2": (TopanLOSModel, list(EOP_SETS["A"])),
    "orun": PARAMETER_SETS["orun"],
    "toutin": PARAMETER_SETS["toutin"],
    "kratky": PARAMETER_SETS["kratky"],
}

__all__ = [
    "TopanLOSModel",
    "OrunNatarajanModel",
    "ToutinModel",
    "KratkyModel",
    "EOP_SETS",
    "SET_ORDER",
    "PARAMETER_SETS",
    "DEFAULT_SETS",
    "build",
]


def build(name: str, reference):
    """The orbital model of parameter set ``name`` built from the image's model ``reference``;
    returns ``(model, parameter names)``."""
    table = {**PARAMETER_SETS, **DEFAULT_SETS}
    if name not in table:
        raise InputError(f"unknown orbital model set {name!r}; choose one of {', '.join(table)}")
    cls, names = table[name]
    return cls.from_model(reference, name=name), list(names)


def register_sets(register) -> None:
    """Register the orbital parameter sets with the adjustment engine's registry
    (:func:`stereodem.sensor.estimation.adjust.register_model_set`): ``eop-poly2`` (Topan's
    model, set A), ``eop-<set>`` for every set of Table 4.2 and ``L``, ``orun``,
    ``orun-full``, ``toutin``, ``toutin-full``, ``kratky``, ``kratky-full``. Each builds the
    orbital model from the image's physical model (or RPC for the ENU models); a class's
    ``PRIORS[set]`` (a-priori sigmas of weakly determined parameters) become the set's priors."""
    for name, (cls, names) in {**PARAMETER_SETS, **DEFAULT_SETS}.items():
        priors = getattr(cls, "PRIORS", {}).get(name, {})
        weighted = f", {len(priors)} weighted" if priors else ""
        register(
            name,
            cls.from_model,
            names,
            replace=True,
            priors=priors,
            description=f"{cls.__name__}: {len(names)} parameters{weighted}",
        )
