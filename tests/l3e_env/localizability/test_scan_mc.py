"""The scan's own Monte-Carlo estimate: its range-image mesh, and errors that follow the geometry."""

import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from l3e_env.config import LidarConfig
from l3e_env.core.transforms import pose_to_matrix
from l3e_env.data.dataset import LabelDataset, row_thresholds
from l3e_env.data.scan_estimates import dataset_scan_errors
from l3e_env.detection.detectors import make_detector
from l3e_env.localizability.labels import LabelConfig
from l3e_env.localizability.registration import RegistrationConfig, RegistrationError
from l3e_env.localizability.scan_mc import (
    ScanMCConfig,
    ScanPatternError,
    beams_and_columns,
    range_image_mesh,
    scan_errors,
)
from l3e_env.model.scores import axis_scores
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster

SENSOR = np.eye(4)
SENSOR[2, 3] = 1.0


def _box(extents, centre=(0.0, 0.0, 1.5)) -> trimesh.Trimesh:
    """A closed box seen from inside (Embree hits faces from either side)."""
    return trimesh.creation.box(extents).apply_translation(centre)


def _scan(mesh: trimesh.Trimesh, rng=None, pose=SENSOR):
    return Lidar(EmbreeCaster(mesh, threads=1), LidarConfig()).scan(pose, rng)


def test_beams_and_columns_are_recovered_from_bare_noisy_points(rng):
    scan = _scan(_box([12, 9, 3]), rng)
    beam, column = beams_and_columns(scan.points.astype(np.float64), scan.pattern)
    assert np.array_equal(beam, scan.beam) and np.array_equal(column, scan.column)
    with pytest.raises(ScanPatternError, match="off the nearest beam of vlp16"):
        beams_and_columns(rng.normal(size=(500, 3)) * 5, scan.pattern)


def test_the_range_image_mesh_gives_back_the_scan_and_bridges_no_depth_jump():
    room = _box([12, 9, 3])
    pillar = _box([0.4, 0.4, 3], centre=(2.0, 0.0, 1.5))
    scene = trimesh.util.concatenate([room, pillar])
    scan = _scan(scene)  # no noise: the mesh's vertices lie on the true surfaces
    mesh = range_image_mesh(scan.points, scan.pattern, max_range_ratio=1.5)
    again = _scan(mesh, pose=np.eye(4))  # the mesh is in the sensor frame
    both = np.intersect1d(scan.beam.astype(int) * 1800 + scan.column, again.beam.astype(int) * 1800 + again.column)
    assert len(both) > 0.95 * len(scan)  # nearly every ray hits its own mesh (the outer beams graze its edges)
    r0 = dict(zip(scan.beam.astype(int) * 1800 + scan.column, np.linalg.norm(scan.points, axis=1)))
    r1 = dict(zip(again.beam.astype(int) * 1800 + again.column, np.linalg.norm(again.points, axis=1)))
    errors = np.abs([r0[k] - r1[k] for k in both])
    assert np.median(errors) < 1e-3 and np.percentile(errors, 99) < 0.05
    ranges = np.linalg.norm(mesh.vertices, axis=1)[mesh.faces]
    assert (ranges.max(axis=1) < 1.5 * ranges.min(axis=1)).all()  # the pillar's edges are not joined to the wall
    assert ranges.min() < 2.5 and ranges.max() > 4.0  # but pillar and wall are both there


def _child_ranges(mesh: trimesh.Trimesh, scene: trimesh.Trimesh, child: np.ndarray, where=None):
    """The ranges of the child's returns in the true scene (those `where` picks, by their points in
    the parent's frame) and of the same rays in its scan of the mesh (NaN: no return)."""
    truth, seen = _scan(scene, pose=SENSOR @ child), _scan(mesh, pose=child)
    ranges = dict(zip(seen.beam.astype(int) * 1800 + seen.column, np.linalg.norm(seen.points, axis=1)))
    keys, r = truth.beam.astype(int) * 1800 + truth.column, np.linalg.norm(truth.points, axis=1)
    pick = np.ones(len(truth), bool) if where is None else where(truth.points.astype(np.float64) + child[:3, 3])
    return r[pick], np.array([ranges.get(k, np.nan) for k in keys[pick]])


