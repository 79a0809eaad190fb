import numpy as np
import pytest
import trimesh

from scenes import (
    TEST_SCENES,
    TRAIN_SCENES,
    VALIDATION_SCENES,
    Scene,
    SceneError,
    check_scene_name,
    list_scenes,
    load_mesh,
    load_route,
    make_scene,
    scene_family,
    scene_from_mesh,
)
from scenes.mesh_io import snap_route_to_floor


@pytest.mark.parametrize("name", list_scenes())
def test_every_family_builds_a_valid_scene(name):
    scene = make_scene(name)
    assert scene.family == name
    assert len(scene.mesh.faces) > 10
    assert scene.sampling_paths and all(p.shape[1] == 3 for p in scene.sampling_paths)
    assert np.isfinite(scene.mesh.vertices).all()
    # start and goal lie on the default route
    assert np.linalg.norm(scene.route[0, :2] - scene.start[:2]) < 1e-6
    assert np.linalg.norm(scene.route[-1, :2] - scene.goal) < 1e-6


def test_seeds_are_reproducible_and_vary():
    a, b, c = make_scene("cave", seed=3), make_scene("cave-3"), make_scene("cave", seed=4)
    assert a.name == b.name == "cave-3" and scene_family(a.name) == scene_family("cave") == "cave"
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    assert a.mesh.vertices.shape != c.mesh.vertices.shape or not np.allclose(a.mesh.vertices, c.mesh.vertices)


def test_split_has_fifteen_distinct_training_environments_and_unseen_test_families():
    assert len(set(TRAIN_SCENES)) >= 15
    train_families = {n.split("-")[0] for n in TRAIN_SCENES}
    assert not {n.split("-")[0] for n in TEST_SCENES} & train_families
    assert not set(VALIDATION_SCENES) & set(TRAIN_SCENES)
    meshes = {make_scene(n).mesh.vertices.tobytes().__hash__() for n in TRAIN_SCENES}
    assert len(meshes) == len(TRAIN_SCENES)


def test_fork_has_a_short_and_a_longer_route():
    fork = make_scene("fork")
    length = lambda r: np.linalg.norm(np.diff(r, axis=0), axis=1).sum()  # noqa: E731
    assert {"short", "rich"} <= set(fork.routes)
    assert 1.1 < length(fork.routes["rich"]) / length(fork.routes["short"]) < 1.5


def test_unknown_scene_names_are_reported_with_the_known_ones():
    with pytest.raises(SceneError, match="known scenes: .*mine"):
        make_scene("volcano")
    with pytest.raises(SceneError, match="family-<seed>"):
        make_scene("cave-x")
    assert check_scene_name("cave-12") == "cave-12"
    for bad, message in [("volcano-2", "known scenes"), ("cave-x", "family-<seed>"), ("missing.obj", "not found")]:
        with pytest.raises(SceneError, match=message):
            check_scene_name(bad)


def test_empty_and_nan_meshes_are_rejected():
    with pytest.raises(SceneError, match="empty"):
        Scene("e", trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)), [], (0, 0, 0), (1, 1))
    bad = trimesh.creation.box()
    verts = bad.vertices.copy()
    verts[0, 0] = np.nan
    with pytest.raises(SceneError, match="NaN"):
        Scene("n", trimesh.Trimesh(verts, bad.faces, process=False), [], (0, 0, 0), (1, 1))
    with pytest.raises(SceneError, match="sampling path"):
        Scene("p", trimesh.creation.box(), [np.array([[0, 0, np.nan], [1, 0, 0]])], (0, 0, 0), (1, 1))


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".glb"])
def test_mesh_import_round_trip_with_up_axis_and_scale(tmp_path, suffix):
    mesh = trimesh.creation.box(extents=(4000.0, 1000.0, 2000.0))  # millimetres, y up
    path = tmp_path / f"room{suffix}"
    mesh.export(path)
    loaded = load_mesh(path, up_axis="y", scale=0.001)
    np.testing.assert_allclose(loaded.extents, (4.0, 2.0, 1.0), atol=1e-6)
    scene = scene_from_mesh(path, up_axis="y", scale=0.001, sampling_paths=[[[0, 0, -1], [1, 0, -1]]])
    assert len(scene.sampling_paths[0]) >= 2 and "main" in scene.routes


