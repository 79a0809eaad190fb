"""The per-step pipeline's parts on their own: the scan registrar, the detect-and-fuse step, and the
environment's online fusion."""

from __future__ import annotations

import numpy as np
import pytest

from fusion import FusionConfig
from fusion.ground import HOLDS_STEPS
from l3e_env.config import FusionSettings, LidarConfig, OdometryConfig
from l3e_env.core.transforms import inverse, matrix_to_pose, pose_to_matrix
from l3e_env.detection.detectors import NoDetector, Prediction
from l3e_env.detection.pipeline import Keyframes, LocalizationPipeline, OnlineFusion, ScanRegistrar
from l3e_env.localizability.registration import RegistrationConfig, RegistrationResult
from l3e_env.sim.imu import ATTITUDE_EVERY
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


@pytest.fixture(scope="module")
def office():
    scene = make_scene("office-0")
    return Lidar(EmbreeCaster(scene.mesh, threads=1), LidarConfig())


def _at(x: float, yaw: float = 0.3) -> np.ndarray:
    return pose_to_matrix(np.array([5.0 + x, 0.0, 0.85, 0.0, 0.0, yaw]))


class _MaskAll:
    name = "mask-all"

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        return Prediction(np.ones(6), np.ones(6, dtype=bool))


class _Broken:
    name = "broken"

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        raise RuntimeError("a detector bug")


def test_the_registrar_registers_each_scan_to_the_last_and_skips_a_scan_too_small(office):
    rng = np.random.default_rng(0)
    registrar = ScanRegistrar(RegistrationConfig(), threads=1)
    registrar.start(office.scan(_at(0.0), rng).points)
    step = registrar.next(office.scan(_at(0.1), rng).points)
    assert step is not None and step.converged
    # the new scan (source) in the last one's frame: the sensor, yawed 0.3 rad, moved 0.1 m along world x
    moved = matrix_to_pose(step.T_target_source)
    assert moved[:3] == pytest.approx([0.1 * np.cos(0.3), -0.1 * np.sin(0.3), 0.0], abs=0.02)
    assert registrar.next(np.zeros((10, 3))) is None  # too few points: no registration ...
    assert registrar.next(office.scan(_at(0.2), rng).points) is None  # ... and no target for the next
    assert registrar.next(office.scan(_at(0.3), rng).points) is not None  # then it goes on


def test_with_keyframes_each_scan_registers_onto_the_keyframe_until_it_has_moved_far_enough(office):
    rng = np.random.default_rng(0)
    registrar = ScanRegistrar(RegistrationConfig(), threads=1, keyframes=Keyframes(distance=0.45))
    registrar.start(office.scan(_at(0.0), rng).points)
    step = inverse(_at(0.0)) @ _at(0.1)  # the sensor's motion from one scan to the next
    biased = step @ pose_to_matrix(np.array([0.01, -0.005, 0.0, 0.0, 0.0, 0.004]))  # the legs' guess, off
    spans = []
    for k in range(1, 8):
        result = registrar.next(office.scan(_at(0.1 * k), rng).points, biased)
        assert result is not None and result.converged
        spans.append(result.span)
        true = inverse(_at(0.1 * (k - result.span))) @ _at(0.1 * k)  # from the keyframe's pose
        error = matrix_to_pose(inverse(true) @ result.T_target_source)
        assert np.abs(error[:3]).max() < 0.02 and np.abs(error[3:]).max() < np.radians(0.3)
    assert spans == [1, 2, 3, 4, 5, 1, 2]  # renewed once 0.5 m from the keyframe (at least 0.45)
    # a registration 0.1 m from the guess (the legs far off, or a slide) is kept, and renews the keyframe
    off = step @ pose_to_matrix(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]))
    assert registrar.next(office.scan(_at(0.8), rng).points, off).span == 3
    assert registrar.next(office.scan(_at(0.9), rng).points, step).span == 1
    assert registrar.next(office.scan(_at(1.0), rng).points, step).span == 2
    registrar.keyframe_here()  # where the detector flags the scan: it becomes the keyframe
    assert registrar.next(office.scan(_at(1.1), rng).points, step).span == 1
    with pytest.raises(ValueError, match="at least 1 step"):
        Keyframes(distance=1.0, steps=0)


