import subprocess
import sys

import pytest
import torch
import yaml

from l3e_env.cli.main import build_parser, main
from l3e_env.cli.option_files import resolve
from l3e_env.cli.options import scene_params
from l3e_env.config import FusionSettings


def test_help_lists_the_subcommands():
    out = subprocess.run(
        [sys.executable, "-m", "l3e_env.cli.main", "--help"], capture_output=True, text=True, check=True
    ).stdout
    for cmd in ("demo", "scenes", "envs", "dataset", "train", "evaluate", "ate", "sweep"):
        assert cmd in out


def test_evaluate_reads_other_datasets_under_both_names():
    args = build_parser().parse_args(
        ["evaluate", "--checkpoint", "m.pt", "--dataset", "d", "--other-sensor", "os0", "--other", "rooms"]
    )
    assert args.other == ["os0", "rooms"]


@pytest.mark.parametrize(
    "argv",
    [
        ["scenes", "volcano"],
        ["ate", "--scene", "volcano", "--out", "{out}"],
        ["demo", "--scene", "volcano", "--out", "{out}"],
        ["sweep", "--scene", "tunnel", "--scene", "volcano", "--out", "{out}"],
        ["dataset", "generate", "--scenes", "tunnel-0,volcano-1", "--out", "{out}"],
        ["policy", "plan", "--scene", "fork-0,volcano", "--out", "{out}"],
    ],
)
def test_unknown_scene_is_refused_before_anything_is_written(argv, tmp_path, capsys):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        main([a.format(out=out) for a in argv])
    assert exit_info.value.code == 2
    assert "unknown scene 'volcano" in capsys.readouterr().err
    assert not out.exists()


def test_sensor_names_are_checked_at_parse_time(capsys):
    assert build_parser().parse_args(["ate", "--sensor", "os0-128"]).sensor == "os0-128"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["policy", "plan", "--sensor", "vlp32"])
    assert "unknown LiDAR model 'vlp32'" in capsys.readouterr().err


def test_mesh_options_apply_to_mesh_scenes_only(tmp_path, capsys):
    (tmp_path / "hall.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert main(["ate", "--scene", "mine", "--route", "r.csv", "--out", str(tmp_path / "a")]) == 2
    assert "--route is only for a scene given as a mesh file" in capsys.readouterr().err
    assert main(["demo", "--scene", str(tmp_path / "hall.obj"), "--out", str(tmp_path / "b")]) == 2
    assert "give its route: --route FILE" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    # more routes: the first is driven, all are paths to sample labels along
    (tmp_path / "r1.txt").write_text("0.1 0.1\n0.5 0.1\n")
    (tmp_path / "r2.txt").write_text("0.1 0.2\n0.1 0.6\n")
    args = build_parser().parse_args(
        [
            "ate",
            "--scene",
            str(tmp_path / "hall.obj"),
            "--route",
            str(tmp_path / "r1.txt"),
            "--route",
            str(tmp_path / "r2.txt"),
        ]
    )
    paths = scene_params(args)["sampling_paths"]
    assert [p[-1][:2] for p in paths] == [[0.5, 0.1], [0.1, 0.6]]


def test_sweep_thresholds_must_be_numbers(capsys):
    assert build_parser().parse_args(["sweep", "--taus", "10,30.5"]).taus == (10.0, 30.5)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["sweep", "--taus", "10,abc"])
    assert "expected comma-separated numbers" in capsys.readouterr().err


