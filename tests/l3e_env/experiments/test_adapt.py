"""`l3e adapt`: a place's own scans labelled by scanmc, the shipped network fine-tuned on them."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from l3e_env.config import LidarConfig
from l3e_env.core.transforms import pose_to_matrix
from l3e_env.experiments import adapt as adapt_module
from l3e_env.experiments.adapt import AdaptError, AdaptOptions, adapt
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene

MIN_SCANS = 6  # the least a fine-tune takes, lowered for these tests: the mechanics are the same with fewer scans
QUICK = AdaptOptions(children=4, epochs=1, samples_per_epoch=8, workers=1, max_scans=MIN_SCANS + 2)


@pytest.fixture(autouse=True)
def fewer_scans(monkeypatch):
    monkeypatch.setattr(adapt_module, "MIN_SCANS", MIN_SCANS)


def _scans(folder, count: int, sensor: str = "vlp16", scene: str = "office-0"):
    """`count` scans along a scene's path, as .npy files in the sensor's frame."""
    place = make_scene(scene)
    lidar = Lidar(EmbreeCaster(place.mesh, threads=1), LidarConfig(model=sensor))
    path = place.sampling_paths[0]
    folder.mkdir(parents=True, exist_ok=True)
    for k, s in enumerate(np.linspace(0.1, 0.9, count)):
        at = path[int(s * (len(path) - 1))]
        T = pose_to_matrix(np.array([at[0], at[1], at[2] + 0.85, 0.0, 0.0, 0.3 * k]))
        np.save(folder / f"scan-{k:03d}.npy", lidar.scan(T, np.random.default_rng(k)).points)
    return folder


@pytest.fixture(scope="module")
def office_scans(tmp_path_factory):
    return _scans(tmp_path_factory.mktemp("office") / "office-0", MIN_SCANS + 2)


@pytest.mark.slow
def test_bad_scans_are_named_before_anything_is_labelled(tmp_path):
    """No scans, too few, or another sensor's than the checkpoint learnt: refused by name, no run folder."""
    (tmp_path / "empty").mkdir()
    with pytest.raises(AdaptError, match="holds no scan files"):
        adapt(tmp_path / "empty", tmp_path / "run", QUICK, progress=False)
    with pytest.raises(AdaptError, match=f"3 readable scans.*at least {MIN_SCANS}"):
        adapt(_scans(tmp_path / "few", 3), tmp_path / "run", QUICK, progress=False)
    with pytest.raises(AdaptError, match="are os1-128 scans and .* learnt vlp16 scans"):
        adapt(_scans(tmp_path / "ouster", MIN_SCANS, "os1-128"), tmp_path / "run", QUICK, progress=False)
    assert not (tmp_path / "run" / "labels").exists()


@pytest.mark.slow
def test_an_adapted_model_is_refused_nowhere_says_what_it_was_adapted_on_and_is_not_scored_there(
    office_scans, tiny_dataset, tmp_path, monkeypatch
):
    from l3e_env.detection.detectors import make_detector
    from l3e_env.model.classifier import Classifier

    result = adapt(office_scans, tmp_path / "run", QUICK, progress=False)
    assert result.labelled == result.scans == MIN_SCANS + 2 and result.checkpoint.exists()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no protocol, sensor or registration warning
        clf = Classifier.load(result.checkpoint)
        Classifier.load(result.checkpoint, symmetric=True)
        make_detector(f"learned:{result.checkpoint}", sensor=LidarConfig())
    adapted = clf.meta["adapted"]
    assert adapted["place"] == "office-0" and adapted["sensor"] == "vlp16" and adapted["scans"] == MIN_SCANS + 2
    assert adapted["source"] == str(office_scans.resolve()) and len(adapted["base_sha256"]) == 64
    assert clf.meta["training"]["train_scenes"] == ["office-0"] and clf.model.config.constraints
    p, mask = clf.predict(np.load(office_scans / "scan-000.npy"))
    assert p.shape == (6,) and mask.dtype == bool
    # a run again resumes: labelled chunks are kept, and a finished run is not trained again; other
    # settings in the folder are refused, before a scan is read
    chunk = tmp_path / "run" / "labels" / "shards" / "chunk-00000.npy"
    before = chunk.stat().st_mtime_ns, result.checkpoint.stat().st_mtime_ns
    again = adapt(office_scans, tmp_path / "run", QUICK, progress=False)
    assert (chunk.stat().st_mtime_ns, result.checkpoint.stat().st_mtime_ns) == before
    assert again.checkpoint == result.checkpoint and again.statistics == result.statistics
    assert "fine-tuning" in result.seconds and "fine-tuning" not in again.seconds
    with monkeypatch.context() as patched:
        patched.setattr(adapt_module, "_read", lambda *args: pytest.fail("scans read before the folder was checked"))
        with pytest.raises(AdaptError, match="holds another adaptation.*children"):
            adapt(office_scans, tmp_path / "run", AdaptOptions(children=20, workers=1), progress=False)
    assert json.loads((tmp_path / "run" / "adapt.json").read_text())["children"] == 4
    # the adapted place's scans are never scored: `l3e evaluate` drops every dataset's rows of the place a
    # checkpoint was adapted on, for every detector alike
    from l3e_env.experiments.table3 import Table3Options, run_table3

    table = run_table3([result.checkpoint], None, tmp_path / "eval", Table3Options(others=[str(tiny_dataset)]), False)
    scored = next(iter(table.results["models"].values()))["splits"][f"all of {tiny_dataset.name}"]["count"]
    assert table.results["left_out"][f"all of {tiny_dataset.name}"] == ["office-0"]
    assert scored == 8  # twelve scans of three scenes, office-0's four left out
