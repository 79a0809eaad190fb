"""ROS bags in and out, through `rosbags` (pure Python, no ROS installation; an optional
dependency: `pip install 'l3e[bag]'`). In: the sensor_msgs/PointCloud2 scans of one topic of a
recorded bag (ROS 1 `.bag`, or a ROS 2 folder of sqlite3 or mcap storage), as (N, 3) points in the
sensor's frame, to be judged. Out: a simulated drive as a bag (`BagRecorder`), full scans with
their beam rings, leg odometry, ground truth and the sensor's mounting, for one's own LiDAR
odometry or SLAM to run on the same scenes."""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from l3e_env.config import OdometryConfig
from l3e_env.core.transforms import inverse, matrix_to_pose
from l3e_env.io.recorded import RecordedScan, RecordingError
from l3e_env.sim.imu import ImuConfig, imu_samples
from l3e_env.sim.odometry import DeadReckoningCovariance
from l3e_env.sim.patterns import TIME_FIELDS

from .imu_up import ImuUp, read_imu_up

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
# sensor_msgs/PointField datatypes
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_FIELD_TYPES = {f"<{kind}": code for code, kind in _DATATYPES.items()}  # the other way, for writing


class BagError(RecordingError):
    """A bag or topic that cannot be read as LiDAR scans; the message says why."""


def _cloud_fields(msg, names: list[str]) -> dict[str, np.ndarray]:
    """The named fields of a PointCloud2 (any field layout, either byte order, padded rows), one
    flat array each. Hand-written: rosbags deserialises the message but does not unpack its fields."""
    fields = {f.name: f for f in msg.fields}
    order = ">" if msg.is_bigendian else "<"
    try:
        formats = [order + _DATATYPES[fields[a].datatype] for a in names]
    except KeyError as exc:
        raise BagError(f"PointField datatype {exc} is not a number type") from exc
    offsets = [int(fields[a].offset) for a in names]
    height, width, point_step, row_step = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    if any(o + np.dtype(f).itemsize > point_step for o, f in zip(offsets, formats)):
        raise BagError(f"a field lies past the point step of {point_step} bytes")
    if row_step < width * point_step:
        raise BagError(f"row step {row_step} bytes is less than {width} points of {point_step} bytes")
    data = np.asarray(msg.data, dtype=np.uint8)
    if len(data) < height * row_step:
        raise BagError(f"{len(data)} bytes of data for {height} rows of {row_step} bytes")
    rows = np.ascontiguousarray(data[: height * row_step].reshape(height, row_step)[:, : width * point_step])
    cloud = rows.view(
        np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    ).reshape(-1)
    return {a: cloud[a] for a in names}