def test_a_route_file_is_read_in_the_mesh_files_axes_and_units(tmp_path):
    (tmp_path / "route.csv").write_text("# x, y, z in mm, y up\n1000, 0, -500\n4000, 0, -500\n4000, 0, -2500\n")
    route = load_route(tmp_path / "route.csv", up_axis="y", scale=0.001)
    np.testing.assert_allclose(route, [[1, 0.5, 0], [4, 0.5, 0], [4, 2.5, 0]], atol=1e-12)  # as load_mesh turns it
    (tmp_path / "flat.txt").write_text("0 0\n3 4\n")
    np.testing.assert_allclose(load_route(tmp_path / "flat.txt"), [[0, 0, 0], [3, 4, 0]])
    mesh = trimesh.creation.box(extents=(8000.0, 1000.0, 6000.0))
    mesh.export(tmp_path / "hall.obj")
    scene = scene_from_mesh(tmp_path / "hall.obj", up_axis="y", scale=0.001, sampling_paths=[route])
    np.testing.assert_allclose(scene.start, [1, 0.5, 0])  # at the route's first point, facing along it
    np.testing.assert_allclose(scene.goal, [4, 2.5])
    with pytest.raises(SceneError, match=r"route point \(1000.0, 500.0, 0.0\) m lies outside the mesh's extent"):
        scene_from_mesh(
            tmp_path / "hall.obj",
            up_axis="y",
            scale=0.001,  # the route read without its scale
            sampling_paths=[load_route(tmp_path / "route.csv", up_axis="y")],
        )
    for text, message in [
        ("1 2 3\n", "two or more"),
        ("1 2 3 4\n5 6 7 8\n", "two or more"),
        ("0 0 0\nnan 1 0\n", "NaN"),
        ("1e300 0 0\n-1e300 1 0\n", "beyond any mesh"),
        ("v 0 0 0\nv 1 0 0\n", "not a table"),
    ]:
        (tmp_path / "bad.txt").write_text(text)
        with pytest.raises(SceneError, match=message):
            load_route(tmp_path / "bad.txt")
    with pytest.raises(SceneError, match="'x y z'"):
        load_route(tmp_path / "flat.txt", up_axis="y")
    with pytest.raises(SceneError, match="route file not found"):
        load_route(tmp_path / "missing.csv")


def test_broken_and_missing_mesh_files_raise_clear_errors(tmp_path):
    broken = tmp_path / "broken.ply"
    broken.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nend_header\n\x00\x01")
    with pytest.raises(SceneError, match="broken.ply"):
        load_mesh(broken)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(SceneError, match="empty|no triangle"):
        load_mesh(empty)
    with pytest.raises(SceneError, match="not found"):
        load_mesh(tmp_path / "missing.stl")
    with pytest.raises(SceneError, match="unsupported"):
        load_mesh(empty.with_suffix(".txt").write_text("x") and empty.with_suffix(".txt"))
    nan_obj = tmp_path / "nan.obj"
    nan_obj.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(SceneError, match="NaN"):
        load_mesh(nan_obj)


def _horizontal_clearance(scene: Scene, points: np.ndarray, height: float = 1.0, max_range: float = 60.0) -> np.ndarray:
    from l3e_env.sim.raycast import EmbreeCaster

    caster = EmbreeCaster(scene.mesh, threads=1)
    angles = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)]).astype(np.float32)
    return np.array([caster.cast(p + (0, 0, height), dirs, max_range) for p in points])


def test_yards_span_empty_to_dense_and_keep_their_paths_clear():
    counts = []
    for seed in range(6):
        yard = make_scene(f"yard-{seed}")
        counts.append(len(yard.mesh.split(only_watertight=False)) - 1)  # minus the ground
        paths = np.vstack(yard.sampling_paths)
        assert _horizontal_clearance(yard, paths[::3]).min() > 1.5  # structures keep 2 m off the paths
    assert min(counts) <= 6 and max(counts) >= 15


