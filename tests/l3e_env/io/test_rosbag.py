"""`l3e judge --bag`: LiDAR scans read from ROS 1 and ROS 2 bags, judged as the same scans in files."""

import dataclasses
import json

import numpy as np
import pytest
import trimesh
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from l3e_env.cli.main import main
from l3e_env.config import LidarConfig
from l3e_env.core.transforms import planar_pose
from l3e_env.experiments.judge import judge_scans
from l3e_env.experiments.judge_plots import flag_matrix
from l3e_env.io.rosbag import BagError, BagRecorder, cloud_points, cloud_rings, read_bag, read_path
from l3e_env.sim.imu import ImuConfig
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.patterns import PATTERNS
from l3e_env.sim.raycast import EmbreeCaster

ROS1, ROS2 = get_typestore(Stores.ROS1_NOETIC), get_typestore(Stores.ROS2_HUMBLE)
CLOUD = "sensor_msgs/msg/PointCloud2"


def _cloud(store, points: np.ndarray, stamp: float, *, dtype="<f4", height=1, pad=0, fields="xyz"):
    """A PointCloud2 of `points` with an intensity field after x, y, z, `pad` bytes after each row."""
    types = store.types
    size = np.dtype(dtype).itemsize
    codes = {"<f4": 7, ">f4": 7, "<f8": 8, ">f8": 8}
    layout = np.dtype(
        {
            "names": list(fields) + ["intensity"],
            "formats": [dtype] * (len(fields) + 1),
            "offsets": [i * size for i in range(len(fields) + 1)],
            "itemsize": (len(fields) + 2) * size,
        }
    )
    table = np.zeros(len(points), dtype=layout)
    for i, name in enumerate(fields):
        table[name] = points[:, i]
    width = len(points) // height
    rows = np.zeros((height, width * layout.itemsize + pad), np.uint8)
    rows[:, : width * layout.itemsize] = table.view(np.uint8).reshape(height, -1)
    time = types["builtin_interfaces/msg/Time"](sec=int(stamp), nanosec=int(round(stamp % 1 * 1e9)))
    header = types["std_msgs/msg/Header"](**({"seq": 0} if store is ROS1 else {}), stamp=time, frame_id="lidar")
    return types[CLOUD](
        header=header,
        height=height,
        width=width,
        is_bigendian=dtype.startswith(">"),
        is_dense=False,
        fields=[
            types["sensor_msgs/msg/PointField"](name=n, offset=i * size, datatype=codes[dtype], count=1)
            for i, n in enumerate(list(fields) + ["intensity"])
        ],
        point_step=layout.itemsize,
        row_step=rows.shape[1],
        data=rows.ravel(),
    )


def _corridor_lidar() -> Lidar:
    """A VLP-16 in a 200 m corridor: free along x only."""
    corridor = trimesh.creation.box([200, 4, 3]).apply_translation([0, 0, 0.5])
    return Lidar(EmbreeCaster(corridor, threads=1), LidarConfig())


def _corridor_scans(rng, n: int) -> list[np.ndarray]:
    lidar = _corridor_lidar()
    return [lidar.scan(np.eye(4), rng).points.astype(np.float32).astype(np.float64) for _ in range(n)]


