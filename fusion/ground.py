"""The ground under the robot as a landmark of the graph: a patch of ground is one plane (GTSAM's
`OrientedPlane3`), and each scan whose ground plane was fitted measures it from its pose
(`OrientedPlane3Factor`). Every pose that sees the same patch is held at the height above it and
the tilt against it that its scan measured, however long the walk across it: the registrations'
small height and pitch steps, and the IMU's slow tilt error, no longer add up there. A new patch
starts where the ground seen changes (a slope, a step: `GroundPatches`), and where the present one
was last seen too long ago for the smoother's window; a patch is as free as the poses that first
see it, so across patches the chain of registrations decides, as without the ground.

Planes here are (n, d) with n . p = d, n the unit normal pointing up at the sensor (d < 0 for
ground below the origin), as `l3e_env`'s ground fits give them; GTSAM writes n . p + d = 0.
"""

from __future__ import annotations

import gtsam
import numpy as np

# the normal's two directions (rad) and the distance (m) of one scan's ground plane, a fit to hundreds
# of returns on the floor: of the order of the registration's own confidence in height and tilt on the
# same floor, so that the ground's hold of a whole patch and the registrations' step by step weigh alike
GROUND_SIGMAS = (0.0005, 0.002)
PATCH_TURN = np.radians(2.0)  # a ground tilted this much against the present patch is a new one
PATCH_STEP = 0.10  # m: so is one this far above or below it, under the robot
HOLDS_STEPS = 100  # a patch seen within this many steps holds the pose (a keyframe's longest run)


def ground_key(n: int) -> int:
    """The key of the n-th ground patch (poses are keyed by their index)."""
    return gtsam.symbol("g", n)


def check_plane(plane: np.ndarray) -> np.ndarray:
    """A plane (n, d) as a float array of 4 with a unit normal, or a ValueError naming the problem."""
    p = np.asarray(plane, dtype=np.float64).reshape(-1)
    if p.shape != (4,) or not np.isfinite(p).all():
        raise ValueError(f"a ground plane is 4 finite numbers (nx, ny, nz, d), got {np.asarray(plane).tolist()!r}")
    norm = float(np.linalg.norm(p[:3]))
    if abs(norm - 1.0) > 1e-6:
        raise ValueError(f"a ground plane's normal (its first 3 numbers) is a unit vector, its length is {norm:.6g}")
    return p


def check_ground_sigmas(sigmas: tuple[float, ...]) -> tuple[float, float]:
    s = tuple(float(v) for v in sigmas)
    if len(s) != 2 or not all(np.isfinite(v) and v > 0 for v in s):
        raise ValueError(f"ground_sigmas are two positive numbers (the normal's rad, the distance's m), got {sigmas!r}")
    return s[0], s[1]


def plane_in_frame(plane: np.ndarray, T_a_b: np.ndarray) -> np.ndarray:
    """A plane (n, d) of frame b written in frame a (T_a_b maps b's points into a)."""
    p = check_plane(plane)
    n = T_a_b[:3, :3] @ p[:3]
    return np.r_[n, p[3] + n @ T_a_b[:3, 3]]


def to_gtsam(plane: np.ndarray) -> gtsam.OrientedPlane3:
    p = check_plane(plane)
    return gtsam.OrientedPlane3(gtsam.Unit3(p[:3]), -p[3])


class GroundPatches:
    """Which patch a pose's ground plane measures: the present one, or a new one (`patch`). The ground
    changes where a plane departs from the one measured before it, carried over by the legs' motion
    between the two (`moved`; a slope begins, a step up), or where its normal departs from the
    patch's as first seen (a floor that bends slowly). Carried by the legs, not by the estimate: a
    registration that slips in height must not read as a step in the ground."""

    def __init__(self, stale_after: int | None):
        self.stale_after = stale_after  # steps unseen after which a patch may have left the window
        self.index = -1  # the present patch (-1: none yet)
        self.seen = 0  # the step that last measured it
        self.plane: gtsam.OrientedPlane3 | None = None  # the present patch in the world, as first seen
        self._last: gtsam.OrientedPlane3 | None = None  # the last plane measured, in its body frame
        self._moved = gtsam.Pose3()  # the legs' motion since that body frame

    def holds(self, k: int) -> bool:
        """Whether a patch holds pose k: one was seen within HOLDS_STEPS steps of it."""
        return self.index >= 0 and k - self.seen <= HOLDS_STEPS

    def moved(self, T_prev_cur: gtsam.Pose3) -> None:
        """One step's motion (the legs', or the registration's where the legs gave none)."""
        self._moved = self._moved.compose(T_prev_cur)

    def patch(self, T_w_b: gtsam.Pose3, measured: np.ndarray, k: int) -> bool:
        """Whether the plane `measured` (n, d, body frame) from pose k (estimated at T_w_b) starts a
        new patch (then `plane` is it, in the world)."""
        here = to_gtsam(measured)
        new = self.plane is None or self._last is None
        new = new or (self.stale_after is not None and k - self.seen > self.stale_after)
        if not new:
            assert self.plane is not None and self._last is not None
            carried = self._last.transform(self._moved).planeCoefficients()  # GTSAM's n . p + d = 0
            first = self.plane.transform(T_w_b).planeCoefficients()
            turn = max(_angle(carried[:3], measured[:3]), _angle(first[:3], measured[:3]))
            new = turn > PATCH_TURN or abs(-carried[3] - measured[3]) > PATCH_STEP
        if new:
            self.index += 1
            self.plane = here.transform(T_w_b.inverse())
        self.seen, self._last, self._moved = k, here, gtsam.Pose3()
        return new


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(a @ b, -1.0, 1.0)))
