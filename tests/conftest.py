from pathlib import Path

import pytest

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
