import json

import numpy as np
import pytest

from l3e_env.config import FusionSettings, LidarConfig
from l3e_env.detection.detectors import DCRegDetector, EigenvalueDetector, NoDetector, make_detector
from l3e_env.experiments.ate import AteOptions, run_ate
from l3e_env.experiments.ate_tables import AteRow, file_stem, format_seed_table, format_table, summarize_seeds
from l3e_env.experiments.drive import DriveOptions, DriveRecord, record_run, register_sequence
from l3e_env.experiments.fuse import fuse_recording
from l3e_env.experiments.recast import OdometryAttitude, RecastCascade, RecastScans
from l3e_env.localizability.labels import AXES
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


@pytest.fixture(scope="module")
def walls_short():
    """The first 20 m (200 steps) of a drive between two parallel walls (x along them is degenerate),
    with its registrations: shared by the tests of the mask, of what a run writes and of how its options
    reach the fusion."""
    rec = record_run("primitives-1", DriveOptions(max_steps=200), progress=False)
    return rec, register_sequence(rec, RegistrationConfig(), progress=False)


@pytest.mark.slow
def test_masking_the_wall_axis_is_what_fixed_sigmas_need_and_the_hessian_weighting_already_does(walls_short):
    """Between two parallel walls x (along them) is free. With the library's fixed ICP sigmas (the
    paper's protocol) unmasked ICP holds x where the walls cannot, and masking it wins by far. Weighed by
    its Hessian, ICP gives x almost no weight itself: the unmasked estimate is near the masked one (on
    a drive either can be the better; the legs' draws decide, docs/results.md)."""
    from fusion import FusionConfig

    rec, regs = walls_short
    w = np.array([np.linalg.eigvalsh(r.hessian)[:2] for r in regs if r is not None])
    tau = float(np.sqrt(np.median(w[:, 0]) * np.median(w[:, 1])))  # between the free axis and the rest
    detectors = [NoDetector(), EigenvalueDetector(tau)]
    full, eigen = fuse_recording(rec, detectors, regs, progress=False)
    assert eigen.masks[:, 0].mean() > 0.8 and eigen.masks[:, 1:].mean() < 0.2
    fixed = FusionConfig(icp_covariance="fixed")
    full_fixed, eigen_fixed = fuse_recording(rec, detectors, regs, fusion=fixed, progress=False)
    assert eigen_fixed.ate < 0.2 * full_fixed.ate  # the mask, where ICP's sigmas say nothing of the walls
    assert full.ate < 0.2 * full_fixed.ate and 0.5 < eigen.ate / full.ate < 2.0  # the Hessian's own weighting
    assert "eigen" in format_table([AteRow.of(full, {}), AteRow.of(eigen, {})])


@pytest.mark.slow
def test_a_saved_recording_evaluates_to_the_same_numbers_without_driving_again(walls_short, tmp_path):
    rec, regs = walls_short
    (eigen,) = fuse_recording(rec, [EigenvalueDetector(100.0)], regs, progress=False)
    rec.save(tmp_path / "rec.npz")
    again = DriveRecord.load(tmp_path / "rec.npz")
    registered = register_sequence(again, RegistrationConfig(), False)
    (eigen2,) = fuse_recording(again, [EigenvalueDetector(100.0)], registered, progress=False)
    assert eigen2.ate == pytest.approx(eigen.ate, rel=1e-9) and eigen.masks.any()


