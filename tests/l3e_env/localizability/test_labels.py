import json
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

from l3e_env.core.transforms import matrix_to_pose, pose_to_matrix
from l3e_env.data.dataset import DatasetError, LabelDataset, label_statistics
from l3e_env.data.generation import config_for, generate
from l3e_env.localizability.labels import (
    LABEL_PROTOCOL,
    LabelConfig,
    SamplingError,
    label_parent,
    sample_parent_pose,
)
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import Scene, SceneError, make_scene

FAST = LabelConfig(children=30)


def labels_at(scene_name, pose, children=30, seed=0, registration=None):
    scene = make_scene(scene_name)
    lidar = Lidar(EmbreeCaster(scene.mesh, threads=1))
    cfg = LabelConfig(children=children)
    return label_parent(
        lidar, pose_to_matrix(np.array(pose)), np.random.default_rng(seed), cfg, registration or RegistrationConfig()
    )


def test_straight_tunnel_flags_its_axis_only():
    res = labels_at("tunnel", [50, 0, 0.85, 0, 0, 0])
    assert res.labels.tolist() == [1, 0, 0, 0, 0, 0], res.errors


def test_tunnel_axis_follows_the_sensor_frame():
    res = labels_at("tunnel", [50, 0, 0.85, 0, 0, np.pi / 2])  # sensor yawed: the tunnel runs along its y
    assert res.labels.tolist() == [0, 1, 0, 0, 0, 0], res.errors


@pytest.mark.parametrize("roll_pitch_deg", [(0, 3), (0, 8), (10, 10), (-10, 6)])
def test_a_tilted_parent_gets_the_level_parents_labels(roll_pitch_deg):
    """Protocol 3: the labels are written in the parent's level frame, so a tilted sensor does not turn
    the tunnel's free slide into z (in the sensor's frame a parent pitched 8 deg reads z 0.2 m)."""
    level = labels_at("tunnel", [50, 0, 0.85, 0, 0, 0], children=40)
    roll, pitch = np.radians(roll_pitch_deg)
    tilted = labels_at("tunnel", [50, 0, 0.85, roll, pitch, 0], children=40)
    assert tilted.labels.tolist() == level.labels.tolist() == [1, 0, 0, 0, 0, 0], (tilted.errors, level.errors)
    assert tilted.errors[2] < 0.02 and tilted.errors[1] < 0.02, tilted.errors  # held well below the 0.04 m threshold


def test_a_yawed_tunnel_flags_x_and_y_by_their_share_of_its_axis():
    res = labels_at("tunnel", [50, 0, 0.85, np.radians(8), 0, np.pi / 4], children=40)  # rolled, 45 deg across
    assert res.labels[:3].tolist() == [1, 1, 0], res.errors
    assert 0.5 < res.errors[0] / res.errors[1] < 2.0, res.errors


def test_feature_rich_room_is_localizable_everywhere():
    res = labels_at("office", [5, 0, 0.85, 0, 0, 0.3])
    assert res.labels.tolist() == [0, 0, 0, 0, 0, 0], res.errors


def test_open_plane_flags_x_y_and_yaw():
    res = labels_at("primitives-0", [0, 0, 0.85, 0, 0, 0])
    assert res.labels.tolist() == [1, 1, 0, 0, 0, 1], res.errors


@pytest.mark.parametrize(
    "scene, pose, free",
    [
        ("primitives-1", [0, 0, 0.85, 0, 0, 0], [1, 0, 0, 0, 0, 0]),  # two parallel walls: the axis along them
        ("primitives-2", [0, 0, 0.85, 0, 0, 0.3], [0, 0, 0, 0, 0, 0]),  # a closed room
        ("primitives-3", [0, 0, 0.85, 0, 0, 0], [0, 0, 0, 0, 0, 1]),  # a round room: yaw
    ],
)
def test_the_analytic_primitives_are_labelled_as_their_geometry_says(scene, pose, free):
    res = labels_at(scene, pose)
    assert res.labels.tolist() == free, res.errors