def _write_bag(
    path, scans: list[np.ndarray], ros2: bool = False, broken: int | None = None, second_cloud: bool = False
) -> None:
    """`scans` on /velodyne_points at 10 Hz from t = 100 s (the scan at `broken` has no z field),
    and a string topic beside them."""
    store = ROS2 if ros2 else ROS1
    serialize = store.serialize_cdr if ros2 else store.serialize_ros1
    with Writer2(path, version=9) if ros2 else Writer1(path) as writer:
        clouds = writer.add_connection("/velodyne_points", CLOUD, typestore=store)
        notes = writer.add_connection("/notes", "std_msgs/msg/String", typestore=store)
        other = writer.add_connection("/front/points", CLOUD, typestore=store) if second_cloud else None
        for k, points in enumerate(scans):
            t = 100.0 + 0.1 * k
            msg = _cloud(store, points, t, fields="xy" if k == broken else "xyz")
            writer.write(clouds, int(t * 1e9), serialize(msg, CLOUD))
            writer.write(
                notes, int(t * 1e9) + 1, serialize(store.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String")
            )
            if other is not None:
                writer.write(other, int(t * 1e9) + 2, serialize(msg, CLOUD))


def test_cloud_points_unpacks_every_layout(rng):
    points = rng.normal(size=(60, 3)) * 10
    for kwargs in ({}, {"dtype": "<f8"}, {"dtype": ">f4"}, {"dtype": ">f8", "height": 3, "pad": 7}):
        read = cloud_points(_cloud(ROS1, points, 1.0, **kwargs))
        np.testing.assert_allclose(read, points, rtol=1e-6, err_msg=str(kwargs))
    with pytest.raises(BagError, match="not x, y and z"):
        cloud_points(_cloud(ROS1, points, 1.0, fields="xy"))
    cut = _cloud(ROS1, points, 1.0)
    cut.data = cut.data[:100]
    with pytest.raises(BagError, match="100 bytes of data"):
        cloud_points(cut)


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
@pytest.mark.slow
def test_a_bag_is_read_and_judged_as_the_same_scans_in_files(tmp_path, rng, ros2):
    scans = _corridor_scans(rng, 5)
    bag = tmp_path / ("run" if ros2 else "run.bag")
    _write_bag(bag, scans, ros2=ros2, broken=2)
    read = list(read_bag(bag, every=2))
    assert [s.name.split("#")[1] for s in read] == ["0", "2", "4"]
    assert [s.stamp for s in read] == pytest.approx([100.0, 100.2, 100.4])
    assert read[1].points is None and "not x, y and z" in read[1].error
    np.testing.assert_array_equal(read[2].points, scans[4])
    window = list(read_bag(bag, "/velodyne_points", start=0.15, end=0.35))
    assert [s.stamp for s in window] == pytest.approx([100.2, 100.3])

    files = []
    for k in (0, 2, 4):
        files.append(tmp_path / f"scan{k}.npy")
        np.save(files[-1], scans[k])
    from_bag = list(judge_scans(read_bag(bag, every=2), ["scanmc:4", "eigen:30"]))
    from_files = list(judge_scans(files, ["scanmc:4", "eigen:30"]))
    assert "not x, y and z" in from_bag[1].error and from_bag[1].stamp == pytest.approx(100.2)
    for b, f in ((from_bag[0], from_files[0]), (from_bag[2], from_files[2])):
        assert b.points == f.points
        for name in f.predictions:
            assert np.array_equal(b.predictions[name].probabilities, f.predictions[name].probabilities)
    assert from_bag[0].predictions["scanmc:4"].mask.tolist() == [True] + [False] * 5
    flags = flag_matrix(from_bag, "scanmc:4")
    assert flags[0, 0] == 1 and flags[1:, 0].sum() == 0 and np.isnan(flags[:, 1]).all()


def test_a_bag_or_topic_that_cannot_be_read_is_named(tmp_path, rng):
    with pytest.raises(BagError, match="no such bag"):
        read_bag(tmp_path / "missing.bag")
    (tmp_path / "junk.bag").write_bytes(b"not a bag")
    with pytest.raises(BagError, match="junk.bag: cannot be read as a ROS bag"):
        read_bag(tmp_path / "junk.bag")
    scans = _corridor_scans(rng, 1)
    _write_bag(tmp_path / "two.bag", scans, second_cloud=True)
    with pytest.raises(BagError, match=r"2 PointCloud2 topics \(/front/points, /velodyne_points\); name one"):
        read_bag(tmp_path / "two.bag")
    with pytest.raises(BagError, match="no topic '/lidar'; its PointCloud2 topics: /front/points, /velodyne"):
        read_bag(tmp_path / "two.bag", "/lidar")
    with pytest.raises(BagError, match="'/notes' carries std_msgs/msg/String, not sensor_msgs/msg/PointCloud2"):
        read_bag(tmp_path / "two.bag", "/notes")
    with pytest.raises(BagError, match="every must be at least 1"):
        read_bag(tmp_path / "two.bag", every=0)


def test_judge_cli_reads_a_bag_and_writes_scores_and_a_timeline(tmp_path, rng, capsys):
    bag = tmp_path / "run.bag"
    _write_bag(bag, _corridor_scans(rng, 3), broken=1)
    out, plot = tmp_path / "judged.json", tmp_path / "timeline.png"
    assert main(["judge", "--bag", str(bag), "--detector", "eigen:30", "--json", str(out), "--plot", str(plot)]) == 2
    captured = capsys.readouterr()
    assert "[t = 100.100 s] run.bag /velodyne_points #1: cannot be read" in captured.err
    assert "1 of 3 scans could not be read" in captured.err and "[t = 100.200 s]" in captured.out
    saved = json.loads(out.read_text())
    assert [round(r["stamp"], 3) for r in saved] == [100.0, 100.1, 100.2] and "error" in saved[1]
    assert saved[0]["detectors"]["eigen:30"]["known"]
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["judge"]) == 2 and main(["judge", "a.npy", "--bag", str(bag)]) == 2
    assert main(["judge", "a.npy", "--topic", "/points"]) == 2
    err = capsys.readouterr().err
    assert "not both and not neither" in err and "--topic, --every, --start and --end read a recording" in err
    assert main(["judge", "--bag", str(bag), "--start", "5", "--detector", "none"]) == 2
    assert "no scan in the recording between --start and --end" in capsys.readouterr().err
    assert main(["judge", "--bag", str(tmp_path / "missing.bag")]) == 2
    assert "missing.bag: no such bag" in capsys.readouterr().err