def test_chambers_are_closed_rooms_from_smooth_to_rough():
    roughness = []
    from scenes.chamber import make_chamber

    for seed in range(5):
        chamber = make_scene(f"chamber-{seed}")
        middle = chamber.sampling_paths[0][len(chamber.sampling_paths[0]) // 2]
        assert np.isfinite(_horizontal_clearance(chamber, middle[None])).all()  # no ray leaves the room
        smooth = make_chamber(seed, roughness=1e-9)  # the same room without the noise field
        roughness.append(np.abs(chamber.mesh.vertices - smooth.mesh.vertices).max(axis=1).mean())
    assert max(roughness) > 5 * min(roughness)


def test_pipe_racks_run_from_short_to_long_bays_and_keep_their_walkway_clear():
    bays = []
    for seed in range(6):
        rack = make_scene(f"piperack-{seed}")
        route = rack.route
        assert _horizontal_clearance(rack, route[::4], height=0.85).min() > 1.0  # columns and clutter beside it
        columns = rack.mesh.vertices[(np.abs(rack.mesh.vertices[:, 1]) > 1.5) & (rack.mesh.vertices[:, 2] > 2.5)]
        bays.append(np.ptp(route[:, 0]) / max(len(np.unique(np.round(columns[:, 0] / 0.3))), 1))
    assert max(bays) > 2 * min(bays)  # the seeds span short and long bays


def test_layouts_span_bare_plains_to_furnished_and_tunnelled_walks():
    furnished, tunnels, ground = [], 0, set()
    for seed in range(12):
        layout = make_scene(f"layout-{seed}")
        walk = layout.route
        assert _horizontal_clearance(layout, walk[::6], height=0.85).min() > 0.5  # the walk stays walkable
        raised = layout.mesh.triangles_center[:, 2] - np.interp(
            layout.mesh.triangles_center[:, 0], walk[:, 0], walk[:, 2]
        )
        furnished.append(int((raised > 1.0).sum()))
        walled = np.isfinite(_horizontal_clearance(layout, walk[::4], max_range=8.0)).mean(axis=1)
        tunnels += bool(walled.max() > 0.6)  # walls within 8 m all round but along the walk: a tunnel
        ground.add(bool(np.ptp(walk[:, 2]) > 0.05))
    assert min(furnished) < 50 < max(furnished) and tunnels >= 1 and ground == {True, False}
    assert np.allclose(make_scene("layout-3").mesh.vertices, make_scene("layout-3").mesh.vertices)


def test_a_route_without_length_or_in_other_units_is_named(cad_corridor):
    """Two identical waypoints made a one-step drive (or a crash in the demo); a millimetre mesh and route
    given no scale made a drive of hours: both are named with what fixes them."""
    mesh, route = cad_corridor
    waypoints = load_route(route, "y", 0.001)
    scene = scene_from_mesh(mesh, "y", 0.001, sampling_paths=[waypoints])
    assert 6.9 < float(np.linalg.norm(np.diff(scene.route[:, :2], axis=0), axis=1).sum()) < 7.1
    with pytest.raises(SceneError, match="0.00 m long on the floor.*two identical waypoints"):
        scene_from_mesh(mesh, "y", 0.001, sampling_paths=[[waypoints[0], waypoints[0]]])
    with pytest.warns(UserWarning, match=r"7\.0 km long, a drive of about 70,000 steps.*--scale 0.001"):
        scene_from_mesh(mesh, "y", 1.0, sampling_paths=[load_route(route, "y", 1.0)])
    with pytest.raises(SceneError, match=r"70 km long: if the mesh and route are in millimetres"):
        scene_from_mesh(mesh, "y", 10.0, sampling_paths=[load_route(route, "y", 10.0)])


def test_a_route_in_other_axes_than_the_mesh_is_refused_naming_the_up_axis(cad_corridor, tmp_path):
    """A z-up route given with a y-up mesh climbed out of the corridor as a vertical line, unnoticed."""
    mesh, _ = cad_corridor
    np.savetxt(tmp_path / "z-up.csv", [[1000.0, 0, 0], [1000, 7000, 0]], delimiter=",")  # along the corridor, z up
    with pytest.raises(SceneError, match=r"route point \(1\.0, 0\.0, 4\.0\) m lies outside.*--up-axis"):
        scene_from_mesh(mesh, "y", 0.001, sampling_paths=[load_route(tmp_path / "z-up.csv", "y", 0.001)])


def test_random_bytes_in_a_mesh_file_are_named_as_damaged(tmp_path):
    path = tmp_path / "tunnel.obj"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(SceneError, match="tunnel.obj: no triangles could be read from it: the file is damaged"):
        scene_from_mesh(path)


def test_a_route_without_floor_under_it_is_named(tmp_path):
    """'x y' lines over a raised floor put the route at z = 0, under the floor: named, not labelled empty."""
    import trimesh

    floor, wall = trimesh.creation.box([10, 4, 0.2]), trimesh.creation.box([10, 0.2, 3])
    floor.apply_translation([5, 0, 1.4])  # the floor's top at 1.5 m
    wall.apply_translation([5, -2.1, 1.5])  # from the ground to above the floor
    trimesh.util.concatenate([floor, wall]).export(tmp_path / "platform.obj")
    np.savetxt(tmp_path / "xy.csv", [[1.0, 0], [8, 0]], delimiter=",")
    with pytest.raises(
        SceneError,
        match=r"route 0: 8 of its 8 points have no floor within 0.5 m under them, "
        r"e.g. \(1.0, 0.0, 0.0\).* or let --snap-route set it",
    ):
        scene_from_mesh(tmp_path / "platform.obj", sampling_paths=[load_route(tmp_path / "xy.csv")])
    np.savetxt(tmp_path / "xyz.csv", [[1.0, 0, 1.5], [8, 0, 1.5]], delimiter=",")
    scene = scene_from_mesh(tmp_path / "platform.obj", sampling_paths=[load_route(tmp_path / "xyz.csv")])
    assert scene.route[0, 2] == 1.5
    snapped = scene_from_mesh(
        tmp_path / "platform.obj", sampling_paths=[load_route(tmp_path / "xy.csv")], snap_to_floor=True
    )  # the 'x y' route set onto the raised floor
    assert np.allclose(snapped.route[:, 2], 1.5)
    assert snap_route_to_floor(trimesh.creation.box([1, 1, 1]), np.array([[9.0, 9, 0]]))[0, 2] == 0  # none there


def test_a_bypass_offers_a_long_smooth_gallery_or_a_clear_way_round_at_most_half_as_long_again():
    from l3e_env.sim.raycast import EmbreeCaster
    from scenes.bypass import EVALUATION_SEEDS, MAX_DETOUR, TRAINING_SEEDS
    from scenes.geometry import polyline_length

    assert not set(TRAINING_SEEDS) & set(EVALUATION_SEEDS)
    lengths = []
    for seed in (0, 1, 2, 100, 101):
        scene = make_scene(f"bypass-{seed}")
        x0, _, x1, _ = scene.regions["corridor"]
        lengths.append(x1 - x0)
        short, rich = (polyline_length(scene.routes[k]) for k in ("short", "rich"))
        assert 1.1 < rich / short <= MAX_DETOUR
        for route in scene.routes.values():
            assert np.allclose(route[-1, :2], scene.goal)
        # nothing stands within 0.6 m of the way round, at the body's height
        caster = EmbreeCaster(scene.mesh, threads=1)
        angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        rays = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(16)])
        for point in scene.routes["rich"][::3]:
            assert caster.cast(point + (0, 0, 0.5), rays, 5.0).min() > 0.6, (seed, point)
    assert min(lengths) >= 60 and max(lengths) <= 150 and max(lengths) - min(lengths) > 30