def test_the_mesh_goes_on_behind_depth_jumps_and_past_the_field_of_view():
    """A child that moves sideways sees the wall behind a pillar, which the scan could not; one
    pitched 5 deg sees floor and walls above and below the scan's beams. The filled mesh gives
    those returns where the scan's own mesh has none, and keeps every face of it."""
    scene = trimesh.util.concatenate([_box([12, 9, 3]), _box([0.4, 1.0, 3], centre=(2.0, 0.0, 1.5))])
    scan = _scan(scene)
    plain = range_image_mesh(scan.points, scan.pattern)
    filled = range_image_mesh(scan.points, scan.pattern, shadow_deg=3.0, beyond_deg=4.0)
    np.testing.assert_array_equal(filled.faces[: len(plain.faces)], plain.faces)
    sideways = pose_to_matrix(np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0]))

    def shadowed(p: np.ndarray) -> np.ndarray:  # the far wall, behind the pillar from the scan's pose
        return (p[:, 0] > 5.5) & (np.abs(np.arctan2(p[:, 1], p[:, 0])) < np.arctan2(0.5, 1.8))

    true, seen = _child_ranges(plain, scene, sideways, shadowed)
    assert len(true) > 200 and np.isnan(seen).all()
    true, seen = _child_ranges(filled, scene, sideways, shadowed)
    # about half of them now return, at or a little beyond the wall: the farthest surface nearby
    assert np.isfinite(seen).mean() > 0.4 and np.nanmin(seen / true) > 0.99 and np.nanmax(seen / true) < 1.05
    pitched = pose_to_matrix(np.array([0.0, 0.0, 0.0, 0.0, np.deg2rad(5.0), 0.0]))
    for mesh, low, high in ((plain, 0.8, 0.86), (filled, 0.9, 1.0)):
        true, seen = _child_ranges(mesh, scene, pitched)
        assert low < np.mean(np.abs(seen - true) < 0.1) < high  # NaN (no return) counts as a miss


def test_a_long_corridor_is_free_along_its_axis_and_a_room_is_not(rng):
    corridor, room = _box([200, 4, 3]), _box([10, 7, 3])
    config = ScanMCConfig(children=6)
    along = scan_errors(
        _scan(corridor, rng).points, LidarConfig(), RegistrationConfig(), LabelConfig(), config, rng
    ).errors
    held = scan_errors(_scan(room, rng).points, LidarConfig(), RegistrationConfig(), LabelConfig(), config, rng).errors
    thresholds = LabelConfig().threshold_vector()
    assert along[0] > 2 * thresholds[0] and along[1] < thresholds[1] and along[5] < thresholds[5]
    assert (held < thresholds).all()
    scaled = scan_errors(
        _scan(room, np.random.default_rng(1)).points,
        LidarConfig(),
        RegistrationConfig(),
        LabelConfig(),
        ScanMCConfig(children=6, calibration=(2.0,) * 6, settle=0),
        np.random.default_rng(2),
    ).errors
    plain = scan_errors(
        _scan(room, np.random.default_rng(1)).points,
        LidarConfig(),
        RegistrationConfig(),
        LabelConfig(),
        ScanMCConfig(children=6, calibration=(1.0,) * 6, settle=0),
        np.random.default_rng(2),
    ).errors
    assert scaled == pytest.approx(2 * plain)


def test_children_stop_once_every_axis_is_settled_and_are_the_same_draws(rng):
    points = _scan(_box([10, 7, 3]), rng).points  # a room: every axis under its threshold
    args = (points, LidarConfig(), RegistrationConfig(), LabelConfig())
    settled = scan_errors(*args, ScanMCConfig(children=32, first=4), np.random.default_rng(3))
    assert settled.children in (4, 8, 16)
    every = scan_errors(*args, ScanMCConfig(children=16, first=4, settle=100.0), np.random.default_rng(3))
    assert every.children == 16
    prefix = scan_errors(*args, ScanMCConfig(children=settled.children, first=1, settle=0), np.random.default_rng(3))
    assert np.array_equal(prefix.errors, settled.errors) and prefix.children == settled.children
    # the raw children behind each estimate: the estimate is their mean times the calibration, and
    # the first children of a longer run are the same draws
    raw = every.child_errors
    assert raw.shape[1] == 6 and 8 <= len(raw) <= 16
    assert every.errors == pytest.approx(raw.mean(axis=0) * np.array(ScanMCConfig.calibration))
    assert np.array_equal(raw[: len(settled.child_errors)], settled.child_errors)
    with pytest.raises(ValueError, match="at least one child"):
        scan_errors(*args, ScanMCConfig(first=0), rng)
    with pytest.raises(ValueError, match="settle must be >= 0"):
        scan_errors(*args, ScanMCConfig(settle=-1.0), rng)


