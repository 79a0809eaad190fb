"""The classifier: input checks, checkpoints, batching, scores and thresholds, resumable training."""

import copy
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from l3e_env.core.transforms import pose_to_matrix
from l3e_env.data.dataset import DatasetError, LabelDataset, error_ratios, open_datasets
from l3e_env.data.generation import config_for, generate
from l3e_env.detection.detectors import LearnedDetector, make_detector
from l3e_env.localizability.labels import LABEL_PROTOCOL, LabelConfig
from l3e_env.model.classifier import (
    CHECKPOINT_VERSION,
    DEFAULT_CHECKPOINT,
    SYMMETRIES,
    CheckpointError,
    Classifier,
    LocalizabilityNet,
    ModelConfig,
    ScanError,
    canonical_view,
    check_scan,
    fold_batch_norms,
    level_scan,
    load_checkpoint,
    model_from_checkpoint,
    model_input,
    model_probabilities,
    one_per_voxel,
    quantize_int8,
    sample_points,
    save_checkpoint,
    symmetry_view,
    up_vector,
)
from l3e_env.model.scores import (
    auroc,
    axis_scores,
    best_thresholds,
    format_table,
    mean_interval,
    mean_scores,
    micro_f1,
    pr_curve,
)
from l3e_env.model.sparse import GatherConv, int8_products_work, int8_residual_block, voxelize
from l3e_env.model.training import (
    SWAP_LABELS,
    TrainConfig,
    TrainingError,
    _resumable,
    augment,
    balanced_pool,
    calibrate_symmetric,
    predict_dataset,
    scaled,
    split_indices,
    train,
    training_targets,
)

SMALL = ModelConfig(points=600, channels=(8, 8, 16, 16), pointnet_channels=(16, 32), head=(16, 16, 16, 16))


def _scan(rng, n=3000):
    return (rng.standard_normal((n, 3)) * [8, 3, 1]).astype(np.float32)


def _checkpoint(path, architecture="resunet", seed=0, symmetric_thresholds=None):
    torch.manual_seed(seed)
    model = LocalizabilityNet(ModelConfig(**{**SMALL.__dict__, "architecture": architecture}))
    extra = None if symmetric_thresholds is None else {"symmetric_thresholds": [float(t) for t in symmetric_thresholds]}
    save_checkpoint(path, model.eval(), np.full(6, 0.5), {"lidar": {"model": "vlp16"}}, extra)
    return path


@pytest.mark.parametrize(
    "bad, words",
    [
        (np.zeros((0, 3)), "0 points"),
        (np.zeros((49, 3)), "49 points"),
        (np.zeros((100, 2)), "shape"),
        (np.array([[np.nan, 0, 0]] + [[1, 2, 3]] * 99), "1 point with NaN"),
        (
            np.array([[30000.0, 0, 0]] + [[1000, 2000, 300]] * 99),
            "reach 30000 m from the sensor, beyond 1000 m .a scan in millimetres",
        ),
        (np.array([[4.2e5, 5.3e6, 300]] * 100), "not in the sensor's frame"),
    ],
)
def test_scans_the_classifier_cannot_judge_are_named(bad, words):
    with pytest.raises(ScanError, match=words):
        check_scan(bad)


def test_learned_detector_answers_unknown_to_an_unjudgeable_scan(tmp_path, rng):
    det = LearnedDetector(str(_checkpoint(tmp_path / "m.pt")))
    assert not det.predict(np.zeros((10, 3), np.float32)).known
    assert not det.predict(np.full((500, 3), np.nan, np.float32)).known
    good = det.predict(_scan(rng))
    assert good.known and good.probabilities.shape == (6,)
    assert ((good.probabilities > 0) & (good.probabilities < 1)).all()


def test_a_scan_is_judged_the_same_alone_or_in_a_batch(tmp_path, rng):
    clf = Classifier.load(_checkpoint(tmp_path / "m.pt"))
    a, b = _scan(rng, 500), _scan(rng, 400) + np.float32(1.0)  # under `points`: no sampling differences
    alone = clf.probabilities([a])[0]
    together = clf.probabilities([b, a])[1]
    assert np.allclose(alone, together, atol=1e-6)
    with torch.no_grad():  # and the batch is not pooled across scans
        feats = clf.model.backbone([torch.from_numpy(b), torch.from_numpy(a)])
        assert torch.allclose(feats[1], clf.model.backbone([torch.from_numpy(a)])[0], atol=1e-5)
        assert not torch.allclose(feats[0], feats[1], atol=1e-3)


@pytest.mark.parametrize("architecture", ["resunet", "pointnet"])
def test_folding_the_batch_norms_into_their_layers_keeps_the_outputs(architecture, rng):
    torch.manual_seed(0)
    cfg = dataclasses.replace(SMALL, architecture=architecture, constraints=architecture == "resunet")
    model = LocalizabilityNet(cfg)
    norms = [m for m in model.modules() if isinstance(m, torch.nn.BatchNorm1d)]
    with torch.no_grad():  # trained-looking norms: statistics and affine maps far from the identity
        for m in norms:
            m.running_mean.uniform_(-1, 1), m.running_var.uniform_(0.5, 2)
            m.weight.uniform_(0.5, 2), m.bias.uniform_(-1, 1)
    batch = [torch.from_numpy(_scan(rng, 500)), torch.from_numpy(_scan(rng, 400))]
    with torch.no_grad():
        untouched = copy.deepcopy(model).eval()  # the same layers with the norms back at the identity
        for m in untouched.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.reset_parameters()
        before, features = model.eval()(batch), model.backbone(batch)
        folded = fold_batch_norms(copy.deepcopy(model))
        after, folded_features = folded(batch), folded.backbone(batch)
        assert len(norms) >= 2 and not any(isinstance(m, torch.nn.BatchNorm1d) for m in folded.modules())
        assert torch.allclose(before, after, atol=1e-5)
        assert torch.allclose(features, folded_features, atol=1e-4 * features.abs().max().item())
        assert (features - untouched.backbone(batch)).abs().max() > 0.1 * features.abs().max()  # the norms did matter
    with pytest.raises(ValueError, match="folded twice"):
        fold_batch_norms(folded)


def test_a_loaded_classifier_runs_with_its_norms_folded(tmp_path, rng):
    path = _checkpoint(tmp_path / "m.pt")
    clf = Classifier.load(path, int8=False)
    assert not any(isinstance(m, torch.nn.BatchNorm1d) for m in clf.model.modules())
    scan = _scan(rng, 500)  # under `points`: the model reads every point
    with torch.no_grad():
        unfolded = torch.sigmoid(model_from_checkpoint(load_checkpoint(path))([torch.from_numpy(scan)]))
    assert np.allclose(clf.probabilities([scan]), unfolded.numpy(), atol=1e-6)


