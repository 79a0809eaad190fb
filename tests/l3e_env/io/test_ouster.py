"""Ouster captures (Ouster's own test data, `tests/data/ouster`): read scan by scan through
ouster-sdk in the lidar frame, damaged ones refused by name, and judged alike by every route in."""

import json
import shutil
from itertools import islice
from pathlib import Path

import numpy as np
import pytest

from l3e_env.cli.main import main
from l3e_env.config import LidarConfig
from l3e_env.experiments.judge import judge_scans
from l3e_env.io.ouster import TURNED, CaptureError, read_capture
from l3e_env.sim.patterns import get_pattern, in_lidar_frame

DATA = Path(__file__).parents[2] / "data" / "ouster"
OS0 = DATA / "OS-0-128_v3.0.1_1024x10_20241017_141645.osf"
OS1_OSF = DATA / "OS-1-128_v2.3.0_1024x10_lb_n3.osf"
OS1_PCAP = DATA / "OS-1-128_v2.3.0_1024x10_lb_n3.pcap"
OS0_8 = DATA / "osf_fw_3.2_10scans.osf"
GOOD = {OS0: (3, 128), OS1_OSF: (3, 128), OS1_PCAP: (3, 128), OS0_8: (10, 8)}
BROKEN = sorted((DATA / "broken").glob("*.osf"))


def _metadata(capture: Path) -> Path:
    return capture.with_name(capture.stem + "_metadata.json")


@pytest.mark.parametrize("capture", list(GOOD), ids=lambda p: p.name)
def test_every_scan_of_a_capture_is_read_in_the_lidar_frame(capture):
    count, beams = GOOD[capture]
    scans = list(read_capture(capture))
    assert len(scans) == count
    for scan in scans:
        assert scan.error is None and scan.pattern.n_beams == beams and scan.frame == TURNED
        assert len(scan.points) == len(scan.rings) > 1000 and scan.rings.min() >= 0 and scan.rings.max() < beams
        # the returns lie on the metadata's beams as read, and not once turned back a second time
        assert in_lidar_frame(scan.points, scan.pattern)[1] is None
        assert np.mean(scan.pattern.locate(scan.points)[0] == scan.rings) > 0.9  # the beam each came on
    assert np.diff([s.stamp for s in scans]).min() > 0.03  # seconds, 10 Hz


def test_the_same_capture_as_osf_and_pcap_reads_alike():
    for a, b in zip(read_capture(OS1_OSF), read_capture(OS1_PCAP), strict=True):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.rings, b.rings)
        assert a.stamp == b.stamp and a.pattern == b.pattern


def test_a_part_revolution_is_named_and_every_every_start_end_pick_scans():
    first = next(read_capture(OS0))
    assert "a part revolution: 384 of 1024 columns" in first.name
    assert [s.name for s in read_capture(OS0_8, every=3)] == [f"{OS0_8.name} #{k}" for k in (0, 3, 6, 9)]
    assert [s.name for s in read_capture(OS0_8, start=0.25, end=0.55)] == [f"{OS0_8.name} #{k}" for k in (3, 4, 5)]


@pytest.mark.parametrize("broken", BROKEN, ids=lambda p: p.name)
def test_a_damaged_capture_is_refused_by_name(broken):
    try:
        scans = list(read_capture(broken))
    except CaptureError as exc:  # no scan in it at all
        assert str(broken) in str(exc) and "holds no scan" in str(exc)
        assert ("damaged" in str(exc)) == (broken.name != "empty_osf.osf")
        return
    assert scans and all(s.points is None and "could not decode" in s.error and broken.name in s.error for s in scans)


def test_a_pcap_without_its_metadata_names_the_fix(tmp_path):
    alone = tmp_path / "capture.pcap"
    shutil.copy(OS1_PCAP, alone)
    with pytest.raises(CaptureError, match="put its metadata JSON beside it as capture.json"):
        read_capture(alone)
    assert len(list(read_capture(alone, _metadata(OS1_PCAP)))) == 3
    for text in ("{not json", "[1, 2]"):  # metadata beside it, or given, that is no JSON object: named
        (tmp_path / "capture.json").write_text(text)
        with pytest.raises(CaptureError, match=r"capture.json: the metadata of capture.pcap is not"):
            read_capture(alone)
        with pytest.raises(CaptureError, match=rf"capture.json: the metadata of {OS1_PCAP.name} is not"):
            read_capture(OS1_PCAP, tmp_path / "capture.json")
    (tmp_path / "capture.json").unlink()
    # another sensor's metadata: its packets are not of that sensor
    with pytest.raises(CaptureError, match="hold no whole revolution for this metadata: the file is cut short, or"):
        read_capture(alone, _metadata(OS0))
    cut = tmp_path / "cut.pcap"  # issue 98: a capture cut to 100 bytes, its metadata good
    cut.write_bytes(OS1_PCAP.read_bytes()[:100])
    with pytest.raises(CaptureError, match="its 100 bytes hold no whole revolution"):
        read_capture(cut, _metadata(OS1_PCAP))
    with pytest.raises(CaptureError, match="no such capture"):
        read_capture(tmp_path / "nothere.osf")