def test_the_detector_flags_the_corridor_and_answers_unknown_to_a_bad_scan(rng):
    detector = make_detector("scanmc:6")
    assert detector.name == "scanmc:6"
    pred = detector.predict(_scan(_box([200, 4, 3]), rng).points)
    assert pred.known and pred.mask[0] and not pred.mask[1] and pred.probabilities[0] > 0.5
    for bad in (np.zeros((0, 3)), np.full((3000, 3), np.nan), rng.normal(size=(3000, 3)) * 5):
        assert not detector.predict(bad).known
    with pytest.raises(RegistrationError, match="NaN"):
        scan_errors(np.full((3000, 3), np.nan), LidarConfig(), RegistrationConfig(), LabelConfig(), ScanMCConfig(), rng)
    for spec in ("scanmc:0", "scanmc:x"):
        with pytest.raises(ValueError, match="number of children"):
            make_detector(spec)


@pytest.mark.slow
def test_evaluate_scores_the_scan_estimate_the_same_with_any_number_of_workers(tiny_dataset, tmp_path):
    from l3e_env.experiments.table3 import Table3Options, run_table3

    res = run_table3(
        [], None, tmp_path / "eval", Table3Options(others=[tiny_dataset], scan_mc=3, workers=2), progress=False
    )
    column = f"all of {Path(tiny_dataset).name}"
    scored = res.models["scanmc:3"]["splits"][column]
    data = LabelDataset(tiny_dataset)
    saved = np.load(tmp_path / "eval" / "scan_mc.npz")[column.replace(" ", "_")]
    # the scans judged here, one at a time, as the two workers judged them (the first four: the same code)
    direct, _ = dataset_scan_errors([str(tiny_dataset)], np.arange(4), ScanMCConfig(children=3), workers=1)
    assert np.isfinite(saved).all() and len(saved) == len(data) and np.array_equal(saved[:4], direct)
    expected = axis_scores(data.labels, saved > row_thresholds(data))
    assert scored["count"] == len(data) and scored["accuracy"] == pytest.approx(expected["accuracy"].tolist())
    assert "scanmc:3" in res.table
    few, _ = dataset_scan_errors([str(tiny_dataset)], np.arange(3), ScanMCConfig(children=3), workers=2)
    assert np.array_equal(few, direct[:3])  # one chunk with two workers asked: judged here
    with pytest.raises(ValueError, match="give a checkpoint"):
        run_table3([], tiny_dataset, tmp_path / "no-checkpoint", Table3Options(scan_mc=3), progress=False)
    for bad in ({"scan_mc": -1}, {"scan_mc": 3, "workers": 0}):
        with pytest.raises(ValueError, match="scan estimate needs"):
            run_table3([], None, tmp_path / "bad", Table3Options(others=[tiny_dataset], **bad), progress=False)
    with pytest.raises(ValueError, match="at least one child"):
        scan_errors(
            data.scan(0),
            LidarConfig(),
            RegistrationConfig(),
            LabelConfig(),
            ScanMCConfig(children=0),
            np.random.default_rng(0),
        )


def test_map_judges_of_the_estimate_and_the_oracle_read_each_pose_by_itself(rng):
    from policies.locmap import MapJudge

    lidar = Lidar(EmbreeCaster(_box([200, 4, 3]), threads=1), LidarConfig())
    judge = MapJudge("scanmc:4", lidar)
    other = MapJudge("scanmc:6", lidar)
    assert judge.identity.startswith("scanmc4-") and other.identity.startswith("scanmc6-")
    along, across = SENSOR.copy(), SENSOR.copy()
    across[:2, :2] = [[0, -1], [1, 0]]  # turned 90 deg: the corridor's axis is the sensor's y
    probs = judge([along, across], [np.random.default_rng(1), np.random.default_rng(2)])
    assert ((probs > 0) & (probs < 1)).all()
    assert probs[0, 0] > 0.5 > probs[0, 1] and probs[1, 1] > 0.5 > probs[1, 0]
    # a pose's children come from its own seed, not from the order of the poses
    again = judge([across, along], [np.random.default_rng(2), np.random.default_rng(1)])
    assert np.array_equal(again, probs[::-1])
    # the oracle judges every pose (the fusion's oracle holds its labels over 5 steps; a map must not)
    oracle = MapJudge("oracle:4", lidar)
    masks = oracle([along, across, along, across], [np.random.default_rng(i) for i in range(4)])
    assert masks[:, :2].tolist() == [[1, 0], [0, 1], [1, 0], [0, 1]]


