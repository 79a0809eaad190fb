"""External odometries on a drive: frames handled once, failures kept in their rows, missing packages named."""

import numpy as np
import pytest

from l3e_env.core.transforms import inverse, pose_to_matrix
from l3e_env.experiments import baselines
from l3e_env.experiments.baselines import BaselineError, check_baselines, run_baseline
from l3e_env.sim.patterns import get_pattern


class _Truthful:
    """An odometry that reports the sensor's true pose in the frame of its first scan, frame after
    frame, and keeps the timestamps it was given."""

    def __init__(self, poses):
        self.poses, self.stamps, self.last_pose, self.k = poses, [], np.eye(4), 0

    def register_frame(self, points, timestamps):
        self.stamps.append(np.asarray(timestamps))
        self.last_pose = inverse(self.poses[0]) @ self.poses[self.k]
        self.k += 1


def _drive(n=30):
    gt = np.stack([pose_to_matrix(np.array([0.1 * k, 0.02 * k, 0.3, 0.01, -0.02, 0.05 * k])) for k in range(n)])
    T_b_s = pose_to_matrix(np.array([0.25, -0.05, 0.5, 0.0, 0.1, 0.3]))  # a lever arm and a tilted, turned sensor
    scans = [np.random.default_rng(k).uniform(-10, 10, (500, 3)) for k in range(n)]
    return gt, T_b_s, scans


def test_an_exact_odometry_gives_the_true_body_trajectory_through_the_mounting(monkeypatch):
    gt, T_b_s, scans = _drive()
    odometry = _Truthful(gt @ T_b_s)  # the sensor's world poses
    monkeypatch.setitem(baselines.BASELINES, "kiss-icp", ("numpy", lambda deskew, max_range: (odometry, {"x": 1})))
    run = run_baseline("kiss-icp", scans, gt[0], T_b_s, get_pattern("vlp16"), progress=False)
    assert run.error is None and run.config == {"x": 1}
    assert np.abs(run.trajectory - gt).max() < 1e-9
    # a swept drive hands each point's firing time over the revolution, in [0, 1]
    assert len(odometry.stamps) == len(scans) and all(len(s) == 500 for s in odometry.stamps)
    assert min(s.min() for s in odometry.stamps) >= 0 and max(s.max() for s in odometry.stamps) <= 1
    odometry.k = 0
    run_baseline("kiss-icp", scans, gt[0], T_b_s, None, progress=False)  # one instant a scan: no times
    assert all(len(s) == 0 for s in odometry.stamps[len(scans) :])


def test_a_failing_or_diverging_odometry_is_reported_not_raised(monkeypatch):
    gt, T_b_s, scans = _drive(5)

    class Broken(_Truthful):
        def register_frame(self, points, timestamps):
            raise RuntimeError("map is empty")

    class Diverging(_Truthful):
        def register_frame(self, points, timestamps):
            self.last_pose = np.full((4, 4), np.nan)

    for odometry, words in ((Broken(gt), "RuntimeError: map is empty"), (Diverging(gt), "diverged")):
        monkeypatch.setitem(baselines.BASELINES, "genz-icp", ("numpy", lambda d, m, o=odometry: (o, {})))
        run = run_baseline("genz-icp", scans, gt[0], T_b_s, None, progress=False)
        assert run.trajectory is None and words in run.error


def test_a_missing_package_or_an_unknown_baseline_is_named_before_anything_runs(monkeypatch):
    with pytest.raises(BaselineError, match="unknown baseline 'loam'"):
        check_baselines(["loam"])
    monkeypatch.setitem(baselines.BASELINES, "kiss-icp", ("no_such_module_here", None))
    with pytest.raises(BaselineError, match=r"pip install 'l3e\[baselines\]'"):
        check_baselines(["kiss-icp"])


@pytest.mark.slow
def test_kiss_icp_and_genz_icp_rows_in_the_ate_table(tmp_path):
    pytest.importorskip("kiss_icp")
    pytest.importorskip("genz_icp")
    from l3e_env.experiments.ate import AteOptions, run_ate

    run = run_ate(
        tmp_path,
        "office",
        ["none", "eigen:30"],
        AteOptions(max_steps=40, baselines=["kiss-icp", "genz-icp"], frontends=["icp", "genz-icp"]),
        progress=False,
    )
    names = [r.detector for r in run.rows]
    assert names == [
        "odometry only",
        "odometry + attitude",  # the one estimator fuses the IMU's tilt: its row of the legs with it alone
        "none",
        "eigen:30",
        "odometry + attitude @genz-icp",
        "none @genz-icp",
        "eigen:30 @genz-icp",
        "kiss-icp",
        "genz-icp",
    ]
    assert all(r.ate_m is not None and np.isfinite(r.ate_m) for r in run.rows)
    assert "kiss-icp" in run.table() and (tmp_path / "trajectories" / "kiss-icp.tum").exists()
    import json

    saved = json.loads((tmp_path / "results.json").read_text())["baselines"]
    assert saved["kiss-icp"]["config"]["mapping"]["voxel_size"] == 1.0 and saved["genz-icp"]["error"] is None
    rows = {r.detector: r for r in run.rows}  # the front end's steps are its own, not ICP's
    assert rows["none @genz-icp"].ate_m != rows["none"].ate_m


def test_a_front_end_takes_the_odometrys_steps_with_the_icp_information():
    gt, T_b_s, _ = _drive(6)
    P = np.stack([inverse(gt[0] @ T_b_s) @ T @ T_b_s for T in gt])
    run = baselines.BaselineRun("kiss-icp", gt, {}, 0.0, sensor_poses=P)
    from l3e_env.localizability.registration import RegistrationResult

    icp = [RegistrationResult(np.eye(4), np.eye(6) * (k + 1), True, 5, 10, 10, 0.0) for k in range(4)] + [None]
    steps = run.registrations(icp)
    assert len(steps) == 5 and all(s.converged for s in steps)
    assert np.allclose(steps[2].T_target_source, inverse(gt[2] @ T_b_s) @ gt[3] @ T_b_s)
    assert np.array_equal(steps[1].hessian, np.eye(6) * 2) and np.isnan(steps[4].hessian).all()
    with pytest.raises(ValueError, match="failed"):
        baselines.BaselineRun("kiss-icp", None, {}, 0.0, "diverged").registrations(icp)
