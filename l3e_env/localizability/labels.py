"""Monte-Carlo localizability labels (L3E, Sec. IV-A): parent poses near sampling paths,
children perturbed around them, each child ray-cast anew and registered to its parent."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from l3e_env.core.transforms import conjugate, inverse, level_rotation_of, matrix_to_pose, pose_to_matrix
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import RayCaster

if TYPE_CHECKING:  # scenes (trimesh) loads slowly: judging a scan needs none
    from scenes import Scene

# the labels' settings and the protocol live with the configuration (a model and a dataset read them
# without the simulation); named here too, where the labels are made
from l3e_env.config.labelling import AXES as AXES
from l3e_env.config.labelling import LABEL_PROTOCOL as LABEL_PROTOCOL
from l3e_env.config.labelling import PROTOCOLS as PROTOCOLS
from l3e_env.config.labelling import LabelConfig
from l3e_env.config.labelling import protocol_name as protocol_name

from .registration import PreparedTarget, RegistrationConfig, RegistrationError, prepare_source, register


@dataclass
class ParentLabel:
    T_w_s: np.ndarray  # parent sensor pose
    points: np.ndarray  # parent scan, sensor frame
    errors: np.ndarray  # (6,) mean absolute registration error, metres and radians
    labels: np.ndarray  # (6,) uint8, 1 = not localizable
    children_failed: int  # children that could not be registered (too few points)
    children_not_converged: int
    extra: dict = field(default_factory=dict)


class SamplingError(RuntimeError):
    """No valid parent pose could be sampled in a scene."""


def sample_parent_pose(scene: Scene, caster: RayCaster, rng: np.random.Generator, config: LabelConfig) -> np.ndarray:
    """A collision-free sensor pose near a random point of the scene's sampling paths."""
    if not scene.sampling_paths:
        raise SamplingError(f"scene '{scene.name}' has no sampling paths: cannot sample parent poses")
    paths = scene.sampling_paths
    lengths = np.array([np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in paths])
    sigma = config.sigma_vector("parent")
    probe = _probe_directions()
    for _ in range(config.max_tries):
        path = paths[rng.choice(len(paths), p=lengths / lengths.sum())]
        seg = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
        s = rng.uniform(0, seg[-1])
        ground = np.array([np.interp(s, seg, path[:, i]) for i in range(3)])
        mean = np.concatenate([ground + (0, 0, config.sensor_height), np.zeros(3)])
        if config.heading == "path":
            k = min(int(np.searchsorted(seg, s, side="right")) - 1, len(path) - 2)
            dx, dy = path[k + 1, :2] - path[k, :2]
            mean[5] = np.arctan2(dy, dx) + rng.integers(4) * np.pi / 2
        elif config.heading != "free":
            raise SamplingError(f"parent heading '{config.heading}': use 'free' or 'path'")
        pose = mean + rng.normal(0, 1, 6) * sigma
        T = pose_to_matrix(pose)
        d = caster.cast(T[:3, 3], probe, 3.0 + config.sensor_height)
        if np.min(d[:-1]) > config.clearance and np.isfinite(d[-1]):
            return T
    raise SamplingError(f"no collision-free parent pose in {config.max_tries} tries in scene '{scene.name}'")


def _probe_directions() -> np.ndarray:
    """26 directions for the clearance check, the last one straight down (ground must exist)."""
    g = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    g = g[np.abs(g).sum(1) > 0]
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    return np.vstack([g, [[0, 0, -1]]]).astype(np.float32)


def registration_error(
    T_est: np.ndarray, T_true: np.ndarray, frame: str = "parent", R_l_s: np.ndarray | None = None
) -> np.ndarray:
    """|gamma| of the error transform, (x, y, z, roll, pitch, yaw), absolute values; with `R_l_s`
    (the parent's level rotation, `level_rotation`) written in the parent's level frame."""
    E = T_est @ inverse(T_true) if frame == "parent" else inverse(T_est) @ T_true
    if R_l_s is not None:
        E = conjugate(E, R_l_s)
    return np.abs(matrix_to_pose(E))


def child_offset(rng: np.random.Generator, sigma: np.ndarray, R_l_s: np.ndarray) -> np.ndarray:
    """T_p_c: a child's pose in its parent's sensor frame, drawn with `sigma` along the axes of the
    parent's level frame (so that a tilted parent's children move as a level one's do)."""
    return conjugate(pose_to_matrix(rng.normal(0, 1, 6) * sigma), R_l_s.T)


def label_parent(
    lidar: Lidar,
    T_w_p: np.ndarray,
    rng: np.random.Generator,
    config: LabelConfig,
    registration: RegistrationConfig,
) -> ParentLabel:
    """Scan at the parent pose, then M children: perturb, ray-cast anew, register from identity.
    Children are drawn and errors written in the parent's level frame (the world's z is up).

    Raises RegistrationError if the parent scan itself is unusable. A child whose scan cannot be
    registered is counted and left out of the mean; more than half failing raises.
    """
    parent = lidar.scan(T_w_p, rng)
    target = PreparedTarget(parent.points, registration)
    sigma, R_l_s = config.sigma_vector("child"), level_rotation_of(T_w_p)
    errors, failed, not_converged = [], 0, 0
    for _ in range(config.children):
        T_p_c = child_offset(rng, sigma, R_l_s)
        child = lidar.scan(T_w_p @ T_p_c, rng)
        try:
            result = register(prepare_source(child.points, registration), target, registration, with_hessian=False)
        except RegistrationError:
            failed += 1
            continue
        not_converged += not result.converged
        errors.append(registration_error(result.T_target_source, T_p_c, config.error_frame, R_l_s))
    if failed > config.children // 2:
        raise RegistrationError(f"{failed} of {config.children} child scans could not be registered")
    e = np.mean(errors, axis=0)
    labels = (e > config.threshold_vector()).astype(np.uint8)
    return ParentLabel(T_w_p, parent.points, e, labels, failed, not_converged)