def test_map_judge_of_the_cascade_puts_its_two_judges_on_one_scale():
    from scipy.special import logit

    from policies.locmap import MapJudge

    lidar = Lidar(EmbreeCaster(_box([200, 4, 3]), threads=1), LidarConfig())
    across = SENSOR.copy()
    across[:2, :2] = [[0, -1], [1, 0]]
    poses = [SENSOR, across]

    def seeds() -> list[np.random.Generator]:
        return [np.random.default_rng(1), np.random.default_rng(2)]

    learned, never = MapJudge("learned", lidar), MapJudge("learned+scanmc:0", lidar)
    always, scanmc = MapJudge("learned+scanmc:100", lidar), MapJudge("scanmc", lidar)
    assert never.identity.startswith("learned+scanmc0-") and always.identity.startswith("learned+scanmc100-")
    assert (never.thresholds == 0.5).all() and not np.array_equal(learned.thresholds, never.thresholds)
    # margin 0: the classifier alone, its probabilities moved so that its thresholds sit at 0.5 (pose by
    # pose: the classifier draws a batch's points by the scan's place in it)
    p = np.concatenate([learned([T], [rng]) for T, rng in zip(poses, seeds())])
    centred = never(poses, seeds())
    assert np.array_equal(centred > 0.5, p > learned.thresholds)
    inside = (p > 1e-5) & (p < 1 - 1e-5)  # log-odds are clipped at +-13.8
    assert inside.sum() >= 8
    np.testing.assert_allclose(logit(centred)[inside], (logit(p) - logit(learned.thresholds))[inside], atol=1e-4)
    assert not never.judge_poses(poses, seeds())[1].any()
    # margin 100: every scan judged by scanmc, with the pose's own children, and said so
    by_cascade, estimated = always.judge_poses(poses, seeds())
    by_scanmc, everywhere = scanmc.judge_poses(poses, seeds())
    assert np.array_equal(by_cascade, by_scanmc) and estimated.all() and everywhere.all()


def test_a_thinned_scan_is_refused_by_name(rng):
    scan = _scan(_box([12, 9, 3]), rng)
    sampled = scan.points[rng.choice(len(scan), 4000, replace=False)]  # as a recording keeps it
    with pytest.raises(ScanPatternError, match="thinned or sampled"):
        range_image_mesh(sampled, scan.pattern)
    assert not make_detector("scanmc:4").predict(sampled).known


def test_near_threshold_measures_log_odds_from_each_axis_threshold():
    from l3e_env.detection.detectors import near_threshold

    thresholds = np.array([0.5, 0.5, 0.2, 0.5, 0.5, 0.9])
    sure = np.array([[0.05, 0.95, 0.01, 0.05, 0.05, 0.999], [0.5, 0.05, 0.05, 0.05, 0.05, 0.05]])
    assert near_threshold(sure, thresholds, 1.0).tolist() == [False, True]  # the second scan: x at its threshold
    one_off = np.full(6, 0.01)
    one_off[2] = 1 / (1 + 4 * np.exp(-0.9))  # 0.9 log-odds above z's threshold of 0.2
    assert near_threshold(one_off, thresholds, 1.0) and not near_threshold(one_off, thresholds, 0.8)
    assert not near_threshold(sure, thresholds, 0.0).any()  # margin 0: never unsure


def test_cascade_detector_asks_the_estimate_only_where_the_classifier_is_unsure(rng):
    from l3e_env.detection.detectors import CascadeDetector, LearnedDetector, ScanMCDetector

    scan = _scan(_box([200, 4, 3]), rng)  # a corridor along x
    learned, scan_mc = LearnedDetector(), ScanMCDetector(LidarConfig(), children=6)
    never, always = CascadeDetector(learned, scan_mc, margin=0.0), CascadeDetector(learned, scan_mc, margin=100.0)
    alone = learned.predict(scan.points)
    kept = never.judge(scan.points, np.random.default_rng(1))
    assert np.array_equal(kept.probabilities, alone.probabilities) and never.checked == 0 and never.calls == 1
    checked = always.judge(scan.points, np.random.default_rng(1))
    estimate = scan_mc.judge(scan.points, np.random.default_rng(1))
    assert checked.known and np.array_equal(checked.probabilities, estimate.probabilities)
    assert checked.mask[0] and always.checked == 1  # the estimate flags the corridor's x
    assert not always.predict(np.full((100, 3), np.nan)).known  # a scan the classifier cannot judge: unknown
    assert always.checked == 1 and always.calls == 2
    made = make_detector("learned+scanmc")
    assert made.name == "learned+scanmc:1" and made.margin == 1.0
    assert make_detector("learned+scanmc:0.5").name == "learned+scanmc:0.5"
    for spec in ("learned+scanmc:x", "learned+scanmc:-1"):
        with pytest.raises(ValueError, match="margin"):
            make_detector(spec)