def test_without_ouster_sdk_the_install_is_named(monkeypatch):
    import l3e_env.io.ouster as ouster

    monkeypatch.setitem(__import__("sys").modules, "ouster.sdk", None)
    monkeypatch.setattr(ouster, "_LOG", None)
    with pytest.raises(CaptureError, match="pip install --no-deps ouster-sdk"):
        read_capture(OS0_8)


def test_judge_reads_good_captures_and_names_the_broken_beside_them(tmp_path, capsys):
    out = tmp_path / "judged.json"
    assert main(["judge", str(OS0_8), *map(str, BROKEN), "--detector", "eigen:30", "--json", str(out)]) == 2
    records = json.loads(out.read_text())
    judged = [r for r in records if "error" not in r]
    assert len(judged) == 10 and all(r["sensor"] == OS0_8.stem and r["frame"] == TURNED for r in judged)
    refused = [r["path"] for r in records if "error" in r]
    assert len(refused) == 4 and all(any(b.name in path for path in refused) for b in BROKEN)
    assert "4 of 14 scans could not be read or judged" in capsys.readouterr().err


def _exported(capture: Path, folder: Path, frame: str) -> list[Path]:
    """The capture's scans written as .npy files, in the lidar frame or turned into the SDK's sensor frame."""
    paths = []
    for k, scan in enumerate(read_capture(capture)):
        points = scan.points
        if frame == "sensor":
            to_sensor = np.asarray(scan.pattern.lidar_to_sensor).reshape(4, 4)
            points = points @ to_sensor[:3, :3].T + to_sensor[:3, 3]
        paths.append(folder / f"{frame}-{k}.npy")
        np.save(paths[-1], points)
    return paths


def _decisions(scans, specs, sensor=None) -> list:
    return [
        None if j.error else {n: (p.known, tuple(p.mask)) for n, p in j.predictions.items()}
        for j in judge_scans(scans, specs, sensor)
    ]


@pytest.mark.slow
@pytest.mark.parametrize("capture", [OS1_OSF, OS0, OS0_8], ids=lambda p: p.name)
def test_every_route_in_gives_the_same_decisions(capture, tmp_path):
    """.osf, .pcap and exported arrays in either frame (with the metadata as --sensor): one set of
    decisions by every detector; and scanmc (with a few children: the routes, not its estimate, are
    what differs) judges the capture's first scan as its array in the lidar frame, where its beams
    come from the metadata given and not from the capture."""
    specs, costly = ["learned", "eigen:30", "dcreg:50"], ["scanmc:4"]
    sensor = LidarConfig(model=str(_metadata(capture)))
    arrays = _exported(capture, tmp_path, "lidar")
    routes = {
        "capture": _decisions([capture], specs),
        "capture, its metadata given": _decisions([capture], specs, sensor),
        "lidar-frame arrays": _decisions(arrays, specs, sensor),
        "sensor-frame arrays": _decisions(_exported(capture, tmp_path, "sensor"), specs, sensor),
    }
    if capture == OS1_OSF:  # the pcap reads as the same scans and sensor (the test above)
        routes["pcap"] = _decisions([OS1_PCAP], specs)
    first = routes.pop("capture")
    assert all(d is not None and all(known for known, _ in d.values()) for d in first)
    for route, decisions in routes.items():
        assert len(decisions) == len(first), route
        for judged, reference in zip(decisions, first):  # each route's detectors decide as the capture's
            assert judged is not None and judged == {name: reference[name] for name in judged}, route
    by_capture = _decisions(list(islice(read_capture(capture), 1)), costly)
    assert all(d is not None and all(known for known, _ in d.values()) for d in by_capture)
    assert _decisions(arrays[:1], costly, sensor) == by_capture
    assert get_pattern(str(_metadata(capture))).n_beams == GOOD[capture][1]


