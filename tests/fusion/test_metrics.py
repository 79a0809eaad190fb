"""Our ATE and RPE against evo's APE and RPE on TUM files (evo is GPL-3.0: test-only)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion import ate, ate_aligned, rpe, write_tum

evo_file = pytest.importorskip("evo.tools.file_interface")
evo_metrics = pytest.importorskip("evo.core.metrics")


def _trajectories(seed=0, n=400):
    """A winding ground-truth path and an estimate with drift and noise in all six axes."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, :3, 3] = np.column_stack([5 * np.sin(0.05 * t) + t, 3 * np.cos(0.11 * t), 0.2 * np.sin(0.3 * t)])
    angles = np.column_stack([0.05 * np.sin(t), 0.03 * np.cos(t), 0.2 * t])
    gt[:, :3, :3] = Rotation.from_euler("xyz", angles).as_matrix()
    est = gt.copy()
    drift = np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0)
    est[:, :3, 3] += drift + [0.5, -0.2, 0.1]
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.002, (n, 3)), 0)).as_matrix()
    return t, gt, est


def _evo(tmp_path, t, gt, est):
    write_tum(tmp_path / "gt.txt", t, gt)
    write_tum(tmp_path / "est.txt", t, est)
    read = evo_file.read_tum_trajectory_file
    return read(tmp_path / "gt.txt"), read(tmp_path / "est.txt")


def _rmse(metric, data):
    metric.process_data(data)
    return metric.get_statistic(evo_metrics.StatisticsType.rmse)


def test_ate_matches_evo_ape_with_and_without_alignment(tmp_path):
    t, gt, est = _trajectories()
    ref, traj = _evo(tmp_path, t, gt, est)
    unaligned = _rmse(evo_metrics.APE(evo_metrics.PoseRelation.translation_part), (ref, traj))
    assert ate(est, gt) == pytest.approx(unaligned, abs=1e-6)
    traj.align(ref, correct_scale=False)
    aligned = _rmse(evo_metrics.APE(evo_metrics.PoseRelation.translation_part), (ref, traj))
    assert ate_aligned(est, gt) == pytest.approx(aligned, abs=1e-6)
    assert aligned < unaligned  # the check can fail: alignment must remove the constant offset


@pytest.mark.parametrize("delta, unit, all_pairs", [(10, "frames", True), (1, "frames", True), (2.0, "meters", False)])
def test_rpe_matches_evo(tmp_path, delta, unit, all_pairs):
    t, gt, est = _trajectories(1)
    ref, traj = _evo(tmp_path, t, gt, est)
    unit_evo = evo_metrics.Unit.frames if unit == "frames" else evo_metrics.Unit.meters
    ours_t, ours_r = rpe(est, gt, delta, unit)
    kw = {"all_pairs": all_pairs, "pairs_from_reference": True}  # our windows lie on the ground truth's path
    theirs_t = _rmse(evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, delta, unit_evo, **kw), (ref, traj))
    theirs_r = _rmse(evo_metrics.RPE(evo_metrics.PoseRelation.rotation_angle_rad, delta, unit_evo, **kw), (ref, traj))
    assert ours_t == pytest.approx(theirs_t, abs=1e-6) and ours_r == pytest.approx(theirs_r, abs=1e-6)
    assert ours_t > 1e-3  # a real error was measured
