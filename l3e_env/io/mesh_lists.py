"""A YAML list of mesh scenes, each with its routes, up axis and scale."""

from __future__ import annotations

from pathlib import Path

MESH_KEYS = {"mesh", "route", "up_axis", "scale", "snap_route"}


def meshes_file(path: str | Path, scenes: list[str], options: list[str]) -> dict[str, dict]:
    """The meshes a YAML file lists, each as {mesh: FILE, route: FILE or [FILE, ...], up_axis: z,
    scale: 1, snap_route: false} with paths relative to the file's folder: absolute mesh path -> make_scene's
    arguments. ValueError naming the entry where one is malformed, or where a mesh or mesh
    options (`options`, as spelt) are also given beside the file."""
    import yaml

    from scenes import canonical_scene_name, is_mesh_path, load_route

    if any(is_mesh_path(s) for s in scenes) or options:
        raise ValueError(
            "--meshes lists the meshes with their routes, axes and scales: give no other mesh scene and "
            "no --route, --up-axis, --scale or --snap-route beside it"
        )
    path = Path(path)
    try:
        entries = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read the list of meshes ({exc})") from exc
    if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
        raise ValueError(
            f"{path}: give a list of meshes, each as 'mesh: FILE' and 'route: FILE' (up_axis, scale optional)"
        )
    meshes: dict[str, dict] = {}
    for i, entry in enumerate(entries, 1):
        where = f"{path}, mesh {i}"
        if unknown := set(entry) - MESH_KEYS:
            raise ValueError(f"{where}: unknown keys {sorted(unknown)} (known: {sorted(MESH_KEYS)})")
        if "mesh" not in entry or "route" not in entry or not is_mesh_path(str(entry["mesh"])):
            raise ValueError(f"{where}: give 'mesh' (a mesh file) and 'route' (its waypoint file or files)")
        up_axis, scale = str(entry.get("up_axis", "z")), entry.get("scale", 1.0)
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
            raise ValueError(f"{where}: scale is metres per mesh unit, a positive number; got {scale!r}")
        snap = entry.get("snap_route", False)
        if not isinstance(snap, bool):
            raise ValueError(f"{where}: snap_route is true or false; got {snap!r}")
        routes = entry["route"] if isinstance(entry["route"], list) else [entry["route"]]
        name = canonical_scene_name(str(path.parent / str(entry["mesh"])))
        if name in meshes:
            raise ValueError(f"{where}: {name} is listed twice (give one mesh its routes as a list)")
        meshes[name] = {
            "up_axis": up_axis,
            "scale": float(scale),
            "sampling_paths": [load_route(path.parent / str(r), up_axis, scale).tolist() for r in routes],
            **({"snap_to_floor": True} if snap else {}),
        }
    return meshes