def test_a_round_pipe_flags_its_axis_and_the_turn_about_it():
    """The sensor sits below the pipe's axis, so a turn about the axis is a roll and a sideways shift
    together; pitch and yaw are held by the pipe's walls. The ground plane's normals would make the
    round floor flat and hold the roll: the registration keeps a curved floor's own normals."""
    res = labels_at("primitives-4", [0, 0, 0.85, 0, 0, 0])
    assert res.labels[[0, 1, 3, 4, 5]].tolist() == [1, 1, 1, 0, 0], res.errors
    assert np.degrees(res.errors[3]) > 3.0  # about what holding still leaves (4 deg for the 5 deg sigma)


def test_an_icp_that_holds_still_along_a_free_axis_labels_it_non_localizable():
    """With the ground plane's normals ICP holds still along the open plane's x and y: each child's
    error is its own offset, 0.1 m * sqrt(2/pi) = 0.080 m on average, under the paper's 0.1 m
    threshold and over this protocol's 0.04 m (docs/decisions.md)."""
    res = labels_at("primitives-0", [0, 0, 0.85, 0, 0, 0], children=60)
    assert (res.errors[:2] > 0.06).all() and (res.errors[:2] < 0.1).all(), res.errors
    assert res.labels[:2].tolist() == [1, 1]
    assert (res.errors[:2] < LabelConfig(thresholds=(0.1, 0.1, 0.1, 2, 2, 2)).threshold_vector()[:2]).all()


def test_parent_sampling_is_collision_free_and_seeded():
    scene = make_scene("office")
    caster = EmbreeCaster(scene.mesh, threads=1)
    poses = [sample_parent_pose(scene, caster, np.random.default_rng(3), FAST) for _ in range(2)]
    np.testing.assert_array_equal(poses[0], poses[1])
    rng = np.random.default_rng(4)
    for _ in range(20):
        T = sample_parent_pose(scene, caster, rng, FAST)
        assert 0.0 < T[2, 3] < 2.8  # between floor and ceiling
    bare = Scene("bare", scene.mesh, [], (0, 0, 0), (1, 1))
    with pytest.raises(SamplingError, match="no sampling paths"):
        sample_parent_pose(bare, caster, rng, FAST)


def test_level_preset_samples_operating_poses_along_the_path():
    scene = make_scene("tunnel-0")  # its sampling path runs along x
    caster = EmbreeCaster(scene.mesh, threads=1)
    cfg = config_for("level").labels
    rng = np.random.default_rng(5)
    poses = np.array([matrix_to_pose(sample_parent_pose(scene, caster, rng, cfg)) for _ in range(60)])
    assert np.abs(poses[:, 3:5]).max() < np.radians(12)  # 3 deg sigma: level within 4 sigma
    assert np.abs(poses[:, 2] - cfg.sensor_height).max() < 0.25
    off_axis = np.angle(np.exp(4j * poses[:, 5])) / 4  # distance to the nearest multiple of 90 deg
    assert np.abs(off_axis).max() < np.radians(60) and np.std(off_axis) < np.radians(25)
    turns = np.round(poses[:, 5] / (np.pi / 2)) % 4
    assert len(set(turns.tolist())) == 4  # along, against and across the path
    free = [matrix_to_pose(sample_parent_pose(scene, caster, rng, FAST))[3:5] for _ in range(60)]
    assert np.abs(free).max() > np.radians(15)  # the paper's sampling is not level
    with pytest.raises(SamplingError, match="heading 'sideways'"):
        sample_parent_pose(scene, caster, rng, LabelConfig(heading="sideways"))


def test_statistics_count_the_64_combinations():
    labels = np.array([[1, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0], [0] * 6, [1, 1, 0, 0, 0, 1]], dtype=np.uint8)
    stats = label_statistics(labels)
    assert stats["powerset_histogram"] == {"x": 2, "none": 1, "x+y+yaw": 1}
    assert stats["positive_rate"]["x"] == 0.75 and stats["positive_rate"]["z"] == 0.0


def small_config(**kw):
    return config_for(
        None, scenes=["tunnel-0", "office-0"], parents_per_scene=3, shard_size=2, labels={"children": 12}, **kw
    )


