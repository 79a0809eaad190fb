"""`--rerun FILE.rrd`: a drive written as a Rerun recording and read back with rerun's own reader."""

import sys

import numpy as np
import pytest

from l3e_env.cli.main import main

rr = pytest.importorskip("rerun")


def _column(table, entity: str, component: str) -> list:
    name = next(c for c in table.column_names if c.startswith(f"{entity}:") and c.endswith(component))
    return table.column(name).to_pylist()


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