def _messages(bag, topic: str) -> list:
    with AnyReader([bag]) as reader:
        chosen = [c for c in reader.connections if c.topic == topic]
        return [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(chosen)]


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_a_drive_written_as_a_bag_reads_back_as_the_same_scans_and_poses(tmp_path, rng, ros2):
    lidar = _corridor_lidar()
    T_b_s = planar_pose(0.1, 0.0, 0.3, 0.0)
    truth = [planar_pose(0.5 * k, 0.2, 0.0, 0.1 * k) for k in range(3)]
    odom = [T @ planar_pose(0.01 * k, 0.0, 0.0, 0.0) for k, T in enumerate(truth)]
    scans = [lidar.scan(T @ T_b_s, rng) for T in truth]
    bag = tmp_path / ("drive" if ros2 else "drive.bag")
    writer = BagRecorder(bag, ros2=ros2)
    for scan, T, T_odom in zip(scans, truth, odom):
        writer(scan, {"T_w_b": T, "odom_T_w_b": T_odom, "T_b_s": T_b_s})
    assert not bag.exists()  # not there until closed: a killed drive leaves no half bag under its name
    assert writer.close() == bag and not (tmp_path / f"{bag.name}.partial").exists()

    read = list(read_bag(bag))
    assert [s.stamp for s in read] == pytest.approx([1.0, 1.1, 1.2])
    for got, scan in zip(read, scans):
        np.testing.assert_array_equal(got.points, scan.points.astype(np.float32))
        np.testing.assert_array_equal(got.rings, scan.beam)  # the ring field read back
    clouds = _messages(bag, "/points")
    assert [f.name for f in clouds[0].fields] == ["x", "y", "z", "ring"] and clouds[0].header.frame_id == "lidar"
    ring = clouds[1].data.view(np.dtype({"names": ["ring"], "formats": ["<u2"], "offsets": [12], "itemsize": 16}))
    np.testing.assert_array_equal(ring["ring"], scans[1].beam)
    np.testing.assert_array_equal(cloud_rings(clouds[1]), scans[1].beam)
    assert cloud_rings(_cloud(ROS1, scans[0].points, 1.0)) is None  # a cloud without a ring field
    truth_read = [(m.pose.position.x, m.pose.position.y, m.pose.orientation.z) for m in _messages(bag, "/ground_truth")]
    np.testing.assert_allclose(truth_read, [(0.5 * k, 0.2, np.sin(0.05 * k)) for k in range(3)], atol=1e-12)
    odom_msgs = _messages(bag, "/odom")
    odom_read = [(m.pose.pose.position.x, m.child_frame_id) for m in odom_msgs]
    assert odom_read == [(pytest.approx(0.5 * k + 0.01 * k * np.cos(0.1 * k)), "base_link") for k in range(3)]
    # the twist over the last step in the body frame, with the covariances of the odometry's noise model
    step = np.linalg.inv(odom[1]) @ odom[2]
    assert odom_msgs[2].twist.twist.linear.x == pytest.approx(step[0, 3] / 0.1)
    assert odom_msgs[2].twist.twist.angular.z == pytest.approx(0.1 / 0.1)
    covariance = [m.pose.covariance.reshape(6, 6) for m in odom_msgs]
    assert not covariance[0].any()  # the start is where odom is defined
    assert 0 < covariance[1][0, 0] < covariance[2][0, 0] and np.allclose(covariance[2], covariance[2].T)
    assert (np.diag(odom_msgs[1].twist.covariance.reshape(6, 6)) > 0).all()
    (mount,) = _messages(bag, "/tf_static")
    t = mount.transforms[0]
    assert (t.header.frame_id, t.child_frame_id) == ("base_link", "lidar")
    assert (t.transform.translation.x, t.transform.translation.z) == pytest.approx((0.1, 0.3))
    assert len(_messages(bag, "/tf")) == 3
    imu = _messages(bag, "/imu")  # 200 Hz over the drive's 0.2 s, turning at 1 rad/s
    assert len(imu) == 41 and imu[0].header.frame_id == "base_link"
    # a nine-axis unit's orientation, in the world frame, within its stated spread of the truth
    quaternion = [getattr(imu[20].orientation, a) for a in "xyzw"]
    heading = Rotation.from_quat(quaternion).as_euler("xyz")[2]
    sigma = np.sqrt(imu[20].orientation_covariance[8])
    assert sigma == pytest.approx(np.deg2rad(ImuConfig().heading_sigma_deg)) and abs(heading - 0.1) < 4 * sigma
    assert np.mean([m.angular_velocity.z for m in imu]) == pytest.approx(1.0, abs=0.01)
    assert np.mean([m.linear_acceleration.z for m in imu]) == pytest.approx(9.81, abs=0.05)
    assert imu[0].angular_velocity_covariance[0] == pytest.approx(ImuConfig().sigmas()[0] ** 2)