def _cloud_arrays(msg, with_rings: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """x, y, z as (N, 3) float64, and the ring field where asked for and present, in one unpacking."""
    names = {f.name for f in msg.fields}
    if not {"x", "y", "z"} <= names:
        raise BagError(f"the cloud has fields {sorted(names)}, not x, y and z")
    ring = with_rings and "ring" in names
    fields = _cloud_fields(msg, ["x", "y", "z"] + (["ring"] if ring else []))
    points = np.stack([fields[a].astype(np.float64) for a in "xyz"], axis=1)
    return points, fields["ring"].astype(np.int64) if ring else None


def cloud_points(msg) -> np.ndarray:
    """x, y, z of a PointCloud2 as (N, 3) float64."""
    return _cloud_arrays(msg, with_rings=False)[0]


def cloud_rings(msg) -> np.ndarray | None:
    """The beam of each point from the cloud's `ring` field (Velodyne and Ouster drivers write
    one), or None where it has none."""
    if "ring" not in {f.name for f in msg.fields}:
        return None
    return _cloud_fields(msg, ["ring"])["ring"].astype(np.int64)


def _open(path: Path):
    """The bag at `path`, opened for reading (the caller closes it)."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise BagError("reading ROS bags needs the rosbags package: pip install 'l3e[bag]'") from exc
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    try:
        # a ROS 2 bag written without its message definitions is read with the current ones
        reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds; name the bag and the problem
        raise BagError(
            f"{path}: cannot be read as a ROS bag ({exc}); give a ROS 1 .bag, a ROS 2 bag folder or .mcap/.db3, "
            "or an Ouster .osf or .pcap"
        ) from exc
    return reader


def _stamp(msg, received: int) -> float:
    """Seconds: the message header's stamp, else (a zero stamp) when the bag received it."""
    header = msg.header.stamp
    return header.sec + header.nanosec * 1e-9 if header.sec or header.nanosec else received * 1e-9


def read_bag(
    path: str | Path, topic: str | None = None, every: int = 1, start: float | None = None, end: float | None = None
) -> Iterator[RecordedScan]:
    """The scans of `topic` (the bag's only PointCloud2 topic if None), every `every`-th message,
    between `start` and `end` seconds after the bag's first message. A bag or topic that cannot
    be read raises BagError here, before any scan is read; a message that cannot be decoded gives a
    RecordedScan with its `error`, and the next one is read."""
    if every < 1:
        raise BagError(f"every must be at least 1, got {every}")
    path = Path(path)
    reader = _open(path)
    try:
        clouds = sorted({c.topic for c in reader.connections if c.msgtype == POINTCLOUD2})
        if topic is None:
            if len(clouds) != 1:
                raise BagError(
                    f"{path}: {'no' if not clouds else len(clouds)} PointCloud2 topics"
                    + (f" ({', '.join(clouds)}); name one with --topic" if clouds else "")
                )
            topic = clouds[0]
        connections = [c for c in reader.connections if c.topic == topic]
        if not connections:
            raise BagError(f"{path}: no topic '{topic}'; its PointCloud2 topics: {', '.join(clouds) or 'none'}")
        if connections[0].msgtype != POINTCLOUD2:
            raise BagError(
                f"{path}: '{topic}' carries {connections[0].msgtype}, not {POINTCLOUD2}; "
                f"its PointCloud2 topics: {', '.join(clouds) or 'none'}"
            )
    except BaseException:
        reader.close()
        raise
    first = reader.start_time
    lo = None if start is None else first + int(start * 1e9)
    hi = None if end is None else first + int(end * 1e9) + 1
    try:
        imu, said = read_imu_up(reader, lo, hi)
    except BaseException:
        reader.close()
        raise
    return _scans(reader, connections, f"{path.name} {topic}", every, (lo, hi), (imu, said))


def _scans(
    reader,
    connections: list,
    prefix: str,
    every: int,
    window: tuple[int | None, int | None],
    imu: tuple[ImuUp | None, str],
) -> Iterator[RecordedScan]:
    """Each cloud message of `connections` as a RecordedScan, with the up direction the bag's IMU
    gives in the cloud's frame where it has one (`imu_up`), or why not."""
    try:
        for k, (connection, received, raw) in enumerate(reader.messages(connections, start=window[0], stop=window[1])):
            if k % every:
                continue
            name, stamp = f"{prefix} #{k}", received * 1e-9
            try:
                msg = reader.deserialize(raw, connection.msgtype)
                stamp = _stamp(msg, received)
                points, rings = _cloud_arrays(msg, with_rings=True)
                up, source = (
                    imu[0].up_in(msg.header.frame_id.lstrip("/"), stamp) if imu[0] is not None else (None, imu[1])
                )
                yield RecordedScan(name, stamp, points, rings=rings, up=up, up_source=source)
            except Exception as exc:  # noqa: BLE001 - one bad message is named, the next is read
                yield RecordedScan(name, stamp, None, f"{name}: cannot be read as a point cloud: {exc}")
    finally:
        reader.close()


POSE_TYPES = {  # message type: its position, read off a deserialised message
    "nav_msgs/msg/Odometry": lambda m: m.pose.pose.position,
    "geometry_msgs/msg/PoseWithCovarianceStamped": lambda m: m.pose.pose.position,
    "geometry_msgs/msg/PoseStamped": lambda m: m.pose.position,
}


@dataclass
class BagPath:
    topic: str
    stamps: np.ndarray  # (K,) seconds, increasing
    positions: np.ndarray  # (K, 3) in the topic's frame

    def at(self, stamps: np.ndarray) -> np.ndarray:
        """Positions (N, 3) at `stamps`, linear between poses; NaN outside the path's time."""
        stamps = np.asarray(stamps, dtype=np.float64)
        out = np.stack([np.interp(stamps, self.stamps, self.positions[:, k]) for k in range(3)], axis=1)
        out[(stamps < self.stamps[0]) | (stamps > self.stamps[-1])] = np.nan
        return out


def read_path(path: str | Path, topic: str | None = None) -> BagPath:
    """Where the robot went: the positions of a pose topic (nav_msgs/Odometry, geometry_msgs/
    PoseStamped or PoseWithCovarianceStamped; default: the bag's only Odometry topic, else its only
    pose topic), at their header stamps, to place the judged scans on a map."""
    path = Path(path)
    reader = _open(path)
    try:
        kinds = {c.topic: c.msgtype for c in reader.connections}
        poses = sorted(t for t, m in kinds.items() if m in POSE_TYPES)
        if topic is None:
            odometry = [t for t in poses if kinds[t] == "nav_msgs/msg/Odometry"]
            chosen = odometry if len(odometry) == 1 else poses
            if len(chosen) != 1:
                raise BagError(
                    f"{path}: {'no' if not poses else len(poses)} pose topics"
                    + (
                        f" ({', '.join(poses)}); name one with --pose-topic"
                        if poses
                        else " (nav_msgs/Odometry, geometry_msgs/PoseStamped or PoseWithCovarianceStamped)"
                    )
                )
            topic = chosen[0]
        if topic not in kinds:
            raise BagError(f"{path}: no topic '{topic}'; its pose topics: {', '.join(poses) or 'none'}")
        if kinds[topic] not in POSE_TYPES:
            raise BagError(
                f"{path}: '{topic}' carries {kinds[topic]}, not a pose; its pose topics: {', '.join(poses) or 'none'}"
            )
        position = POSE_TYPES[kinds[topic]]
        stamps, positions = [], []
        for connection, received, raw in reader.messages([c for c in reader.connections if c.topic == topic]):
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception as exc:  # noqa: BLE001 - a path with a hole would misplace scans silently
                raise BagError(f"{path}: a '{topic}' message at {received * 1e-9:.3f} s cannot be read: {exc}") from exc
            stamps.append(_stamp(msg, received))
            p = position(msg)
            positions.append((p.x, p.y, p.z))
    finally:
        reader.close()
    if len(stamps) < 2:
        raise BagError(f"{path}: '{topic}' holds {len(stamps)} poses; a path needs two or more")
    order = np.argsort(stamps, kind="stable")
    return BagPath(topic, np.asarray(stamps)[order], np.asarray(positions, dtype=np.float64)[order])


def split_stamp(stamp: float) -> tuple[int, int]:
    """Seconds and nanoseconds of a stamp, rounded to the nanosecond as one integer first, so that a stamp
    a hair under a whole second (3.9999999997 s) becomes (4, 0), not (3, 0), and time never runs back."""
    total = int(round(stamp * 1e9))
    return total // 1_000_000_000, total % 1_000_000_000


class BagRecorder:
    """Writes each step of a drive (`record_run(on_step=...)`) into a bag at `path`, at the
    drive's 10 Hz from `start` seconds:
    - `/points` sensor_msgs/PointCloud2 in frame `lidar`: x, y, z (float32) and ring (uint16, the
      beam's index in the pattern: for the built-in ones the lowest first, as Velodyne's driver
      numbers them), one revolution a message;
    - `/odom` nav_msgs/Odometry, frame `odom` to `base_link`: the leg odometry's dead reckoning
      (`odom` is the world frame at the start), its twist over the last step, and the covariances
      that `odometry`'s noise model gives both (`DeadReckoningCovariance`; the default is the
      simulation's own);
    - `/ground_truth` geometry_msgs/PoseStamped of `base_link` in frame `world`;
    - `/tf` odom to base_link each step, `/tf_static` base_link to lidar once;
    - `/imu` sensor_msgs/Imu in frame `base_link` at `imu.rate` (None: no IMU), read off splines
      through the true poses with `imu`'s noise and biases, seeded by `seed`, and the orientation
      of a nine-axis unit in the world frame where `imu.orientation`; written on `close`, from the
      first scan's stamp on (a swept first revolution began a step before the first pose).
    The bag is written in a folder beside `path` and moved there when `close` is called, so a
    killed drive leaves no half bag under that name (the next one removes the folder). ROS 2
    (`ros2=True`) writes a sqlite3 bag folder."""

    def __init__(
        self,
        path: str | Path,
        ros2: bool = False,
        dt: float = 0.1,
        start: float = 1.0,
        odometry: OdometryConfig | None = None,
        imu: ImuConfig | None = ImuConfig(),
        seed: int = 0,
    ):
        try:
            from rosbags.rosbag1 import Writer as Writer1
            from rosbags.rosbag2 import Writer as Writer2
            from rosbags.typesys import Stores, get_types_from_msg, get_typestore
        except ImportError as exc:
            raise BagError("writing ROS bags needs the rosbags package: pip install 'l3e[bag]'") from exc
        self.path, self.ros2, self.dt, self.start = Path(path), ros2, dt, start
        if self.path.exists():
            raise BagError(f"{self.path} exists; remove it or choose another name")
        if not ros2 and self.path.suffix != ".bag":
            raise BagError(f"{self.path}: a ROS 1 bag's name ends in .bag (or write a ROS 2 bag folder)")
        # written in a folder beside it under its own name (a ROS 2 bag names its database after it)
        self.folder = self.path.with_name(self.path.name + ".partial")
        _remove(self.folder)  # the leftover of a killed drive
        self.folder.mkdir(parents=True)
        self.partial = self.folder / self.path.name
        self.store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
        if "tf2_msgs/msg/TFMessage" not in self.store.types:  # rosbags' Noetic store leaves tf2_msgs out
            self.store.register(
                get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
            )
        self.serialize = self.store.serialize_cdr if ros2 else self.store.serialize_ros1
        self.writer = Writer2(self.partial, version=9) if ros2 else Writer1(self.partial)
        self.writer.open()
        self.steps = 0
        self.covariance = DeadReckoningCovariance(odometry)
        self.last_odom: np.ndarray | None = None
        self.truth: list = []
        self.imu, self.seed, self.swept = imu, seed, False
        self.topics = {}
        for topic, msgtype in (
            ("/points", POINTCLOUD2),
            ("/odom", "nav_msgs/msg/Odometry"),
            ("/ground_truth", "geometry_msgs/msg/PoseStamped"),
            ("/tf", "tf2_msgs/msg/TFMessage"),
            ("/tf_static", "tf2_msgs/msg/TFMessage"),
            *((("/imu", "sensor_msgs/msg/Imu"),) if imu is not None else ()),
        ):
            extra: dict[str, Any] = {"latching": 1} if topic == "/tf_static" and not ros2 else {}
            self.topics[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store, **extra)

    def _header(self, stamp: float, frame: str, seq: int | None = None):
        t = self.store.types
        sec, nanosec = split_stamp(stamp)
        time = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        seq = self.steps if seq is None else seq
        return t["std_msgs/msg/Header"](**({} if self.ros2 else {"seq": seq}), stamp=time, frame_id=frame)

    def _transform(self, stamp: float, parent: str, child: str, T: np.ndarray):
        t = self.store.types
        x, y, z, w = _quaternion(T)
        return t["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp, parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](*T[:3, 3]),
                rotation=t["geometry_msgs/msg/Quaternion"](x, y, z, w),
            ),
        )

    def _pose(self, T: np.ndarray):
        t = self.store.types
        x, y, z, w = _quaternion(T)
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](*T[:3, 3]), orientation=t["geometry_msgs/msg/Quaternion"](x, y, z, w)
        )

    def _write(self, topic: str, stamp: float, msg) -> None:
        connection = self.topics[topic]
        self.writer.write(connection, int(round(stamp * 1e9)), self.serialize(msg, connection.msgtype))

    def __call__(self, scan, info: dict) -> None:
        """One step: `scan` (a lidar.Scan) with info's T_w_b, odom_T_w_b and T_b_s."""
        t = self.store.types
        stamp = self.start + self.steps * self.dt
        if self.steps == 0:
            self._write(
                "/tf_static",
                stamp,
                t["tf2_msgs/msg/TFMessage"](
                    transforms=[self._transform(stamp, "base_link", "lidar", np.asarray(info["T_b_s"], np.float64))]
                ),
            )
        # a swept revolution is stamped when it began, its points' times counted from there (as the
        # Velodyne and Ouster drivers write them, and as LIO-SAM and FAST-LIO read them)
        began = stamp if scan.times is None else stamp - self.dt
        if self.steps == 0:
            self.swept = scan.times is not None
        self._write(
            "/points",
            began,
            _cloud_message(
                t,
                self._header(began, "lidar"),
                scan.points,
                scan.beam.astype(np.uint16),
                scan.times,
                scan.pattern.time_field,
            ),
        )
        odom = np.asarray(info["odom_T_w_b"], dtype=np.float64)
        increment = np.eye(4) if self.last_odom is None else inverse(self.last_odom) @ odom
        self.last_odom = odom
        pose_covariance, twist_covariance = self.covariance.step(increment, odom, self.dt)
        velocity = matrix_to_pose(increment) / self.dt  # over the step just taken, in the body frame
        vector = t["geometry_msgs/msg/Vector3"]
        self._write(
            "/odom",
            stamp,
            t["nav_msgs/msg/Odometry"](
                header=self._header(stamp, "odom"),
                child_frame_id="base_link",
                pose=t["geometry_msgs/msg/PoseWithCovariance"](
                    pose=self._pose(odom), covariance=pose_covariance.ravel()
                ),
                twist=t["geometry_msgs/msg/TwistWithCovariance"](
                    twist=t["geometry_msgs/msg/Twist"](linear=vector(*velocity[:3]), angular=vector(*velocity[3:])),
                    covariance=twist_covariance.ravel(),
                ),
            ),
        )
        self._write(
            "/tf", stamp, t["tf2_msgs/msg/TFMessage"](transforms=[self._transform(stamp, "odom", "base_link", odom)])
        )
        self.truth.append(np.asarray(info["T_w_b"], dtype=np.float64))
        self._write(
            "/ground_truth",
            stamp,
            t["geometry_msgs/msg/PoseStamped"](header=self._header(stamp, "world"), pose=self._pose(self.truth[-1])),
        )
        self.steps += 1

    def _write_imu(self) -> None:
        """`/imu` over the whole drive, once its poses are known: the splines through them need
        the poses after each sample as well as before."""
        if self.imu is None or len(self.truth) < 2:
            return
        t = self.store.types
        poses, first = self.truth, self.start
        if self.swept:  # the first revolution began a step before the first pose, the robot standing
            poses, first = [self.truth[0]] + self.truth, self.start - self.dt
        stamps = first + self.dt * np.arange(len(poses))
        imu = imu_samples(stamps, poses, self.imu, np.random.default_rng(self.seed))
        gyro_sigma, accel_sigma = self.imu.sigmas()
        if imu.orientation is None:
            quaternions, covariance = np.tile([0.0, 0.0, 0.0, 1.0], (len(imu.stamps), 1)), np.zeros(9)
            covariance[0] = -1.0  # REP 145: no orientation estimate
        else:
            quaternions, covariance = imu.orientation, np.diag(self.imu.orientation_sigmas() ** 2).ravel()
        vector = t["geometry_msgs/msg/Vector3"]
        for k, (stamp, w, a, q) in enumerate(zip(imu.stamps, imu.gyro, imu.accel, quaternions)):
            self._write(
                "/imu",
                float(stamp),
                t["sensor_msgs/msg/Imu"](
                    header=self._header(float(stamp), "base_link", k),
                    orientation=t["geometry_msgs/msg/Quaternion"](*(float(v) for v in q)),
                    orientation_covariance=covariance,
                    angular_velocity=vector(*w),
                    angular_velocity_covariance=np.diag([gyro_sigma**2] * 3).ravel(),
                    linear_acceleration=vector(*a),
                    linear_acceleration_covariance=np.diag([accel_sigma**2] * 3).ravel(),
                ),
            )

    def abort(self) -> None:
        """Drop the unfinished bag: a drive that failed or was stopped leaves nothing half-written."""
        with contextlib.suppress(Exception):  # the writer may be in any state; the folder goes regardless
            self.writer.close()
        _remove(self.folder)

    def close(self) -> Path:
        """Finish the bag (writing `/imu`) and move it to its name."""
        self._write_imu()
        self.writer.close()
        os.replace(self.partial, self.path)
        self.folder.rmdir()
        return self.path


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()