@pytest.mark.slow
def test_ate_from_a_recording_writes_results_and_figures(walls_short, tmp_path):
    rec, _ = walls_short
    rec.save(tmp_path / "rec.npz")
    run = run_ate(
        tmp_path / "out", "mine", ["eigen:30", "none"], AteOptions(recording=tmp_path / "rec.npz"), progress=False
    )  # the recording's scene, not the argument, is used
    rows = run.rows
    assert all(path.is_file() for path in run.written) and not run.swept
    tracks = {
        f"{stem}.{kind}"
        for stem in ("ground_truth", "odometry_only", "odometry_attitude", "eigen_30", "none")
        for kind in ("tum", "kitti")
    }
    assert {p.name for p in run.written} == {
        "results.json",
        "trajectories.png",
        "timeline.png",
        "map_odometry_attitude.png",
        "map_odometry_attitude.ply",
        "map_eigen_30.png",
        "map_eigen_30.ply",
        "map_none.png",
        "map_none.ply",
        *tracks,
    }
    evo_file = pytest.importorskip("evo.tools.file_interface")
    evo_metrics = pytest.importorskip("evo.core.metrics")
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data(
        (
            evo_file.read_tum_trajectory_file(tmp_path / "out" / "trajectories" / "ground_truth.tum"),
            evo_file.read_tum_trajectory_file(tmp_path / "out" / "trajectories" / "none.tum"),
        )
    )
    none_row = next(r for r in run.rows if r.detector == "none")
    assert ape.get_statistic(evo_metrics.StatisticsType.rmse) == pytest.approx(none_row.ate_m, abs=1e-3)
    kitti = evo_file.read_kitti_poses_file(tmp_path / "out" / "trajectories" / "none.kitti")
    tum = evo_file.read_tum_trajectory_file(tmp_path / "out" / "trajectories" / "none.tum")
    np.testing.assert_allclose(kitti.positions_xyz, tum.positions_xyz, atol=1e-6)
    assert [r.detector for r in rows] == ["odometry only", "odometry + attitude", "eigen:30", "none"]
    written = {p.name for p in (tmp_path / "out").iterdir()}
    assert {"results.json", "trajectories.png", "timeline.png", "map_eigen_30.png", "map_none.png"} <= written
    assert "recording.npz" not in written
    summary = json.loads((tmp_path / "out" / "results.json").read_text())
    assert summary["scene"] == "primitives-1"
    assert summary["registration"]["downsampling_resolution"] == 0.15  # the registration that ran, written down