def test_judge_places_a_bags_scans_on_its_path_and_draws_the_map(tmp_path, rng, capsys):
    """`--path-plot`: each scan's position on the bag's odometry (or a pose topic named), in the
    JSON and on a map; a bag or topic without poses is refused before anything is judged."""
    lidar = _corridor_lidar()
    truth = [planar_pose(1.0 * k, 0.1 * k, 0.0, 0.05) for k in range(5)]
    odom = [T @ planar_pose(0.02 * k, 0.0, 0.0, 0.0) for k, T in enumerate(truth)]
    bag = tmp_path / "drive.bag"
    writer = BagRecorder(bag, imu=None)
    for T, T_odom in zip(truth, odom):
        writer(lidar.scan(T, rng), {"T_w_b": T, "odom_T_w_b": T_odom, "T_b_s": np.eye(4)})
    writer.close()
    out, plot = tmp_path / "j.json", tmp_path / "map.png"
    assert (
        main(
            [
                "judge",
                "--bag",
                str(bag),
                "--every",
                "2",
                "--detector",
                "eigen:30",
                "--json",
                str(out),
                "--path-plot",
                str(plot),
            ]
        )
        == 0
    )
    assert "written: " + str(plot) in capsys.readouterr().out and plot.read_bytes()[:4] == b"\x89PNG"
    saved = json.loads(out.read_text())
    np.testing.assert_allclose([r["position"] for r in saved], [odom[k][:3, 3] for k in (0, 2, 4)], atol=1e-9)
    assert (
        main(
            [
                "judge",
                "--bag",
                str(bag),
                "--every",
                "2",
                "--detector",
                "none",
                "--json",
                str(out),
                "--pose-topic",
                "/ground_truth",
            ]
        )
        == 0
    )
    np.testing.assert_allclose(
        [r["position"] for r in json.loads(out.read_text())], [truth[k][:3, 3] for k in (0, 2, 4)], atol=1e-9
    )
    path = read_path(bag)
    assert path.topic == "/odom" and len(path.stamps) == 5
    halfway = path.at(np.array([1.05, 0.5, 1.45]))  # between the first two poses, before and after the path
    np.testing.assert_allclose(halfway[0], (odom[0][:3, 3] + odom[1][:3, 3]) / 2, atol=1e-9)
    assert np.isnan(halfway[1:]).all()
    capsys.readouterr()
    assert main(["judge", "--bag", str(bag), "--path-plot", str(plot), "--pose-topic", "/points"]) == 2
    assert "'/points' carries sensor_msgs/msg/PointCloud2, not a pose" in capsys.readouterr().err
    bare = tmp_path / "bare.bag"
    _write_bag(bare, _corridor_scans(rng, 2))
    assert main(["judge", "--bag", str(bare), "--path-plot", str(plot)]) == 2
    assert "bare.bag: no pose topics (nav_msgs/Odometry" in capsys.readouterr().err
    assert main(["judge", "a.npy", "--path-plot", str(plot)]) == 2
    assert "read the path from a bag: give --bag" in capsys.readouterr().err


