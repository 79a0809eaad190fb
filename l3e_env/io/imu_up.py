"""The up direction in a bag's LiDAR frame from the bag's own IMU: the accelerometer's mean specific
force over a second around the scan (gravity's reaction, the robot's own accelerations averaging
out), turned from the IMU's frame into the cloud's by the bag's /tf_static. Hand-written: rosbags
reads the messages but has no transform tree, and tf2 needs a ROS installation."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

IMU = "sensor_msgs/msg/Imu"
TF_STATIC = "/tf_static"
WINDOW = 0.5  # s either side of a scan's stamp: a stride or two of a walking robot
MIN_SAMPLES = 5


def _matrix(transform) -> np.ndarray:
    """geometry_msgs/Transform as a 4x4."""
    from scipy.spatial.transform import Rotation

    q, t = transform.rotation, transform.translation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = (t.x, t.y, t.z)
    return T


@dataclass
class ImuUp:
    """A bag's IMU readings and static transforms, asked for the up direction in a frame at a time."""

    topic: str
    frame: str  # the IMU messages' frame_id
    stamps: np.ndarray  # (K,) s, increasing
    accel: np.ndarray  # (K, 3) m/s^2: the specific force, up at rest
    parents: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)  # child: (parent, T_parent_child)

    def _to_root(self, frame: str) -> tuple[str, np.ndarray]:
        """The root of `frame`'s static tree and T_root_frame."""
        T, seen = np.eye(4), {frame}
        while frame in self.parents:
            parent, T_parent_child = self.parents[frame]
            T, frame = T_parent_child @ T, parent
            if frame in seen:  # a loop in a damaged tree: no path
                break
            seen.add(frame)
        return frame, T

    def rotation_to(self, frame: str) -> np.ndarray | None:
        """R_frame_imu through the static tree, or None where the two frames are not joined."""
        if frame == self.frame:
            return np.eye(3)
        root_a, T_root_frame = self._to_root(frame)
        root_b, T_root_imu = self._to_root(self.frame)
        if root_a != root_b:
            return None
        return T_root_frame[:3, :3].T @ T_root_imu[:3, :3]

    def up_in(self, frame: str, stamp: float) -> tuple[np.ndarray | None, str]:
        """The unit up direction in `frame` at `stamp`, and where it came from or why there is none."""
        turn = self.rotation_to(frame)
        if turn is None:
            return None, f"the bag's IMU {self.topic} (frame {self.frame}) has no /tf_static path to {frame}"
        near = (self.stamps >= stamp - WINDOW) & (self.stamps <= stamp + WINDOW)
        if near.sum() < MIN_SAMPLES:
            return None, f"the bag's IMU {self.topic} has {int(near.sum())} readings within {WINDOW:g} s of the scan"
        force = self.accel[near].mean(axis=0)
        norm = float(np.linalg.norm(force))
        if not np.isfinite(norm) or not 4.9 < norm < 14.7:  # 0.5 g to 1.5 g: free fall, a crash or not m/s^2
            return None, f"the bag's IMU {self.topic} reads {norm:.1f} m/s^2 around the scan, not gravity"
        return turn @ (force / norm), f"from the bag's IMU {self.topic}"


def read_imu_up(reader, lo: int | None = None, hi: int | None = None) -> tuple[ImuUp | None, str]:
    """The bag's IMU (its only sensor_msgs/Imu topic) between `lo` and `hi` (ns, widened by the window)
    with the bag's static transforms; None, and why, where it has none or several."""
    topics = sorted({c.topic for c in reader.connections if c.msgtype == IMU})
    if len(topics) != 1:
        return None, "the bag has no IMU topic" if not topics else f"the bag has {len(topics)} IMU topics"
    margin = int(2 * WINDOW * 1e9)
    stamps, accel, frame = [], [], ""
    connections = [c for c in reader.connections if c.topic == topics[0]]
    start = None if lo is None else lo - margin
    stop = None if hi is None else hi + margin
    for connection, received, raw in reader.messages(connections, start=start, stop=stop):
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception:  # noqa: BLE001 - an unreadable reading is left out of the mean
            continue
        header, a = msg.header, msg.linear_acceleration
        stamps.append(header.stamp.sec + header.stamp.nanosec * 1e-9 if header.stamp.sec else received * 1e-9)
        accel.append((a.x, a.y, a.z))
        frame = frame or header.frame_id
    if not stamps:
        return None, f"the bag's IMU {topics[0]} has no readings"
    parents: dict[str, tuple[str, np.ndarray]] = {}
    statics = [c for c in reader.connections if c.topic == TF_STATIC]
    for connection, _, raw in reader.messages(statics):
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception:  # noqa: BLE001 - a damaged transform message joins no frames
            continue
        for t in msg.transforms:
            parents[t.child_frame_id.lstrip("/")] = (t.header.frame_id.lstrip("/"), _matrix(t.transform))
    order = np.argsort(stamps, kind="stable")
    found = ImuUp(
        topics[0], frame.lstrip("/"), np.asarray(stamps)[order], np.asarray(accel, np.float64)[order], parents
    )
    return found, f"the bag's IMU {topics[0]}"
