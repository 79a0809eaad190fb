"""The scan's point-to-plane Hessian and the constraint layer fitted over the network's logits."""

import dataclasses
import itertools

import numpy as np
import pytest
import torch

from l3e_env.core.normals import smallest_eigenvector
from l3e_env.data.dataset import LabelDataset
from l3e_env.model.classifier import (
    Classifier,
    LocalizabilityNet,
    ModelConfig,
    load_checkpoint,
    model_from_checkpoint,
    model_probabilities,
)
from l3e_env.model.constraints import (
    AxisStacker,
    fit_stacker,
    hessian_features,
    scan_features,
    surface_rows,
    voxel_hessian,
)
from l3e_env.model.scores import auroc, axis_scores, mean_scores
from l3e_env.model.sparse import voxelize
from l3e_env.model.training import (
    TrainConfig,
    TrainingError,
    fit_constraints,
    network_parts,
    predict_dataset,
    split_indices,
    train,
)

SMALL = ModelConfig(points=600, channels=(8, 8, 16, 16), head=(16, 16, 16, 16))


def _box_room(rng, length: float, width: float = 4.0, height: float = 3.0, ends: bool = True, n: int = 6000):
    """Points on the walls, floor and ceiling of a box around the sensor; without its two end
    walls it is a corridor along x."""
    faces = [(1, -width / 2), (1, width / 2), (2, -1.0), (2, height - 1.0)]
    if ends:
        faces += [(0, -length / 2), (0, length / 2)]
    extent = np.array([length / 2, width / 2, height / 2])
    centre = np.array([0.0, 0.0, height / 2 - 1.0])
    points = []
    for axis, value in faces:
        p = centre + rng.uniform(-1, 1, (n // len(faces), 3)) * extent
        p[:, axis] = value
        points.append(p)
    return torch.from_numpy(np.concatenate(points).astype(np.float32))


def _brute_force_hessian(points: np.ndarray, voxel: float) -> np.ndarray:
    """The same Hessian by explicit loops: voxel means, each voxel's 3x3x3 block, eigh normals."""
    cells: dict[tuple, list] = {}
    for p in points:
        cells.setdefault(tuple(np.floor(p / voxel).astype(int)), []).append(p)
    means = {c: np.mean(v, axis=0) for c, v in cells.items()}
    H = np.zeros((6, 6))
    for c, m in means.items():
        block = [means[k] for k in (tuple(np.add(c, d)) for d in itertools.product((-1, 0, 1), repeat=3)) if k in means]
        if len(block) < 4:
            continue
        block = np.array(block, dtype=np.float64)
        w, V = np.linalg.eigh(np.cov(block.T, bias=True))
        if not w[0] < 0.1 * w[1]:
            continue
        row = np.r_[V[:, 0], np.cross(m, V[:, 0])]
        H += np.outer(row, row)
    return H


def test_the_closed_form_normal_is_the_smallest_eigenvector(rng):
    a = rng.standard_normal((500, 3, 3))
    c = a @ a.transpose(0, 2, 1)
    c[0] = np.diag([1.0, 2.0, 0.01])  # axis-aligned plane
    c[1] = np.diag([1.0, 1.0, 0.0])  # a perfect plane: rank two
    normal, smallest, middle = smallest_eigenvector(c)
    w, V = np.linalg.eigh(c)
    assert np.allclose(smallest, w[:, 0], atol=1e-6) and np.allclose(middle, w[:, 1], atol=1e-6)
    assert np.allclose(np.abs((normal * V[:, :, 0]).sum(1)), 1.0, atol=1e-6)
    assert np.allclose(np.abs(normal[:2]), [[0.0, 0.0, 1.0]] * 2)


def test_voxel_hessian_matches_a_brute_force_sum_and_keeps_scans_apart(rng):
    room = _box_room(rng, 8.0, n=1500)
    corridor = _box_room(rng, 30.0, ends=False, n=1500) + torch.tensor([0.05, 0.0, 0.0])
    level, means, _ = voxelize([room, corridor], 0.2)
    both = voxel_hessian(level, means, 2)
    for k, points in enumerate([room, corridor]):
        expected = _brute_force_hessian(points.numpy().astype(np.float64), 0.2)
        assert np.allclose(both[k], expected, rtol=1e-4, atol=1e-3)
    assert expected[0, 0] < 0.02 * expected[1, 1]  # the corridor's walls hold (almost) nothing along x


def test_surface_rows_face_the_sensor_and_sum_to_the_hessian(rng):
    """The ResUNet's surface input: each planar voxel's row J = [n, p x n] with its normal turned to
    the sensor, 1 in the last column; the Hessian is the sum of their outer products."""
    room = _box_room(rng, 8.0, n=3000)
    level, means, _ = voxelize([room], 0.2)
    rows = surface_rows(level, means).numpy().astype(np.float64)
    planar = rows[:, 6] == 1
    assert rows.shape == (len(means), 7) and planar.mean() > 0.6 and not rows[~planar].any()
    p, n = means.numpy().astype(np.float64)[planar], rows[planar, :3]
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6) and ((p * n).sum(1) < 0).all()
    np.testing.assert_allclose(rows[planar, 3:6], np.cross(p, n), atol=1e-5)
    J = rows[planar, :6]
    np.testing.assert_allclose(J.T @ J, voxel_hessian(level, means, 1)[0], rtol=1e-5, atol=1e-3)
    floor = np.abs(p[:, 2] + 1.0) < 0.05  # the floor 1 m below the sensor: its normal points up
    up = np.abs(n[floor] - [0.0, 0.0, 1.0]).max(axis=1) < 0.05  # all but beside the walls' feet
    assert floor.sum() > 50 and up.mean() > 0.8
    net = LocalizabilityNet(dataclasses.replace(SMALL, surface_rows=True))
    out = net([room, room * 1.5])
    out.sum().backward()
    assert out.shape == (2, 6) and net.backbone.stem.weight.grad[-7:].abs().sum() > 0  # the rows are read
    with pytest.raises(ValueError, match="surface rows"):
        LocalizabilityNet(dataclasses.replace(SMALL, architecture="pointnet", surface_rows=True))


def test_the_coarser_levels_features_are_those_of_the_finer_voxels_means_on_the_coarser_grid(rng):
    corridor = _box_room(rng, 30.0, ends=False, n=3000)
    level, means, _ = voxelize([corridor], 0.2)
    both = scan_features(level, means, 1, (0, 1))[0].numpy()
    assert both.shape == (24,)
    assert np.allclose(both[:12], hessian_features(voxel_hessian(level, means, 1))[0])
    # a 0.2 m voxel's mean lies in its 0.4 m parent, so the brute force over the means on the 0.4 m grid
    # weighs every finer voxel once, as the coarser level does
    expected = _brute_force_hessian(means.numpy().astype(np.float64), 0.4)
    assert np.allclose(both[12:], hessian_features(expected[None])[0], atol=1e-3)
    assert np.allclose(scan_features(level, means, 1, (1,))[0].numpy(), both[12:])
    room = _box_room(rng, 8.0, n=3000)
    level, means, _ = voxelize([room, corridor], 0.2)  # a batch: each scan keeps its own rows
    batch = scan_features(level, means, 2, (0, 1)).numpy()
    alone = scan_features(*voxelize([room], 0.2)[:2], 1, (0, 1))[0].numpy()
    assert np.allclose(batch[1], both, atol=1e-4) and np.allclose(batch[0], alone, atol=1e-4)
    assert not np.allclose(batch[0], batch[1], atol=0.1)


def test_the_features_see_a_corridor_along_x_and_a_closed_room_everywhere(rng):
    def features(points):
        level, means, _ = voxelize([points], 0.2)
        return hessian_features(voxel_hessian(level, means, 1))[0]

    corridor, room = features(_box_room(rng, 30.0, ends=False)), features(_box_room(rng, 8.0))
    log_var = {"corridor": corridor[:6], "room": room[:6]}
    assert log_var["corridor"][0] > log_var["corridor"][1] + 3  # x is free, y is held by the walls
    assert log_var["corridor"][0] > log_var["room"][0] + 3  # the end walls hold x
    assert abs(log_var["room"][0] - log_var["room"][1]) < 2  # a room holds x and y alike
    assert np.all(np.isfinite(corridor)) and np.all(np.diff(corridor[6:]) >= 0)  # eigenvalues ascending


def test_an_unfitted_stacker_passes_the_logits_and_a_fitted_one_learns_the_features(rng):
    logits = torch.from_numpy(rng.standard_normal((40, 6)).astype(np.float32))
    features = torch.from_numpy(rng.standard_normal((40, 12)).astype(np.float32))
    assert torch.allclose(AxisStacker()(logits, features), logits)
    n = 400
    logits, features = rng.standard_normal((n, 6)), rng.standard_normal((n, 12))
    labels = np.zeros((n, 6), dtype=bool)
    labels[:, 0] = features[:, 0] > 1.0  # x: told by the first variance alone, not by the logit
    labels[:, 1:] = (logits[:, 1:] + 0.3 * rng.standard_normal((n, 5))) > 0.5  # the others: by the logit
    stacker = fit_stacker(logits, features, labels)
    out = stacker(torch.from_numpy(logits).float(), torch.from_numpy(features).float()).detach().numpy()
    assert auroc(labels[:, 0], out[:, 0]) > 0.95 and auroc(labels[:, 0], logits[:, 0]) < 0.7
    assert all(auroc(labels[:, a], out[:, a]) > 0.9 for a in range(1, 6))
    with pytest.raises(ValueError, match="NaN"):
        fit_stacker(np.full((4, 6), np.nan), features[:4], labels[:4])


def test_a_constraint_model_saves_loads_and_refuses_a_pointnet(tmp_path, rng):
    from l3e_env.model.classifier import save_checkpoint

    model = LocalizabilityNet(dataclasses.replace(SMALL, constraints=True, constraint_levels=(0, 1))).eval()
    with torch.no_grad():
        model.stacker.weight.normal_()
    save_checkpoint(tmp_path / "c.pt", model, np.full(6, 0.5), {})
    scan = _box_room(rng, 20.0, ends=False, n=500).numpy()  # fewer than SMALL.points: all are read
    clf = Classifier.load(tmp_path / "c.pt")
    batch = [torch.from_numpy(scan)]
    assert np.allclose(clf.probabilities([scan]), model_probabilities(model, batch), atol=1e-6)
    net, feats = model.parts(batch)
    assert feats.shape == (1, 24) and not torch.allclose(model(batch), net)
    with pytest.raises(ValueError, match="PointNet"):
        LocalizabilityNet(dataclasses.replace(SMALL, architecture="pointnet", constraints=True))
    for levels in [(), (1, 0), (0, 4)]:  # none, out of order, beyond the four levels
        with pytest.raises(ValueError, match="constraint levels"):
            LocalizabilityNet(dataclasses.replace(SMALL, constraints=True, constraint_levels=levels))


def test_fit_constraints_fits_on_training_scenes_and_keeps_the_network(tiny_dataset, tmp_path):
    cfg = TrainConfig(
        model=SMALL,
        epochs=1,
        samples_per_epoch=8,
        batch_size=4,
        threads=1,
        train_scenes=["tunnel-0", "field-0"],
        validation_scenes=["office-0"],
    )
    train(tiny_dataset, tmp_path / "run", cfg, progress=False)
    base = Classifier.load(tmp_path / "run" / "model.pt")
    out = tmp_path / "new" / "c.pt"  # a folder that does not exist yet
    result = fit_constraints(tmp_path / "run" / "model.pt", tiny_dataset, out, beta=1.0, levels=(0, 1), progress=False)
    fitted = Classifier.load(out)
    assert fitted.model.config.constraints and fitted.meta["threshold_beta"] == 1.0
    assert fitted.model.config.constraint_levels == (0, 1)
    assert np.allclose(fitted.thresholds, result["thresholds"], atol=1e-4)
    for name, weight in base.model.state_dict().items():  # the network itself is untouched
        assert torch.equal(weight, fitted.model.state_dict()[name])
    data = LabelDataset(tiny_dataset)
    rows = split_indices(data, ["tunnel-0", "field-0"])
    logits, features, _ = network_parts(fitted.model, data, rows)
    assert np.all(np.isfinite(features)) and features.shape == (len(rows), 24)
    assert np.allclose(network_parts(base.model, data, rows)[1], features[:, :12])  # the base reads level 0 only
    assert fitted.model.stacker.mean[1:].numpy() == pytest.approx(features.mean(0), rel=1e-4, abs=1e-4)
    # its scores are its own on the validation scenes; the network's are kept apart
    val_rows = split_indices(data, ["office-0"])
    predicted = predict_dataset(fitted.model, data, val_rows) > fitted.thresholds
    own = mean_scores(axis_scores(data.labels[val_rows], predicted))
    assert fitted.meta["scores"]["val_f1"] == pytest.approx(own["f1"]) and "epoch" not in fitted.meta
    assert fitted.meta["constraints"]["base_scores"] == base.meta["scores"]
    with pytest.raises(TrainingError, match="constraint levels"):
        fit_constraints(tmp_path / "run" / "model.pt", tiny_dataset, tmp_path / "bad.pt", levels=(5,), progress=False)
    with pytest.raises(TrainingError, match="fit-constraints"):  # the layer is never trained with the network
        train(tiny_dataset, tmp_path / "bad", dataclasses.replace(cfg, model=fitted.model.config), progress=False)
    # but a checkpoint with the layer is fine-tuned from: its network, the layer left to be fitted again
    tuned = train(
        tiny_dataset, tmp_path / "tuned", dataclasses.replace(cfg, init=str(out), learning_rate=0.0), progress=False
    )
    weights, start = (
        dict(model_from_checkpoint(load_checkpoint(p)).named_parameters())
        for p in (tmp_path / "tuned" / "model.pt", tmp_path / "run" / "model.pt")
    )
    assert not any(k.startswith("stacker.") for k in weights) and "best_epoch" in tuned
    assert weights.keys() == start.keys() and all(torch.equal(w, weights[k]) for k, w in start.items())