def test_a_bag_recorder_refuses_to_overwrite_and_clears_a_killed_drive(tmp_path, rng):
    (tmp_path / "old.bag").write_bytes(b"keep me")
    with pytest.raises(BagError, match="old.bag exists"):
        BagRecorder(tmp_path / "old.bag")
    assert (tmp_path / "old.bag").read_bytes() == b"keep me"
    with pytest.raises(BagError, match="ends in .bag"):
        BagRecorder(tmp_path / "run.db")
    killed = BagRecorder(tmp_path / "run.bag")
    killed(_corridor_lidar().scan(np.eye(4), rng), {"T_w_b": np.eye(4), "odom_T_w_b": np.eye(4), "T_b_s": np.eye(4)})
    del killed  # never closed
    again = BagRecorder(tmp_path / "run.bag", imu=None)
    again(_corridor_lidar().scan(np.eye(4), rng), {"T_w_b": np.eye(4), "odom_T_w_b": np.eye(4), "T_b_s": np.eye(4)})
    again.close()
    assert len(list(read_bag(tmp_path / "run.bag"))) == 1
    with AnyReader([tmp_path / "run.bag"]) as reader:  # without an IMU, no empty /imu topic either
        assert "/imu" not in {c.topic for c in reader.connections}
    six = tmp_path / "six.bag"
    writer = BagRecorder(six, imu=ImuConfig(orientation=False))
    for x in (0.0, 0.5):
        writer(
            _corridor_lidar().scan(np.eye(4), rng),
            {"T_w_b": planar_pose(x, 0, 0, 0), "odom_T_w_b": planar_pose(x, 0, 0, 0), "T_b_s": np.eye(4)},
        )
    writer.close()
    assert all(m.orientation_covariance[0] == -1 for m in _messages(six, "/imu"))  # REP 145: none