def test_a_keyframes_ground_plane_comes_with_the_registration_that_made_it_one(office):
    rng = np.random.default_rng(0)
    registrar = ScanRegistrar(RegistrationConfig(), threads=1, keyframes=Keyframes(distance=0.45))
    registrar.start(office.scan(_at(0.0), rng).points)
    level = np.array([0.0, 0.0, 1.0, -0.85])  # the office's floor under the level sensor, 0.85 m up
    assert registrar.ground == pytest.approx(level, abs=0.005)
    step = inverse(_at(0.0)) @ _at(0.1)
    made = []
    for k in range(1, 8):
        result = registrar.next(office.scan(_at(0.1 * k), rng).points, step)
        assert result is not None
        made.append(result.ground is not None)
        if result.ground is not None:
            assert result.ground == pytest.approx(level, abs=0.005)
    assert made == [False, False, False, False, True, False, False]  # the 5th became the keyframe
    assert registrar.keyframe_here() == pytest.approx(level, abs=0.005)
    assert registrar.keyframe_here() is None  # already the keyframe: nothing new
    points = office.scan(_at(0.0), rng).points
    registrar.start(points)
    assert registrar.first_ground(points) is registrar.ground
    assert registrar.target is not None
    registrar.target.ground = None  # a floor the keyframe's fit refuses (furniture among its candidates)
    assert registrar.first_ground(points) == pytest.approx(level, abs=0.01)  # the search that levels scans


def test_the_pipeline_takes_the_ground_where_its_settings_say_and_refuses_it_on_the_filter(office):
    odometry = OdometryConfig()
    level = np.array([0.0, 0.0, 1.0, -0.85])
    sensor_up = pose_to_matrix(np.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.0]))  # the sensor 0.3 m above the body
    T_w_b = pose_to_matrix(np.array([0.0, 0.0, 0.55, 0.0, 0.0, 0.0]))
    for ground, patches in (("plane", 1), ("none", 0)):
        pipeline = LocalizationPipeline(NoDetector(), "graph", FusionConfig(), odometry, sensor_up, ground=ground)
        pipeline.start(T_w_b, level)
        assert pipeline.backend.ground.index + 1 == patches
    walked = LocalizationPipeline(NoDetector(), "graph", FusionConfig(), odometry, sensor_up, ground="plane")
    walked.start(T_w_b, level)
    up = pose_to_matrix(np.array([0.1, 0.0, 0.05, 0.0, 0.0, 0.0]))  # the legs say 5 cm up; the ground says level
    for _ in range(3):
        out = walked.step(
            up,
            RegistrationResult(np.eye(4), np.full((6, 6), np.nan), False, 0, 0, 0, 0.0, ground=level),
            np.zeros((0, 3)),
            None,
        )
    assert out.T_w_b[2, 3] < 0.55 + 0.05  # held near its patch, not 15 cm up
    # the IMU's readings weigh as correlated while a ground patch holds the pose, as independent where none does
    factor = np.sqrt((1 + np.exp(-1 / 30)) / (1 - np.exp(-1 / 30)))
    for ground, start_ground, weighed in (("plane", level, factor), ("plane", None, 1.0), ("none", level, 1.0)):
        imu = LocalizationPipeline(NoDetector(), "graph", FusionConfig(), odometry, sensor_up, "tilt", ground=ground)
        imu.start(T_w_b, start_ground)
        assert imu.attitude_sigmas is not None
        assert imu.attitude_weights()[0] == pytest.approx(weighed * imu.attitude_sigmas[0])
    imu = LocalizationPipeline(NoDetector(), "graph", FusionConfig(), odometry, sensor_up, "tilt", ground="plane")
    imu.start(T_w_b, level)
    for _ in range(HOLDS_STEPS + 1):  # the patch unseen for longer: independent again
        imu.backend.add_step(up, np.full(6, 0.01))
    assert imu.attitude_sigmas is not None
    assert imu.attitude_weights()[0] == pytest.approx(imu.attitude_sigmas[0])
    with pytest.raises(ValueError, match="graph backend"):
        LocalizationPipeline(NoDetector(), "ekf", FusionConfig(), odometry, sensor_up, ground="plane")
    with pytest.raises(ValueError, match="ground 'plane'.*EKF"):
        FusionSettings(backend="ekf", ground="plane")
    assert FusionSettings().ground == "plane" and FusionSettings(backend="ekf").ground == "none"


def test_a_keyframes_factor_ties_the_new_pose_to_the_keyframes_pose():
    odometry = OdometryConfig()
    step = pose_to_matrix(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]))
    short = pose_to_matrix(np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]))  # what the legs read: half the step
    pipeline = LocalizationPipeline(NoDetector(), "graph", FusionConfig(), odometry, np.eye(4))
    pipeline.start(np.eye(4))
    for _ in range(3):
        pipeline.step(short, None, np.zeros((0, 3)), None)
    icp = RegistrationResult(np.linalg.matrix_power(step, 3), 1e6 * np.eye(6), True, 3, 900, 1000, 0.0, span=3)
    out = pipeline.step(short, icp, np.zeros((0, 3)), None)
    # pose 4 held 0.3 m ahead of pose 1 by the stiff factor, against the legs' 0.05 m a step
    trajectory = pipeline.trajectory()
    assert out.icp_used and (inverse(trajectory[1]) @ trajectory[4])[0, 3] == pytest.approx(0.3, abs=1e-3)
    with pytest.raises(ValueError, match="spans 1 to 5 steps"):
        pipeline.step(
            step, RegistrationResult(step, np.eye(6), True, 3, 900, 1000, 0.0, span=9), np.zeros((0, 3)), None
        )
    ekf = LocalizationPipeline(NoDetector(), "ekf", FusionConfig(), odometry, np.eye(4))
    ekf.start(np.eye(4))
    with pytest.raises(ValueError, match="need the graph backend"):
        ekf.step(step, icp, np.zeros((0, 3)), None)
    with pytest.raises(ValueError, match="use backend graph"):
        FusionSettings(backend="ekf", keyframe_distance=4.0)
    with pytest.raises(ValueError, match="at least 0"):
        FusionSettings(keyframe_distance=-1.0)


