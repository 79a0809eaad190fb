import os
from pathlib import Path

# Under pytest-xdist each test process is one worker of several: its share of the cores for OpenMP
# (torch, small_gicp), BLAS and each part of a step (core.threads.part_threads), set before they load,
# as the project's own worker pools hold theirs.
if "PYTEST_XDIST_WORKER_COUNT" in os.environ:
    _share = str(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))
    for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "L3E_PART_THREADS"):
        os.environ.setdefault(_name, _share)

import numpy as np
import pytest
import trimesh

from l3e_env.data.generation import config_for, generate
from scenes import make_scene


def pytest_collection_modifyitems(config, items):
    """The slow end-to-end tests first (in their order; a stable sort): under pytest-xdist's work
    stealing the long ones start early and the run ends on short ones, whichever worker takes them."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture(scope="session")
def run_wide(tmp_path_factory, worker_id) -> Path:
    """A folder every pytest-xdist worker of this run shares (xdist's own recipe): what one worker
    builds there, under a lock and cached by its settings, the others read instead of building it."""
    root = tmp_path_factory.getbasetemp()
    path = (root if worker_id == "master" else root.parent) / "run-wide"
    path.mkdir(exist_ok=True)
    return path


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
    cfg = config_for(
        None, scenes=["tunnel-0", "office-0", "field-0"], parents_per_scene=4, shard_size=2, labels={"children": 8}
    )
    generate(out, cfg, workers=1, progress=False)
    return out


@pytest.fixture
def cad_corridor(tmp_path) -> tuple[Path, Path]:
    """A 10 m corridor exported as a CAD tool would (y up, millimetres; floor, two walls, an end wall
    behind the start, no roof) and its route file in the same axes and units: (mesh, route)."""
    parts = [trimesh.creation.box(extents) for extents in ([10, 4, 0.2], [10, 0.2, 3], [10, 0.2, 3], [0.2, 4, 3])]
    for part, offset in zip(parts, ([5, 0, -0.1], [5, 2, 1.5], [5, -2, 1.5], [-0.1, 0, 1.5])):
        part.apply_translation(offset)
    to_y_up = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    mesh = trimesh.util.concatenate(parts)
    mesh.vertices = mesh.vertices @ to_y_up.T * 1000
    mesh.export(tmp_path / "corridor.obj")
    np.savetxt(tmp_path / "route.csv", np.array([[1.0, 0, 0], [8, 0, 0]]) @ to_y_up.T * 1000, delimiter=",")
    return tmp_path / "corridor.obj", tmp_path / "route.csv"


@pytest.fixture
def rerun_table():
    """A Rerun recording read back as one Arrow table on a time line, by rerun's own catalog reader (in
    this process; skipped where rerun-sdk's catalog extra is not installed)."""
    rr = pytest.importorskip("rerun")
    pytest.importorskip("datafusion")

    def read(path, index: str):
        with rr.server.Server(datasets={"drive": [str(path)]}) as server:
            client = server.client()
            dataset = client.get_dataset("drive")
            return dataset.reader(index=index).to_arrow_table()

    return read
