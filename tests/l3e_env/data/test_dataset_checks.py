"""A dataset is checked once where it is opened: a tampered manifest or array is refused by name."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from l3e_env.data.dataset import DatasetError, LabelDataset


def _copy(tiny_dataset, tmp_path):
    folder = tmp_path / "d"
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(tiny_dataset, folder)
    return folder


def _manifest(folder, change):
    path = folder / "manifest.json"
    manifest = json.loads(path.read_text())
    change(manifest)
    path.write_text(json.dumps(manifest))


def _array(folder, name, change):
    array = np.load(folder / f"{name}.npy")
    np.save(folder / f"{name}.npy", change(array))


MANIFESTS = {
    "format_version": (lambda m: m.update(format_version=99), "format_version 99"),
    "settings": (lambda m: m.update(settings=None), "settings must be a mapping"),
    "lidar": (lambda m: m["settings"].update(lidar="vlp16"), "settings.lidar must be a mapping"),
    "thresholds": (lambda m: m["settings"]["labels"].update(thresholds=[0.04] * 5), "six positive numbers"),
    "scenes": (lambda m: m.update(scenes=[5]), "scenes must be a list of scene names"),
    "count": (lambda m: m.update(count="four"), "count must be a whole number"),
    # issue 98: the settings, each field against its type and range
    "children float": (lambda m: m["settings"]["labels"].update(children=2.5), "children takes a whole number"),
    "children 0": (lambda m: m["settings"]["labels"].update(children=0), "labels.children must be at least 1"),
    "parents text": (lambda m: m["settings"].update(parents_per_scene="four"), "parents_per_scene takes a whole"),
    "settings scenes": (lambda m: m["settings"].update(scenes=5), "scenes takes a list"),
    "sensor": (lambda m: m["settings"]["lidar"].update(model="nosuch"), "nosuch"),
}
ARRAYS = {
    "labels 7": ("labels", lambda a: np.where(a == 1, 7, a).astype(np.uint8), "other than 0 and 1: \\['7'\\]"),
    "labels short": ("labels", lambda a: a[:-1], "labels.npy is uint8 \\(11, 6\\)"),
    "labels float": ("labels", lambda a: a.astype(np.float32) * 0.5, "labels.npy is float32"),
    "errors nan": ("errors", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 3, np.nan, a), "NaN"),
    "offsets scaled": ("offsets", lambda a: a * 2, "offsets.npy does not cut"),
    "scene -1": ("scene", lambda a: np.where(np.arange(len(a)) == 0, -1, a).astype(a.dtype), "indices outside"),
    "scene beyond": ("scene", lambda a: a + 3, "indices outside the manifest's 3 scenes"),
    "points 2 columns": ("points", lambda a: a[:, :2], "points.npy is float32"),
}


@pytest.mark.parametrize("case", sorted(MANIFESTS))
def test_a_tampered_manifest_is_refused_by_its_field(case, tiny_dataset, tmp_path):
    change, said = MANIFESTS[case]
    folder = _copy(tiny_dataset, tmp_path)
    _manifest(folder, change)
    with pytest.raises(DatasetError, match=said):
        LabelDataset(folder)


def test_a_manifest_that_is_no_mapping_is_named_as_such(tiny_dataset, tmp_path):
    """Issue 98: a JSON list was answered "generation has not finished"."""
    folder = _copy(tiny_dataset, tmp_path)
    (folder / "manifest.json").write_text("[1, 2]")
    with pytest.raises(DatasetError, match="holds a JSON list, not a dataset's manifest"):
        LabelDataset(folder)


def test_a_scan_of_nan_points_is_named_with_its_file(tiny_dataset, tmp_path):
    """Issue 98: before, "voxel coordinates beyond +-32768" from the network, naming no file."""
    folder = _copy(tiny_dataset, tmp_path)
    _array(folder, "points", lambda a: np.full_like(a, np.nan))
    data = LabelDataset(folder)
    with pytest.raises(DatasetError, match=r"points.npy: scan 0 holds NaN or infinite coordinates"):
        data.scan(0)


@pytest.mark.parametrize("case", sorted(ARRAYS))
def test_a_tampered_array_is_refused_by_its_file(case, tiny_dataset, tmp_path):
    name, change, said = ARRAYS[case]
    folder = _copy(tiny_dataset, tmp_path)
    _array(folder, name, change)
    with pytest.raises(DatasetError, match=said):
        LabelDataset(folder)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(row=st.integers(0, 11), axis=st.integers(0, 5), value=st.integers(2, 255))
def test_any_label_but_0_or_1_is_refused(tiny_dataset, tmp_path, row, axis, value):
    folder = _copy(tiny_dataset, tmp_path)
    labels = np.load(folder / "labels.npy")
    labels[row, axis] = value
    np.save(folder / "labels.npy", labels)
    with pytest.raises(DatasetError, match="other than 0 and 1"):
        LabelDataset(folder)
    assert len(LabelDataset(tiny_dataset)) == 12  # the original stays readable


def test_a_run_refused_at_its_start_leaves_no_folder(tiny_dataset, tmp_path):
    """l3e train with no training scene in the data, l3e evaluate with a checkpoint of broken weights:
    refused, and nothing left where the run would have written (issue 90: leftovers)."""
    import torch

    from l3e_env.experiments.table3 import Table3Options, run_table3
    from l3e_env.model.classifier import DEFAULT_CHECKPOINT, CheckpointError
    from l3e_env.model.training import TrainConfig, TrainingError, train

    with pytest.raises(TrainingError, match="are not in dataset"):
        train(tiny_dataset, tmp_path / "run", TrainConfig(train_scenes=["cave-9"], epochs=1), progress=False)
    assert not (tmp_path / "run").exists()
    state = torch.load(DEFAULT_CHECKPOINT, weights_only=True)
    first = next(k for k, v in state["state_dict"].items() if v.is_floating_point())
    state["state_dict"][first] = state["state_dict"][first] * float("nan")
    torch.save(state, tmp_path / "broken.pt")
    with pytest.raises(CheckpointError, match="non-finite weights"):
        run_table3([tmp_path / "broken.pt"], None, tmp_path / "eval", Table3Options(others=[str(tiny_dataset)]), False)
    assert not (tmp_path / "eval").exists()
    (tmp_path / "kept").mkdir()
    with pytest.raises(TrainingError):
        train(tiny_dataset, tmp_path / "kept", TrainConfig(train_scenes=["cave-9"], epochs=1), progress=False)
    assert (tmp_path / "kept").is_dir()  # a folder that was there stays


def test_dataset_stats_counts_the_arrays_labels_not_the_manifests_word(tiny_dataset, tmp_path, capsys):
    from l3e_env.cli.main import main

    folder = _copy(tiny_dataset, tmp_path)
    labels = np.load(folder / "labels.npy")
    told = {a: 0.123 for a in ("x", "y", "z", "roll", "pitch", "yaw")}
    _manifest(folder, lambda m: m.update(statistics={**m["statistics"], "positive_rate": told}))
    assert main(["dataset", "stats", str(folder)]) == 0
    said = capsys.readouterr().out
    rates = labels.mean(axis=0)
    assert f"x {rates[0]:.2f}" in said and f"yaw {rates[5]:.2f}" in said and "0.12" not in said


def test_a_generation_that_labels_no_parent_fails_naming_the_folder(tmp_path, capsys, monkeypatch):
    import l3e_env.data.generation as generation
    from l3e_env.cli.main import main
    from l3e_env.data.dataset import label_statistics

    failure = {"scene": "tunnel-0", "parent": 0, "reason": "the sensor saw nothing"}
    empty = {
        "count": 0,
        "failures": [failure],
        "statistics": label_statistics(np.zeros((0, 6), np.uint8)),
        "generation_seconds_last_run": 0.0,
    }
    monkeypatch.setattr(generation, "generate", lambda *a, **k: empty)
    out = tmp_path / "none"
    assert main(["dataset", "generate", "--scene", "tunnel-0", "--parents", "1", "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert "the sensor saw nothing" in captured.out and f"no parent could be labelled in {out}" in captured.err
