"""Topan's pre-adjustment types 1 and 2 through the adjustment engine."""

import pytest
from helpers.orbital import NOISE_PX, aster_scene, control_points, icp_rmse

from stereodem.core.errors import InputError, SensorModelError
from stereodem.sensor.estimation.adjust import adjust_model, model_set
from stereodem.sensor.models.orbital import TopanLOSModel
from stereodem.sensor.models.orbital.topan_los import LOOK, eop_set, preadjust
from stereodem.sensor.simulation.control_points import to_control_points


@pytest.fixture(scope="module")
def setup():
    meta, _, _ = aster_scene()
    pts = control_points(15, n_icp=30, seed=21)
    return TopanLOSModel.from_model(meta), pts, to_control_points(pts["gcp"], "gcp")


@pytest.mark.slow
def test_type1_fixes_pointing_type2_fixes_the_drift(setup):
    model, pts, gcp = setup
    start = icp_rmse(model, pts["icp"], true=True)
    t1 = preadjust(model, gcp, kind=1, sigma_px=NOISE_PX)
    assert len(t1) == 1 and set(t1[0].names) == set(LOOK)
    after1 = icp_rmse(t1[-1].model, pts["icp"], true=True)
    t2 = preadjust(model, gcp, kind=2, eop_set_name="A_1", sigma_px=NOISE_PX)
    after2 = icp_rmse(t2[-1].model, pts["icp"], true=True)
    joint = adjust_model(model, gcp, list(LOOK) + eop_set("A_1"), sigma_px=NOISE_PX).model
    after_joint = icp_rmse(joint, pts["icp"], true=True)
    # the look-angle corrections absorb the biases; the time-dependent drift is left until
    # the attitude rates (set 11, A_1) are freed in the type-2 step
    assert start > 2.0 and after1 < 0.5 * start
    assert after2 < after1
    assert 2 <= len(t2) <= 4  # type 1 + at most three EOP iterations
    # sequential (Topan's type 2: look angles fitted first, then held) stops short of the
    # joint adjustment of the same 9 unknowns, which reaches the truth to the noise level
    assert after_joint < NOISE_PX and after_joint < after2


def test_type2_needs_a_set_and_types_are_1_or_2(setup):
    model, _, gcp = setup
    with pytest.raises(InputError, match="needs an EOP set"):
        preadjust(model, gcp, kind=2)
    with pytest.raises(InputError, match="must be 1 or 2"):
        preadjust(model, gcp, kind=3)


@pytest.mark.slow
def test_registered_sets_build_from_the_physical_model(setup):
    meta, _, _ = aster_scene()
    for name, n in (("eop-poly2", 9), ("eop-P_S0", 3), ("orun", 10), ("toutin", 8), ("kratky", 7)):
        adjustable, names, _ = model_set(name).prepare(meta)
        assert len(names) == n and set(names) <= set(adjustable.parameters())


def test_velocity_set_refused_as_singular(setup):
    model, _, gcp = setup

    with pytest.raises(SensorModelError, match="near-singular normal matrix"):
        adjust_model(model, gcp, eop_set("V_S0"), sigma_px=NOISE_PX)