@pytest.mark.slow
def test_the_imu_attitude_joins_every_detector_alike_and_adds_its_own_reference_row(walls_short, tmp_path):
    from l3e_env.cli.main import main

    rec, regs = walls_short
    (plain,) = fuse_recording(rec, [NoDetector()], regs, progress=False)
    held, again = fuse_recording(
        rec, [NoDetector(), NoDetector()], regs, progress=False, settings=FusionSettings(attitude="full")
    )
    np.testing.assert_array_equal(held.trajectory, again.trajectory)  # the same readings for every detector
    assert np.abs(held.trajectory - plain.trajectory).max() > 1e-6
    # the reference row has nothing of the scans: no ICP, and no ground from them either
    rows = {
        ground: fuse_recording(
            rec, [OdometryAttitude(), NoDetector()], regs, progress=False, settings=FusionSettings(ground=ground)
        )
        for ground in ("plane", "none")
    }
    np.testing.assert_array_equal(rows["plane"][0].trajectory, rows["none"][0].trajectory)
    assert np.abs(rows["plane"][1].trajectory - rows["none"][1].trajectory).max() > 1e-6
    rec.save(tmp_path / "rec.npz")
    assert (
        main(
            [
                "ate",
                "--recording",
                str(tmp_path / "rec.npz"),
                "--detector",
                "none",
                "--attitude",
                "tilt",
                "--out",
                str(tmp_path / "out"),
                "--quiet",
            ]
        )
        == 0
    )
    summary = json.loads((tmp_path / "out" / "results.json").read_text())
    assert summary["fusion"]["attitude"] == "tilt" and summary["fusion"]["backend"] == "graph"
    assert [r["detector"] for r in summary["rows"]] == ["odometry only", "odometry + attitude", "none"]
    with pytest.raises(ValueError, match="attitude must be one of"):
        run_ate(tmp_path / "bad", "mine", ["none"], AteOptions(fusion_settings=FusionSettings(attitude="compass")))
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_the_hessian_weighs_the_icp_factor_and_the_settings_are_written(walls_short, tmp_path):
    from dataclasses import replace

    from fusion import FusionConfig

    whole, all_regs = walls_short
    steps = 80  # of the walls' drive: the run and the sweep register it again
    rec = replace(
        whole, ground_truth=whole.ground_truth[: steps + 1], odometry=whole.odometry[:steps],
        scans=whole.scans[: steps + 1], samples=whole.samples[: steps + 1],
    )  # fmt: skip
    regs = all_regs.first(steps)
    rec.save(tmp_path / "rec.npz")
    (fixed,) = fuse_recording(rec, [NoDetector()], regs, fusion=FusionConfig(icp_covariance="fixed"), progress=False)
    (weighed,) = fuse_recording(rec, [NoDetector()], regs, progress=False)
    assert weighed.ate != pytest.approx(fixed.ate, rel=1e-3)  # the library's fixed sigmas are another estimator
    scan_to_scan = FusionSettings(keyframe_distance=0.0)  # as `regs` were registered
    options = AteOptions(recording=tmp_path / "rec.npz", fusion_settings=scan_to_scan)
    rows = run_ate(tmp_path / "out", "mine", ["none"], options, progress=False).rows
    assert next(r for r in rows if r.detector == "none").ate_m == round(weighed.ate, 3)  # rows are rounded
    written = json.loads((tmp_path / "out" / "results.json").read_text())["fusion"]
    assert written["odometry_bias"] == ["yaw", "scale"] and written["attitude"] == "tilt"  # the one estimator
    from l3e_env.experiments.tau_sweep import SweepOptions, run_sweep

    options = SweepOptions(
        taus=(1e12,), kappas=(1e15,), xicps=(1e9,), drpms=(1e-3,), references=("none",), fusion_settings=scan_to_scan
    )
    swept = run_sweep(tmp_path / "sweep", ["primitives-1"], options, {"primitives-1": str(tmp_path / "rec.npz")}, False)
    row = swept["primitives-1"]
    # no axis that well held, or every axis flagged: the legs and the IMU's tilt alone, the same fusion
    assert row["xicp_ate"][0] == pytest.approx(row["eigen_ate"][0], rel=1e-6)
    assert row["drpm_flagged"][0][1:] == [0.0] * 5  # a tiny signal-to-noise factor: only the walls' free axis
    assert row["fusion"]["odometry_bias"] == ["yaw", "scale"] and row["none"] == pytest.approx(weighed.ate, rel=1e-9)
    assert row["eigen_flagged"][0] == [1.0] * 6 and row["xicp_flagged"][0] == [1.0] * 6
    assert row["dcreg_ate"][0] == pytest.approx(row["none"], rel=1e-9)  # no ratio that high: nothing flagged
    assert row["dcreg_flagged"][0] == [0.0] * 6 and (tmp_path / "sweep" / "tau_sweep.png").stat().st_size > 0