@pytest.mark.slow
def test_demo_drives_the_mine_and_writes_pictures(tmp_path, capsys, rerun_table):
    assert main(["demo", "--out", str(tmp_path), "--quiet"]) == 0
    names = {p.name for p in tmp_path.iterdir()}
    assert {
        "path_topdown.png",
        "scan_yard.png",
        "scan_tunnel.png",
        "scan_quarry.png",
        "config.yaml",
        "localizability.png",
    } <= names
    out = capsys.readouterr().out
    assert "flagged non-localizable by the learned detector" in out and "tunnel" in out
    assert all((tmp_path / n).stat().st_size > 10_000 for n in names if n.endswith(".png"))
    assert main(["judge", str(tmp_path / "scan_tunnel.npy"), "--detector", "eigen:30"]) == 0  # the README's
    assert "scan_tunnel.npy" in capsys.readouterr().out  # quickstart
    if "drive.rrd" in names:  # rerun-sdk installed (the dev extra): the drive's recording, and how to open it
        assert f"rerun {tmp_path / 'drive.rrd'}" in out and (tmp_path / "drive.rrd").stat().st_size < 100e6
        table = rerun_table(tmp_path / "drive.rrd", "step")
        entities = {c.split(":")[0] for c in table.column_names}
        assert {"/world/truth", "/world/scan", "/flags/x/probability", "/flags/yaw/flagged"} <= entities
        steps = int(out.split(" steps,")[0].split()[-1])
        assert table.column("step").to_pylist() == list(range(steps + 1))


def test_record_options_give_the_imu_asked_for():
    from l3e_env.cli.drive import record_imu

    default = record_imu(build_parser().parse_args(["record", "--out", "a.bag"]))
    assert default.footfall_accel > 0 and default.orientation and default.rate == 200.0
    quiet = record_imu(
        build_parser().parse_args(
            ["record", "--out", "a.bag", "--no-imu-footfalls", "--no-imu-orientation", "--imu-rate", "100"]
        )
    )
    assert quiet.footfall_accel == 0.0 and not quiet.orientation and quiet.rate == 100.0
    assert record_imu(build_parser().parse_args(["record", "--out", "a.bag", "--imu-rate", "0"])) is None


def test_options_come_from_a_yaml_file_the_command_line_and_set_in_that_order(tmp_path):
    from l3e_env.cli.option_files import resolve

    (tmp_path / "ate.yaml").write_text("scene: tunnel\nseed: 3\nodometry-bias: [yaw]\ndetector: [none, 'eigen:30']\n")
    args = resolve(build_parser(), ["ate", "--config", str(tmp_path / "ate.yaml")])
    assert (args.scene, args.seed, args.odometry_bias, args.detector) == ("tunnel", 3, ["yaw"], ["none", "eigen:30"])
    args = resolve(build_parser(), ["ate", "--config", str(tmp_path / "ate.yaml"), "--seed", "4"])
    assert args.seed == 4 and args.scene == "tunnel"  # the command line wins over the file
    args = resolve(
        build_parser(),
        [
            "ate",
            "--config",
            str(tmp_path / "ate.yaml"),
            "--seed",
            "4",
            "--set",
            "seed=5",
            "--set",
            "quiet=true",
            "--set",
            "up-axis=y",
        ],
    )
    assert (args.seed, args.quiet, args.up_axis) == (5, True, "y")  # --set wins over both
    args = resolve(build_parser(), ["train", "--dataset", "d", "--out", "o", "--set", "epochs=2"])
    assert args.epochs == 2 and args.config is None  # train keeps its own --config (a TrainConfig YAML)