def test_compositions_span_open_to_enclosed_places_and_keep_their_walk_clear():
    """The randomised places (scenes.composition): the walk stays walkable, and the seeds span open
    ground to enclosed, roofed to open-sky places; the same seed builds the same mesh."""
    enclosed, roofed = [], []
    for seed in range(8):
        place = make_scene(f"composition-{seed}")
        walk = place.route
        assert _horizontal_clearance(place, walk[::3], height=0.85).min() > 0.5
        walled = np.isfinite(_horizontal_clearance(place, walk[::4], max_range=8.0)).mean(axis=1)
        enclosed.append(float(walled.mean()))
        above = place.mesh.ray.intersects_any(
            ray_origins=walk[::4] + (0, 0, 0.7), ray_directions=np.tile((0, 0, 1.0), (len(walk[::4]), 1))
        )
        roofed.append(float(above.mean()))
    assert min(enclosed) < 0.4 < max(enclosed) and min(roofed) < 0.2 and max(roofed) > 0.8
    assert np.array_equal(make_scene("composition-5").mesh.vertices, make_scene("composition-5").mesh.vertices)


def test_randomised_places_are_used_by_no_split():
    """Their seeds are their own: no training, validation, test or held-out scene is a composition,
    and the three sensors' presets draw disjoint places."""
    from scenes import COMPOSITION_SCENES, HELDOUT_SCENES

    assert not {scene_family(s) for s in TRAIN_SCENES + VALIDATION_SCENES + TEST_SCENES + HELDOUT_SCENES} & {
        "composition"
    }
    assert len(set(COMPOSITION_SCENES)) == len(COMPOSITION_SCENES) >= 1000
