import numpy as np
import pytest

from l3e_env.detectors import EigenvalueDetector, NoDetector, make_detector
from l3e_env.experiment import Recording, evaluate, file_stem, format_table, record_run, register_sequence
from l3e_env.registration import RegistrationConfig


@pytest.fixture(scope="module")
def walls_run():
    rec = record_run("primitives-1", seed=0, progress=False)  # two parallel walls: along-wall x is degenerate
    return rec, register_sequence(rec, RegistrationConfig(), progress=False)


def test_masking_the_wall_axis_beats_full_icp(walls_run, tmp_path):
    rec, regs = walls_run
    assert len(rec.scans) == len(rec.ground_truth) == len(rec.odometry) + 1
    w = np.array([np.linalg.eigvalsh(r.hessian)[:2] for r in regs if r is not None])
    tau = float(np.sqrt(np.median(w[:, 0]) * np.median(w[:, 1])))  # between the free axis and the rest
    full, eigen = evaluate(rec, [NoDetector(), EigenvalueDetector(tau)], regs, progress=False)
    assert eigen.masks[:, 0].mean() > 0.8 and eigen.masks[:, 1:].mean() < 0.2
    assert eigen.ate < full.ate
    assert "eigen" in format_table([full.row(), eigen.row()])
    # a saved recording evaluates to the same numbers without driving again
    rec.save(tmp_path / "rec.npz")
    again = Recording.load(tmp_path / "rec.npz")
    registered = register_sequence(again, RegistrationConfig(), False)
    (eigen2,) = evaluate(again, [EigenvalueDetector(tau)], registered, progress=False)
    assert eigen2.ate == pytest.approx(eigen.ate, rel=1e-9)


def test_detector_specs_and_errors():
    assert make_detector("none").name == "none"
    assert make_detector("eigen:110").tau == 110.0
    with pytest.raises(ValueError, match="eigen:<tau>"):
        make_detector("eigen:lots")
    with pytest.raises(ValueError, match="positive"):
        make_detector("eigen:-3")
    with pytest.raises(ValueError, match="unknown detector"):
        make_detector("magic")
    with pytest.raises(ValueError, match="LiDAR"):
        make_detector("oracle")
    unknown = EigenvalueDetector(10.0).predict(np.zeros((5, 3)), None)
    assert not unknown.known and not unknown.mask.any()


def test_a_tau_is_reported_only_when_it_is_as_good_as_the_reference_everywhere():
    from l3e_env.sweep import beaten_everywhere

    results = {"tunnel": {"taus": [30.0, 110.0], "eigen_ate": [5.0, 1.0], "learned": 1.2},
               "field": {"taus": [30.0, 110.0], "eigen_ate": [0.5, 3.0], "learned": 0.6}}
    assert beaten_everywhere(results) == []
    results["field"]["eigen_ate"][1] = 0.6
    assert beaten_everywhere(results) == [110.0]


def test_detector_names_become_flat_file_names():
    assert file_stem("eigen:110") == "eigen_110"
    assert file_stem("learned:runs/a b/model.pt") == "learned_runs_a_b_model.pt"
    assert "/" not in file_stem("learned:/abs/path/model.pt")