def test_same_seed_same_dataset_whatever_the_workers_and_after_a_resume(tmp_path):
    cfg = small_config()
    one = generate(tmp_path / "one", cfg, workers=1, progress=False)
    two = generate(tmp_path / "two", cfg, workers=2, progress=False)
    a, b = LabelDataset(tmp_path / "one"), LabelDataset(tmp_path / "two")
    assert one["count"] == two["count"] == len(a) == 6
    for key in ("points", "offsets", "poses", "errors", "labels", "scene"):
        np.testing.assert_array_equal(a.arrays[key], b.arrays[key])
    # a killed run: one shard missing, a half-written temporary left behind
    shards = sorted((tmp_path / "two" / "shards").glob("*.npz"))
    kept = shards[0].read_bytes()
    shards[1].unlink()
    (tmp_path / "two" / "shards" / (shards[1].name + ".tmp")).write_bytes(b"half")
    generate(tmp_path / "two", cfg, workers=1, progress=False)
    assert shards[0].read_bytes() == kept  # finished work is not redone
    c = LabelDataset(tmp_path / "two")
    np.testing.assert_array_equal(a.arrays["errors"], c.arrays["errors"])
    assert c.scan(1).shape[1] == 3 and c.scan(1).dtype == np.float32
    manifest = json.loads((tmp_path / "two" / "manifest.json").read_text())
    assert manifest["settings"]["registration"]["max_correspondence_distance"] == [2.0, 0.5]
    assert manifest["statistics"]["positive_rate"]["x"] > 0  # the tunnel parents


def test_resuming_with_other_settings_or_reading_unfinished_data_is_refused(tmp_path):
    generate(tmp_path / "d", small_config(), workers=1, progress=False)
    with pytest.raises(DatasetError, match="other settings \\(seed 0, now 5\\)"):
        generate(tmp_path / "d", small_config(seed=5), workers=1, progress=False)
    # a folder begun before an option existed (its manifest lacks the LiDAR's sweep) resumes, since
    # it was made as that option's default makes it; an option no config knows is another dataset
    path = tmp_path / "d" / "manifest.json"
    manifest = json.loads(path.read_text())
    del manifest["settings"]["lidar"]["sweep"]
    path.write_text(json.dumps(manifest))
    assert generate(tmp_path / "d", small_config(), workers=1, progress=False)["count"] == 6
    manifest["settings"]["lidar"]["wobble"] = 1.0
    path.write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="other settings"):
        generate(tmp_path / "d", small_config(), workers=1, progress=False)
    (tmp_path / "e").mkdir()
    with pytest.raises(DatasetError, match="not a dataset"):
        LabelDataset(tmp_path / "e")
    with pytest.raises(DatasetError, match="unknown preset"):
        config_for("huge")
    with pytest.raises(SceneError, match="unknown scene 'volcano-0'"):
        generate(tmp_path / "f", config_for(None, scenes=["tunnel-0", "volcano-0"]), workers=1, progress=False)
    with pytest.raises(DatasetError, match="parents_per_scene must be at least 1, got 0; unknown LiDAR model 'vlp32'"):
        generate(tmp_path / "f", config_for(None, parents_per_scene=0, lidar={"model": "vlp32"}), progress=False)
    assert not (tmp_path / "f").exists()


