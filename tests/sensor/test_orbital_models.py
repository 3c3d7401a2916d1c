"""Orbital models (Topan 2009, Orun & Natarajan 1994, Toutin, Kratky) on a simulated ASTER 3N
scene whose ephemeris and attitude carry biases and drifts."""

import numpy as np
import pytest
from helpers.orbital import NOISE_PX, aster_scene, control_points, gauss_newton, icp_rmse

from stereodem.core.errors import InputError, SensorModelError
from stereodem.sensor.io.sidecar import load_model, save_model
from stereodem.sensor.models.orbital import (
    KratkyModel,
    OrunNatarajanModel,
    TopanLOSModel,
    ToutinModel,
    build,
)
from stereodem.sensor.models.orbital._common import require_gcps, require_inside
from stereodem.sensor.models.orbital.topan_los import EOP_SETS, SET_ORDER, eop_set
from stereodem.sensor.models.parameters import project_jacobian

#: the models whose fit takes ~0.5-0.7 s: in the full suite only
SLOW_FITS = [
    pytest.param(OrunNatarajanModel, marks=pytest.mark.slow, id="OrunNatarajanModel"),
    pytest.param(KratkyModel, marks=pytest.mark.slow, id="KratkyModel"),
]


@pytest.fixture(scope="module")
def scene():
    return aster_scene()


def _grid(model, h=(0.0, 1500.0)):
    c, r, z = np.meshgrid(
        np.linspace(0, model.width - 1, 7),
        np.linspace(0, model.height - 1, 7),
        np.asarray(h),
        indexing="ij",
    )
    return c.ravel(), r.ravel(), z.ravel()


@pytest.mark.parametrize("cls", [TopanLOSModel, ToutinModel, *SLOW_FITS])
def test_initial_model_reproduces_metadata_and_round_trips(scene, cls):
    meta, _, _ = scene
    m = cls.from_model(meta)
    c, r, z = _grid(meta)
    lon, lat = meta.localize(c, r, z)
    pc, pr = m.project(lon, lat, z)
    # the metadata model's own geometry, to a small fraction of a pixel
    assert np.sqrt(np.mean((pc - c) ** 2 + (pr - r) ** 2)) < 0.06
    lo, la = m.localize(pc, pr, z)
    assert np.max(np.abs(lo - lon)) < 1e-7 and np.max(np.abs(la - lat)) < 1e-7
    assert set(m.parameters()) and m.width == meta.width and m.height == meta.height


def test_topan_sets_are_the_19_of_table_4_2():
    assert len(SET_ORDER) == 19
    sizes = [len(EOP_SETS[k]) for k in SET_ORDER]
    assert sizes == [9, 3, 3, 3, 9, 3, 3, 3, 9, 3, 3, 3, 18, 6, 18, 6, 18, 6, 9]
    assert (
        eop_set("16") == eop_set("(P_S A)_0") == ["X_0", "Y_0", "Z_0", "roll_0", "pitch_0", "yaw_0"]
    )
    with pytest.raises(InputError, match="unknown Topan EOP set"):
        eop_set("P_Q")


@pytest.mark.slow
def test_eop_poly2_recovers_truth_at_icps_with_10_gcps(scene):
    meta, truth, _ = scene
    pts = control_points(10)
    start = TopanLOSModel.from_model(meta)
    before = icp_rmse(start, pts["icp"], true=True)
    fitted, cond, _ = gauss_newton(start, pts["gcp"], eop_set("A"))
    after = icp_rmse(fitted, pts["icp"], true=True)
    assert before > 2.0  # the metadata is several pixels off
    assert after < NOISE_PX  # the truth, to the noise level, at independent points
    assert np.isfinite(cond)


@pytest.mark.slow
def test_few_gcps_failure_mode_is_ill_conditioning(scene):
    meta, _, _ = scene
    orun = OrunNatarajanModel.from_model(meta)
    names = orun.ADJUST_SETS["orun"]
    conds = {}
    for n in (6, 20):
        pts = control_points(n, seed=7)
        _, conds[n], _ = gauss_newton(orun, pts["gcp"], names, iterations=3)
    # the same 10 unknowns (unweighted) are far worse determined by 6 GCPs than by 20
    assert conds[6] > 3 * conds[20]
    # with fewer than 6 GCPs the set is refused, saying how many are needed
    with pytest.raises(InputError, match="at least 6 are needed"):
        require_gcps(5, names, "orun")


def test_velocity_sets_are_singular_whatever_the_gcps(scene):
    """Only the turn of V about Z changes the image: V_S0 has rank 1 (Topan's sets 5, 13-19
    blow up)."""
    meta, _, _ = scene
    m = TopanLOSModel.from_model(meta)
    pts = control_points(12, seed=9)["gcp"]
    _, _, J = project_jacobian(m, pts["lon"], pts["lat"], pts["h"], eop_set("V_S0"))
    A = np.concatenate([J[:, 0], J[:, 1]])
    sv = np.linalg.svd(A / np.linalg.norm(A, axis=0), compute_uv=False)
    assert sv[1] / sv[0] < 1e-3


def test_icps_outside_image_refused(scene):
    meta, _, _ = scene
    with pytest.raises(InputError, match="2 of 3 check points lie outside the 4100 x 4200 image"):
        require_inside(meta, [10.0, -3.0, 5000.0], [10.0, 10.0, 10.0])


def test_topan_bad_inputs():
    with pytest.raises(SensorModelError, match="monotonic"):
        TopanLOSModel(
            width=10, height=10, coefficients={}, psi_x=np.zeros(3), psi_y=[0.0, 0.1, 0.05]
        )
    with pytest.raises(SensorModelError, match="unknown parameter"):
        TopanLOSModel(
            width=10, height=10, coefficients={"Q_0": 1.0}, psi_x=np.zeros(3), psi_y=[0, 0.1, 0.2]
        )
    with pytest.raises(InputError, match="unknown orbital model set"):
        build("orbit-magic", None)


@pytest.mark.parametrize("cls", [TopanLOSModel, ToutinModel, *SLOW_FITS])
def test_sidecar_round_trip(scene, cls, tmp_path):
    meta, _, _ = scene
    m = cls.from_model(meta)
    m = m.with_parameters(**{n: v + 1e-6 for n, v in list(m.parameters().items())[:2]})
    save_model(m, tmp_path / "m.model.json")
    back = load_model(tmp_path / "m.model.json")
    assert type(back) is cls and back.parameters() == m.parameters()
    c, r, z = _grid(meta)
    lon, lat = meta.localize(c, r, z)
    assert np.allclose(back.project(lon, lat, z), m.project(lon, lat, z), atol=1e-9, rtol=0)
