"""Datasets labelled by each scan's own estimate (`labeller="scan"`): a distillation set for training,
refused wherever labels are taken as ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from l3e_env.config import LidarConfig
from l3e_env.core.transforms import level_rotation_of
from l3e_env.data.dataset import DatasetError, DatasetUnion, LabelDataset, scan_labelled
from l3e_env.data.generation import config_for, generate
from l3e_env.localizability.labels import LabelConfig
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.localizability.scan_mc import ScanMCConfig, scan_errors
from l3e_env.sim.patterns import get_pattern


def _distill_config(**kw):
    settings = {"scenes": ["tunnel-10", "office-10"], "parents_per_scene": 2, **kw}
    return config_for(None, shard_size=1, labeller="scan", scan_mc={"children": 10, "first": 10}, **settings)


@pytest.fixture(scope="module")
def distill_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("distill")
    generate(out, _distill_config(), workers=1, progress=False)
    return out


def test_a_scan_labelled_dataset_holds_each_scans_own_estimate(distill_dataset):
    data = LabelDataset(distill_dataset)
    assert data.labeller == "scan" and len(data) == 4
    assert json.loads((distill_dataset / "manifest.json").read_text())["settings"]["scan_mc"]["children"] == 10
    thresholds = LabelConfig().threshold_vector()
    assert (data.errors > 0).all()
    assert np.array_equal(data.labels, (data.errors > thresholds).astype(np.uint8))
    # the stored errors are the scan estimate of the stored scan: the same estimate again from the
    # scan with another seed lies near them (one Monte-Carlo draw of 10 children against another)
    again = scan_errors(
        data.scan(0),
        LidarConfig(),
        RegistrationConfig(),
        LabelConfig(),
        ScanMCConfig(children=10, first=10),
        np.random.default_rng(123),
        level_rotation_of(data.poses[0]),  # the estimate is written in the scan's level frame, as labels are
    )
    assert np.all(np.abs(np.log(again.errors / data.errors[0])) < 1.5)


def test_the_same_command_gives_the_same_distillation_set(distill_dataset, tmp_path):
    generate(tmp_path / "again", _distill_config(), workers=2, progress=False)
    assert np.array_equal(LabelDataset(tmp_path / "again").errors, LabelDataset(distill_dataset).errors)


def test_an_unknown_labeller_is_refused_before_the_folder(tmp_path):
    with pytest.raises(DatasetError, match="labeller must be one of scene, scan"):
        generate(tmp_path / "d", config_for(None, scenes=["tunnel-0"], labeller="mesh"), progress=False)
    assert not (tmp_path / "d").exists()


def test_a_distillation_set_is_no_ground_truth_to_score_or_choose_epochs_on(distill_dataset, tiny_dataset, tmp_path):
    from l3e_env.experiments.table3 import Table3Options, run_table3
    from l3e_env.model.training import TrainingError, train

    union = DatasetUnion([tiny_dataset, distill_dataset])
    assert scan_labelled(union).tolist() == [False] * 12 + [True] * 4
    with pytest.raises(DatasetError, match="labelled by each scan's own estimate .* no ground truth to score"):
        run_table3([], None, tmp_path / "t3", Table3Options(others=[distill_dataset]), progress=False)
    assert not (tmp_path / "t3").exists()  # a run refused leaves no folder that looks like a result
    with pytest.raises(TrainingError, match="validation scenes are in a dataset labelled by each scan's own"):
        train(
            [tiny_dataset, distill_dataset], tmp_path / "run", _train_cfg(["tunnel-0"], ["office-10"]), progress=False
        )


def test_a_network_trained_with_a_distillation_set_gets_its_layer_fitted_on_the_scene_labels(
    distill_dataset, tiny_dataset, tmp_path
):
    from l3e_env.model.classifier import load_checkpoint
    from l3e_env.model.training import fit_constraints, train

    cfg = _train_cfg(["tunnel-0", "field-0", "tunnel-10", "office-10"], ["office-0"])
    train([tiny_dataset, distill_dataset], tmp_path / "net", cfg, progress=False)
    with pytest.raises(DatasetError, match="no ground truth to fit the constraint layer"):
        fit_constraints(
            tmp_path / "net" / "model.pt", [tiny_dataset, distill_dataset], tmp_path / "c.pt", progress=False
        )
    net = tmp_path / "net" / "model.pt"
    fit_constraints(net, tiny_dataset, tmp_path / "c.pt", progress=False)
    fitted = load_checkpoint(tmp_path / "c.pt")["constraints"]
    assert fitted["fitted_rows"] == 8  # tunnel-0 and field-0's parents: the distilled scenes left out


def _train_cfg(train_scenes, validation_scenes):
    from l3e_env.model.classifier import ModelConfig
    from l3e_env.model.training import TrainConfig

    small = ModelConfig(points=600, channels=(8, 8, 16, 16), pointnet_channels=(16, 32), head=(16, 16, 16, 16))
    return TrainConfig(
        model=small,
        epochs=1,
        samples_per_epoch=8,
        batch_size=4,
        train_scenes=train_scenes,
        validation_scenes=validation_scenes,
        threads=1,
        soft_labels=4.0,
    )


def test_distilled_training_learns_the_distillation_sets_places_and_never_a_test_familys(
    distill_dataset, tiny_dataset, tmp_path, capsys
):
    from l3e_env.cli.main import main
    from l3e_env.model.training import TrainingError, distilled_scenes

    assert distilled_scenes([tiny_dataset, distill_dataset]) == ["tunnel-10", "office-10"]  # their own places
    with pytest.raises(TrainingError, match="none of the datasets is a distillation set"):
        distilled_scenes([tiny_dataset])
    mine = tmp_path / "mine"
    generate(mine, _distill_config(scenes=["mine-0"], parents_per_scene=1), workers=1, progress=False)
    args = [
        "train",
        "--dataset",
        str(tiny_dataset),
        "--dataset",
        str(mine),
        "--distilled",
        "--out",
        str(tmp_path / "m"),
    ]
    assert main(args) == 2
    said = capsys.readouterr().err
    assert "mine-0" in said and "never trained on" in said and not (tmp_path / "m").exists()


def test_the_randomised_presets_cover_three_sensors_on_disjoint_places():
    """1 000 randomised places, 10 000 scans, seen by a 16-, a 32- and a 128-beam sensor; each scan
    labelled by its own estimate (scenes.composition)."""
    configs = [config_for(p) for p in ("random", "random-32", "random-128")]
    places = [set(c.scenes) for c in configs]
    assert sum(len(p) for p in places) == len(set().union(*places)) >= 1000
    assert sum(len(c.scenes) * c.parents_per_scene for c in configs) >= 10_000
    assert [get_pattern(c.lidar.model).n_beams for c in configs] == [16, 32, 128]
    assert {c.labeller for c in configs} == {"scan"} and len({c.seed for c in configs}) == 3


@pytest.mark.slow
def test_a_network_learns_several_sensors_scans_and_says_which(distill_dataset, tiny_dataset, tmp_path):
    """Distillation sets of a 128-beam and a 16-beam sensor train one network: the checkpoint names
    both sensors, warns for neither and for a third; evaluation still reads one sensor at a time."""
    import warnings

    from l3e_env.model.classifier import Classifier
    from l3e_env.model.training import train

    ouster = tmp_path / "os1"
    generate(
        ouster,
        _distill_config(scenes=["office-10"], parents_per_scene=2, lidar={"model": "os1-128"}),
        workers=1,
        progress=False,
    )
    with pytest.raises(DatasetError, match="lidar settings"):
        DatasetUnion([distill_dataset, ouster])
    cfg = _train_cfg(["tunnel-0", "field-0", "tunnel-10", "office-10"], ["office-0"])
    train([tiny_dataset, distill_dataset, ouster], tmp_path / "m", cfg, progress=False)
    clf = Classifier.load(tmp_path / "m" / "model.pt")
    assert clf.meta["sensors"] == ["vlp16", "os1-128"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        clf.check_settings("os1-128")
        clf.check_settings("vlp16-calibrated")
    with pytest.warns(UserWarning, match="trained on vlp16, os1-128 scans and now sees hdl32e"):
        clf.check_settings("hdl32e")