@pytest.mark.parametrize("model,field", [("vlp16", "time"), ("os0-128", "t"), ("sensor-in-ns", "t")])
def test_swept_scans_are_stamped_when_they_began_with_each_point_s_time(tmp_path, rng, monkeypatch, model, field):
    """As the drivers write them: the stamp at the revolution's start and each point's time since
    then, Velodyne's `time` in float32 seconds, Ouster's `t` in uint32 nanoseconds, as the
    pattern's `time_field` says whatever its name."""
    if model not in PATTERNS:
        monkeypatch.setitem(PATTERNS, model, dataclasses.replace(PATTERNS["vlp16"], name=model, time_field=field))
    corridor = trimesh.creation.box([200, 4, 3]).apply_translation([0, 0, 0.5])
    lidar = Lidar(EmbreeCaster(corridor, threads=1), LidarConfig(model=model))
    truth = [planar_pose(0.1 * k, 0.0, 0.0, 0.05 * k) for k in range(3)]
    scans = [lidar.scan(truth[0], rng)] + [lidar.scan(T, rng, start=before) for before, T in zip(truth, truth[1:])]
    scans[0] = lidar.scan(truth[0], rng, start=truth[0])  # the revolution before the start, standing
    bag = tmp_path / "swept.bag"
    writer = BagRecorder(bag, imu=ImuConfig(rate=100.0))
    for scan, T in zip(scans, truth):
        writer(scan, {"T_w_b": T, "odom_T_w_b": T, "T_b_s": np.eye(4)})
    writer.close()
    clouds = _messages(bag, "/points")
    stamps = [c.header.stamp.sec + 1e-9 * c.header.stamp.nanosec for c in clouds]
    assert stamps == pytest.approx([0.9, 1.0, 1.1])  # each a step before its pose
    imu = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in _messages(bag, "/imu")]
    assert imu[0] == pytest.approx(0.9) and imu[-1] == pytest.approx(1.2) and len(imu) == 31  # from the first scan
    assert [f.name for f in clouds[1].fields] == ["x", "y", "z", "ring", field] and clouds[1].point_step == 20
    kind = "<f4" if field == "time" else "<u4"
    times = clouds[2].data.view(np.dtype({"names": [field], "formats": [kind], "offsets": [16], "itemsize": 20}))
    expected = scans[2].times if field == "time" else np.round(scans[2].times.astype(np.float64) * 1e9)
    np.testing.assert_array_equal(times[field], expected)
    assert times[field].min() >= 0 and times[field].max() <= (0.1 if field == "time" else 1e8)
    np.testing.assert_array_equal(next(iter(read_bag(bag, topic="/points"))).points, scans[0].points)
    at_rest = BagRecorder(tmp_path / "still.bag", imu=None)  # a revolution at one pose: no times, its own stamp
    at_rest(lidar.scan(truth[0], rng), {"T_w_b": truth[0], "odom_T_w_b": truth[0], "T_b_s": np.eye(4)})
    at_rest.close()
    (still,) = _messages(tmp_path / "still.bag", "/points")
    assert [f.name for f in still.fields] == ["x", "y", "z", "ring"] and still.header.stamp.sec == 1