@pytest.mark.slow
def test_a_users_mesh_is_labelled_resumed_by_its_own_bytes_and_scored(cad_corridor, tmp_path, capsys, monkeypatch):
    """`l3e dataset generate --scenes corridor.obj --route ...` and then `l3e evaluate --other` alone:
    how the shipped model does on a user's own scene, without the training data."""
    from l3e_env.cli.main import main
    from l3e_env.model.classifier import load_checkpoint

    mesh, route = cad_corridor
    out, args = (
        tmp_path / "d",
        ["--up-axis", "y", "--scale", "0.001", "--parents", "2", "--children", "5", "--workers", "1", "--quiet"],
    )
    assert (
        main(["dataset", "generate", "--out", str(out), "--scenes", f"{mesh},office-0", "--route", str(route), *args])
        == 0
    )
    data = LabelDataset(out)
    assert data.manifest["scenes"] == [str(mesh.resolve()), "office-0"]
    assert sorted(p.name for p in (out / "shards").glob("*.npz")) == ["mesh0-corridor-00000.npz", "office-0-00000.npz"]
    mesh_rows = np.flatnonzero(np.asarray(data.arrays["scene"]) == 0)
    assert len(mesh_rows) == 2
    ground = data.poses[mesh_rows][:, :3, 3]  # sampled along the route: 1-8 m down the corridor, on its floor
    assert (ground[:, 0] > 0.5).all() and (ground[:, 0] < 8.5).all() and (np.abs(ground[:, 1]) < 1.7).all()
    assert (np.abs(ground[:, 2] - 0.85) < 1.2).all()
    capsys.readouterr()
    assert (
        main(
            [
                "evaluate",
                "--other",
                str(out),
                "--by-family",
                "--by-region",
                "--out",
                str(tmp_path / "ev"),
                "--scan-mc",
                "3",
                "--cascade",
                "1",
                "--quiet",
            ]
        )
        == 0
    )
    lines = capsys.readouterr().out.splitlines()
    written = next(line for line in lines if line.startswith("written: "))  # the cascade's figure among the others
    assert written.endswith(str(tmp_path / "ev" / "cascade.png"))
    assert lines[-1].startswith(f"options: {tmp_path / 'ev' / 'options.yaml'}")
    assert (tmp_path / "ev" / "cascade.png").exists()
    columns = json.loads((tmp_path / "ev" / "results.json").read_text())["models"]["resunet"]["splits"]
    assert columns["all of d"]["count"] == 4 and columns["corridor of d"]["count"] == 2
    assert set(columns) == {"all of d", "corridor of d", "office of d"}  # a mesh, and the office, name no regions
    # a training config names the mesh relative to the folder it runs in; the checkpoint, for good
    monkeypatch.chdir(mesh.parent)
    Path("split.yaml").write_text("train_scenes: [corridor.obj]\nvalidation_scenes: [office-0]\nsamples_per_epoch: 4\n")
    assert (
        main(["train", "--dataset", str(out), "--out", "run", "--config", "split.yaml", "--epochs", "1", "--quiet"])
        == 0
    )
    assert load_checkpoint("run/model.pt")["training"]["train_scenes"] == [str(mesh.resolve())]
    assert np.isfinite(json.loads(Path("run/log.jsonl").read_text())["train_loss"])  # 4 samples: still one batch
    # the same command resumes; another route, or the mesh file edited, is another dataset
    assert (
        main(["dataset", "generate", "--out", str(out), "--scenes", f"{mesh},office-0", "--route", str(route), *args])
        == 0
    )
    np.savetxt(tmp_path / "other.csv", [[1000.0, 0, 0], [6000, 0, 0]])
    assert (
        main(
            [
                "dataset",
                "generate",
                "--out",
                str(out),
                "--scenes",
                f"{mesh},office-0",
                "--route",
                str(tmp_path / "other.csv"),
                *args,
            ]
        )
        == 2
    )
    assert "other settings (scene_params." in capsys.readouterr().err
    mesh.write_text(mesh.read_text() + "# edited\n")
    assert (
        main(["dataset", "generate", "--out", str(out), "--scenes", f"{mesh},office-0", "--route", str(route), *args])
        == 2
    )
    assert "other settings (mesh_sha256." in capsys.readouterr().err
    # a mesh needs its route, one mesh a dataset, mesh options a mesh; all refused before the folder
    for scenes, extra, message in [
        (str(mesh), [], "give its route"),
        (f"{mesh},{mesh}", ["--route", str(route)], "one mesh file in --scenes"),
        ("office-0", ["--route", str(route)], "only for a scene given as a mesh"),
    ]:
        assert main(["dataset", "generate", "--out", str(tmp_path / "no"), "--scenes", scenes, *extra]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


def test_several_meshes_are_labelled_from_a_list_with_their_own_routes_axes_and_scales(cad_corridor, tmp_path, capsys):
    from l3e_env.cli.main import main

    mesh, route = cad_corridor  # y up, millimetres
    folder = tmp_path / "meshes"
    folder.mkdir()
    z_up = trimesh.load(mesh, force="mesh")
    z_up.vertices = z_up.vertices @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]).T / 1000  # z up, metres
    z_up.export(folder / "plain.stl")
    np.savetxt(folder / "plain.txt", [[1.0, 0], [8, 0]])
    listing = folder / "list.yaml"
    listing.write_text(
        f"- mesh: {mesh}\n  route: [{route}]\n  up_axis: y\n  scale: 0.001\n- mesh: plain.stl\n  route: plain.txt\n"
    )  # relative to the list's folder
    out = tmp_path / "d"
    assert (
        main(
            [
                "dataset",
                "generate",
                "--out",
                str(out),
                "--meshes",
                str(listing),
                "--parents",
                "2",
                "--children",
                "5",
                "--workers",
                "1",
                "--quiet",
            ]
        )
        == 0
    )
    data = LabelDataset(out)
    assert data.manifest["scenes"] == [str(mesh.resolve()), str((folder / "plain.stl").resolve())]
    scene = np.asarray(data.arrays["scene"])
    for i in (0, 1):  # each sampled along its own route, on its own floor, in metres
        ground = data.poses[scene == i][:, :3, 3]
        assert len(ground) == 2 and (ground[:, 0] > 0.5).all() and (ground[:, 0] < 8.5).all()
        assert (np.abs(ground[:, 1]) < 1.7).all() and (np.abs(ground[:, 2] - 0.85) < 1.2).all()
    # a malformed list is named, and refused before the folder
    for text, message in [
        ("mesh: a.obj", "give a list of meshes"),
        ("- mesh: plain.stl", "give 'mesh'"),
        ("- mesh: plain.stl\n  route: plain.txt\n  units: mm", "unknown keys"),
        ("- mesh: plain.stl\n  route: plain.txt\n  scale: mm", "mesh 1: scale is metres"),
        ("- mesh: plain.stl\n  route: missing.txt", "route file not found"),
    ]:
        listing.write_text(text)
        assert main(["dataset", "generate", "--out", str(tmp_path / "no"), "--meshes", str(listing)]) == 2
        assert message in capsys.readouterr().err
    assert (
        main(["dataset", "generate", "--out", str(tmp_path / "no"), "--meshes", str(listing), "--route", str(route)])
        == 2
    )
    assert "give no other mesh scene" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


