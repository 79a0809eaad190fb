"""Scan-to-scan point-to-plane ICP (small_gicp), returning the 6x6 Hessian in project order.

One registration everywhere: the ICP that labels the training data is the ICP the fusion runs
between consecutive scans, built from the same `RegistrationConfig`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import small_gicp
from numba import njit

from l3e_env.config.labelling import RegistrationConfig
from l3e_env.core.normals import neighbourhood_normals
from l3e_env.core.transforms import adjoint, inverse, rotation_pose

# small_gicp's tangent order is (rx, ry, rz, tx, ty, tz); the project's is (x, y, z, roll, pitch, yaw).
TO_PROJECT_ORDER = np.array([3, 4, 5, 0, 1, 2])


class RegistrationError(ValueError):
    """Input that registration cannot use (too few or non-finite points)."""


@dataclass
class RegistrationResult:
    T_target_source: np.ndarray  # 4x4, maps source points into the target frame
    hessian: np.ndarray  # 6x6 Gauss-Newton A^T A at the solution, (x, y, z, roll, pitch, yaw); NaN if not asked
    converged: bool
    iterations: int
    num_inliers: int
    num_source: int
    error: float
    # steps from the target scan to the source scan: 1 where consecutive scans were registered, more
    # where a registrar registers each scan onto a keyframe (detection.pipeline.ScanRegistrar)
    span: int = 1
    # the source scan's ground plane (n, d; n . p = d in its sensor frame), where a registrar prepared
    # the source as its next target (a keyframe) and found one (detection.pipeline.ScanRegistrar)
    ground: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.converged

    def in_frame(self, T_b_s: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The registered step and its Hessian seen in frame b, T_b_s the sensor's mounting (what
        the fusion's body-frame ICP factor takes), or None where the registration did not converge."""
        if not self.converged:
            return None
        return T_b_s @ self.T_target_source @ inverse(T_b_s), hessian_in_frame(self.hessian, T_b_s)


