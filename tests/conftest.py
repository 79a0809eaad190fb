import numpy as np
import pytest

from scenes import make_scene


@pytest.fixture(scope="session")
def mine():
    return make_scene("mine")


@pytest.fixture(scope="session")
def office():
    return make_scene("office")


@pytest.fixture
def rng():
    return np.random.default_rng(0)
