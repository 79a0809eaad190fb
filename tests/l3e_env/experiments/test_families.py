import json

import pytest

from l3e_env.experiments.families import (
    FAILED,
    FamiliesOptions,
    format_families,
    run_families,
    verdict,
)


def drive(legs, none, learned):
    return {"odometry only": legs * 1.1, "odometry + attitude": legs, "none": none, "learned": learned}


def test_the_verdict_weighs_the_default_against_the_smaller_part_in_the_mean_and_on_each_drive():
    ok = verdict("tunnel", [drive(2.0, 0.5, 0.6), drive(3.0, 30.0, 1.0), drive(1.0, 0.01, 0.025)])
    assert ok.mean_ok and ok.drives_ok == [True, True, True]  # 0.6 <= 1.5 x 0.5; 0.025 within 2 cm of 0.01
    worse = verdict("yard", [drive(2.0, 0.1, 1.8), drive(2.0, 0.1, 0.1)])
    assert not worse.mean_ok and worse.drives_ok == [False, True]
    failed = verdict("cave", [drive(1.0, 0.5, 0.5), {FAILED: "the robot would be inside scene geometry"}])
    assert failed.mean_ok and failed.drives_ok == [True] and failed.failed
    table = format_families([ok, worse, failed])
    assert "| tunnel |" in table and "no (mean over, 1/2 drives)" in table and "a drive failed" in table


def test_options_are_checked_before_any_drive():
    for bad in (
        FamiliesOptions(families=("tunel",)),
        FamiliesOptions(seeds=0),
        FamiliesOptions(detectors=("none",)),
        FamiliesOptions(backend="slurm"),
    ):
        with pytest.raises(ValueError):
            bad.check()
    assert FamiliesOptions().key() != FamiliesOptions(detectors=("none", "learned")).key()


@pytest.mark.slow
def test_a_family_is_driven_once_fused_and_resumed(tmp_path):
    options = FamiliesOptions(families=("chamber",), seeds=1, detectors=("none", "learned"), oracle_seeds=0)
    run = run_families(tmp_path, options, progress=False)
    [chamber] = run.families
    assert set(chamber.ate) == {"odometry only", "odometry + attitude", "none", "learned"}
    assert chamber.ate["learned"][0] < chamber.ate["odometry + attitude"][0]
    rows = next(tmp_path.glob("drives/chamber-0/fused-*/rows.json"))
    made = rows.stat().st_mtime_ns
    again = run_families(tmp_path, options, progress=False)  # resumed: nothing driven or fused again
    assert rows.stat().st_mtime_ns == made and again.families[0].ate == chamber.ate
    assert json.loads((tmp_path / "families.json").read_text())["families"][0]["family"] == "chamber"
    assert (tmp_path / "families.png").stat().st_size > 0