@pytest.mark.slow
def test_ray_backend_gives_the_same_dataset(tmp_path):
    pytest.importorskip("ray")
    cfg = config_for(None, scenes=["office-0"], parents_per_scene=2, shard_size=1, labels={"children": 8})
    generate(tmp_path / "local", cfg, workers=1, progress=False)
    generate(tmp_path / "ray", cfg, workers=2, backend="ray", progress=False)
    a, b = LabelDataset(tmp_path / "local"), LabelDataset(tmp_path / "ray")
    for key in ("points", "errors", "labels", "poses"):
        np.testing.assert_array_equal(a.arrays[key], b.arrays[key])


def test_a_full_disk_is_a_clear_error_and_keeps_finished_shards(tmp_path, monkeypatch):
    import errno

    import l3e_env.data.generation as ds

    cfg = config_for(None, scenes=["office-0"], parents_per_scene=2, shard_size=1, labels={"children": 6})
    real_savez, calls = np.savez, []

    def savez_then_full(fh, **arrays):
        calls.append(1)
        if len(calls) > 1:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_savez(fh, **arrays)

    monkeypatch.setattr(ds.np, "savez", savez_then_full)
    with pytest.raises(DatasetError, match="No space left.*resume"):
        generate(tmp_path, cfg, workers=1, progress=False)
    shards = sorted(p.name for p in (tmp_path / "shards").iterdir())
    assert shards == ["office-0-00000.npz"]  # the finished shard stays, no temporary is left
    monkeypatch.setattr(ds.np, "savez", real_savez)
    assert generate(tmp_path, cfg, workers=1, progress=False)["count"] == 2


