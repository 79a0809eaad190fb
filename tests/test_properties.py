"""Property-based tests of the input boundaries users reach: each states what the project promises for any
input of its kind (a clear error of a named type, or a finite answer), and hypothesis searches for a
counter-example."""

from __future__ import annotations

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

from l3e_env.config.detector_spec import DETECTOR_KINDS, parse_detector  # noqa: E402
from l3e_env.io.scan_files import ScanFileError, read_scan  # noqa: E402

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=32)
SMALL = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@SMALL
@given(
    array=hnp.arrays(
        st.sampled_from([np.float32, np.float64, np.int16, np.uint8]),
        hnp.array_shapes(min_dims=1, max_dims=3, max_side=6),
        elements=st.integers(0, 100),
    )
)
def test_any_npy_array_reads_as_points_or_is_refused_by_name(tmp_path, array):
    path = tmp_path / "scan.npy"
    np.save(path, array)
    try:
        points = read_scan(path)
    except ScanFileError as exc:
        assert str(path) in str(exc)
        return
    assert points.ndim == 2 and points.shape[1] == 3 and points.dtype == np.float64
    assert array.ndim == 2 and array.shape[1] >= 3 and len(points) == len(array)


@SMALL
@given(text=st.binary(max_size=200))
def test_any_bytes_in_a_scan_file_read_as_points_or_are_refused_by_name(tmp_path, text):
    for suffix in (".pcd", ".bin", ".xyz", ".npz", ".npy", ".ply", ".csv"):
        path = tmp_path / f"scan{suffix}"
        path.write_bytes(text)
        try:
            points = read_scan(path)
        except ScanFileError as exc:
            assert str(path) in str(exc)
            continue
        assert points.ndim == 2 and points.shape[1] == 3


@settings(max_examples=200, deadline=None)
@given(text=st.text(max_size=30))
def test_any_detector_spec_parses_or_is_refused_with_a_value_error(text):
    try:
        spec = parse_detector(text)
    except ValueError as exc:
        assert text in str(exc) or "eigenvalue threshold" in str(exc)
        return
    assert spec.kind in DETECTOR_KINDS
    assert spec.tau is None or spec.tau > 0
    assert spec.children is None or spec.children >= 1


@pytest.fixture(scope="module")
def learned():
    from l3e_env.detection.detectors import LearnedDetector

    return LearnedDetector()


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(points=hnp.arrays(np.float32, st.tuples(st.integers(0, 3000), st.just(3)), elements=FLOATS))
def test_any_scan_gets_finite_probabilities_or_unknown_from_the_learned_detector(learned, points):
    """Empty, tiny, NaN, infinite or far-away scans: a finite answer or 'unknown', never an exception."""
    prediction = learned.predict(points)
    if prediction.known:
        assert np.isfinite(prediction.probabilities).all() and prediction.mask.dtype == bool
    else:
        assert not prediction.mask.any()  # unknown masks nothing


@pytest.fixture(scope="module")
def tunnel_env():
    from l3e_env.envs.navigation import NavigationEnv

    env = NavigationEnv(dict(scene="tunnel"))
    env.reset(seed=0)
    yield env
    env.close()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(action=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=4))
def test_any_action_steps_the_environment_or_is_refused_with_a_value_error(tunnel_env, action):
    try:
        obs, reward, terminated, truncated, info = tunnel_env.step(action)
    except ValueError as exc:
        assert "action" in str(exc)
        return
    assert np.isfinite(reward) and np.isfinite(info["T_w_b"]).all()
    if terminated or truncated:
        tunnel_env.reset(seed=1)


YAML_VALUES = st.one_of(
    st.integers(-5, 5),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=6),
    st.lists(st.integers(-2, 2), max_size=2),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=1),
)


@SMALL
@given(
    option=st.sampled_from(["every", "workers", "seed", "start", "end"]),
    value=YAML_VALUES,
)
def test_any_option_value_from_set_is_typed_and_in_range_or_refused_naming_the_option(option, value, capsys):
    """`--set KEY=VALUE` (VALUE in YAML): the option gets a value of its own type and range (a whole
    number of 1 or more workers, a finite start), or the command stops naming the option."""
    import math

    import yaml

    from l3e_env.cli.main import build_parser
    from l3e_env.cli.option_files import MINIMUM, resolve

    text = yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()
    try:
        args = resolve(build_parser(), ["judge", "--bag", "x.bag", "--set", f"{option}={text}"])
    except SystemExit:
        assert option in capsys.readouterr().err
        return
    got = getattr(args, option)
    kind = float if option in ("start", "end") else int
    assert type(got) is kind and math.isfinite(got) and got >= MINIMUM[option], (value, got)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**12), 10**12) | st.floats(allow_nan=True) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12,
)
PATTERN_KEYS = [
    "elevations_deg",
    "columns",
    "max_range",
    "min_range",
    "azimuth_offsets_deg",
    "beam_origin_offset",
    "beam_vertical_offsets",
    "image_width",
    "spin",
    "scan_start_deg",
    "time_field",
    "beams",
    "from",
    "to",
]


@SMALL
@given(spec=st.dictionaries(st.sampled_from(PATTERN_KEYS), JSON_VALUES, max_size=8))
def test_any_beam_pattern_file_loads_or_is_refused_by_name(tmp_path, spec):
    """Whatever its values (huge counts among them), a pattern file loads as a checked pattern or is
    refused naming the file, before any array of its declared size is made."""
    import json

    from l3e_env.sim.patterns import PatternError, load_pattern

    path = tmp_path / "beams.json"
    path.write_text(json.dumps(spec))
    try:
        pattern = load_pattern(path)
    except PatternError as exc:
        assert str(path) in str(exc)
        return
    assert 1 <= pattern.n_beams <= 512 and pattern.n_azimuth >= 1


@SMALL
@given(meta=JSON_VALUES)
def test_any_policy_record_is_read_or_refused_by_name(tmp_path, meta):
    from policies.ppo import PolicyCheckpointError, _checked_meta

    path = tmp_path / "policy.json"
    try:
        checked = _checked_meta(path, meta)
    except PolicyCheckpointError as exc:
        assert str(path) in str(exc)
        return
    assert checked["fast_env"]["action_repeat"] >= 1


@SMALL
@given(data=st.binary(max_size=300))
def test_any_bytes_as_a_checkpoint_are_refused_by_name(tmp_path, data):
    from l3e_env.model.classifier import CheckpointError, Classifier

    path = tmp_path / "model.pt"
    path.write_bytes(data)
    with pytest.raises(CheckpointError, match=str(path)):
        Classifier.load(path)