@pytest.mark.slow
def test_record_cli_writes_a_drive_that_judge_reads_back(tmp_path, capsys, rerun_table):
    bag, rec, rrd = tmp_path / "walls.bag", tmp_path / "walls.npz", tmp_path / "walls.rrd"
    argv = ["record", "--scene", "primitives-1", "--out", str(bag), "--recording", str(rec), "--rerun", str(rrd)]
    assert main([*argv, "--max-steps", "250", "--quiet"]) == 0  # 3 s standing, then 22 m between the walls
    from l3e_env.experiments.drive import DriveRecord

    recording = DriveRecord.load(rec)
    assert recording.sweep
    table = rerun_table(rrd, "step")  # the drive as a Rerun recording: its true path, step by step
    strips = next(c for c in table.column_names if c.startswith("/world/truth:") and c.endswith("strips"))
    truth = np.array([s[0][-1] for s in table.column(strips).to_pylist()])
    np.testing.assert_allclose(truth, recording.ground_truth[:, :3, 3], atol=1e-4)
    scans = list(read_bag(bag, every=200))
    assert len(scans) == len(range(0, len(recording.ground_truth), 200))
    assert main(["judge", "--bag", str(bag), "--every", "200", "--detector", "eigen:30"]) == 0
    said = capsys.readouterr().out
    assert said.count("eigen:30: not localizable along x") == len(scans)  # between two walls
    assert said.count("up from the bag's IMU /imu, the sensor tilted") == len(scans)  # not the ground's fit
    assert main(["record", "--scene", "primitives-1", "--out", str(bag), "--quiet"]) == 2
    assert "walls.bag exists" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # refused where the options are read, before the drive
        main(["record", "--out", str(tmp_path / "other.bag"), "--imu-rate", "-1", "--quiet"])
    assert "--imu-rate takes 0.0 or more, got '-1'" in capsys.readouterr().err
    imu = _messages(bag, "/imu")
    assert len(imu) == 20 * len(recording.ground_truth) + 1  # 200 Hz from the first swept scan to the last pose
    assert imu[0].orientation_covariance[0] > 0  # a nine-axis unit's orientation by default
    with AnyReader([bag]) as reader:  # swept by default: stamped a revolution before the first pose
        connection, _, raw = next(reader.messages([c for c in reader.connections if c.topic == "/points"]))
        first = reader.deserialize(raw, connection.msgtype)
    assert first.fields[-1].name == "time" and first.header.stamp.nanosec == pytest.approx(9e8, abs=1e3)
    vertical = np.array([m.linear_acceleration.z for m in imu])
    assert np.abs(vertical - 9.81).max() > 0.7 * ImuConfig().footfall_accel  # footfalls jolt it by default
    # the robot first stands for 3 s: an initialiser averaging /imu there sees gravity alone, level
    moved = np.linalg.norm(recording.ground_truth[:, :3, 3] - recording.ground_truth[0, :3, 3], axis=1)
    assert moved[:30].max() < 0.01 and moved[40] > 0.5
    at_rest = np.array(
        [[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for m in imu[:500]]
    ).mean(axis=0)  # its first 2.5 s
    assert np.degrees(np.arctan2(np.linalg.norm(at_rest[:2]), at_rest[2])) < 1.0


def test_a_stamp_a_hair_under_a_second_is_not_written_a_second_early():
    from l3e_env.io.rosbag import split_stamp

    assert split_stamp(3.9999999996) == (4, 0)  # rounding the fraction alone gave (3, 0): time ran back 1 s
    assert split_stamp(3.9999999) == (3, 999_999_900) and split_stamp(0.0) == (0, 0)
    stamps = np.arange(20_000) * 0.1 + 1e-10 * np.random.default_rng(0).standard_normal(20_000)
    parts = np.array([split_stamp(s) for s in np.sort(stamps)])
    assert (parts[:, 1] < 1_000_000_000).all() and (parts[:, 1] >= 0).all()
    total = parts[:, 0] * 1_000_000_000 + parts[:, 1]
    assert (np.diff(total) >= 0).all()  # the stamps of a drive never run back


def test_a_failed_or_stopped_record_leaves_no_half_written_bag(tmp_path, monkeypatch, capsys):
    def stopped(*args, **kwargs):
        raise RuntimeError("the drive was stopped")

    monkeypatch.setattr("l3e_env.experiments.drive.record_run", stopped)
    assert main(["record", "--scene", "primitives-1", "--out", str(tmp_path / "walls.bag"), "--quiet"]) == 2
    assert "the drive was stopped" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # neither the bag nor its .partial folder


def test_record_says_how_large_the_bag_may_grow_before_driving(tmp_path, capsys):
    import re

    assert (
        main(["record", "--scene", "primitives-1", "--out", str(tmp_path / "short.bag"), "--max-steps", "5", "--quiet"])
        == 0
    )
    said = re.search(r"recording about 6 scans of vlp16: the bag's scans take up to (\d+) MiB", capsys.readouterr().out)
    assert said and (tmp_path / "short.bag").stat().st_size <= 1.1 * int(said.group(1)) * 2**20


@pytest.mark.parametrize(
    "name, content, words",
    [
        ("notes.txt", b"hello\n", "cannot be read as a ROS bag .* give a ROS 1 .bag"),
        ("junk.bag", bytes(range(256)) * 4, "cannot be read as a ROS bag"),
        ("empty.osf", b"", "the file is empty; give an Ouster .osf or .pcap"),
    ],
)
def test_a_file_that_is_no_recording_is_named_with_what_to_give(tmp_path, name, content, words):
    from l3e_env.io.recorded import RecordingError
    from l3e_env.io.recordings import read_recording

    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=words) as caught:
        list(read_recording(path))
    assert str(path) in str(caught.value)