@pytest.mark.slow
def test_evaluate_scores_the_cascade_from_the_classifier_and_the_estimate(tiny_dataset, tmp_path):
    from l3e_env.experiments.table3 import Table3Options, run_table3
    from l3e_env.model.classifier import DEFAULT_CHECKPOINT

    res = run_table3(
        [DEFAULT_CHECKPOINT],
        None,
        tmp_path / "eval",
        Table3Options(others=[tiny_dataset], scan_mc=3, cascade=[0.0, 100.0]),
        progress=False,
    )
    column = f"all of {Path(tiny_dataset).name}"
    model = next(name for name in res.models if "scanmc" not in name)
    never, always = (res.models[f"{model}+scanmc:{m}"]["splits"][column] for m in ("0", "100"))
    assert never["checked"] == 0.0 and always["checked"] == 1.0  # margin 0: the classifier; 100: the estimate
    for cascade, alone in ((never, res.models[model]), (always, res.models["scanmc:3"])):
        for key in ("accuracy", "f1", "precision", "recall"):
            assert cascade[key] == pytest.approx(alone["splits"][column][key], nan_ok=True)
    assert f"{model}+scanmc:100: share of scans checked by scanmc:3: {column} 1.00" in res.table
    # random checks of no scan are the classifier, of every scan the estimate; the plot is drawn
    random = res.results["cascade_random_checks"][column]
    assert random["share"][0] == 0.0 and random["share"][-1] == 1.0
    assert random["mean_f1"][0] == pytest.approx(never["mean"]["f1"], nan_ok=True)
    assert random["mean_f1"][-1] == pytest.approx(always["mean"]["f1"], nan_ok=True)
    assert (tmp_path / "eval" / "cascade.png").stat().st_size > 10_000
    for bad in ({"scan_mc": 0, "cascade": [1.0]}, {"scan_mc": 3, "cascade": [-1.0]}):
        with pytest.raises(ValueError, match="cascade"):
            run_table3(
                [DEFAULT_CHECKPOINT],
                None,
                tmp_path / "bad",
                Table3Options(others=[tiny_dataset], **bad),
                progress=False,
            )
    with pytest.raises(ValueError, match="cascade"):
        run_table3(
            [], None, tmp_path / "bad", Table3Options(others=[tiny_dataset], scan_mc=3, cascade=[1.0]), progress=False
        )


def test_random_checks_move_from_the_first_detector_to_the_second_with_their_share():
    from l3e_env.experiments.table3 import random_checks

    labels = np.random.default_rng(0).random((400, 6)) < 0.3
    curve = random_checks(labels, labels.copy(), ~labels)  # the first right everywhere, the second wrong
    assert curve["share"] == pytest.approx(np.linspace(0, 1, 11))
    assert curve["mean_f1"][0] == 1.0 and curve["mean_f1"][-1] == 0.0
    assert np.all(np.diff(curve["mean_f1"]) < 0)
    # half the scans wrong: TP P/2, FN P/2, FP N/2 on each axis, so F1 = P / (1.5 P + N / 2)
    positives, negatives = labels.sum(axis=0), (~labels).sum(axis=0)
    expected = np.mean(positives / (1.5 * positives + negatives / 2))
    assert curve["mean_f1"][5] == pytest.approx(expected, abs=0.02)
    # a split with no positive label where neither detector flags: no F1 at any share, and no warning
    quiet = np.zeros((50, 6), dtype=bool)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(random_checks(quiet, quiet, quiet, repeats=3)["mean_f1"]).all()


def test_open_ground_keeps_z_where_the_scene_keeps_it():
    """In an open field the scene's ground goes on where the scan's returns end: a child that slides
    along the free axes off the scan's own mesh lost z (10x its threshold); with the fitted ground
    continued under the children (ScanMCConfig.ground_reach, the default) z stays localizable."""
    from l3e_env.core.transforms import pose_to_matrix
    from scenes import make_scene

    field = make_scene("field-0")
    at = field.route[len(field.route) // 2]
    T_w_s = pose_to_matrix(np.array([at[0], at[1], at[2] + 0.85, 0.0, 0.0, 0.2]))
    points = Lidar(EmbreeCaster(field.mesh, threads=1), LidarConfig()).scan(T_w_s, np.random.default_rng(0)).points
    threshold = LabelConfig().threshold_vector()[2]

    def z_over_threshold(reach: float) -> float:
        config = ScanMCConfig(children=20, ground_reach=reach)
        found = scan_errors(
            points, LidarConfig(), RegistrationConfig(), LabelConfig(), config, np.random.default_rng(1)
        )
        return float(found.errors[2] / threshold)

    assert z_over_threshold(ScanMCConfig().ground_reach) < 0.5 < 2.0 < z_over_threshold(0.0)