@pytest.mark.skipif(not int8_products_work(), reason="this torch build has no CPU int8 products")
def test_a_loaded_classifier_convolves_in_int8_except_its_stem_and_stays_near_float32(tmp_path, rng):
    path = _checkpoint(tmp_path / "m.pt")
    quantised, exact = Classifier.load(path), Classifier.load(path, int8=False)
    convs = [m for m in quantised.model.backbone.modules() if isinstance(m, GatherConv)]
    assert [m.int8_weight is None for m in convs].count(True) == 1 and quantised.model.backbone.stem.int8_weight is None
    scans = [_scan(rng, 500) for _ in range(4)]
    p, q = quantised.probabilities(scans), exact.probabilities(scans)
    assert np.abs(p - q).max() < 0.02 and not np.array_equal(p, q)


@pytest.mark.skipif(not int8_products_work(), reason="this torch build has no CPU int8 products")
@torch.no_grad()
def test_the_fused_int8_residual_block_matches_its_modules_and_steps_aside_where_it_does_not_apply(rng):
    torch.manual_seed(1)
    model = LocalizabilityNet(SMALL)
    for norm in (m for m in model.modules() if isinstance(m, torch.nn.BatchNorm1d)):  # folded biases not zero
        norm.running_mean.uniform_(-0.5, 0.5)
        norm.running_var.uniform_(0.5, 2.0)
        norm.bias.data.uniform_(-0.3, 0.3)
    block = quantize_int8(fold_batch_norms(model)).backbone.down_block[1]  # 16 channels in and out
    points = torch.from_numpy(_scan(rng, 2000))
    level, _, _ = voxelize([points], 0.2)
    x = torch.rand(len(level.coords), 16) * 2
    fused = int8_residual_block(block.conv1, block.conv2, x, level)
    modules = torch.relu(block.conv2(block.norm1(block.conv1(x, level)), level) + x)
    scale = float(modules.abs().max())
    assert fused is not None and (fused - modules).abs().max() < 1e-3 * scale
    assert (fused - torch.relu(x)).abs().max() > 0.1 * scale  # the convolutions did add something
    assert torch.equal(block(x, level), fused)  # the module takes the fused path
    assert int8_residual_block(block.conv1, block.conv2, x - 0.5, level) is None  # not after a ReLU
    two_scans, _, _ = voxelize([points, points], 0.2)
    assert int8_residual_block(block.conv1, block.conv2, torch.rand(len(two_scans.coords), 16), two_scans) is None


def test_symmetric_inference_is_the_mean_over_the_views_and_blind_to_mirrors_and_swaps(tmp_path, rng):
    path = _checkpoint(tmp_path / "m.pt", symmetric_thresholds=np.full(6, 0.4))
    plain, sym = Classifier.load(path), Classifier.load(path, symmetric=True)
    assert sym.thresholds.tolist() == [0.4] * 6 and plain.thresholds.tolist() == [0.5] * 6
    scan = _scan(rng, 500)  # under `points`: every view holds the same points
    views = []
    for sx, sy, swap in SYMMETRIES:
        view = scan * np.float32([sx, sy, 1])
        p = plain.probabilities([view[:, [1, 0, 2]] if swap else view])[0]
        views.append(p[SWAP_LABELS] if swap else p)
    assert np.allclose(sym.probabilities([scan])[0], np.mean(views, axis=0), atol=1e-5)
    assert np.ptp(np.array(views), axis=0).max() > 1e-3  # the views differ: the average is not trivial
    mirrored, swapped = scan * np.float32([-1, 1, 1]), scan[:, [1, 0, 2]]
    assert np.allclose(sym.probabilities([mirrored])[0], sym.probabilities([scan])[0], atol=1e-5)
    assert np.allclose(sym.probabilities([swapped])[0], sym.probabilities([scan])[0][SWAP_LABELS], atol=1e-5)
    det = make_detector(f"learned-sym:{path}")
    assert det.name == f"learned-sym:{path}" and det.classifier.symmetric
    with pytest.raises(CheckpointError, match="l3e calibrate"):
        Classifier.load(_checkpoint(tmp_path / "old.pt"), symmetric=True)


@pytest.mark.parametrize("architecture", ["resunet", "pointnet"])
def test_a_canonical_frame_model_answers_every_mirror_and_quarter_turn_of_a_scan_alike(architecture, rng):
    torch.manual_seed(0)
    model = LocalizabilityNet(ModelConfig(**{**SMALL.__dict__, "architecture": architecture, "frame": "canonical"}))
    sensor = LocalizabilityNet(ModelConfig(**{**SMALL.__dict__, "architecture": architecture})).eval()
    sensor.load_state_dict(model.state_dict())
    clf, plain = Classifier(model.eval(), np.full(6, 0.5)), Classifier(sensor, np.full(6, 0.5))
    scan = _scan(rng, 500) + np.float32([2, -1, 0])  # no symmetry of its own: every view is another scan
    own = clf.probabilities([scan])[0]
    turned = []
    for sx, sy, swap in SYMMETRIES:  # the mirrors, the turns by 180 deg and, with a swap, by +-90 deg
        view = scan * np.float32([sx, sy, 1])
        p = clf.probabilities([view[:, [1, 0, 2]] if swap else view])[0]
        assert np.allclose(p[SWAP_LABELS] if swap else p, own, atol=1e-5)
        q = plain.probabilities([view[:, [1, 0, 2]] if swap else view])[0]
        turned.append(q[SWAP_LABELS] if swap else q)
    assert np.ptp(np.array(turned), axis=0).max() > 1e-3  # the sensor-frame model does tell the views apart
    turned = torch.from_numpy(scan * np.float32([-1, -1, 1]))
    own_view, turned_view = canonical_view(torch.from_numpy(scan)), canonical_view(turned)
    assert own_view != turned_view and not own_view[2]  # the scan lies along x: no swap
    assert torch.allclose(symmetry_view(turned, turned_view), symmetry_view(torch.from_numpy(scan), own_view))