def test_odometry_bias_axes_are_gathered_from_every_repeat_and_a_file():
    from l3e_env.cli.option_files import resolve
    from l3e_env.cli.options import fusion_settings

    args = resolve(build_parser(), ["ate", "--odometry-bias", "yaw", "--odometry-bias", "scale,z"])
    assert fusion_settings(args).odometry_bias == ("yaw", "scale", "z")
    args = resolve(build_parser(), ["ate", "--set", "odometry-bias=[yaw, scale]"])
    assert fusion_settings(args).odometry_bias == ("yaw", "scale")
    default = fusion_settings(resolve(build_parser(), ["ate"]))  # the one estimator's
    assert default == FusionSettings() and default.odometry_bias == ("yaw", "scale") and default.attitude == "tilt"
    assert fusion_settings(resolve(build_parser(), ["ate", "--odometry-bias", "none"])).odometry_bias == ()
    ekf = fusion_settings(resolve(build_parser(), ["ate", "--backend", "ekf"]))
    assert ekf.keyframe_distance == 0.0 and default.keyframe_distance == 4.0  # the EKF keeps no keyframe's pose
    with pytest.raises(ValueError, match="names an axis twice"):
        fusion_settings(resolve(build_parser(), ["ate", "--odometry-bias", "yaw", "--odometry-bias", "yaw"]))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["ate", "--set", "bogus=1"], "l3e ate has no option 'bogus'"),
        (["ate", "--set", "seeds"], "give KEY=VALUE"),
        (["ate", "--set", "detector=[none, 'foo']"], "option detector: unknown detector 'foo'"),
        (["ate", "--set", "backend=slam"], "option backend: 'slam' is not one of"),
        (["ate", "--set", "scene=no-such-family"], "option scene"),
        (["ate", "--set", "quiet=maybe"], "option quiet: give true or false"),
        (["ate", "--config", "CONFIG"], "give a YAML mapping of option names to values, not a list"),
        (["ate", "--config", "MISSING"], "cannot read the options"),
        (["ate", "--config", "BINARY"], "binary.yaml: cannot read the options as YAML"),
        (["ate", "--set", "out={a: 1}"], "option out: takes text (a path or a name), got {'a': 1}"),
        (["judge", "--set", "json=[a]", "x.npy"], "option json: takes text (a path or a name), got ['a']"),
        (["dataset", "generate", "--preset", "small"], "required: --out (on the command line, or in --config"),
    ],
)
def test_a_bad_option_file_or_pair_is_refused_by_name_before_anything_runs(tmp_path, capsys, argv, message):
    (tmp_path / "list.yaml").write_text("[1, 2]\n")
    (tmp_path / "binary.yaml").write_bytes(bytes(range(256)))
    files = {"CONFIG": "list.yaml", "MISSING": "none.yaml", "BINARY": "binary.yaml"}
    argv = [str(tmp_path / files[a]) if a in files else a for a in argv]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_a_run_writes_its_resolved_options_and_they_run_it_again(tmp_path, capsys):
    out = tmp_path / "vlp16.yaml"
    assert main(["sensor", "vlp16", "--out", str(out)]) == 0
    written = tmp_path / "vlp16.yaml.options.yaml"  # beside the file it made
    assert f"options: {written}" in capsys.readouterr().out
    options = yaml.safe_load(written.read_text())
    assert options["source"] == "vlp16" and options["out"] == str(out)
    out.unlink()
    assert main(["sensor", "--config", str(written)]) == 0 and out.is_file()  # the same run, from the file alone
    capsys.readouterr()
    assert main(["scenes", "tunnel"]) == 0 and "options:" not in capsys.readouterr().out  # it made nothing


