"""`--rerun FILE.rrd`: a drive written as a Rerun recording and read back with rerun's own reader."""

import sys

import numpy as np
import pytest

from l3e_env.cli.main import main

rr = pytest.importorskip("rerun")


def _column(table, entity: str, component: str) -> list:
    name = next(c for c in table.column_names if c.startswith(f"{entity}:") and c.endswith(component))
    return table.column(name).to_pylist()


@pytest.mark.slow
def test_an_ate_drive_is_recorded_with_every_row_and_read_back(cad_corridor, tmp_path, rerun_table):
    mesh, route = cad_corridor
    out, recording = tmp_path / "ate", tmp_path / "drive.rrd"
    args = ["ate", "--scene", str(mesh), "--route", str(route), "--up-axis", "y", "--scale", "0.001"]
    assert main([*args, "--detector", "eigen:30", "--out", str(out), "--rerun", str(recording), "--quiet"]) == 0
    table = rerun_table(recording, "step")
    entities = {c.split(":")[0] for c in table.column_names if c.startswith("/")}
    rows = ["odometry_only", "odometry___attitude", "eigen_30"]
    paths = {f"/world/estimate/{r}" for r in rows} | {f"/error/{r}" for r in rows}
    assert {"/world/truth", "/world/scan", *paths} <= entities
    assert {f"/flags/{axis}/{what}" for axis in ("x", "yaw") for what in ("probability", "flagged")} <= entities
    steps = table.column("step").to_pylist()
    assert steps == sorted(steps) and steps[0] == 0 and len(steps) == len(set(steps))
    truth = np.loadtxt(out / "trajectories" / "ground_truth.tum")
    assert len(steps) == len(truth)  # one row a step, the start's first
    for row, stem in (("eigen_30", "eigen_30"), ("odometry_only", "odometry_only")):
        strips = _column(table, f"/world/estimate/{row}", "strips")
        ends = np.array([s[0][-1] for s in strips])  # each step's segment ends at its estimate
        np.testing.assert_allclose(ends, np.loadtxt(out / "trajectories" / f"{stem}.tum")[:, 1:4], atol=1e-4)
    scans = [s for s in _column(table, "/world/scan", "positions") if s is not None]
    assert len(scans) == len(steps) and 100 < len(scans[5]) <= 3000
    flagged = [f for f in _column(table, "/flags/x/flagged", "scalars") if f is not None]
    assert len(flagged) == len(steps) - 1 and set(np.ravel(flagged)) <= {0.0, 1.0}


def test_rerun_is_refused_by_name_where_it_cannot_be_written(tmp_path, capsys, monkeypatch):
    with pytest.raises(SystemExit):
        main(["ate", "--scene", "tunnel-0", "--rerun", str(tmp_path / "drive.txt")])
    assert "a Rerun recording is a .rrd file" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "rerun", None)  # not installed
    args = ["ate", "--scene", "tunnel-0", "--rerun", str(tmp_path / "d.rrd"), "--out", str(tmp_path / "o")]
    assert main(args) == 2
    assert "pip install 'l3e[viewer]'" in capsys.readouterr().err


def test_judged_scans_are_recorded_each_as_its_own_entity_with_its_flags(tmp_path, rng, capsys, rerun_table):
    import json

    import trimesh

    from l3e_env.config import LidarConfig
    from l3e_env.sim.lidar import Lidar
    from l3e_env.sim.raycast import EmbreeCaster

    def scan(extents):
        room = trimesh.creation.box(extents).apply_translation([0.5, 0.3, 0.5])
        return Lidar(EmbreeCaster(room, threads=1), LidarConfig()).scan(np.eye(4), rng).points

    np.save(tmp_path / "corridor.npy", scan([200, 4, 3]))
    np.save(tmp_path / "hall.npy", scan([20, 14, 3]))
    files = [str(tmp_path / "corridor.npy"), str(tmp_path / "hall.npy")]
    judged = ["judge", *files, "--detector", "eigen:30", "--json", str(tmp_path / "j.json")]
    assert main([*judged, "--rerun", str(tmp_path / "judged.rrd")]) == 0
    assert f"rerun {tmp_path / 'judged.rrd'}" in capsys.readouterr().out
    table = rerun_table(tmp_path / "judged.rrd", "scan")
    entities = {c.split(":")[0] for c in table.column_names}
    assert {"/scans/corridor_npy", "/scans/hall_npy"} <= entities
    corridor = [p for p in _column(table, "/scans/corridor_npy", "positions") if p is not None]
    assert len(corridor) == 1 and 100 < len(corridor[0]) <= 3000
    written = json.loads((tmp_path / "j.json").read_text())
    flags = _column(table, "/flags/eigen_30/x/flagged", "scalars")
    assert [f[0] for f in flags if f is not None] == [
        float("x" in s["detectors"]["eigen:30"]["not_localizable"]) for s in written
    ]
    assert [f[0] for f in flags if f is not None] == [1.0, 0.0]  # the corridor's length, and the hall