def test_the_cli_reads_a_capture_as_a_recording_and_its_sensor(tmp_path, capsys):
    alone = tmp_path / "capture.pcap"
    shutil.copy(OS1_PCAP, alone)
    out = tmp_path / "judged.json"
    assert (
        main(
            [
                "judge",
                "--bag",
                str(alone),
                "--sensor",
                str(_metadata(OS1_PCAP)),
                "--every",
                "2",
                "--detector",
                "eigen:30",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    assert [r["path"] for r in json.loads(out.read_text())] == ["capture.pcap #0", "capture.pcap #2"]
    assert main(["judge", "--bag", str(alone), "--topic", "/points"]) == 2
    assert "not an Ouster capture" in capsys.readouterr().err
    assert main(["sensor", str(OS0_8)]) == 0
    said = capsys.readouterr().out
    assert "8 beams" in said and "2048 columns" in said and "from the metadata" in said


def test_a_librarys_warning_is_a_line_of_the_commands_own(capsys):
    assert (
        main(["judge", "--bag", str(OS0_8), "--sensor", str(_metadata(OS0_8)), "--detector", "learned", "--every", "5"])
        == 0
    )
    err = capsys.readouterr().err
    assert "l3e judge: warning: the classifier was trained on vlp16 scans" in err and "UserWarning" not in err


@pytest.fixture(scope="module")
def two_sensors(tmp_path_factory) -> Path:
    """An .osf holding two sensors: the OS0-128 capture's three scans and the OS1-128 capture's three."""
    import ouster.sdk as sdk
    from ouster.sdk import osf

    sources = [sdk.open_source(str(OS0)), sdk.open_source(str(OS1_OSF))]
    path = tmp_path_factory.mktemp("two") / "two.osf"
    writer = osf.Writer(str(path), [s.sensor_info[0] for s in sources])
    for i, source in enumerate(sources):
        for frames in source:
            writer.save(i, frames[0])
    writer.close()
    return path


def test_a_capture_of_two_sensors_gives_each_sensors_scans_with_its_own_beams(two_sensors, tmp_path, capsys):
    scans = list(read_capture(two_sensors))
    names = [s.name.split(" (a part")[0] for s in scans]  # the OS0's first scan is a part revolution
    assert sorted(names) == sorted(f"two.osf sensor {i} #{k}" for i in (0, 1) for k in range(3))
    patterns = {name.split(" #")[0]: s.pattern for name, s in zip(names, scans)}
    assert {p.name for p in patterns.values()} == {"two-sensor0", "two-sensor1"}
    assert all(p.n_beams == 128 for p in patterns.values())
    alone = [s.points for s in read_capture(OS1_OSF)]
    second = [s for s in read_capture(two_sensors, sensor_index=1)]
    assert [s.name for s in second] == [f"two.osf sensor 1 #{k}" for k in range(3)]
    assert all(np.array_equal(a, s.points) for a, s in zip(alone, second))  # the same scans as the OS1's own file
    with pytest.raises(CaptureError, match=r"holds 2 sensor\(s\) \(0: .*1: .*\); --sensor-index 2 is none of them"):
        read_capture(two_sensors, sensor_index=2)
    with pytest.raises(CaptureError, match="holds the scans of 2 sensors .*pick one with --sensor-index"):
        read_capture(two_sensors, one_sensor=True)
    out, plot = tmp_path / "judged.json", tmp_path / "flags.png"
    args = ["judge", str(two_sensors), "--detector", "eigen:30", "--json", str(out), "--plot", str(plot)]
    assert main(args) == 0
    records = json.loads(out.read_text())
    assert len(records) == 6 and {r["sensor"] for r in records} == {"two-sensor0", "two-sensor1"}
    assert plot.stat().st_size > 10_000
    assert main([*args[:2], "--sensor-index", "0", *args[2:]]) == 0
    assert {r["sensor"] for r in json.loads(out.read_text())} == {"two-sensor0"}
    assert main(["sensor", str(two_sensors)]) == 2
    assert "pick one with --sensor-index" in capsys.readouterr().err
    assert main(["sensor", str(two_sensors), "--sensor-index", "1"]) == 0
    assert "128 beams" in capsys.readouterr().out


POSE_DELTA = DATA / "pose_delta_2_128.osf"


def test_the_sdks_warnings_are_no_damage_and_are_said_once_per_file():
    """A legacy two-sensor OSF on which the SDK logs warnings when it opens it: both sensors' scans are
    read whole, neither is called damaged, and the warning is said once, whichever sensor is read."""
    for index in (None, 0, 1):
        with pytest.warns(UserWarning, match="the Ouster SDK warns: Legacy OSF contains out-of-order data") as said:
            scans = list(read_capture(POSE_DELTA, sensor_index=index))
        assert len([w for w in said if "Ouster SDK warns" in str(w.message)]) == 1
        assert scans and all(s.error is None and len(s.points) > 200_000 for s in scans), [s.error for s in scans]
    for broken in BROKEN:  # what the SDK reports as an error stays damage: refused, or its scans named
        try:
            read = list(read_capture(broken))
        except CaptureError as exc:
            assert "damaged" in str(exc) or "empty" in str(exc), exc
        else:
            assert any(s.error and "damaged" in s.error for s in read), broken


@pytest.mark.slow
def test_every_sensor_of_a_real_two_sensor_capture_is_judged_by_the_classifier_and_scanmc(tmp_path):
    judged = list(judge_scans([POSE_DELTA], ["learned", "scanmc:4"]))  # a few children: whether it judges
    assert [j.error for j in judged] == [None, None]
    assert all(p.known for j in judged for p in j.predictions.values()), [j.predictions for j in judged]
    assert all(j.up and "tilted" in j.up for j in judged)