def test_version_and_no_pybullet_banner_in_a_command_s_output():
    from importlib.metadata import version

    out = subprocess.run(
        [sys.executable, "-m", "l3e_env.cli.main", "--version"], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == f"l3e {version('l3e')}"
    out = subprocess.run(
        [sys.executable, "-m", "l3e_env.cli.main", "scenes", "tunnel"], capture_output=True, text=True, check=True
    )
    assert out.stdout.startswith("tunnel-0 (tunnel, seed 0)") and "pybullet build time" not in out.stdout + out.stderr
    assert "its route 108 m, a drive of about 108 s (1080 steps)" in out.stdout  # what a drive there will cost


@pytest.mark.slow
def test_a_short_run_stops_after_max_steps(tmp_path):
    import json

    assert (
        main(
            [
                "ate",
                "--scene",
                "primitives-1",
                "--detector",
                "none",
                "--max-steps",
                "20",
                "--quiet",
                "--out",
                str(tmp_path / "ate"),
            ]
        )
        == 0
    )
    results = json.loads((tmp_path / "ate" / "results.json").read_text())
    assert results["steps"] == 20 and results["registration"]["ground_normals"] is True  # the labels' registration
    with pytest.raises(SystemExit):
        main(["record", "--out", str(tmp_path / "r.bag"), "--max-steps", "-3"])


def _loaded_after(code: str) -> set[str]:
    """The modules (and their top-level packages) that a fresh interpreter has loaded after running `code`."""
    out = subprocess.run(
        [sys.executable, "-c", f"{code}\nimport sys\nprint(' '.join(sys.modules))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return set(out.split()) | {name.split(".")[0] for name in out.split()}


def test_short_commands_load_no_heavy_library():
    # the CLI's start-up and judging a scan with a classical detector: no torch, Gymnasium, trimesh,
    # pybullet or scipy.signal
    heavy = {"torch", "gymnasium", "trimesh", "pybullet", "networkx"}
    assert not _loaded_after("import l3e_env.cli.main; l3e_env.cli.main.build_parser()") & heavy
    assert not _loaded_after("import l3e_env.experiments.judge") & heavy
    assert "scipy.signal" not in _loaded_after("import l3e_env.io.rosbag")


def test_ids_are_registered_whichever_is_imported_first():
    check = "import gymnasium as gym\nassert gym.spec('l3e/Office-v0').max_episode_steps == 840"
    _loaded_after("import l3e_env\n" + check)
    _loaded_after(check.replace("import gymnasium as gym", "import gymnasium as gym\nimport l3e_env"))


def test_a_range_of_scene_variants_is_spelt_once():
    args = build_parser().parse_args(["policy", "evaluate", "--scene", "bypass-100..102,fork-3"])
    assert args.scene == [["bypass-100", "bypass-101", "bypass-102", "fork-3"]]
    for bad in ("bypass-9..3", "bypass-a..3", "volcano-1..2"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["policy", "evaluate", "--scene", bad])


def test_every_command_reports_an_error_one_way(tmp_path, capsys):
    """A usage error found by a command and an error raised by the library read alike: one line on
    stderr, `l3e <command>: error: ...`, and exit status 2."""
    cases = [
        (["sensor"], "l3e sensor: error: give a sensor (name or pattern file), a scan file or --bag"),
        (["ate", "--recording", "r.npz", "--seeds", "2"], "l3e ate: error: --seeds is 1 or more drives"),
        (["judge", "a.npy", "--bag", "b.bag"], "l3e judge: error: give scan files or --bag, not both"),
        (["judge", "a.npy", "--sensor-index", "5"], "l3e judge: error: --sensor-index chooses the sensor of an Ouster"),
        (["evaluate", "--other", str(tmp_path / "none")], f"l3e evaluate: error: {tmp_path / 'none'} is not a dataset"),
    ]
    for argv, said in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [err[0]] and err[0].startswith(said), (argv, err)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present: --device cuda runs")
@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--dataset", "{tmp}/nowhere", "--out", "{tmp}/run"],
        ["evaluate", "--dataset", "{tmp}/nowhere", "--out", "{tmp}/run"],
        ["judge", "{tmp}/scan.npy", "--detector", "learned"],
    ],
)
def test_a_missing_gpu_is_named_in_one_line_before_anything_is_read(argv, tmp_path, capsys):
    """--device cuda on a machine without a GPU: one line naming the fix, exit 2, nothing written."""
    assert main([a.format(tmp=tmp_path) for a in argv] + ["--device", "cuda"]) == 2
    said = capsys.readouterr().err.strip().splitlines()
    assert len(said) == 1 and "sees no CUDA GPU" in said[0] and "--device cpu" in said[0]
    assert not (tmp_path / "run").exists()
    assert main([a.format(tmp=tmp_path) for a in argv] + ["--device", "tpu"]) == 2
    assert "unknown device 'tpu'" in capsys.readouterr().err


BIG = "1000000000000"


@pytest.mark.parametrize(
    "argv",
    [
        ["judge", "x.npy", "--workers", BIG],
        ["judge", "x.npy", "--start", "1e300"],
        ["judge", "x.npy", "--every", "0"],
        ["dataset", "generate", "--out", "{tmp}/d", "--parents", BIG],
        ["dataset", "generate", "--out", "{tmp}/d", "--children", "100001"],
        ["ate", "--seeds", "100000"],
        ["record", "--out", "{tmp}/x.bag", "--imu-rate", "1e12"],
        ["policy", "map", "--resolution", "0.001"],
        ["policy", "map", "--resolution", "1e300"],
        ["policy", "evaluate", "--episodes", BIG],
        ["policy", "train", "--envs", BIG, "--out", "{tmp}/p"],
        ["demo", "--scale", "1e300"],
        ["train", "--dataset", "{tmp}/d", "--out", "{tmp}/r", "--epochs", "0"],
        ["adapt", "--scans", "{tmp}", "--out", "{tmp}/a", "--max-scans", "5"],
        ["ate", "--keyframe-distance", "1e300"],
        ["ate", "--keyframe-distance", "-5"],
        ["ate", "--detector-every", "0"],
        ["ate", "--detector-every", "101"],
        ["policy", "evaluate", "--lam", "1e300"],
        ["policy", "evaluate", "--stop-radius", "5"],
        ["train", "--dataset", "{tmp}/d", "--out", "{tmp}/r", "--lr", "1e300"],
        ["train", "--dataset", "{tmp}/d", "--out", "{tmp}/r", "--soft-labels", "-1"],
    ],
)
def test_every_count_and_size_has_bounds_checked_where_it_enters(argv, tmp_path, capsys):
    """Issue 90: a count or a size beyond any practical run is refused by name before work is sized."""
    with pytest.raises(SystemExit) as stop:
        main([a.format(tmp=tmp_path) for a in argv])
    assert stop.value.code == 2
    said = capsys.readouterr().err
    option = next(a for a in argv if a.startswith("--") and a not in ("--out", "--dataset", "--scans"))
    assert f"argument {option}: {option} takes" in said and ("or more" in said or "at most" in said)
    assert not any(tmp_path.iterdir())


def test_a_required_option_may_come_from_the_runs_own_options_file(tmp_path):
    (tmp_path / "options.yaml").write_text(f"out: {tmp_path / 'data'}\npreset: small\n")
    args = resolve(build_parser(), ["dataset", "generate", "--config", str(tmp_path / "options.yaml")])
    assert args.out == str(tmp_path / "data") and args.preset == "small"
    args = resolve(build_parser(), ["dataset", "generate", "--set", "out=elsewhere"])
    assert args.out == "elsewhere"
    # l3e train's --config is its TrainConfig; the run's own options.yaml given there is read as options
    (tmp_path / "train.yaml").write_text(f"dataset: [{tmp_path / 'd'}]\nout: {tmp_path / 'r'}\nsamples-per-epoch: 8\n")
    args = resolve(build_parser(), ["train", "--config", str(tmp_path / "train.yaml")])
    assert args.dataset == [str(tmp_path / "d")] and args.out == str(tmp_path / "r") and args.config is None
    assert args.samples_per_epoch == 8
    (tmp_path / "recipe.yaml").write_text("epochs: 2\n")
    args = resolve(build_parser(), ["train", "--config", str(tmp_path / "recipe.yaml"), "--dataset", "d", "--out", "r"])
    assert args.config == str(tmp_path / "recipe.yaml")


@pytest.mark.parametrize(
    "text, message",
    [
        ('batch_size: "8"\n', "TrainConfig: option batch_size takes a whole number, got '8'"),
        ("epochs: 2.5\n", "option epochs takes a whole number"),
        ("optimizer: [adam]\n", "option optimizer takes"),
        ('epochs: !!python/object/apply:os.system ["echo ran"]\n', "cannot be read as TrainConfig YAML"),
        ("[1, 2]\n", "give a YAML mapping of TrainConfig's options, not a list"),
    ],
)
def test_a_train_config_of_wrong_types_or_a_code_tag_is_refused_naming_the_file(tmp_path, capsys, text, message):
    (tmp_path / "train.yaml").write_text(text)
    argv = [
        "train",
        "--config",
        str(tmp_path / "train.yaml"),
        "--dataset",
        str(tmp_path),
        "--out",
        str(tmp_path / "run"),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'train.yaml'}: " in err and message in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()
