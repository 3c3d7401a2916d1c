from pathlib import Path

import pytest

from stereodem.sensor.simulation.simulate import simulate_scene

DATA = Path(__file__).parent / "data"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def data_dir():
    return DATA


@pytest.fixture(scope="session")
def shared_data():
    """The large real data set beside the repository (../shared/data); skip when absent."""
    if not SHARED.is_dir():
        pytest.skip("../shared/data is not present (only in the development workspace)")
    return SHARED


@pytest.fixture(scope="session")
def aster600():
    """The 600 x 600 simulated ASTER-like pair (noise 1 DN, seed 0) shared by the stereo tests;
    read-only (tests that change a scene simulate their own)."""
    return simulate_scene("aster", size=(600, 600), noise=1.0, seed=0)