@pytest.mark.slow
def test_the_legs_bias_as_a_fusion_state_from_the_command_line(walls_short, tmp_path, capsys):
    from l3e_env.cli.main import main
    from l3e_env.config import OdometryConfig
    from l3e_env.sim.odometry import SCALE_WALK, odometry_fusion_config

    rec, regs = walls_short
    rec.save(tmp_path / "rec.npz")
    noisy = OdometryConfig(yaw_bias_std=0.004, z_bias_walk=0.002)
    config = odometry_fusion_config(noisy, FusionSettings(odometry_bias=("yaw",)))
    assert config.odometry_bias == ("yaw",)
    assert config.odometry_bias_sigmas == (0.004, noisy.z_bias_std, noisy.scale_error_std)
    assert config.odometry_bias_walk == (noisy.yaw_bias_walk, 0.002, SCALE_WALK)
    (plain,) = fuse_recording(rec, [NoDetector()], regs, progress=False)
    both = odometry_fusion_config(OdometryConfig(), FusionSettings(odometry_bias=("yaw", "z")))
    (learnt,) = fuse_recording(rec, [NoDetector()], regs, fusion=both, progress=False)
    assert np.abs(learnt.trajectory - plain.trajectory).max() > 1e-6
    assert (
        main(
            [
                "ate",
                "--recording",
                str(tmp_path / "rec.npz"),
                "--detector",
                "none",
                "--odometry-bias",
                "yaw,z",
                "--keyframe-distance",
                "0",
                "--out",
                str(tmp_path / "out"),
                "--quiet",
            ]
        )
        == 0
    )
    summary = json.loads((tmp_path / "out" / "results.json").read_text())
    none = next(r for r in summary["rows"] if r["detector"] == "none")
    assert summary["fusion"]["odometry_bias"] == ["yaw", "z"] and none["ate_m"] == round(learnt.ate, 3)
    with pytest.raises(SystemExit):
        main(["ate", "--recording", str(tmp_path / "rec.npz"), "--odometry-bias", "roll", "--quiet"])
    assert "expected none or distinct axes among yaw, z, scale" in capsys.readouterr().err
    with pytest.raises(ValueError, match="odometry_bias takes distinct axes"):
        run_ate(
            tmp_path / "bad", "mine", ["none"], AteOptions(fusion_settings=FusionSettings(odometry_bias=("yaw", "yaw")))
        )
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_a_swept_recording_says_so_when_replayed(walls_short, tmp_path, capsys):
    from dataclasses import replace

    from l3e_env.cli.main import main

    rec, _ = walls_short
    assert not rec.sweep
    replace(rec, sweep=True).save(tmp_path / "swept.npz")
    assert DriveRecord.load(tmp_path / "swept.npz").sweep
    assert (
        main(
            [
                "ate",
                "--recording",
                str(tmp_path / "swept.npz"),
                "--detector",
                "none",
                "--quiet",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    summary = json.loads((tmp_path / "out" / "results.json").read_text())
    assert summary["swept"] and summary["deskew"] == "gyro"
    out = capsys.readouterr().out
    assert "swept over the robot's motion; each was deskewed" in out and "the gyro's rotation" in out
    assert (
        main(
            [
                "ate",
                "--recording",
                str(tmp_path / "swept.npz"),
                "--detector",
                "none",
                "--quiet",
                "--deskew",
                "odometry",
                "--out",
                str(tmp_path / "legs"),
            ]
        )
        == 0
    )
    assert json.loads((tmp_path / "legs" / "results.json").read_text())["deskew"] == "odometry"
    assert "with the odometry's rotation" in capsys.readouterr().out
    with pytest.raises(ValueError, match="deskew must be one of"):
        run_ate(
            tmp_path / "bad",
            "mine",
            ["none"],
            AteOptions(recording=tmp_path / "swept.npz", fusion_settings=FusionSettings(deskew="imu")),
        )


@pytest.mark.slow
def test_scanmc_in_a_replay_judges_scans_cast_again_at_the_true_poses(walls_short, tmp_path):
    rec, _ = walls_short  # two parallel walls: x (along them) is degenerate, nothing else
    rec.save(tmp_path / "rec.npz")
    run_ate(tmp_path / "out", "ignored", ["scanmc:4"], AteOptions(recording=tmp_path / "rec.npz"), progress=False)
    (row,) = [
        r for r in json.loads((tmp_path / "out" / "results.json").read_text())["rows"] if r["detector"] == "scanmc:4"
    ]
    assert row["unknown_steps"] == row["detector_errors"] == 0  # the recording's thinned scans would all be unknown
    assert row["flagged"]["x"] > 0.8 and max(row["flagged"][a] for a in AXES[1:]) < 0.2


@pytest.mark.slow
def test_a_recast_detector_judges_every_stride_steps_alike_in_workers_and_holds_no_failure(walls_short):
    rec, _ = walls_short
    scene = make_scene(rec.scene)
    lidar = Lidar(EmbreeCaster(scene.mesh), LidarConfig())
    poses = [T @ rec.T_b_s for T in rec.ground_truth[1:13]]

    def replay(recast):
        return [recast.predict(rec.scans[0], None, T) for T in poses]

    alone = replay(RecastScans(make_detector("scanmc:3", lidar), lidar, stride=4))
    ahead = RecastScans(make_detector("scanmc:3", lidar), lidar, stride=4)
    ahead.judge_ahead(poses, scene, workers=2, progress=False)
    assert ahead._ahead.keys() == {0, 4, 8}
    shared = replay(ahead)
    assert all(p.known for p in alone) and not ahead._ahead  # every judgement taken from the workers
    assert all(np.array_equal(a.probabilities, b.probabilities) for a, b in zip(alone, shared))
    assert [p.probabilities.tolist() for p in alone[:4]] == [alone[0].probabilities.tolist()] * 4  # held

    class Failing:
        name = "failing"

        def judge(self, points, rng, T_w_s=None):
            raise RuntimeError("a detector bug")

    failing = RecastScans(Failing(), lidar, stride=4)
    with pytest.raises(RuntimeError):
        failing.predict(rec.scans[0], None, poses[0])
    assert not failing.predict(rec.scans[0], None, poses[1]).known  # not held as a judgement
    with pytest.raises(ValueError, match="true sensor pose"):
        failing.predict(rec.scans[0])


@pytest.mark.slow
def test_the_cascade_in_a_replay_checks_only_unsure_steps_alike_in_workers(walls_short):
    from l3e_env.detection.detectors import CascadeDetector, LearnedDetector, ScanMCDetector

    rec, _ = walls_short
    scene = make_scene(rec.scene)
    lidar = Lidar(EmbreeCaster(scene.mesh), LidarConfig())
    poses = [T @ rec.T_b_s for T in rec.ground_truth[1:13]]
    samples = [rec.detector_input(k + 1) for k in range(len(poses))]
    learned = LearnedDetector()

    def replay(detector):
        return [detector.predict(points, None, T) for points, T in zip(samples, poses)]

    def cascade(margin: float) -> RecastCascade:
        return RecastCascade(
            CascadeDetector(learned, ScanMCDetector(lidar.config, children=3), margin), lidar, stride=4
        )

    sure = cascade(0.0)  # never unsure: the classifier on the recorded samples
    assert all(np.array_equal(a.probabilities, b.probabilities) for a, b in zip(replay(sure), replay(learned)))
    assert sure.cascade.checked == 0 and sure.cascade.calls == len(poses)
    unsure = cascade(100.0)  # always unsure: the estimate on recast scans, once a block, as scanmc alone
    estimate = replay(RecastScans(make_detector("scanmc:3", lidar), lidar, stride=4))
    alone = replay(unsure)
    assert unsure.cascade.checked == len(poses) and unsure.judged_steps == 3 and all(p.known for p in alone)
    assert all(np.array_equal(a.probabilities, b.probabilities) for a, b in zip(alone, estimate))
    ahead = cascade(100.0)
    ahead.judge_ahead(samples, poses, scene, workers=2, progress=False)
    assert ahead.recast._ahead.keys() == {0, 4, 8}
    shared = replay(ahead)
    assert not ahead.recast._ahead and all(
        np.array_equal(a.probabilities, b.probabilities) for a, b in zip(alone, shared)
    )
    with pytest.raises(ValueError, match="true sensor pose"):
        unsure.predict(samples[0])


@pytest.mark.slow
def test_a_users_mesh_and_route_are_driven_and_replayed(cad_corridor, tmp_path, capsys):
    """A corridor exported as a CAD tool would (y up, millimetres) with its route in the same units."""
    from l3e_env.cli.main import main

    mesh, route = cad_corridor
    out = tmp_path / "ate"
    assert (
        main(
            [
                "ate",
                "--scene",
                str(mesh),
                "--route",
                str(route),
                "--up-axis",
                "y",
                "--scale",
                "0.001",
                "--detector",
                "eigen:30",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    first = json.loads((out / "results.json").read_text())["rows"]
    rec = DriveRecord.load(out / "recording.npz")
    assert rec.scene_params["up_axis"] == "y" and len(rec.ground_truth) > 50
    assert rec.ground_truth[-1][0, 3] > 7.0 and abs(rec.ground_truth[-1][1, 3]) < 0.3  # along the corridor
    again = run_ate(
        tmp_path / "again", "ignored", ["eigen:30"], AteOptions(recording=out / "recording.npz"), progress=False
    ).rows  # rebuilt from the recording's mesh path and parameters
    assert again[1].ate_m == first[1]["ate_m"]
    # the mesh moved: the recording names its old path, and takes the new one as the scene
    moved = mesh.rename(tmp_path / "moved.obj")
    replay = ["ate", "--recording", str(out / "recording.npz"), "--detector", "eigen:30", "--quiet"]
    assert main([*replay, "--out", str(tmp_path / "a")]) == 2
    assert "give its new path as the scene" in capsys.readouterr().err
    assert main([*replay, "--scene", str(moved), "--out", str(tmp_path / "b")]) == 0
    assert json.loads((tmp_path / "b" / "results.json").read_text())["rows"][1]["ate_m"] == first[1]["ate_m"]
    moved.write_text(moved.read_text() + "# edited\n")  # another mesh at that path
    assert main([*replay, "--scene", str(moved), "--out", str(tmp_path / "c")]) == 2
    assert "not the mesh this recording was made in" in capsys.readouterr().err


def test_detector_specs_and_errors():
    assert make_detector("none").name == "none"
    assert make_detector("eigen:110").tau == 110.0
    with pytest.raises(ValueError, match="eigen:<tau>"):
        make_detector("eigen:lots")
    with pytest.raises(ValueError, match="positive"):
        make_detector("eigen:-3")
    with pytest.raises(ValueError, match="unknown detector"):
        make_detector("magic")
    assert make_detector("dcreg:10").kappa == 10.0 and make_detector("dcreg:10").name == "dcreg:10"
    with pytest.raises(ValueError, match="dcreg:<kappa>"):
        make_detector("dcreg:")
    with pytest.raises(ValueError, match="exceed 1"):
        make_detector("dcreg:0.5")
    assert not DCRegDetector(10.0).predict(np.zeros((5, 3)), None).known
    with pytest.raises(ValueError, match="LiDAR"):
        make_detector("oracle")
    unknown = EigenvalueDetector(10.0).predict(np.zeros((5, 3)), None)
    assert not unknown.known and not unknown.mask.any()


@pytest.mark.parametrize("spec, message", [("eigen:lots", "eigen:<tau>"), ("learned:missing.pt", "no checkpoint")])
def test_a_bad_detector_fails_before_the_drive(spec, message, tmp_path, monkeypatch):
    def no_drive(*args, **kwargs):
        raise AssertionError("the route was driven before the detectors were checked")

    monkeypatch.setattr("l3e_env.experiments.ate.record_run", no_drive)
    with pytest.raises((ValueError, RuntimeError), match=message):  # what `l3e` reports as an error
        run_ate(tmp_path / "out", "primitives-1", ["none", spec], progress=False)
    assert not (tmp_path / "out").exists()


def test_a_tau_is_reported_only_when_it_is_as_good_as_the_reference_everywhere():
    from l3e_env.experiments.tau_sweep import beaten_everywhere

    results = {
        "tunnel": {"taus": [30.0, 110.0], "eigen_ate": [5.0, 1.0], "learned": 1.2},
        "field": {"taus": [30.0, 110.0], "eigen_ate": [0.5, 3.0], "learned": 0.6},
    }
    assert beaten_everywhere(results) == []
    results["field"]["eigen_ate"][1] = 0.6
    assert beaten_everywhere(results) == [110.0]


def test_detector_names_become_flat_file_names():
    assert file_stem("eigen:110") == "eigen_110"
    assert file_stem("learned:runs/a b/model.pt") == "learned_runs_a_b_model.pt"
    assert "/" not in file_stem("learned:/abs/path/model.pt")


def _row(name: str, ate: float, tunnel_pct: float | None = None) -> AteRow:
    return AteRow(name, ate, ate / 2, drift={"tunnel": {"m": tunnel_pct, "pct": tunnel_pct}})


def test_several_drives_summarised_per_detector_and_against_odometry_on_the_same_drive():
    runs = {
        3: [_row("odometry only", 2.0, 4.0), _row("learned", 1.0, 1.0)],
        4: [_row("odometry only", 4.0, 6.0), _row("learned", 3.0)],  # a drive that never entered the tunnel
        5: [_row("odometry only", 3.0, 5.0), _row("learned", 1.5, 2.0)],
    }
    odometry, learned = summarize_seeds(runs)
    assert learned["seeds"] == [3, 4, 5] and learned["ate_m"] == [1.0, 3.0, 1.5]
    assert learned["ate_mean_m"] == pytest.approx(11 / 6, abs=1e-3)
    assert learned["ate_std_m"] == pytest.approx(np.std([1.0, 3.0, 1.5], ddof=1), abs=1e-3)
    assert (learned["ate_min_m"], learned["ate_max_m"]) == (1.0, 3.0)
    assert learned["ate_over_odometry_mean"] == pytest.approx(np.mean([0.5, 0.75, 0.5]), abs=1e-3)
    assert odometry["ate_over_odometry_mean"] == 1.0 and odometry["ate_over_odometry_std"] == 0.0
    assert learned["ate_aligned_mean_m"] == pytest.approx(11 / 12, abs=1e-3)
    assert learned["drift_mean"]["tunnel"]["pct"] == 1.5 and odometry["drift_mean"]["tunnel"]["pct"] == 5.0
    table = format_seed_table([odometry, learned])
    assert "over 3 drives (seeds 3-5)" in table and "drift tunnel %" in table and table.endswith("1.5")
    runs[5] = [_row("odometry only", 3.0), _row("eigen:30", 1.5)]
    with pytest.raises(ValueError, match="same detectors"):
        summarize_seeds(runs)


@pytest.mark.slow
def test_ate_over_several_seeds_drives_each_and_writes_the_summary(tmp_path, capsys):
    from l3e_env.cli.main import main

    out = tmp_path / "ate"
    assert (
        main(
            [
                "ate",
                "--scene",
                "primitives-1",
                "--detector",
                "none",
                "--detector",
                "eigen:30",
                "--seed",
                "7",
                "--max-steps",
                "80",
                "--seeds",
                "2",
                "--quiet",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    summary = json.loads((out / "seeds.json").read_text())
    assert [r["detector"] for r in summary] == ["odometry only", "odometry + attitude", "none", "eigen:30"]
    first = json.loads((out / "seed-7" / "results.json").read_text())["rows"]
    second = json.loads((out / "seed-8" / "results.json").read_text())["rows"]
    assert summary[3]["ate_m"] == [first[3]["ate_m"], second[3]["ate_m"]] and first[3]["ate_m"] != second[3]["ate_m"]
    assert (out / "seeds.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "over 2 drives (seeds 7-8)" in capsys.readouterr().out
    assert main(["ate", "--recording", "r.npz", "--seeds", "2"]) == 2
    assert "a recording is one drive" in capsys.readouterr().err


def test_a_swept_recording_is_deskewed_by_its_odometry_and_gyro_before_it_is_fused():
    """The sensor sits 0.3 m above and 0.2 m ahead of the body, which walks and turns. The legs
    measure the step's translation exactly but its turn 50% high: deskewed with the gyro's turn,
    every point lies on the room's walls seen from its revolution's end; with the odometry's, the
    far walls are off."""
    from dataclasses import replace

    import trimesh

    from l3e_env.core.transforms import pose_to_matrix
    from l3e_env.experiments.drive import deskewed

    room = trimesh.creation.box(extents=(10.0, 6.0, 4.0))
    lidar = Lidar(EmbreeCaster(room), LidarConfig(range_noise_std=0.0))
    T_b_s = pose_to_matrix([0.2, 0.0, 0.3, 0.0, 0.0, 0.0])
    step = pose_to_matrix([0.1, 0.02, 0.0, 0.0, 0.0, 0.1])  # steady: the mean of two steps is the step
    truth = [pose_to_matrix([0.0, 0.0, -0.5, 0.0, 0.0, 0.0])]
    for _ in range(3):
        truth.append(truth[-1] @ step)
    scans = [lidar.scan(truth[0] @ T_b_s, start=truth[0] @ T_b_s).points]
    scans += [lidar.scan(T @ T_b_s, start=before @ T_b_s).points for before, T in zip(truth, truth[1:])]
    odometry = np.array([pose_to_matrix([0.1, 0.02, 0.0, 0.0, 0.0, 0.15]) for _ in range(3)])
    rec = DriveRecord("box", "vlp16", 0, T_b_s, np.array(truth), odometry, scans, scans, sweep=True)

    def off_the_walls(recording: DriveRecord) -> list[float]:
        worst = []
        for T, points in zip(truth, recording.scans):
            world = points.astype(np.float64) @ (T @ T_b_s)[:3, :3].T + (T @ T_b_s)[:3, 3]
            worst.append(np.abs(np.abs(world) - [5.0, 3.0, 2.0]).min(axis=1).max())
        return worst

    straight = deskewed(rec)
    assert max(off_the_walls(straight)) < 2e-3
    assert min(off_the_walls(deskewed(rec, "odometry"))[1:]) > 0.05  # the legs' turn is 0.05 rad too much
    assert np.abs(straight.scans[2] - rec.scans[2]).max() > 0.1  # the motion was taken out
    np.testing.assert_array_equal(straight.samples[2], straight.scans[2])  # the samples alike
    with pytest.raises(ValueError, match="deskewing source"):
        deskewed(rec, "lidar")
    still = replace(rec, sweep=False)
    assert deskewed(still) is still  # a recording taken at one pose a revolution is fused as it is


@pytest.mark.slow
def test_a_recording_is_saved_whole_and_a_damaged_one_is_named(walls_short, tmp_path, capsys, monkeypatch):
    from l3e_env.cli.main import main
    from l3e_env.experiments.drive import DriveRecordError

    rec, _ = walls_short
    rec.save(tmp_path / "rec.npz")
    whole = (tmp_path / "rec.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(DriveRecordError, match="cut.npz cannot be read as a recording"):
        DriveRecord.load(tmp_path / "cut.npz")
    assert main(["ate", "--recording", str(tmp_path / "cut.npz"), "--quiet", "--out", str(tmp_path / "o")]) == 2
    assert "cut.npz cannot be read as a recording" in capsys.readouterr().err
    with pytest.raises(DriveRecordError, match="missing.npz"):
        DriveRecord.load(tmp_path / "missing.npz")

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # the run is stopped while the file is written

    monkeypatch.setattr(np, "savez", killed)
    with pytest.raises(KeyboardInterrupt):
        rec.save(tmp_path / "rec.npz")
    assert (tmp_path / "rec.npz").read_bytes() == whole and not list(tmp_path.glob("*.tmp"))


def test_the_drift_of_each_region_is_its_own_and_the_table_shows_it():
    from l3e_env.core.transforms import pose_to_matrix
    from l3e_env.experiments.ate_tables import format_table, region_drift, regions_inside
    from scenes import make_scene

    mine = make_scene("mine")
    xs = np.arange(-20.0, 40.0, 0.5)  # 20 m of yard, 40 m of tunnel, no quarry
    gt = np.stack([pose_to_matrix(np.array([x, 0, 0, 0, 0, 0])) for x in xs])
    est = gt.copy()
    est[:, 0, 3] -= 0.05 * np.clip(np.arange(len(xs)) - 40, 0, None)  # 5 cm short a step once in the tunnel
    drift = region_drift(est, gt, regions_inside(gt, mine))
    yard, tunnel, quarry = (drift[g] for g in ("yard", "tunnel", "quarry"))
    assert yard["m"] == pytest.approx(0.0, abs=1e-9) and tunnel["m"] == pytest.approx(3.9)
    assert tunnel["pct"] == pytest.approx(100 * 3.9 / 39.0)  # x = 0 is the yard's, the tunnel's from 0.5
    assert quarry["m"] is None and quarry["pct"] is None
    row = AteRow("none", 1.0, None, 0.1, 0.1, dict.fromkeys(AXES, 0.0), 1.0, drift=drift)
    table = format_table([row])
    assert "drift tunnel" in table and "3.90 m  10.0%" in table and table.splitlines()[-1].endswith("-")


@pytest.mark.parametrize(
    ("field", "value", "says"), [("taus", -5.0, "taus: .*positive"), ("kappas", 0.5, "kappas: .*exceed 1")]
)
def test_a_sweeps_threshold_its_test_cannot_take_is_named_before_a_drive(tmp_path, monkeypatch, field, value, says):
    from l3e_env.experiments import tau_sweep

    monkeypatch.setattr(
        tau_sweep, "record_run", lambda *a, **k: pytest.fail("driven before the thresholds were checked")
    )
    with pytest.raises(ValueError, match=says):
        tau_sweep.run_sweep(tmp_path, ["tunnel-0"], tau_sweep.SweepOptions(**{field: (10.0, value)}), progress=False)
