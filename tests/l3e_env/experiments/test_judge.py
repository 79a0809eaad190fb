"""`l3e judge`: scan files of every format read alike, and judged by the detectors."""

import json

import numpy as np
import pytest
import trimesh

from l3e_env.cli.main import main
from l3e_env.config import LidarConfig
from l3e_env.experiments.judge import JudgeOptions, format_judgement, judge_scans
from l3e_env.io.scan_files import ScanFileError, read_scan
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster


def _corridor_scan(rng) -> np.ndarray:
    """A VLP-16 scan in a 200 m corridor, 1 m above its floor: free along x only."""
    corridor = trimesh.creation.box([200, 4, 3]).apply_translation([0, 0, 0.5])
    return Lidar(EmbreeCaster(corridor, threads=1), LidarConfig()).scan(np.eye(4), rng).points.astype(np.float64)


def _write_pcd(path, points: np.ndarray, binary: bool) -> None:
    header = (
        f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    table = np.c_[points, np.arange(len(points))].astype(np.float32)
    with open(path, "wb") as f:
        f.write(header.encode())
        if binary:
            f.write(table.tobytes())
        else:
            np.savetxt(f, table, fmt="%.6f")


def test_every_format_reads_the_same_points(tmp_path, rng):
    points = rng.normal(size=(300, 3)) * 5
    np.save(tmp_path / "a.npy", np.c_[points, np.ones(300)])
    np.savez(tmp_path / "b.npz", points=points, other=np.zeros(3))
    np.c_[points, np.ones(300)].astype(np.float32).tofile(tmp_path / "c.bin")
    trimesh.PointCloud(points).export(tmp_path / "d.ply")
    _write_pcd(tmp_path / "e.pcd", points, binary=True)
    _write_pcd(tmp_path / "f.pcd", points, binary=False)
    np.savetxt(tmp_path / "g.xyz", points)
    np.savetxt(tmp_path / "h.csv", points, delimiter=",")
    for name in ("a.npy", "b.npz", "c.bin", "d.ply", "e.pcd", "f.pcd", "g.xyz", "h.csv"):
        read = read_scan(tmp_path / name)
        assert read.shape == (300, 3), name
        np.testing.assert_allclose(read, points, atol=1e-4, err_msg=name)  # float32 formats to 1e-4


def test_a_broken_or_unknown_scan_file_is_named(tmp_path):
    (tmp_path / "broken.npy").write_bytes(b"not numpy at all")
    np.save(tmp_path / "flat.npy", np.zeros((10, 2)))
    np.savez(tmp_path / "two.npz", a=np.zeros((3, 3)), b=np.zeros((3, 3)))
    np.zeros(7, np.float32).tofile(tmp_path / "odd.bin")
    (tmp_path / "stub.bin").write_bytes(b"abc")  # under one float: np.fromfile reads it as no points
    (tmp_path / "cut.pcd").write_bytes(
        b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 100\nDATA binary\n" + b"\0" * 40
    )
    (tmp_path / "packed.pcd").write_bytes(b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA binary_compressed\n")
    _write_pcd(tmp_path / "half.pcd", np.ones((20, 3)), binary=False)
    lines = (tmp_path / "half.pcd").read_bytes().splitlines(keepends=True)
    (tmp_path / "half.pcd").write_bytes(b"".join(lines[:-10]))  # ten rows of twenty: cut short
    np.save(tmp_path / "rows.npy", np.zeros((3, 500)))
    # x y z triples of 400 points: 4800 bytes divide by 16, and would read as 300 quadruples
    (np.random.default_rng(0).normal(size=(400, 3)) * 5).astype(np.float32).tofile(tmp_path / "triples.bin")
    cases = {
        "triples.bin": r"fourth float of \d+% of the points is negative.*save them as .npy",
        "broken.npy": "cannot be read as numpy",
        "flat.npy": r"shape \(10, 2\)",
        "two.npz": "name the points",
        "half.pcd": "the PCD header says 20 points and the file holds 10 rows",
        "rows.npy": r"shape \(3, 500\): a scan is \(N, 3\) or \(N, 4\), one point a row.*points.T",
        "odd.bin": "KITTI",
        "stub.bin": "3 bytes",
        "cut.pcd": "cut short",
        "packed.pcd": "ascii or binary",
        "scan.las": "unknown scan format",
        "missing.npy": "no such file",
    }
    for name, message in cases.items():
        with pytest.raises(ScanFileError, match=message) as info:
            read_scan(tmp_path / name)
        assert name in str(info.value)


def test_a_corridor_scan_is_judged_free_along_its_axis_and_no_return_points_are_dropped(tmp_path, rng):
    points = _corridor_scan(rng)
    with_gaps = np.r_[points, np.full((5, 3), np.nan), np.zeros((3, 3))]  # an organised cloud's empty returns
    _write_pcd(tmp_path / "corridor.pcd", with_gaps, binary=True)
    np.save(tmp_path / "empty.npy", np.zeros((0, 3)))
    first, empty = judge_scans(
        [tmp_path / "corridor.pcd", tmp_path / "empty.npy"], ["eigen:30", "scanmc:8", "learned", "none"]
    )  # a generator: unpacked
    assert first.points == len(points) and first.dropped == 8
    scanmc, eigen = first.predictions["scanmc:8"], first.predictions["eigen:30"]
    assert scanmc.known and scanmc.mask.tolist() == [True, False, False, False, False, False]
    assert eigen.known and eigen.mask[0] and not eigen.mask[1]
    assert first.predictions["learned"].known and not first.predictions["none"].mask.any()
    assert empty.points == 0 and not any(p.known for n, p in empty.predictions.items() if n != "none")
    text = format_judgement(first)
    assert "scanmc:8: not localizable along x" in text and "corridor.pcd: " in text
    assert "cannot judge this scan" in format_judgement(empty)
    with pytest.raises(ValueError, match="needs the scene"):
        list(judge_scans([tmp_path / "corridor.pcd"], ["oracle"]))
    with pytest.raises(ValueError, match="unknown LiDAR model"):
        list(judge_scans([tmp_path / "corridor.pcd"], ["none"], LidarConfig(model="hdl64")))


def test_the_judge_command_prints_and_writes_the_scores(tmp_path, rng, capsys):
    np.save(tmp_path / "corridor.npy", _corridor_scan(rng))
    out = tmp_path / "scores" / "judged.json"
    assert main(["judge", str(tmp_path / "corridor.npy"), "--detector", "eigen:30", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "eigen:30: not localizable along x" in printed and "share of the axis" in printed
    saved = json.loads(out.read_text())
    assert saved[0]["detectors"]["eigen:30"]["not_localizable"][0] == "x"
    assert saved[0]["sensor"] is None  # no detector asked here simulates the sensor
    np.save(tmp_path / "few.npy", _corridor_scan(rng)[:20])
    assert main(["judge", str(tmp_path / "few.npy"), "--detector", "eigen:30", "--json", str(out)]) == 0
    assert json.loads(out.read_text())[0]["detectors"]["eigen:30"] == {
        "known": False,
        "scores": [None] * 6,
        "not_localizable": [],
    }
    # a file that cannot be read is named, and the ones after it are still judged and saved
    assert (
        main(
            [
                "judge",
                str(tmp_path / "nothing.pcd"),
                str(tmp_path / "corridor.npy"),
                "--detector",
                "none",
                "--json",
                str(out),
            ]
        )
        == 2
    )
    captured = capsys.readouterr()
    assert "nothing.pcd: no such file" in captured.err and "1 of 2 scans could not be read or judged" in captured.err
    assert "none: localizable along every axis" in captured.out
    saved = json.loads(out.read_text())
    assert "no such file" in saved[0]["error"] and saved[1]["detectors"]["none"]["known"]
    # a scan in millimetres is not judged by any detector, and says why
    np.save(tmp_path / "millimetres.npy", _corridor_scan(rng) * 1000)
    assert (
        main(
            [
                "judge",
                str(tmp_path / "millimetres.npy"),
                "--detector",
                "eigen:30",
                "--detector",
                "learned",
                "--json",
                str(out),
            ]
        )
        == 2
    )
    assert "a scan in millimetres, or not in the sensor's frame?): not judged" in capsys.readouterr().err
    assert "beyond 1000 m" in json.loads(out.read_text())[0]["error"]


@pytest.mark.slow
def test_files_judged_by_two_workers_are_judged_alike_and_in_order(tmp_path, rng):
    np.save(tmp_path / "a.npy", _corridor_scan(rng))
    (tmp_path / "b.npy").write_bytes(b"broken")
    np.save(tmp_path / "c.npy", _corridor_scan(rng))
    paths = [tmp_path / n for n in ("a.npy", "b.npy", "c.npy")]
    alone = list(judge_scans(paths, ["scanmc:4", "eigen:30"]))
    shared = list(judge_scans(paths, ["scanmc:4", "eigen:30"], options=JudgeOptions(workers=2)))
    assert [j.path for j in shared] == [str(p) for p in paths] and "b.npy" in shared[1].error
    for a, b in zip(alone, shared):
        assert a.predictions.keys() == b.predictions.keys()
        for name in a.predictions:
            assert np.array_equal(a.predictions[name].probabilities, b.predictions[name].probabilities)
    assert shared[0].predictions["scanmc:4"].mask.tolist() == [True] + [False] * 5
    with pytest.raises(ValueError, match="workers must be at least 1"):
        list(judge_scans(paths, ["none"], options=JudgeOptions(workers=0)))


def test_the_cascade_judges_a_file_with_the_estimate_where_it_is_unsure(tmp_path, rng):
    from l3e_env.detection.detectors import make_detector
    from l3e_env.experiments.judge import level_pose, needs_sensor, score_legend, up_direction

    points = _corridor_scan(rng)
    np.save(tmp_path / "corridor.npy", points)
    (judged,) = judge_scans(
        [tmp_path / "corridor.npy"], ["learned+scanmc:100", "learned+scanmc:0", "learned"], LidarConfig()
    )
    checked = judged.predictions["learned+scanmc:100"]  # always unsure: the estimate, seeded by the file's place
    up, how = up_direction(points, None)  # levelled by the ground plane's fit, as the judgement says
    assert how.startswith("up from the ground plane's fit") and judged.up == how
    estimate = make_detector("scanmc", sensor=LidarConfig()).judge(
        points, np.random.default_rng([0, 0]), level_pose(up)
    )
    assert checked.known and checked.mask.tolist() == [True] + [False] * 5
    assert np.array_equal(checked.probabilities, estimate.probabilities)
    assert np.array_equal(
        judged.predictions["learned+scanmc:0"].probabilities, judged.predictions["learned"].probabilities
    )  # never unsure: the classifier alone
    assert needs_sensor(["learned+scanmc"]) and not needs_sensor(["learned"])
    assert "learned+scanmc: the classifier's probability where it is sure" in score_legend(["learned+scanmc:1"])


def test_a_cloud_larger_than_any_revolution_is_refused_by_name_before_any_work(tmp_path, capsys):
    from l3e_env.core.points import MAX_REVOLUTION_POINTS

    big = tmp_path / "map.npy"
    np.save(big, np.random.default_rng(0).uniform(-50, 50, (MAX_REVOLUTION_POINTS + 1, 3)).astype(np.float32))
    (judged,) = judge_scans([big], ["eigen:30", "scanmc:4"])
    assert judged.error and "more than any spinning LiDAR returns in one revolution" in judged.error
    assert "accumulated map" in judged.error and not judged.predictions
    assert main(["judge", str(big), "--detector", "learned"]) == 2
    said = capsys.readouterr()
    assert "accumulated map" in said.err and "1 of 1 scans could not be read or judged" in said.err


def test_a_ply_of_text_garbage_is_named_as_no_ply_point_cloud(tmp_path):
    from l3e_env.io.scan_files import ScanFileError, read_scan

    path = tmp_path / "bad.ply"
    path.write_text("ply\nformat ascii 1.0\ngarbage\n")
    with pytest.raises(ScanFileError, match=r"bad.ply: not a PLY point cloud: its header must open with 'ply'"):
        read_scan(path)


def test_scan_files_of_two_sensors_given_together_are_each_read_with_their_own(tmp_path):
    """The sensor recognised from the first file is not forced on the next: an OS0-128 scan judged
    after a VLP-16 one is read on its own beams, and scanmc judges both."""
    from l3e_env.config import LidarConfig
    from l3e_env.core.transforms import pose_to_matrix
    from l3e_env.experiments.judge import judge_scans
    from l3e_env.sim.lidar import Lidar
    from l3e_env.sim.raycast import EmbreeCaster
    from scenes import make_scene

    caster = EmbreeCaster(make_scene("office").mesh, threads=1)
    pose = pose_to_matrix(np.array([5.0, 0.0, 0.85, 0.0, 0.0, 0.3]))
    paths = []
    for model in ("vlp16", "os0-128"):
        paths.append(tmp_path / f"{model}.npy")
        np.save(paths[-1], Lidar(caster, LidarConfig(model=model)).scan(pose, np.random.default_rng(0)).points)
    judged = list(judge_scans(paths, ["scanmc:4"]))
    assert [j.sensor for j in judged] == ["vlp16", "os0-128"]
    assert all(j.error is None and j.predictions["scanmc:4"].known for j in judged)


def test_a_long_detector_name_keeps_its_columns_apart():
    import numpy as np

    from l3e_env.detection.detectors import Prediction
    from l3e_env.experiments.judge import Judgement

    names = ["learned:runs/a-long-folder/model.pt", "scanmc:60"]
    flagged = Prediction(np.linspace(0.1, 0.6, 6), np.array([0, 0, 0, 0, 0, 1], bool))
    table = format_judgement(Judgement("scan.npy", 1000, 0, {n: flagged for n in names})).splitlines()
    header, yaw = table[1], table[-3]
    assert f"  {names[0]}" in header and f"  {names[1]}" in header  # two spaces before each name
    assert len(header) == len(yaw) and yaw.endswith("0.60*")  # each score ends under its name, then its flag


def _tilted_corridor_scan(rng, pitch_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A VLP-16 pitched `pitch_deg` in the corridor, and the up direction in its frame."""
    from l3e_env.core.transforms import pose_to_matrix

    corridor = trimesh.creation.box([200, 4, 3]).apply_translation([0, 0, 0.5])
    T = pose_to_matrix([0, 0, 0, 0, np.radians(pitch_deg), 0])
    points = Lidar(EmbreeCaster(corridor, threads=1), LidarConfig()).scan(T, rng).points.astype(np.float64)
    return points, T[2, :3]


def test_a_tilted_scan_is_judged_in_its_level_frame_from_the_given_up_or_the_ground(tmp_path, rng, capsys):
    """Pitched 12 deg, the corridor's free axis is the sensor's x and z together; in the level frame it
    is x alone, whether the up direction is given or fitted to the ground, and the judgement says which."""
    points, up = _tilted_corridor_scan(rng, 12.0)
    np.save(tmp_path / "tilted.npy", points)
    specs = ["eigen:30", "dcreg:10", "xicp:100"]
    (fitted,) = judge_scans([tmp_path / "tilted.npy"], specs)
    (given,) = judge_scans([tmp_path / "tilted.npy"], specs, options=JudgeOptions(gravity=up))
    (unlevelled,) = judge_scans(
        [tmp_path / "tilted.npy"], specs, options=JudgeOptions(gravity=np.array([0.0, 0.0, 1.0]))
    )
    assert "ground plane's fit, the sensor tilted 12.0 deg" in fitted.up and "as given" in given.up
    for judged in (fitted, given):
        for name in ("eigen:30", "dcreg:10"):
            assert judged.predictions[name].mask[:3].tolist() == [True, False, False], (name, judged.predictions)
    share = unlevelled.predictions["eigen:30"].probabilities  # the free axis seen in the tilted sensor's own axes
    assert share[2] > 0.03 > given.predictions["eigen:30"].probabilities[2]
    given_up = "--gravity=" + ",".join(map(str, up))  # a negative first number: one word with its option
    assert main(["judge", str(tmp_path / "tilted.npy"), "--detector", "eigen:30", given_up]) == 0
    assert "up as given, the sensor tilted 12.0 deg" in capsys.readouterr().out


def test_bad_up_directions_are_refused_by_name(tmp_path, rng, capsys):
    points, up = _tilted_corridor_scan(rng, 0.0)
    np.save(tmp_path / "scan.npy", points)
    (down,) = judge_scans(
        [tmp_path / "scan.npy"], ["eigen:30"], options=JudgeOptions(gravity=np.array([1.0, 0.0, 0.1]))
    )
    assert down.error and "deg from the scan's ground plane" in down.error and not down.predictions
    (zero,) = judge_scans([tmp_path / "scan.npy"], ["eigen:30"], options=JudgeOptions(gravity=np.zeros(3)))
    assert zero.error and "up vector is zero" in zero.error
    rows = tmp_path / "up.txt"
    rows.write_text("0 0 1\n")
    judged = list(
        judge_scans(
            [tmp_path / "scan.npy", tmp_path / "scan.npy"],
            ["eigen:30"],
            options=JudgeOptions(gravity=np.loadtxt(rows, ndmin=2)),
        )
    )
    assert judged[0].error is None and "scan 2 has none" in judged[1].error
    assert main(["judge", str(tmp_path / "scan.npy"), "--detector", "eigen:30", "--gravity", "0,0,nan"]) == 2
    rows.write_text("0 0\n")
    assert main(["judge", str(tmp_path / "scan.npy"), "--detector", "eigen:30", "--gravity", str(rows)]) == 2
    assert "one X Y Z row per scan" in capsys.readouterr().err
    np.save(tmp_path / "walls.npy", points[points[:, 2] > -0.3])  # walls and ceiling: nothing level below the sensor
    (none,) = judge_scans([tmp_path / "walls.npy"], ["eigen:30"])
    assert none.error and "no ground plane could be fitted" in none.error and "--gravity" in none.error
    assert "holds no" not in none.error  # walls are geometry: no degeneracy to name


def test_a_scan_without_geometry_is_named_as_such(tmp_path):
    """Issue 98: every point at one place, or all on one line, is named, not only "no ground plane"."""
    np.save(tmp_path / "one.npy", np.tile([[2.0, 1.0, 0.5]], (500, 1)).astype(np.float32))
    line = np.linspace(-5.0, 5.0, 500)[:, None] * np.array([[1.0, 0.5, -0.2]])
    np.save(tmp_path / "line.npy", line.astype(np.float32))
    one, on_line = judge_scans([tmp_path / "one.npy", tmp_path / "line.npy"], ["eigen:30"])
    assert "every point of the scan lies at one place" in one.error and "--gravity" in one.error
    assert "the scan's points lie on one line" in on_line.error


def test_a_scan_a_detector_cannot_judge_is_told_with_the_detectors_own_reason(tmp_path, rng):
    points = _corridor_scan(rng)
    np.save(tmp_path / "few.npy", points[:40])
    (few,) = judge_scans([tmp_path / "few.npy"], ["learned"], options=JudgeOptions(gravity=np.array([0.0, 0.0, 1.0])))
    assert not few.predictions["learned"].known
    assert "cannot judge this scan (the scan has 40 points; the classifier needs at least 50)" in format_judgement(few)
    thinned = tmp_path / "thinned.npy"
    np.save(thinned, points[::3])  # every third return: no longer a revolution of the sensor's beams
    (sparse,) = judge_scans([thinned], ["scanmc:4"], LidarConfig())
    assert "returns have one beside them" in sparse.predictions["scanmc:4"].reason


@pytest.mark.parametrize("height_m", [6.0, 10.0])
def test_a_scan_from_a_tilted_mast_is_judged_without_a_given_up(tmp_path, rng, height_m):
    """An OS0-128 on a mast 6 or 10 m above a yard of sheds, tilted 25 deg: the ground is found below it
    (a small share of the returns, most of them far), and the learned model and scanmc judge the scan
    in its level frame with no --gravity."""
    from l3e_env.core.transforms import pose_to_matrix

    parts = [trimesh.creation.box([200, 200, 0.2]).apply_translation([0, 0, -0.1])]
    for k in range(8):
        angle, size = k * np.pi / 4, rng.uniform(3, 10, 3)
        parts.append(
            trimesh.creation.box(size).apply_translation([20 * np.cos(angle), 20 * np.sin(angle), size[2] / 2])
        )
    yard = trimesh.util.concatenate(parts)
    T = pose_to_matrix([0, 0, height_m, 0, np.radians(25.0), 0])
    points = Lidar(EmbreeCaster(yard, threads=1), LidarConfig(model="os0-128")).scan(T, rng).points
    np.save(tmp_path / "mast.npy", points.astype(np.float64))
    (judged,) = judge_scans([tmp_path / "mast.npy"], ["learned", "scanmc:8"], LidarConfig(model="os0-128"))
    assert judged.error is None and "ground plane's fit, the sensor tilted 25.0 deg" in judged.up, judged.up
    assert all(p.known for p in judged.predictions.values()), judged.predictions