def test_wrong_checkpoints_are_refused_by_name(tmp_path):
    path = _checkpoint(tmp_path / "p.pt", "pointnet")
    state = torch.load(path, weights_only=True)
    state["model"]["architecture"] = "resunet"
    torch.save(state, tmp_path / "swapped.pt")
    with pytest.raises(CheckpointError, match="does not fit the resunet architecture"):
        Classifier.load(tmp_path / "swapped.pt")
    state["version"] = CHECKPOINT_VERSION + 1
    torch.save(state, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match="version"):
        Classifier.load(tmp_path / "future.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=r"\(not a weights-only torch file, or corrupt\)$"):
        Classifier.load(tmp_path / "junk.pt")  # torch's advice to load with code execution is not passed on
    torch.save({"weights": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not an l3e classifier"):
        Classifier.load(tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="no checkpoint"):
        Classifier.load(tmp_path / "missing.pt")
    good = torch.load(path, weights_only=True)
    for name, change, message in [
        ("nomodel.pt", lambda st: st.pop("model"), "lacks its model settings or weights"),
        ("listmodel.pt", lambda st: st.__setitem__("model", [1, 2]), "lacks its model settings or weights"),
        ("zero.pt", lambda st: st["model"].__setitem__("points", 0), "cannot build: a model reads at least one point"),
        ("arch.pt", lambda st: st["model"].__setitem__("architecture", "mlp"), "cannot build: unknown architecture"),
    ]:
        state = {**good, "model": dict(good["model"])}
        change(state)
        torch.save(state, tmp_path / name)
        with pytest.raises(CheckpointError, match=f"{name}.* {message}"):
            Classifier.load(tmp_path / name)


def test_a_broken_checkpoint_is_refused_and_a_non_finite_answer_is_unknown(tmp_path, monkeypatch):
    """NaN weights would answer 'localizable along every axis'; NaN thresholds never flag; three
    thresholds broke inside numpy without naming the file."""
    from l3e_env.detection.detectors import UNKNOWN, LearnedDetector

    shipped = torch.load(DEFAULT_CHECKPOINT, weights_only=True)
    nan = {**shipped, "state_dict": dict(shipped["state_dict"])}
    name = next(k for k, t in nan["state_dict"].items() if t.is_floating_point())
    nan["state_dict"][name] = torch.full_like(nan["state_dict"][name], float("nan"))
    torch.save(nan, tmp_path / "nan.pt")
    with pytest.raises(CheckpointError, match=f"nan.pt has non-finite weights in {name}"):
        Classifier.load(tmp_path / "nan.pt")
    for bad in ([0.5, 0.5, 0.5], [0.5] * 5 + [float("nan")], [0.5] * 5 + [1.5], "0.5"):
        torch.save({**shipped, "thresholds": bad}, tmp_path / "thresholds.pt")
        with pytest.raises(CheckpointError, match="thresholds.pt: its thresholds must be six probabilities"):
            Classifier.load(tmp_path / "thresholds.pt")
    detector = LearnedDetector()
    scan = np.random.default_rng(0).uniform(-10, 10, (3000, 3)).astype(np.float32)
    assert detector.predict(scan).known
    monkeypatch.setattr(detector.classifier, "probabilities", lambda scans, poses=None: np.full((1, 6), np.nan))
    assert detector.predict(scan) is UNKNOWN  # nothing masked, and counted as not judged


def test_the_shipped_model_loads_by_default_and_is_small():
    assert DEFAULT_CHECKPOINT.exists() and DEFAULT_CHECKPOINT.stat().st_size <= 20 * 2**20
    det = make_detector("learned")
    assert det.classifier.model.config.architecture == "resunet"
    assert det.classifier.meta["lidar"]["model"] == "vlp16"
    assert ((det.classifier.thresholds > 0) & (det.classifier.thresholds < 1)).all()
    symmetric = make_detector("learned-sym").classifier.thresholds
    assert ((symmetric > 0) & (symmetric < 1)).all()
    # a model that reads each scan in its canonical view answers all eight views alike: their mean is its answer
    canonical = det.classifier.model.config.frame == "canonical"
    assert np.allclose(symmetric, det.classifier.thresholds) == canonical


def test_sensor_or_registration_mismatch_is_a_warning_and_a_match_is_silent(tmp_path):
    import warnings

    clf = Classifier.load(_checkpoint(tmp_path / "m.pt"))
    clf.meta["protocol"] = LABEL_PROTOCOL
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clf.check_settings("os0-128")
        clf.check_settings("vlp16")
        clf.check_settings("vlp16-calibrated")  # the same sensor, its beams' origins calibrated
    assert [str(w.message) for w in caught] == ["the classifier was trained on vlp16 scans and now sees os0-128 scans"]
    from dataclasses import asdict

    from l3e_env.localizability.registration import RegistrationConfig

    clf.meta["registration"] = asdict(RegistrationConfig())
    clf.meta["protocol"] = LABEL_PROTOCOL
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clf.check_settings(registration=asdict(RegistrationConfig(max_iterations=30)))
        clf.check_settings(registration=asdict(RegistrationConfig(ground_normals=False)))
        clf.check_settings(registration=asdict(RegistrationConfig()))
    assert len(caught) == 2 and all("other registration settings" in str(w.message) for w in caught)
    clf.meta["protocol"] = 1  # labels of the paper's thresholds: named, with what remakes them
    with pytest.warns(UserWarning, match="label protocol 1 .*l3e fit-constraints"):
        clf.check_settings(registration=asdict(RegistrationConfig()))


def test_region_rows_split_the_scenes_by_their_named_places():
    from types import SimpleNamespace

    from l3e_env.experiments.table3 import region_rows

    xy = [(-20, 0), (50, 0), (120, 0), (200, 0), (10, 0), (0, 40), (5, 5)]  # yard, tunnel, quarry, none; ...
    poses = np.tile(np.eye(4), (len(xy), 1, 1))
    poses[:, :2, 3] = xy
    data = SimpleNamespace(
        manifest={"scenes": ["mine-0", "fork-0", "tunnel-0"]},
        poses=poses,
        arrays={"scene": np.array([0, 0, 0, 0, 1, 1, 2])},
    )
    found = region_rows(data, np.arange(len(xy)))
    assert list(found) == ["yard of mine-0", "tunnel of mine-0", "quarry of mine-0", "corridor of fork-0"]
    assert [at.tolist() for at in found.values()] == [[0], [1], [2], [4]]
    found = region_rows(data, np.array([6, 2, 5, 0]))  # positions within the rows given
    assert {k: at.tolist() for k, at in found.items()} == {"quarry of mine-0": [1], "yard of mine-0": [3]}


def test_axis_scores_by_hand():
    y = np.array([[1, 0, 0, 0, 0, 1], [1, 1, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0]])
    p = np.array([[1, 0, 0, 0, 0, 0], [0, 1, 0, 0, 1, 0], [0, 0, 0, 0, 0, 0], [1, 1, 0, 0, 0, 0]])
    s = axis_scores(y, p)
    assert s["accuracy"].tolist() == [0.5, 1.0, 1.0, 1.0, 0.75, 0.75]
    assert s["precision"][0] == 0.5 and s["recall"][0] == 0.5 and s["f1"][0] == 0.5
    assert s["f1"][1] == 1.0 and np.isnan(s["f1"][2]) and s["f1"][4] == 0.0 and s["f1"][5] == 0.0
    assert mean_scores(s)["f1"] == pytest.approx((0.5 + 1 + 0 + 0) / 4)  # z and roll: undefined, left out


def test_a_wide_table_goes_on_in_blocks_that_keep_every_column_once(rng):
    y = rng.random((40, 6)) < 0.3
    rows = {m: {f"split {k}": axis_scores(y, rng.random((40, 6)) < 0.3) for k in range(7)} for m in ("one", "two")}
    blocks = format_table(rows, per_block=5).split("\n\n")
    assert [len(b.splitlines()[1].split("split")) - 1 for b in blocks] == [5, 5, 4]
    assert len({len(b.splitlines()) for b in blocks}) == 1  # the same rows in each block
    whole = format_table(rows, per_block=14)
    assert "\n\n" not in whole
    for line, *parts in zip(whole.splitlines(), *(b.splitlines() for b in blocks)):  # the same cells, in order
        assert line == parts[0] + "".join(p[16:] for p in parts[1:])


def test_bootstrap_interval_brackets_the_mean_and_widens_with_few_positives(rng):
    y = rng.random((400, 6)) < 0.3
    assert mean_interval(y, y)["f1"] == (1.0, 1.0)
    noisy = y ^ (rng.random((400, 6)) < 0.1)
    lo, hi = mean_interval(y, noisy)["f1"]
    assert lo < mean_scores(axis_scores(y, noisy))["f1"] < hi and hi - lo < 0.1
    rare = np.zeros((400, 6), bool)
    rare[:2] = True  # two positives per axis: one miss moves F1 a lot
    guess = rare.copy()
    guess[0] = False
    guess[10] = True
    lo_rare, hi_rare = mean_interval(rare, guess)["f1"]
    assert hi_rare - lo_rare > 3 * (hi - lo)


def test_micro_f1_pools_every_axis_decision_and_has_its_interval(rng):
    y = rng.random((300, 6)) < 0.2
    p = y ^ (rng.random((300, 6)) < 0.1)
    tp, fp, fn = (int(((a == 1) & (b == 1)).sum()) for a, b in ((y, p), (~y, p), (y, ~p)))
    assert micro_f1(y, p) == pytest.approx(2 * tp / (2 * tp + fp + fn))
    assert np.isnan(micro_f1(np.zeros((5, 6), bool), np.zeros((5, 6), bool)))
    interval = mean_interval(y, p)
    assert interval["micro_f1"][0] < micro_f1(y, p) < interval["micro_f1"][1]
    f1_x = axis_scores(y, p)["f1"][1]
    assert interval["f1 y"][0] < f1_x < interval["f1 y"][1]


def test_pr_curve_and_thresholds_match_brute_force(rng):
    y = rng.random((300, 6)) < 0.3
    p = np.clip(y * 0.3 + rng.random((300, 6)) * 0.7, 0, 1).round(2)  # ties on purpose
    for a in range(6):
        precision, recall, thr = pr_curve(y[:, a], p[:, a])
        for t, pr, rc in zip(thr, precision, recall):
            pred = p[:, a] >= t
            assert pr == pytest.approx((pred & y[:, a]).sum() / pred.sum())
            assert rc == pytest.approx((pred & y[:, a]).sum() / y[:, a].sum())
    t = best_thresholds(y, p)
    f1_at = axis_scores(y, p > t)["f1"]
    for a in range(6):
        brute = max(
            axis_scores(y[:, a : a + 1].repeat(6, 1), (p[:, a : a + 1] > c).repeat(6, 1))["f1"][0]
            for c in np.unique(np.r_[0.0, p[:, a]]) - 1e-9
        )
        assert f1_at[a] == pytest.approx(brute)


def test_auroc_is_the_chance_a_positive_outranks_a_negative(rng):
    y = rng.random(200) < 0.2
    p = (y * 0.2 + rng.random(200)).round(1)  # ties on purpose
    pairs = p[y][:, None] - p[~y][None, :]
    assert auroc(y, p) == pytest.approx(((pairs > 0) + 0.5 * (pairs == 0)).mean())
    assert auroc(y, np.where(y, 1.0, 0.0)) == 1.0 and auroc(y, np.where(y, 0.0, 1.0)) == 0.0
    assert np.isnan(auroc(np.zeros(5, bool), np.arange(5.0)))


def test_power_set_balancing_up_samples_to_the_second_most_common_combination():
    labels = np.array([[0] * 6] * 50 + [[1, 0, 0, 0, 0, 0]] * 20 + [[1, 1, 0, 0, 0, 1]] * 5 + [[0, 0, 1, 0, 0, 0]] * 1)
    pool = balanced_pool(labels, max_upsampling=10)
    codes = (labels[pool].astype(int) << np.arange(6)).sum(1)
    assert np.bincount(codes, minlength=64)[[0, 1, 35, 4]].tolist() == [50, 20, 20, 10]  # 10: the cap


def test_voxel_sampling_keeps_one_scan_point_per_voxel_whatever_the_density(rng):
    near = rng.normal(0, 0.15, (5000, 3))  # a dense blob next to the sensor, a few voxels wide
    far = rng.uniform(-40, 40, (300, 3))  # sparse points far out, almost one per voxel
    scan = np.vstack([near, far])
    kept = one_per_voxel(scan, 0.2, rng)
    cells = lambda p: {tuple(c) for c in np.floor(p / 0.2).astype(int)}  # noqa: E731
    assert cells(kept) == cells(scan) and len(kept) == len(cells(scan))
    assert {tuple(p) for p in kept} <= {tuple(p) for p in scan}  # scan points, not voxel centres
    # drawn from the points, the far ones are a few percent of the input; from the voxels, most of it
    by_points = model_input(scan, ModelConfig(points=400), rng).numpy()
    by_voxels = model_input(scan, ModelConfig(points=400, sampling="voxels"), rng).numpy()
    share = lambda p: float(np.mean(np.abs(p).max(axis=1) > 2))  # noqa: E731
    assert len(by_points) == len(by_voxels) == 400
    assert share(by_points) < 0.15 and share(by_voxels) > 0.5
    with pytest.raises(ValueError, match="sampling"):
        LocalizabilityNet(ModelConfig(sampling="grid"))
    with pytest.raises(ValueError, match="at least one point"):
        LocalizabilityNet(ModelConfig(points=0))


def test_augmentation_permutes_the_labels_and_turns_the_up_vector_with_the_points(rng):
    pts = _scan(rng, 100)
    lab = np.array([1, 0, 0, 1, 0, 0], dtype=np.uint8)
    up = np.array([0.3, -0.5, 0.81])
    seen = set()
    for _ in range(40):
        p2, l2, up2 = augment(pts, lab, rng, up)
        swapped = not np.allclose(np.abs(p2[:, 0]), np.abs(pts[:, 0]))
        assert np.allclose(np.abs(p2[:, :2]), np.abs(pts[:, [1, 0]] if swapped else pts[:, :2]))
        assert (l2 == (lab[SWAP_LABELS] if swapped else lab)).all()
        # the up vector is a direction of the same frame: mirrored and swapped as the points are
        sign = np.sign(p2[0, :2] / (pts[0, [1, 0]] if swapped else pts[0, :2]))
        assert np.allclose(up2[:2], sign * (up[[1, 0]] if swapped else up[:2])) and up2[2] == up[2]
        seen.add((swapped, *sign))
    assert len(seen) == 8
    assert augment(pts, lab, rng)[2] is None


def test_a_gravity_model_reads_the_tilt_and_refuses_to_guess_without_it(tiny_dataset, tmp_path, rng):
    roll = 0.3
    T = pose_to_matrix(np.array([1.0, 2.0, 0.5, roll, 0.0, 0.0]))
    assert np.allclose(up_vector(T), [0.0, np.sin(roll), np.cos(roll)])  # the world's up seen from the sensor
    sensor_frame = dataclasses.replace(SMALL, gravity=True, level=False)  # the up vector as an input instead
    train(tiny_dataset, tmp_path / "g", _train_cfg(model=sensor_frame), progress=False)
    clf = Classifier.load(tmp_path / "g" / "model.pt")
    assert clf.needs_pose and clf.model.head[0].in_features == SMALL.feature + 3
    scan = _scan(rng, 500)
    with pytest.raises(ValueError, match="tilt"):
        clf.probabilities([scan])
    level, tilted = clf.probabilities([scan, scan], np.stack([np.eye(4), T]))
    assert not np.allclose(level, tilted)  # the tilt changes the answer for the same points
    det = LearnedDetector(str(tmp_path / "g" / "model.pt"))
    assert np.allclose(det.predict(scan, None, T).probabilities, tilted)
    assert np.allclose(det.predict(scan).probabilities, level)  # a detector given no pose takes the sensor as level
    # symmetric inference turns the up vector with each view: mirrored scan and pose, same answer
    probs = [
        model_probabilities(clf.model, [torch.from_numpy(s)], True, u[None])[0]
        for s, u in [(scan, up_vector(T)), (scan * np.float32([1, -1, 1]), up_vector(T) * [1, -1, 1])]
    ]
    assert np.allclose(*probs, atol=1e-5)
    data = LabelDataset(tiny_dataset)  # predictions on a dataset read each parent's tilt from its pose
    sampled = [sample_points(data.scan(i), SMALL.points, np.random.default_rng([0, i])) for i in range(3)]
    expected = [
        model_probabilities(clf.model, [pts], False, up_vector(data.poses[i])[None])[0] for i, pts in enumerate(sampled)
    ]
    assert np.allclose(predict_dataset(clf.model, data, np.arange(3)), expected, atol=1e-6)


def test_a_level_model_reads_a_tilted_scan_as_the_level_one(tiny_dataset, tmp_path, rng):
    """ModelConfig.level (the default): the scan is turned into its level frame by its pose's tilt, so
    a tilted sensor's view of the same surfaces gets the level sensor's answer, on the level frame's
    axes; a dataset's scans are levelled by their own poses."""
    train(tiny_dataset, tmp_path / "l", _train_cfg(), progress=False)
    clf = Classifier.load(tmp_path / "l" / "model.pt", int8=False)
    assert clf.model.config.level and clf.needs_pose
    scan = _scan(rng, 500)
    T = pose_to_matrix(np.array([1.0, 2.0, 0.5, 0.25, -0.15, 0.0]))
    tilted = (scan @ T[:3, :3]).astype(np.float32)  # the same points seen from the tilted sensor
    level, from_tilted, unlevelled = clf.probabilities([scan, tilted, tilted], np.stack([np.eye(4), T, np.eye(4)]))
    np.testing.assert_allclose(from_tilted, level, atol=1e-5)
    assert not np.allclose(unlevelled, level, atol=1e-5)  # read without its tilt, the scan is another scan
    data = LabelDataset(tiny_dataset)
    sampled = [
        sample_points(
            level_scan(data.scan(i), data.poses[i], clf.model.config), SMALL.points, np.random.default_rng([0, i])
        )
        for i in range(3)
    ]
    expected = [model_probabilities(clf.model, [pts])[0] for pts in sampled]
    assert np.allclose(predict_dataset(clf.model, data, np.arange(3)), expected, atol=1e-6)


def _train_cfg(**kw):
    return TrainConfig(
        **{
            "model": SMALL,
            "epochs": 2,
            "samples_per_epoch": 8,
            "batch_size": 4,
            "train_scenes": ["tunnel-0", "field-0"],
            "validation_scenes": ["office-0"],
            "threads": 1,
            **kw,
        }
    )


def test_settings_no_run_can_use_are_refused_before_the_folder(tiny_dataset, tmp_path):
    with pytest.raises(TrainingError, match="epochs must be at least 1, got 0; optimizer must be sgd or adamw"):
        train(tiny_dataset, tmp_path / "run", _train_cfg(epochs=0, optimizer="adam"), progress=False)
    with pytest.raises(TrainingError, match="scale_augment must be 1 \\(off\\) or more, got 0.8"):
        train(tiny_dataset, tmp_path / "run", _train_cfg(scale_augment=0.8), progress=False)
    assert not (tmp_path / "run").exists()


def test_a_new_run_that_fails_in_its_first_epoch_leaves_no_folder(tiny_dataset, tmp_path):
    """Issue 98: a training that failed after it started left its config.yaml behind."""
    import shutil

    from l3e_env.data.dataset import DatasetError

    broken = tmp_path / "nan"
    shutil.copytree(tiny_dataset, broken)
    points = np.load(broken / "points.npy")
    np.save(broken / "points.npy", np.full_like(points, np.nan))
    with pytest.raises(DatasetError, match="NaN or infinite coordinates"):
        train(broken, tmp_path / "run", _train_cfg(), progress=False)
    assert not (tmp_path / "run").exists()


def test_scale_augmentation_draws_factors_log_uniformly_within_its_range(rng):
    pts = rng.normal(size=(50, 3)).astype(np.float32)
    factors = np.array([(scaled(pts, 1.3, rng) / pts).mean() for _ in range(2000)])
    assert factors.min() >= 1 / 1.3 - 1e-6 and factors.max() <= 1.3 + 1e-6
    logs = np.log(factors)  # uniform on [-ln 1.3, ln 1.3]: as many shrunk as grown, the ends reached
    assert abs(np.median(logs)) < 0.02 and logs.min() < -0.24 and logs.max() > 0.24
    assert scaled(pts, 1.3, rng).dtype == np.float32
    state = rng.bit_generator.state
    assert scaled(pts, 1.0, rng) is pts and rng.bit_generator.state == state  # off: nothing drawn


@pytest.mark.parametrize("group_dro,scale", [(0.0, 1.0), (0.5, 1.3)])
def test_a_killed_run_resumes_to_the_same_model(tiny_dataset, tmp_path, group_dro, scale):
    whole = train(
        tiny_dataset, tmp_path / "whole", _train_cfg(group_dro=group_dro, scale_augment=scale), progress=False
    )
    cfg = _train_cfg(group_dro=group_dro, scale_augment=scale)
    cfg.epochs = 1
    train(tiny_dataset, tmp_path / "cut", cfg, progress=False)
    cfg.epochs = 2  # the 'kill' came after epoch 1; the same command with the full epoch count resumes
    with pytest.raises(TrainingError, match=r"other settings \(seed 0, now 3\)"):
        train(
            tiny_dataset, tmp_path / "cut", _train_cfg(seed=3, group_dro=group_dro, scale_augment=scale), progress=False
        )
    resumed = train(
        tiny_dataset, tmp_path / "cut", _train_cfg(group_dro=group_dro, scale_augment=scale), progress=False
    )
    assert {k: v for k, v in resumed.items() if k != "seconds"} == {k: v for k, v in whole.items() if k != "seconds"}
    log = [json.loads(line) for line in (tmp_path / "cut" / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in log] == [1, 2]
    if group_dro:  # the families' weights go on from where the killed run left them
        weights = [json.loads(line)["family_weights"] for line in (tmp_path / "whole" / "log.jsonl").open()]
        assert [r["family_weights"] for r in log] == weights and set(weights[0]) == {"field", "tunnel"}
        assert sum(weights[-1].values()) == pytest.approx(1.0, abs=1e-3) and weights[0] != weights[1]
    a = torch.load(tmp_path / "whole" / "last.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "cut" / "last.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    shipped = Classifier.load(tmp_path / "whole" / "model.pt")
    assert "optimizer" not in shipped.meta and shipped.meta["registration"]["max_iterations"] > 0


def test_datasets_are_read_as_one_with_scenes_matched_by_name(tiny_dataset, tmp_path):
    other = tmp_path / "other"
    generate(
        other,
        config_for(
            None, scenes=["field-0", "tunnel-7"], parents_per_scene=2, shard_size=2, seed=4, labels={"children": 8}
        ),
        workers=1,
        progress=False,
    )
    a, b = LabelDataset(tiny_dataset), LabelDataset(other)
    union = open_datasets([tiny_dataset, other])
    assert len(union) == len(a) + len(b) and union.name == f"{a.name}+{b.name}"
    assert union.manifest["scenes"] == ["tunnel-0", "office-0", "field-0", "tunnel-7"]
    np.testing.assert_array_equal(union.scan(len(a) + 1), b.scan(1))
    np.testing.assert_array_equal(union.labels[len(a) :], b.labels)
    np.testing.assert_array_equal(union.poses[len(a) + 1], b.poses[1])
    assert union.poses.shape == (len(union), 4, 4) and np.allclose(union.poses[:, 3], [0, 0, 0, 1])
    assert union.manifest["count"] == len(union) and union.manifest["settings"]["seed"] == [0, 4]
    field = split_indices(union, ["field-0"])
    assert len(field) == 4 + 2 and field[-2:].tolist() == [len(a), len(a) + 1]
    assert split_indices(union, ["tunnel-7"]).tolist() == [len(a) + 2, len(a) + 3]
    os0 = tmp_path / "os0"
    generate(
        os0,
        config_for(
            None,
            scenes=["field-0"],
            parents_per_scene=1,
            shard_size=1,
            labels={"children": 4},
            lidar={"model": "os0-128"},
        ),
        workers=1,
        progress=False,
    )
    with pytest.raises(DatasetError, match="lidar settings .*model 'vlp16', now 'os0-128'"):
        open_datasets([tiny_dataset, os0])
    older = tmp_path / "older"  # made before the LiDAR's `sweep` option existed: as its default makes it
    shutil.copytree(other, older)
    manifest = json.loads((older / "manifest.json").read_text())
    del manifest["settings"]["lidar"]["sweep"]
    (older / "manifest.json").write_text(json.dumps(manifest))
    assert len(open_datasets([tiny_dataset, older])) == len(a) + len(b)
    manifest["settings"]["lidar"]["sweep"] = True
    (older / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="sweep False, now True"):
        open_datasets([tiny_dataset, older])


def test_fine_tuning_starts_from_the_given_weights(tiny_dataset, tmp_path):
    train(tiny_dataset, tmp_path / "base", _train_cfg(), progress=False)
    base = tmp_path / "base" / "model.pt"
    start = _train_cfg(init=str(base), learning_rate=0.0, epochs=1)  # no step: the weights stay the base's
    train(tiny_dataset, tmp_path / "tuned", start, progress=False)
    weights = [
        dict(model_from_checkpoint(load_checkpoint(p)).named_parameters())
        for p in (base, tmp_path / "tuned" / "model.pt")
    ]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])  # batch-norm statistics may move
    assert torch.load(tmp_path / "base" / "last.pt", weights_only=True)["training"]["init"] is None
    other = dataclasses.replace(_train_cfg(init=str(base)), model=dataclasses.replace(SMALL, channels=(8, 8, 16, 24)))
    with pytest.raises(TrainingError, match="model settings"):
        train(tiny_dataset, tmp_path / "bad", other, progress=False)


@pytest.mark.slow
def test_evaluate_writes_table_curves_and_results(tiny_dataset, tmp_path, monkeypatch):
    from l3e_env.experiments import table3
    from l3e_env.experiments.table3 import Table3Options, run_table3

    train(tiny_dataset, tmp_path / "run", _train_cfg(), progress=False)
    res = run_table3(
        [tmp_path / "run" / "model.pt"],
        tiny_dataset,
        tmp_path / "eval",
        Table3Options(others=[tiny_dataset, tiny_dataset], eigen=[1e9], by_family=True),
        progress=False,
    )
    eigen = res.models.pop("eigen:1e+09")
    ((name, model),) = res.models.items()
    assert set(eigen["splits"]) == set(model["splits"]) and eigen["splits"]["valid"]["unregistrable"] == 0
    data = LabelDataset(tiny_dataset)
    rows = split_indices(data, ["office-0"])  # the validation scene: an enormous tau flags every axis
    everything = axis_scores(data.labels[rows], np.ones((len(rows), 6)))
    assert eigen["splits"]["valid"]["f1"] == pytest.approx(everything["f1"], nan_ok=True)
    whole = f"all of {Path(tiny_dataset).name}"
    families = {f"{f} of {d}" for f in ("tunnel", "office", "field") for d in (Path(tiny_dataset).name, tiny_dataset)}
    assert set(model["splits"]) == {"train", "valid", whole, f"all of {tiny_dataset}", *families}  # no test family
    assert model["splits"]["train"]["count"] == 8 and model["splits"][whole]["count"] == 12
    clf = Classifier.load(tmp_path / "run" / "model.pt")
    for family in ("tunnel", "office", "field"):  # each family's column: the whole column's predictions on its rows
        rows = split_indices(data, [f"{family}-0"])
        expected = axis_scores(data.labels[rows], predict_dataset(clf.model, data, rows) > clf.thresholds)
        column = model["splits"][f"{family} of {Path(tiny_dataset).name}"]
        assert column["count"] == 4 and column["f1"] == pytest.approx(expected["f1"].tolist(), nan_ok=True)
        assert column["accuracy"] == pytest.approx(expected["accuracy"].tolist())
    assert f"office of {Path(tiny_dataset).name}" in res.table
    monkeypatch.setattr(table3, "TEST_SCENES", ["field-0", "tunnel-0"])  # a test split of two families
    built = table3.make_scene

    def tunnel_as_one_region(name: str):  # the tiny dataset's scenes name no regions: give the tunnel one
        scene = built(name)
        scene.regions = {"anywhere": np.array([-1e3, -1e3, 1e3, 1e3])} if name == "tunnel-0" else {}
        return scene

    monkeypatch.setattr(table3, "make_scene", tunnel_as_one_region)
    drawn = run_table3(
        [tmp_path / "run" / "model.pt"],
        tiny_dataset,
        tmp_path / "eval-test",
        Table3Options(by_family=True, by_region=True, draws=3),
        progress=False,
    )
    splits = drawn.models[name]["splits"]
    assert set(splits) == {"train", "valid", "test", "tunnel of test", "field of test", "anywhere of tunnel-0"}
    region, family = (
        {k: v for k, v in splits[c].items() if k != "dataset"} for c in ("anywhere of tunnel-0", "tunnel of test")
    )
    assert json.dumps(region, sort_keys=True) == json.dumps(family, sort_keys=True)  # NaN F1 where no positive
    test_rows = split_indices(data, ["field-0", "tunnel-0"])
    assert splits["test"]["draws"]["mean_f1"][0] == pytest.approx(splits["test"]["mean"]["f1"], nan_ok=True)
    again = mean_scores(
        axis_scores(data.labels[test_rows], predict_dataset(clf.model, data, test_rows, seed=2) > clf.thresholds)
    )
    assert splits["test"]["draws"]["mean_accuracy"][2] == pytest.approx(again["accuracy"])
    assert len(splits["valid"]["draws"]["mean_f1"]) == 3 and "draws" not in splits["tunnel of test"]
    # the headline: the test split's micro-F1, axes with at least 30 positives only (none here: 8 scans)
    test_y = data.labels[test_rows]
    test_p = predict_dataset(clf.model, data, test_rows) > clf.thresholds
    head = drawn.results["headline"][name]["columns"]["test"]
    assert head["micro_f1"] == pytest.approx(micro_f1(test_y, test_p), nan_ok=True) and head["axes"] == {}
    assert "pooled" not in drawn.results["headline"][name]  # one test column: nothing to pool
    assert "headline: F1 per axis with at least 30 positives" in drawn.table
    assert "over 3 draws of the points" in drawn.table
    with pytest.raises(ValueError, match="draws must be at least 1"):
        run_table3(
            [tmp_path / "run" / "model.pt"],
            tiny_dataset,
            tmp_path / "eval-none",
            Table3Options(draws=0),
            progress=False,
        )
    rows = split_indices(data, ["tunnel-0"])
    expected = axis_scores(data.labels[rows], predict_dataset(clf.model, data, rows) > clf.thresholds)
    assert splits["test"]["count"] == 8 and splits["tunnel of test"]["count"] == 4
    assert splits["tunnel of test"]["f1"] == pytest.approx(expected["f1"].tolist(), nan_ok=True)
    assert model["splits"][whole]["sensor"] == "vlp16"
    assert "accuracy mean" in res.table and (tmp_path / "eval" / "pr_curves.png").stat().st_size > 10_000
    stored = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert stored["models"][name]["thresholds"] == pytest.approx(model["thresholds"])
    lo, hi = model["splits"]["valid"]["mean_95_interval"]["f1"]
    assert lo <= model["splits"]["valid"]["mean"]["f1"] <= hi and "f1 95% CI" in res.table
    point = model["f1_operating_point"]
    valid_y, valid_p = _valid_predictions(tmp_path / "run" / "model.pt", tiny_dataset)
    assert point["thresholds"] == pytest.approx(best_thresholds(valid_y, valid_p, beta=1.0).tolist())
    assert "F1-best validation thresholds" in res.table and set(point["splits"]) == set(model["splits"])
    sym = run_table3(
        [tmp_path / "run" / "model.pt"],
        tiny_dataset,
        tmp_path / "eval-sym",
        Table3Options(symmetric=True),
        progress=False,
    )
    assert sym.results["symmetric"] and sym.table.startswith("probabilities averaged over the eight")
    stored = Classifier.load(tmp_path / "run" / "model.pt", symmetric=True).thresholds
    assert sym.models[name]["thresholds"] == pytest.approx(stored.tolist())


def _valid_predictions(checkpoint, dataset, symmetric=False):
    clf = Classifier.load(checkpoint)
    data = open_datasets(dataset)
    rows = split_indices(data, clf.meta["training"]["validation_scenes"])
    return data.labels[rows], predict_dataset(clf.model, data, rows, symmetric=symmetric)


def test_training_stores_symmetric_thresholds_and_calibrate_adds_them_to_older_checkpoints(tiny_dataset, tmp_path):
    train(tiny_dataset, tmp_path / "run", _train_cfg(), progress=False)
    model = tmp_path / "run" / "model.pt"
    valid_y, valid_p = _valid_predictions(model, tiny_dataset, symmetric=True)
    expected = best_thresholds(valid_y, valid_p, beta=TrainConfig().threshold_beta)
    assert Classifier.load(model, symmetric=True).thresholds == pytest.approx(expected, abs=1e-5)
    state = torch.load(model, weights_only=True)
    del state["symmetric_thresholds"]
    torch.save(state, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="no thresholds for symmetric"):
        Classifier.load(tmp_path / "old.pt", symmetric=True)
    assert calibrate_symmetric(tmp_path / "old.pt", tiny_dataset, progress=False) == pytest.approx(expected, abs=1e-5)
    done = torch.load(tmp_path / "old.pt", weights_only=True)
    assert done["symmetric_thresholds"] == pytest.approx(expected.tolist(), abs=1e-5)
    assert {k: v for k, v in done.items() if k != "state_dict"} == {
        k: v for k, v in torch.load(model, weights_only=True).items() if k != "state_dict"
    }
    assert all(torch.equal(done["state_dict"][k], state["state_dict"][k]) for k in state["state_dict"])


def test_soft_targets_follow_the_error_to_threshold_ratio(tiny_dataset, tmp_path):
    data = LabelDataset(tiny_dataset)
    assert np.array_equal(training_targets(data, 0.0), data.labels)
    soft = training_targets(data, 4.0)
    t = LabelConfig().threshold_vector()
    ratio = data.errors / t
    assert np.allclose(error_ratios(data), ratio) and np.array_equal(error_ratios(data) > 1, data.labels.astype(bool))
    assert np.allclose(soft, 1 / (1 + np.exp(-4 * np.log(ratio))), atol=1e-5)
    assert np.array_equal(soft > 0.5, data.labels.astype(bool))  # the same side of the threshold
    train(tiny_dataset, tmp_path / "soft", _train_cfg(soft_labels=4.0, epochs=1), progress=False)
    assert Classifier.load(tmp_path / "soft" / "model.pt").meta["training"]["soft_labels"] == 4.0
    # a run folder written before soft targets existed resumes as a hard-label run
    assert _resumable({"seed": 0}) == _resumable({"seed": 0, "soft_labels": 0.0}) != _resumable({"soft_labels": 4.0})


def test_group_dro_weighs_the_family_with_the_higher_loss_up():
    from l3e_env.model.training import GroupWeights, scene_families

    class Rows:  # a dataset's scene table, as scene_families reads it
        manifest = {"scenes": ["tunnel-0", "tunnel-3", "office-1", "/meshes/my-mine.obj"]}
        arrays = {"scene": np.array([0, 1, 2, 3, 0, 2])}

    index, families = scene_families(Rows(), np.array([0, 1, 2, 3, 4]))
    assert families == ["my-mine", "office", "tunnel"] and index.tolist() == [2, 2, 1, 0, 2]
    groups = GroupWeights(["office", "tunnel"], eta=1.0)
    per_scan = torch.tensor([1.0, 1.0, 0.1, 0.1], requires_grad=True)
    loss = groups.loss(per_scan, torch.tensor([0, 0, 1, 1]))
    q = groups.state()
    assert q["office"] > q["tunnel"] and sum(q.values()) == pytest.approx(1.0)
    assert loss.item() > 0.55  # above the plain mean: the harder family counts more
    loss.backward()
    assert per_scan.grad[0] > per_scan.grad[2] > 0
    groups.loss(torch.tensor([0.5, 0.5]), torch.tensor([1, 1]))  # a family alone in a batch: only its weight moves
    assert groups.state()["tunnel"] > q["tunnel"]


def test_one_scan_is_judged_on_one_torch_thread_and_the_threads_are_set_back(monkeypatch):
    """Spinning OpenMP threads made a single scan 30-50x slower beside other work (bench_load.py)."""
    clf = Classifier.load()
    seen = []
    real = clf.probabilities
    monkeypatch.setattr(
        clf, "probabilities", lambda scans, poses=None: seen.append(torch.get_num_threads()) or real(scans, poses)
    )
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        clf.predict(np.random.default_rng(0).uniform(-10, 10, (3000, 3)).astype(np.float32))
        assert seen == [1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_the_shipped_model_with_the_default_registration_warns_of_nothing():
    import warnings

    from l3e_env.detection.detectors import make_detector

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert make_detector("learned").name == "learned"


def test_the_kept_epoch_is_the_best_by_the_validation_micro_f1(tiny_dataset, tmp_path):
    """A mean F1 over axes swings by a sixth where an axis with no positive gets one false flag; the
    epoch kept is the one whose every axis decision, pooled, scores best on the validation scenes."""
    train(tiny_dataset, tmp_path / "m", _train_cfg(epochs=3), progress=False)
    log = [json.loads(line) for line in (tmp_path / "m" / "log.jsonl").read_text().splitlines()]
    micro = [r["val_micro_f1"] for r in log]
    assert all(np.isfinite(m) or np.isnan(m) for m in micro) and len(micro) == 3
    finite = [m if np.isfinite(m) else -1.0 for m in micro]
    assert load_checkpoint(tmp_path / "m" / "best.pt")["epoch"] == int(np.argmax(finite))
    kept = load_checkpoint(tmp_path / "m" / "last.pt")["best"]
    assert kept["epoch"] == int(np.argmax(finite)) + 1 and kept["micro_f1"] == pytest.approx(max(finite), nan_ok=True)


def test_replayed_places_take_their_share_of_the_training_pool(tiny_dataset):
    from l3e_env.data.dataset import LabelDataset
    from l3e_env.model.training import TrainConfig, TrainingError, _training_pool, split_indices

    data = LabelDataset(tiny_dataset)
    scenes = ["tunnel-0", "office-0", "field-0"]
    rows = split_indices(data, scenes)
    old = np.isin(rows, split_indices(data, ["office-0", "field-0"]))
    for share in (0.5, 0.8):
        cfg = TrainConfig(train_scenes=scenes, replay_scenes=["office-0", "field-0"], replay_share=share)
        pool = _training_pool(data, rows, cfg)
        replayed = old[pool].mean()
        assert abs(replayed - share) < 0.1  # the share asked for, whatever the places' scan counts
        assert np.array_equal(pool, _training_pool(data, rows, cfg))  # seeded
    with pytest.raises(TrainingError, match="replay needs new scans and replayed ones"):
        _training_pool(data, rows, TrainConfig(train_scenes=scenes, replay_scenes=scenes))


@pytest.mark.parametrize("thresholds", [{"eigen": [30.0, -5.0]}, {"dcreg": [0.5]}, {"eigen": [float("nan")]}])
def test_a_classical_threshold_no_test_can_take_is_named_before_anything_is_read(tmp_path, thresholds):
    from l3e_env.experiments.table3 import Table3Options

    with pytest.raises(ValueError, match="eigen: thresholds tau must be positive.*dcreg: condition ratios"):
        Table3Options(others=[tmp_path / "nowhere"], **thresholds).check([], None)