def _quaternion(T: np.ndarray) -> tuple[float, float, float, float]:
    from scipy.spatial.transform import Rotation

    x, y, z, w = (float(v) for v in Rotation.from_matrix(T[:3, :3]).as_quat())
    return x, y, z, w


def bag_size_bound(rays_per_scan: int, scans: int, swept: bool) -> int:
    """At most how many bytes a recorded drive's `/points` take: every ray a return, 16-byte points (20
    with each point's time), the scans of the whole drive; the other topics add a few percent."""
    return rays_per_scan * scans * (20 if swept else 16)


def _cloud_message(
    types, header, points: np.ndarray, ring: np.ndarray, times: np.ndarray | None = None, time_field: str = "time"
):
    """x, y, z float32 and ring uint16 in 16-byte points, as a VLP-16 driver lays them out; with
    `times`, each point's time since the stamp in 20-byte points, as the sensor's driver writes it
    (`time_field`, one of patterns.TIME_FIELDS: Velodyne's `time`, Ouster's `t`)."""
    names, formats, offsets = ["x", "y", "z", "ring"], ["<f4", "<f4", "<f4", "<u2"], [0, 4, 8, 12]
    if times is not None:
        _, time_format, per_second = TIME_FIELDS[time_field]
        names, formats, offsets = names + [time_field], formats + [time_format], offsets + [16]
    step = 16 if times is None else 20
    table = np.zeros(
        len(points), dtype=np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    )
    for i, a in enumerate("xyz"):
        table[a] = points[:, i]
    table["ring"] = ring
    if times is not None:
        table[time_field] = np.round(times.astype(np.float64) * per_second) if per_second != 1.0 else times
    field = types["sensor_msgs/msg/PointField"]
    return types[POINTCLOUD2](
        header=header,
        height=1,
        width=len(points),
        is_bigendian=False,
        is_dense=True,
        point_step=step,
        row_step=step * len(points),
        data=table.view(np.uint8).copy(),
        fields=[field(name=n, offset=o, datatype=_FIELD_TYPES[f], count=1) for n, o, f in zip(names, offsets, formats)],
    )