def _checked(points: np.ndarray, what: str, min_points: int) -> np.ndarray:
    """The points as float64, or a RegistrationError naming the problem (checked before small_gicp,
    which only prints a warning for an empty cloud)."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise RegistrationError(f"{what} must be an (N, 3) array, got shape {pts.shape}")
    if len(pts) < min_points:
        raise RegistrationError(f"{what} has {len(pts)} points (minimum {min_points})")
    if not np.isfinite(pts).all():
        raise RegistrationError(f"{what} contains NaN or infinite points")
    return pts.astype(np.float64, copy=False)


GROUND_BAND = 0.05  # m: voxels this close to the fitted ground plane are the ground's
GROUND_TILT = np.cos(np.radians(30.0))  # a ground candidate's own normal lies within 30 deg of the sensor's z
GROUND_BELOW = 0.3  # m: and it lies this far below the sensor at least


GROUND_FLAT = 0.85  # the share of ground candidates that the plane must hold: less is a curved floor


def ground_plane(points: np.ndarray, normals: np.ndarray) -> np.ndarray | None:
    """The plane n.p = d (as (n, d), n pointing up the sensor's z) of the ground under the sensor,
    fitted by least squares to the voxels below it whose own normals are near vertical and refitted
    three times to those within GROUND_BAND of it; None where too few voxels are ground."""
    low = points[(np.abs(normals[:, 2]) > GROUND_TILT) & (points[:, 2] < -GROUND_BELOW)]
    if len(low) < 30:
        return None
    plane = _fit_ground(low)
    if plane is None:
        return None
    return plane if np.mean(np.abs(low @ plane[:3] - plane[3]) < GROUND_BAND) >= GROUND_FLAT else None


def ground_voxels(points: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Which voxels lie on the ground plane (n, d)."""
    return np.abs(points @ plane[:3] - plane[3]) < GROUND_BAND


def _fit_ground(low: np.ndarray) -> np.ndarray | None:
    fit = low[np.abs(low[:, 2] - np.median(low[:, 2])) < 4 * GROUND_BAND]
    for _ in range(3):
        if len(fit) < 30:
            return None
        a, b, c = np.linalg.lstsq(np.c_[fit[:, :2], np.ones(len(fit))], fit[:, 2], rcond=None)[0]
        fit = low[np.abs(low[:, 2] - low[:, :2] @ (a, b) - c) < GROUND_BAND]
    n = np.array([-a, -b, 1.0]) / np.sqrt(a * a + b * b + 1.0)
    return np.r_[n, c * n[2]]


class PreparedTarget:
    """A target scan downsampled, with normals and a k-d tree: prepared once, matched many times.
    `threads` (the normals' neighbour search) changes the speed, not the result: registrations onto
    it are the same to the bit. With `config.ground_normals` the ground's voxels take the ground plane's
    normal (`normals`), and the other voxels' normals (from their `num_neighbors` nearest, as
    small_gicp estimates them) are computed when first matched (`normals_at`): the neighbour search
    was most of a step's registration cost, and a registration matches a fifth of the voxels; the
    ground plane needs the normals of the voxels below the sensor only."""

    def __init__(self, points: np.ndarray, config: RegistrationConfig, threads: int = 1):
        pts = _checked(points, "target scan", config.min_points)
        self.config, self.threads = config, max(1, int(threads))
        # preprocess_points thins with small_gicp's OpenMP voxel grid (which keeps a voxel whose points
        # straddle two of its blocks as two part means; the labels were made on it) and builds the
        # k-d tree; with the ground's normals, asked for one neighbour's, it spends next to nothing on
        # normals, which are computed where matched (normals_at). On one thread: on more, its voxel
        # grid's part means vary from run to run with the threads' timing (small_gicp's own note)
        neighbours = 1 if config.ground_normals else config.num_neighbors
        self.cloud, self.tree = small_gicp.preprocess_points(pts, config.downsampling_resolution, neighbours)
        if self.cloud.size() < config.min_points:
            raise RegistrationError(
                f"target scan has {self.cloud.size()} points after {config.downsampling_resolution} m downsampling "
                f"(minimum {config.min_points})"
            )
        self.points = np.ascontiguousarray(np.asarray(self.cloud.points())[:, :3])
        self.ground = None  # the plane (n, d) whose normal the ground's voxels took
        if not config.ground_normals:  # small_gicp's own PLANE_ICP reads them from the cloud
            self._normals, self._known = np.asarray(self.cloud.normals())[:, :3], np.ones(len(self.points), bool)
            return
        self._normals, self._known = np.zeros((len(self.points), 3)), np.zeros(len(self.points), bool)
        low = np.flatnonzero(self.points[:, 2] < -GROUND_BELOW)  # ground_plane's candidates lie there
        self.ground = ground_plane(self.points[low], self.normals_at(low)[low])
        if self.ground is not None:
            on_ground = ground_voxels(self.points, self.ground)
            self._normals[on_ground], self._known[on_ground] = self.ground[:3], True

    def normals_at(self, which: np.ndarray) -> np.ndarray:
        """The (N, 3) normals, those of the voxels `which` computed where not yet (the others may be zero)."""
        missing = np.unique(which[~self._known[which]])
        if len(missing):
            neighbours, _ = self.tree.batch_knn_search(
                self.points[missing], self.config.num_neighbors, num_threads=self.threads
            )
            neighbourhood_normals(self.points, np.asarray(neighbours, dtype=np.int64), missing, self._normals)
            self._known[missing] = True
        return self._normals

    @property
    def normals(self) -> np.ndarray:
        """(N, 3) every voxel's normal (the ground's: the plane's)."""
        return self.normals_at(np.arange(len(self.points)))

    @normals.setter
    def normals(self, normals: np.ndarray) -> None:
        """Match onto other normals (a study's: the mesh's own, another estimate), one per voxel."""
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != self.points.shape:
            raise ValueError(f"{len(self.points)} normals needed, one per voxel, got shape {normals.shape}")
        self._normals, self._known = normals.copy(), np.ones(len(self.points), bool)


def prepare_source(points: np.ndarray, config: RegistrationConfig) -> small_gicp.PointCloud:
    pts = _checked(points, "source scan", config.min_points)
    cloud = small_gicp.voxelgrid_sampling(pts, config.downsampling_resolution)
    if config.max_source_points and cloud.size() > config.max_source_points:
        # deterministic stride: voxel output order is spatially scrambled, so this is an even thinning
        stride = int(np.ceil(cloud.size() / config.max_source_points))
        cloud = small_gicp.PointCloud(np.asarray(cloud.points())[::stride, :3])
    if cloud.size() < config.min_points:
        raise RegistrationError(
            f"source scan has {cloud.size()} points after {config.downsampling_resolution} m downsampling "
            f"(minimum {config.min_points})"
        )
    return cloud


def _rigid_guess(T: np.ndarray) -> np.ndarray:
    """The initial guess as a float64 4x4, or a ValueError where it is not a rigid transform: ICP's
    updates keep whatever shear or scale the guess has, and a chain of such poses amplifies it."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"init_T_target_source must be a finite 4x4 transform, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 0:
        raise ValueError(
            "init_T_target_source is not a rigid transform (its rotation is not orthonormal, or its last row "
            "is not 0 0 0 1): take the nearest rotation (by SVD) of a pose composed from many"
        )
    return T


def register(
    source: np.ndarray | small_gicp.PointCloud,
    target: np.ndarray | PreparedTarget,
    config: RegistrationConfig | None = None,
    init_T_target_source: np.ndarray | None = None,
    with_hessian: bool = True,
) -> RegistrationResult:
    """Point-to-plane ICP of `source` onto `target` from `init` (identity by default).

    Raises RegistrationError for unusable input; a run that does not converge or keeps too few
    correspondences is returned with converged=False, never silently as a good estimate.
    """
    config = config or RegistrationConfig()
    tgt = target if isinstance(target, PreparedTarget) else PreparedTarget(target, config)
    src = source if isinstance(source, small_gicp.PointCloud) else prepare_source(source, config)
    T = np.eye(4) if init_T_target_source is None else _rigid_guess(init_T_target_source)
    source_points = np.asarray(src.points())[:, :3]
    iterations = 0
    for distance in config.max_correspondence_distance:
        hessian = None  # small_gicp's is from its last linearisation, one update before the solution
        if config.ground_normals:
            T, done, converged, inliers, error, hessian = _plane_icp(source_points, tgt, T, distance, config)
        else:
            result = small_gicp.align(
                tgt.cloud,
                src,
                tgt.tree,
                init_T_target_source=T,
                registration_type="PLANE_ICP",
                max_correspondence_distance=distance,
                max_iterations=config.max_iterations,
                rotation_epsilon=config.rotation_epsilon,
                translation_epsilon=config.translation_epsilon,
            )
            T, done, converged = np.asarray(result.T_target_source), int(result.iterations), bool(result.converged)
            inliers, error = int(result.num_inliers), float(result.error)
        iterations += done
    converged = converged and bool(np.isfinite(T).all())
    if inliers < config.min_inlier_ratio * src.size():
        converged = False
    if not with_hessian:
        H = np.full((6, 6), np.nan)
    elif hessian is not None:  # the last stage's at the pose returned: the final correspondences
        H = hessian
    else:
        H = point_to_plane_hessian(source_points, tgt, T, config.max_correspondence_distance[-1])
    return RegistrationResult(T, H, converged, iterations, inliers, int(src.size()), error)


@njit(cache=True)
def _normal_equations(source, R, moved, idx, sq, points, normals, max_sq):  # pragma: no cover - compiled
    """J^T J, J^T r, the squared residuals' sum and the correspondences of point-to-plane ICP at the
    pose (R, moved = R p + t): rows J = [R^T n, p x R^T n] (d r / d delta for T exp(delta), delta in the
    source frame), residuals r = n . (R p + t - q), over the matches within sqrt(max_sq)."""
    H, g = np.zeros((6, 6)), np.zeros(6)
    total, count = 0.0, 0
    j = np.zeros(6)
    for i in range(len(idx)):
        k = idx[i]
        if k < 0 or sq[i] >= max_sq:
            continue
        n0, n1, n2 = normals[k, 0], normals[k, 1], normals[k, 2]
        r = n0 * (moved[i, 0] - points[k, 0]) + n1 * (moved[i, 1] - points[k, 1]) + n2 * (moved[i, 2] - points[k, 2])
        a0 = R[0, 0] * n0 + R[1, 0] * n1 + R[2, 0] * n2  # R^T n
        a1 = R[0, 1] * n0 + R[1, 1] * n1 + R[2, 1] * n2
        a2 = R[0, 2] * n0 + R[1, 2] * n1 + R[2, 2] * n2
        p0, p1, p2 = source[i, 0], source[i, 1], source[i, 2]
        j[0], j[1], j[2] = a0, a1, a2
        j[3], j[4], j[5] = p1 * a2 - p2 * a1, p2 * a0 - p0 * a2, p0 * a1 - p1 * a0
        for u in range(6):
            g[u] += j[u] * r
            for v in range(6):
                H[u, v] += j[u] * j[v]
        total += r * r
        count += 1
    return H, g, total, count


def _linearise(
    source: np.ndarray, target: PreparedTarget, T: np.ndarray, distance: float
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """The point-to-plane normal equations at T over the nearest target voxels within `distance`
    (`_normal_equations`): J^T J, J^T r, the squared residuals' sum and the correspondences."""
    moved = source @ T[:3, :3].T + T[:3, 3]
    idx, sq = target.tree.batch_nearest_neighbor_search(moved)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    sq = np.asarray(sq, dtype=np.float64).reshape(-1)
    normals = target.normals_at(idx[(idx >= 0) & (sq < distance**2)])
    return _normal_equations(
        source, np.ascontiguousarray(T[:3, :3]), moved, idx, sq, target.points, normals, distance**2
    )


def _plane_icp(
    source: np.ndarray, target: PreparedTarget, T: np.ndarray, distance: float, config: RegistrationConfig
) -> tuple[np.ndarray, int, bool, int, float, np.ndarray]:
    """One stage of point-to-plane ICP onto the target's own `normals` (nearest neighbour within
    `distance`, T <- T exp(delta)): Gauss-Newton as small_gicp's PLANE_ICP (damping 1e-6, stop when
    the update is under the epsilons), except that a step that turns back on the one before and
    raises the mean squared residual over its new correspondences is not taken: there a weakly held
    axis's matches flip back and forth and the pose would swing between two, the better one is kept.
    Returns the pose, iterations, whether it converged, the final correspondences, half their
    squared residuals and J^T J there (the Hessian at the pose returned). Hand-written: small_gicp
    cannot be handed normals other than its own; the sums are compiled (numba), since numpy's
    per-operation overhead on a thousand rows was most of a registration's time."""

    def linearised(T: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, float, int]:
        H, g, total, count = _linearise(source, target, T, distance)
        # per correspondence: how many there are moves with the pose
        return total / max(count, 1), H, g, total, count

    cost, H, g, total, count = linearised(T)
    before = np.zeros(6)
    for iteration in range(1, config.max_iterations + 1):
        delta = np.linalg.solve(H + 1e-6 * np.eye(6), -g)
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = _rotation(delta[3:]), delta[:3]
        trial = T @ step
        trial_cost, trial_H, trial_g, trial_total, trial_count = linearised(trial)
        if delta @ before < -0.5 * np.linalg.norm(delta) * np.linalg.norm(before) and trial_cost > cost:
            return T, iteration, True, count, 0.5 * total, H  # back uphill to where it came from: swinging
        T, cost, H, g, total, count, before = trial, trial_cost, trial_H, trial_g, trial_total, trial_count, delta
        small = np.linalg.norm(delta[3:]) < config.rotation_epsilon
        if small and np.linalg.norm(delta[:3]) < config.translation_epsilon:
            return T, iteration, True, count, 0.5 * total, H
    return T, config.max_iterations, False, count, 0.5 * total, H


def _rotation(w: np.ndarray) -> np.ndarray:
    """exp of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def point_to_plane_hessian(
    source: np.ndarray, target: PreparedTarget, T: np.ndarray, max_distance: float
) -> np.ndarray:
    """A^T A of the point-to-plane residuals at T, from the final correspondences.

    small_gicp's `H` is that of its last linearisation, one update before the solution (5 %
    off on a converged office pair); the degeneracy test wants the Hessian at the solution.
    Rows are d r / d delta for T * exp(delta), delta in project order: [R^T n, p x R^T n].
    """
    return _linearise(source, target, T, max_distance)[0]


def hessian_in_frame(hessian: np.ndarray, T_b_s: np.ndarray) -> np.ndarray:
    """A registration's Hessian (project order, scans in frame s) for the same step seen in frame b,
    T_b_s the sensor's mounting: a perturbation d of T_target_source is Ad(T_b_s) d in b, so the
    Hessian becomes Ad^-T H Ad^-1 = Ad(T_s_b)^T H Ad(T_s_b) (what the fusion's body-frame ICP factor weighs)."""
    back = adjoint(inverse(T_b_s))
    return back.T @ np.asarray(hessian, dtype=np.float64) @ back


def hessian_in_level(hessian: np.ndarray, R_l_s: np.ndarray) -> np.ndarray:
    """A registration's Hessian (project order, sensor frame) on the axes of the scan's level frame,
    R_l_s its rotation (core.transforms.level_rotation): the information the classical tests split
    into per-axis answers, written where the labels are."""
    return hessian_in_frame(hessian, rotation_pose(R_l_s))


def scan_hessian(points: np.ndarray, config: RegistrationConfig | None = None) -> np.ndarray:
    """The point-to-plane Hessian of a scan registered onto itself at identity: what Zhang's test
    sees in a single scan (the same source thinning, normals and distance as `register`), so that
    the eigenvalue detector can be scored on labelled single scans beside the classifier."""
    config = config or RegistrationConfig()
    target = PreparedTarget(points, config)
    source = np.asarray(prepare_source(points, config).points())[:, :3]
    return point_to_plane_hessian(source, target, np.eye(4), config.max_correspondence_distance[-1])


def eigen_mask(hessian: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Zhang et al. (2016) degeneracy, projected to axes: returns (scores, mask).

    Eigen-directions of the Hessian with eigenvalue below tau are degenerate; axis i's score is
    sum_k V_ik^2 [lambda_k < tau] (the share of that axis lying in the degenerate subspace), and
    the axis is flagged when the score exceeds 0.5.
    """
    H = np.asarray(hessian, dtype=np.float64)
    if H.shape != (6, 6) or not np.isfinite(H).all():
        raise ValueError("the Hessian must be a finite 6x6 matrix")
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    scores = (V**2) @ (w < tau).astype(np.float64)
    return scores, scores > 0.5


# the assignments of three eigenvectors to three axes, for DCReg's basis alignment
_PERMUTATIONS = np.array(list(itertools.permutations(range(3))))


def aligned_axes(V: np.ndarray) -> np.ndarray:
    """For each physical axis a of a 3x3 block, the column of the eigenvectors V aligned with it: the
    one-to-one assignment with the largest total |component| (DCReg's basis alignment)."""
    fit = np.abs(V)[np.arange(3)[None, :], _PERMUTATIONS].sum(axis=1)  # axis a takes eigenvector perm[a]
    return _PERMUTATIONS[int(np.argmax(fit))]


def _aligned_ratios(block: np.ndarray) -> np.ndarray:
    """Per physical axis of a 3x3 information block: the largest eigenvalue over the eigenvalue of the
    eigenvector aligned with that axis (aligned_axes)."""
    w, V = np.linalg.eigh(0.5 * (block + block.T))
    w = np.maximum(w, 1e-12 * max(float(w[-1]), 1e-300))  # a null direction has an infinite ratio, not a NaN
    return w[-1] / w[aligned_axes(V)]


def dcreg_mask(hessian: np.ndarray, kappa: float) -> tuple[np.ndarray, np.ndarray]:
    """DCReg's degeneracy detection (Hu et al., 2025, arXiv 2509.06285), projected to axes: returns
    (scores, mask) on (x, y, z, roll, pitch, yaw).

    The Hessian's rotation and translation blocks are decoupled by Schur complements (the information
    on rotation with translation marginalised out, and the other way round), so that neither hides
    the other's weak directions and their units never meet. Each complement's eigenvectors are aligned
    one-to-one with the physical axes, and an axis is flagged when its subspace's condition ratio,
    the largest eigenvalue over the axis's own, exceeds `kappa`. Only the detection: the paper's
    preconditioned solver is not part of this. scores: log(ratio) / (2 log kappa), clipped to [0, 1],
    so that a flag is a score over 0.5 as in eigen_mask.
    """
    H = np.asarray(hessian, dtype=np.float64)
    if H.shape != (6, 6) or not np.isfinite(H).all():
        raise ValueError("the Hessian must be a finite 6x6 matrix")
    if not kappa > 1:
        raise ValueError(f"DCReg's condition ratio threshold must exceed 1, got {kappa}")
    H = 0.5 * (H + H.T)
    t, r = slice(0, 3), slice(3, 6)
    ridge = 1e-9 * max(float(np.trace(H)), 1e-300) * np.eye(3)  # keeps a singular block invertible
    translation = H[t, t] - H[t, r] @ np.linalg.solve(H[r, r] + ridge, H[r, t])
    rotation = H[r, r] - H[r, t] @ np.linalg.solve(H[t, t] + ridge, H[t, r])
    ratios = np.concatenate([_aligned_ratios(translation), _aligned_ratios(rotation)])
    scores = np.clip(np.log(ratios) / (2 * np.log(kappa)), 0.0, 1.0)
    return scores, ratios > kappa
