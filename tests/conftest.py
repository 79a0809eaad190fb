import numpy as np
import pytest

from l3e_env.dataset import config_for, generate
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


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """Twelve labelled parents in three scenes, for training and evaluation tests."""
    out = tmp_path_factory.mktemp("tiny")
    cfg = config_for(None, scenes=["tunnel-0", "office-0", "field-0"], parents_per_scene=4, shard_size=2,
                     labels={"children": 8})
    generate(out, cfg, workers=1, progress=False)
    return out