def test_an_empty_bag_or_one_of_unreadable_scans_says_why_without_blaming_options_not_given(tmp_path, rng, capsys):
    empty, broken = tmp_path / "empty.bag", tmp_path / "broken.bag"
    _write_bag(empty, [])
    assert main(["judge", "--bag", str(empty), "--detector", "none"]) == 2
    err = capsys.readouterr().err
    assert "no scan in the recording" in err and "--start" not in err
    _write_bag(broken, _corridor_scans(rng, 1), broken=0)
    assert main(["sensor", "--bag", str(broken)]) == 2
    err = capsys.readouterr().err
    assert "none of its 1 scan(s) could be read: the first, broken.bag /velodyne_points #0" in err
    assert main(["sensor", "--bag", str(empty)]) == 2
    assert "holds no scan" in capsys.readouterr().err


def test_the_up_direction_of_a_bags_imu_is_turned_into_the_clouds_frame_by_its_static_transforms():
    from scipy.spatial.transform import Rotation

    from l3e_env.io.imu_up import ImuUp

    # the IMU in base_link, the LiDAR pitched 20 deg on a mast (base_link -> mast -> lidar)
    mast = np.eye(4)
    mast[:3, 3] = (0.1, 0.0, 0.5)
    lidar = np.eye(4)
    lidar[:3, :3] = Rotation.from_euler("y", 20, degrees=True).as_matrix()
    stamps = np.arange(0.0, 2.0, 0.005)
    rng = np.random.default_rng(0)
    accel = np.tile([0.0, 0.0, 9.81], (len(stamps), 1)) + rng.normal(0.0, 0.5, (len(stamps), 3))
    imu = ImuUp("/imu", "base_link", stamps, accel, {"mast": ("base_link", mast), "lidar": ("mast", lidar)})
    up, said = imu.up_in("lidar", 1.0)
    assert up is not None and said == "from the bag's IMU /imu"
    expected = lidar[:3, :3].T @ [0.0, 0.0, 1.0]  # the world's up seen from the pitched LiDAR
    assert np.degrees(np.arccos(np.clip(up @ expected, -1, 1))) < 0.5
    assert imu.up_in("base_link", 1.0)[0] @ [0.0, 0.0, 1.0] > 0.999
    none, why = imu.up_in("camera", 1.0)
    assert none is None and "no /tf_static path to camera" in why
    none, why = imu.up_in("lidar", 10.0)
    assert none is None and "0 readings within 0.5 s" in why
    falling = ImuUp("/imu", "base_link", stamps, accel * 0.1, {})
    assert "not gravity" in falling.up_in("base_link", 1.0)[1]


def test_a_bag_without_an_imu_is_levelled_by_the_ground_and_says_why(tmp_path, rng, capsys):
    bag = tmp_path / "run.bag"
    _write_bag(bag, _corridor_scans(rng, 1))
    scan = next(iter(read_bag(bag)))
    assert scan.up is None and scan.up_source == "the bag has no IMU topic"
    assert main(["judge", "--bag", str(bag), "--detector", "eigen:30"]) == 0
    assert (
        "up from the ground plane's fit, the sensor tilted 0.0 deg (the bag has no IMU topic)"
        in capsys.readouterr().out
    )
