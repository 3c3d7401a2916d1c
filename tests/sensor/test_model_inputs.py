"""What every sensor model's ``project``/``localize``/``rays``/``localize_dem`` does with
inputs of the wrong kind: one :class:`SensorModelError` (or :class:`DEMError`) naming the
model and the problem, not numpy's ValueError or an AttributeError from inside."""

import numpy as np
import pytest

from stereodem.core.errors import DEMError, SensorModelError
from stereodem.sensor.estimation.rpcfit import fit_rpc
from stereodem.sensor.simulation.simulate import simulate_scene


@pytest.fixture(scope="module")
def scenes():
    out = {p: simulate_scene(p, size=(64, 64), seed=0) for p in ("frame", "pushbroom")}
    out["rpc"] = out["pushbroom"]
    return out


def _model(scenes, kind):
    model = scenes[kind].left_model
    if kind == "rpc":
        model, _ = fit_rpc(model, height_range=(500.0, 4000.0), grid=(6, 6, 4))
    return model


@pytest.mark.parametrize("kind", ["frame", "pushbroom", "rpc"])
def test_coordinates_of_shapes_that_do_not_broadcast_are_one_line(scenes, kind):
    """``model.localize(np.zeros(3), np.zeros(2), 0.0)`` raised numpy's "shape mismatch"
    ValueError (RPC, frame camera, generic models), naming neither the model nor the
    shapes; ``project("abc", ...)`` numpy's "could not convert"."""
    model = _model(scenes, kind)
    lon, lat = model.localize(30.0, 30.0, 2000.0)
    name = type(model).__name__
    with pytest.raises(SensorModelError, match=rf"{name}: image coordinates.*\(3,\), \(2,\)"):
        model.localize(np.zeros(3), np.zeros(2), 0.0)
    with pytest.raises(SensorModelError, match=rf"{name}: ground coordinates.*\(3,\), \(2,\)"):
        model.project(np.full(3, lon), np.full(2, lat), 0.0)
    with pytest.raises(SensorModelError, match=rf"{name}: ground coordinates must be numbers"):
        model.project("abc", lat, 0.0)
    col, row = model.project(np.full(3, lon), lat, 2000.0)  # broadcasting still works
    assert np.allclose(col, 30.0, atol=1e-3) and np.allclose(row, 30.0, atol=1e-3)


@pytest.mark.parametrize("kind", ["frame", "pushbroom"])
def test_localize_dem_takes_a_dem_or_its_path(scenes, kind, tmp_path):
    """``model.localize_dem(col, row, "dem.tif")`` (or a height array) raised an
    AttributeError ('str' object has no attribute 'sample'); a path is read as everywhere
    else, an array is a DEMError saying what is expected."""
    scene = scenes[kind]
    path = scene.truth_dem.write(tmp_path / "truth.tif")
    by_path = scene.left_model.localize_dem(np.array([30.0]), np.array([30.0]), path)
    by_dem = scene.left_model.localize_dem(np.array([30.0]), np.array([30.0]), scene.truth_dem)
    assert by_path.converged.all()
    assert np.allclose(by_path.h, by_dem.h, atol=1e-3)
    with pytest.raises(DEMError, match="localize_dem: dem must be a DEM.*got ndarray"):
        scene.left_model.localize_dem(np.array([30.0]), np.array([30.0]), np.zeros((3, 3)))