def test_a_step_fuses_odometry_alone_where_every_axis_is_masked_and_counts_a_failing_detector():
    odometry = OdometryConfig()
    step = pose_to_matrix(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.02]))
    pipeline = LocalizationPipeline(_MaskAll(), "graph", FusionConfig(), odometry, np.eye(4))
    with pytest.raises(RuntimeError, match="call start"):
        pipeline.step(step, None, np.zeros((0, 3)), None)
    pipeline.start(np.eye(4))
    for _ in range(5):
        out = pipeline.step(step, None, np.zeros((0, 3)), None)
    assert not out.icp_used and not out.detector_failed and out.prediction.mask.all()
    assert out.T_w_b == pytest.approx(np.linalg.matrix_power(step, 5), abs=1e-6)  # dead reckoning
    assert pipeline.trajectory().shape == (6, 4, 4)
    broken = LocalizationPipeline(_Broken(), "ekf", FusionConfig(), odometry, np.eye(4))
    broken.start(np.eye(4))
    failed = broken.step(step, None, np.zeros((0, 3)), None)
    assert failed.detector_failed and not failed.prediction.known
    tilted = LocalizationPipeline(NoDetector(), "graph", FusionConfig(), odometry, np.eye(4), attitude="tilt")
    tilted.start(np.eye(4))
    with pytest.raises(ValueError, match="every step needs the IMU's attitude"):
        for _ in range(ATTITUDE_EVERY):
            tilted.step(step, None, np.zeros((0, 3)), None)


def test_the_online_fusion_follows_a_drive_and_counts_what_it_did(office):
    rng = np.random.default_rng(1)
    fusion = OnlineFusion(FusionSettings(enabled=True, detector="eigen:30"), office, OdometryConfig(), np.eye(4))
    truth = [_at(0.1 * k) for k in range(8)]
    info = fusion.reset(truth[0], office.scan(truth[0], rng).points)
    assert info["running_ate"] == 0.0 and not info["localizability_known"]
    for k in range(1, len(truth)):
        step = inverse(truth[k - 1]) @ truth[k]  # perfect odometry: the estimate must stay on the truth
        info = fusion.step(step, office.scan(truth[k], rng).points, truth[k])
    assert np.linalg.norm(info["fused_T_w_b"][:3, 3] - truth[-1][:3, 3]) < 0.05
    assert info["running_ate"] < 0.05 and info["localizability_known"]
    assert info["fusion_counts"] == {"icp_failed": 0, "unknown": 0, "detector_errors": 0, "fallbacks": 0}
    assert fusion.detector.name == "eigen:30" and fusion.registration == RegistrationConfig()
    fusion.close()


class _FlagsFromStep:
    """Flags x from scan `flip` on (read off the scan's one point), counting its calls."""

    name = "flags-from-step"

    def __init__(self, flip: int) -> None:
        self.flip, self.calls = flip, []

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        k = int(points[0, 0])
        self.calls.append(k)
        mask = np.zeros(6, dtype=bool)
        mask[0] = k >= self.flip
        return Prediction(mask.astype(float), mask)


@pytest.mark.parametrize("every", [1, 3, 4])
def test_a_detector_judging_every_kth_scan_holds_its_answer_and_is_late_by_at_most_k_minus_1(every):
    step = pose_to_matrix(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]))
    detector = _FlagsFromStep(flip=7)
    pipeline = LocalizationPipeline(
        detector, "graph", FusionConfig(), OdometryConfig(), np.eye(4), detector_every=every
    )
    pipeline.start(np.eye(4))
    flagged = [bool(pipeline.step(step, None, np.full((1, 3), float(k)), None).prediction.mask[0]) for k in range(20)]
    assert detector.calls == list(range(0, 20, every))  # the first scan and every k-th after it
    first = flagged.index(True)
    assert 7 <= first <= 7 + every - 1 and all(flagged[first:])  # late by at most k - 1 steps, then held
    pipeline.start(np.eye(4))  # a new drive judges its first scan again
    pipeline.step(step, None, np.full((1, 3), 3.0), None)
    assert detector.calls[-1] == 3
    with pytest.raises(ValueError, match="detector_every is a whole number of steps from 1 to 100"):
        FusionSettings(detector_every=0)
    with pytest.raises(ValueError, match="detector_every >= 1"):
        LocalizationPipeline(detector, "graph", FusionConfig(), OdometryConfig(), np.eye(4), detector_every=0)