def test_a_damaged_dataset_names_the_file_that_is_damaged(tiny_dataset, tmp_path):
    """A cut-short shard, manifest or array gives an error naming the file, not a zipfile or JSON traceback."""
    import shutil

    from l3e_env.data.dataset import DatasetError, LabelDataset
    from l3e_env.data.generation import config_for, consolidate

    copy = tmp_path / "copy"
    shutil.copytree(tiny_dataset, copy)
    points = copy / "points.npy"
    points.write_bytes(points.read_bytes()[:200])
    with pytest.raises(DatasetError, match="points.npy cannot be read"):
        LabelDataset(copy)
    (copy / "manifest.json").write_text('{"complete": tr')
    with pytest.raises(DatasetError, match="manifest.json cannot be read"):
        LabelDataset(copy)
    cfg = config_for(
        None, scenes=["tunnel-0", "office-0", "field-0"], parents_per_scene=4, shard_size=2, labels={"children": 8}
    )
    shard = sorted((copy / "shards").glob("*.npz"))[0]
    shard.write_bytes(shard.read_bytes()[:100])
    with pytest.raises(DatasetError, match=f"shard {shard} is unreadable.*delete it and run again"):
        consolidate(copy, cfg, {})


def test_two_runs_into_one_dataset_folder_are_refused_by_name(tmp_path):
    from l3e_env.core.files import FolderBusyError, folder_lock
    from l3e_env.data.generation import config_for, generate

    cfg = config_for(None, scenes=["tunnel-0"], parents_per_scene=1, labels={"children": 4})
    busy = f"{tmp_path / 'd'}: another run \\(pid {os.getpid()}\\)"
    with folder_lock(tmp_path / "d"), pytest.raises(FolderBusyError, match=busy):  # a run already writing there
        generate(tmp_path / "d", cfg, workers=1, progress=False)
    assert generate(tmp_path / "d", cfg, workers=1, progress=False)["count"] == 1  # free again: it runs
    assert not (tmp_path / "d" / ".lock").exists()  # and the run that ended took its lock file with it


def test_a_dataset_of_the_papers_protocol_is_refused_with_the_command_that_labels_it_again(tiny_dataset, tmp_path):
    import shutil

    old = tmp_path / "old"
    shutil.copytree(tiny_dataset, old)
    manifest = json.loads((old / "manifest.json").read_text())
    del manifest["protocol"]  # written before datasets recorded their protocol: the paper's
    (old / "manifest.json").write_text(json.dumps(manifest))
    for read in (lambda: LabelDataset(old), lambda: generate(old, config_for(None, **manifest["settings"]))):
        with pytest.raises(
            DatasetError,
            match=rf"label protocol 1 .*l3e dataset generate --out .*old-p{LABEL_PROTOCOL} --scenes "
            r"tunnel-0,office-0,field-0 --parents 4 --seed 0",
        ):
            read()
    assert LabelDataset(tiny_dataset).manifest["protocol"] == LABEL_PROTOCOL == 3


def test_a_dataset_of_protocol_2_is_refused_by_name(tiny_dataset, tmp_path):
    import shutil

    old = tmp_path / "sensor-frame"
    shutil.copytree(tiny_dataset, old)
    manifest = json.loads((old / "manifest.json").read_text())
    manifest["protocol"] = 2  # labels written in the sensor's frame: never mixed with the level frame's
    (old / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match=r"label protocol 2 .*label protocol 3 .*level frame.*sensor-frame-p3"):
        LabelDataset(old)


def test_a_mesh_where_no_parent_can_be_labelled_is_refused_and_leaves_nothing(tmp_path, capsys):
    """A floor of 1.5 m square: no scan there holds enough points, so no parent is labelled; the run is
    refused with the parents' reasons, and neither a dataset of 0 parents nor its lock is left."""
    from l3e_env.cli.main import main

    trimesh.creation.box([1.5, 1.5, 0.2]).apply_translation([0, 0, -0.1]).export(tmp_path / "tiny.obj")
    np.savetxt(tmp_path / "route.csv", [[-0.5, 0, 0], [0.5, 0, 0]], delimiter=",")
    args = ["--scenes", str(tmp_path / "tiny.obj"), "--route", str(tmp_path / "route.csv"), "--parents", "2"]
    common = ["dataset", "generate", *args, "--children", "5", "--workers", "1", "--quiet"]
    assert main([*common, "--out", str(tmp_path / "d")]) == 2
    assert "no parent of" in (err := capsys.readouterr().err) and "points (minimum" in err
    assert not (tmp_path / "d").exists()
    (tmp_path / "kept").mkdir()  # a folder the user made: kept, with nothing of the run in it
    assert main([*common, "--out", str(tmp_path / "kept")]) == 2
    assert list((tmp_path / "kept").rglob("*")) == []
