"""Detectors adapted to a recorded drive: the scan estimate and the cascade re-cast at the drive's
poses (`RecastScans`, `RecastCascade`), and the IMU's attitude as a row (`OdometryAttitude`)."""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from l3e_env.config import LidarConfig
from l3e_env.core.workers import ordered_map
from l3e_env.detection.detectors import (
    UNKNOWN,
    CascadeDetector,
    Prediction,
    ScanMCDetector,
)
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import Scene


class RecastScans:
    """The scan estimate (scanmc), in a replay. It meshes every return of a revolution, and a
    recording keeps thinned scans, so the scan is cast again from the scene at the recorded true
    sensor pose: the same scene, sensor and pose, another draw of the range noise and dropout. It
    is judged every `stride` steps and held between, as the oracle is, since a judgement costs up
    to M registrations (about 2 s at M = 60). Each judged step draws its scan and children from its
    own seed, so `judge_ahead` can judge a whole route in several processes first."""

    def __init__(self, detector: ScanMCDetector, lidar: Lidar, stride: int = 5, seed: int = 0):
        if stride < 1:
            raise ValueError(f"a detector is judged every stride >= 1 steps, got {stride}")
        self.detector, self.lidar, self.stride, self.seed = detector, lidar, stride, seed
        self.name = detector.name
        self._calls, self._last = 0, UNKNOWN
        self._ahead: dict[int, Prediction] = {}

    def judge_step(self, step: int, T_w_s: np.ndarray) -> Prediction:
        scan = self.lidar.scan(T_w_s, np.random.default_rng([self.seed, 2, step]))
        return self.detector.judge(scan.points, np.random.default_rng([self.seed, 3, step]), T_w_s)

    def judgement(self, step: int, T_w_s: np.ndarray) -> Prediction:
        """The step's judgement: the one made ahead, or made now."""
        return self._ahead.pop(step, None) or self.judge_step(step, T_w_s)

    def judge_ahead(
        self, poses: list[np.ndarray], scene: Scene, workers: int, progress: bool = True, steps: list[int] | None = None
    ) -> None:
        """Judge the steps that `predict` will be asked for (every `stride`-th, or `steps`), T_w_s of
        call k being poses[k]."""
        steps = list(range(0, len(poses), self.stride)) if steps is None else steps
        jobs = [(k, poses[k]) for k in steps]
        judged = list(
            tqdm(
                ordered_map(_judge_recast_step, jobs, self, _recast_on, (self, scene.mesh), workers),
                total=len(jobs),
                disable=not progress,
                desc=f"judging with {self.name} ({workers} workers)",
                unit="scan",
            )
        )
        self._ahead = dict(zip(steps, judged))

    def __getstate__(self) -> dict:  # a worker gets the settings, and casts against its own scene
        return {**self.__dict__, "lidar": self.lidar.config, "_ahead": {}}

    def predict(self, points: np.ndarray, registration=None, T_w_s: np.ndarray | None = None) -> Prediction:
        if T_w_s is None:
            raise ValueError(f"{self.name} in a replay casts the scan again at the true sensor pose: give T_w_s")
        try:
            if self._calls % self.stride == 0:
                self._last = UNKNOWN  # a judgement that raises is not held over the next steps
                self._last = self.judgement(self._calls, T_w_s)
            return self._last
        finally:
            self._calls += 1


class RecastCascade:
    """learned+scanmc in a replay: the classifier reads the recorded samples, and where it is unsure
    the estimate judges the scan cast again at the true pose (RecastScans). At most one judgement
    per `stride` steps, as the estimate alone has: the first unsure step of each block of `stride`
    steps is judged, and its judgement serves the block's later unsure steps."""

    def __init__(self, cascade: CascadeDetector, lidar: Lidar, stride: int = 5, seed: int = 0):
        self.cascade, self.recast = cascade, RecastScans(cascade.scan_mc, lidar, stride, seed)
        self.name = cascade.name
        self._calls = 0
        self._held: dict[int, Prediction] = {}
        self._classified: dict[int, tuple[Prediction, bool]] = {}  # by judge_ahead, for predict to take

    def predict(self, points: np.ndarray, registration=None, T_w_s: np.ndarray | None = None) -> Prediction:
        if T_w_s is None:
            raise ValueError(f"{self.name} in a replay casts the scan again at the true sensor pose: give T_w_s")
        step, self._calls = self._calls, self._calls + 1
        self.cascade.calls += 1
        classified = self._classified.pop(step, None)
        first, unsure = classified if classified is not None else self.cascade.classify(points, T_w_s)
        if not unsure:
            return first
        self.cascade.checked += 1
        block = step // self.recast.stride
        if block not in self._held:
            self._held[block] = self.recast.judgement(step, T_w_s)
        return self._held[block]

    @property
    def judged_steps(self) -> int:
        """Scans the estimate has judged (one per block with an unsure step)."""
        return len(self._held)

    def judge_ahead(
        self, samples: list[np.ndarray], poses: list[np.ndarray], scene: Scene, workers: int, progress: bool = True
    ) -> None:
        """Judge the steps that `predict` will ask the estimate for, the samples and T_w_s of call k
        being samples[k] and poses[k]."""
        self._classified = {k: self.cascade.classify(points, T) for k, (points, T) in enumerate(zip(samples, poses))}
        first_unsure: dict[int, int] = {}
        for k, (_, unsure) in self._classified.items():
            if unsure:
                first_unsure.setdefault(k // self.recast.stride, k)
        self.recast.judge_ahead(poses, scene, workers, progress, steps=list(first_unsure.values()))


def _recast_on(recast: RecastScans, mesh) -> RecastScans:
    """A worker's own copy, with a LiDAR on its own copy of the scene."""
    config = recast.lidar if isinstance(recast.lidar, LidarConfig) else recast.lidar.config  # pickled as its config
    recast.lidar = Lidar(EmbreeCaster(mesh, threads=1), config)
    return recast


def _judge_recast_step(recast: RecastScans, job: tuple[int, np.ndarray]) -> Prediction:
    return recast.judge_step(*job)


class OdometryAttitude:
    """The odometry fused with the IMU's attitude alone: every ICP axis masked and the scans' ground
    left out (`reads_scans`), for the reference row against which the detectors' rows show what the
    scans add to the IMU."""

    name = "odometry + attitude"
    reads_scans = False  # fuse_recording: no ground planes from the scans either

    def predict(self, points: np.ndarray, registration=None, T_w_s: np.ndarray | None = None) -> Prediction:
        return Prediction(np.ones(6), np.ones(6, dtype=bool))
