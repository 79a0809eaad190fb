"""Dataset generation: sharded, deterministic, resumable; consolidated into the memory-mapped arrays
that `dataset` reads (the folder's layout is described there).

Parent i of a scene always uses the generator seeded by (seed, scene index, i), so the labels do
not depend on the number of workers or on which shards a killed run had finished.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import re
import shutil
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from tqdm import tqdm

from l3e_env.config import LABELLERS, LidarConfig, from_dict, settings_changed
from l3e_env.config.labelling import LABEL_PROTOCOL, LabelConfig, RegistrationConfig, ScanMCConfig
from l3e_env.core.files import folder_lock, npy_writer, write_atomic
from l3e_env.core.transforms import level_rotation_of
from l3e_env.localizability.labels import (
    ParentLabel,
    SamplingError,
    label_parent,
    sample_parent_pose,
)
from l3e_env.localizability.registration import RegistrationError
from l3e_env.localizability.scan_mc import ScanPatternError, scan_errors
from l3e_env.sim.lidar import Lidar, get_pattern
from l3e_env.sim.raycast import EmbreeCaster
from scenes import (
    COMPOSITION_SCENES,
    DATASET_SCENES,
    DISTILL_SCENES,
    check_scene_name,
    file_sha256,
    is_mesh_path,
    make_scene,
)

from .dataset import FORMAT_VERSION, DatasetError, check_protocol, label_statistics
from .jobs import JOB_BACKENDS, run_jobs


def _write_atomic(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """A full disk leaves what was finished in place (`write_atomic`), with an error that says so."""
    try:
        write_atomic(path, write)
    except OSError as exc:
        raise DatasetError(
            f"cannot write {path} ({exc.strerror or exc}); finished shards are kept, run again to resume"
        ) from exc


@dataclass
class DatasetConfig:
    scenes: list[str] = field(default_factory=lambda: ["tunnel-0", "office-0", "field-0"])
    parents_per_scene: int = 8
    seed: int = 0
    shard_size: int = 4  # parents per shard: the unit of work and of resumption
    lidar: LidarConfig = field(default_factory=LidarConfig)
    labels: LabelConfig = field(default_factory=LabelConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    # "scene": children ray-cast in the scene (the paper's Monte-Carlo labels, the ground truth of
    # every score); "scan": the parent scan's own estimate (localizability.scan_mc), which needs no
    # more than the scan: a distillation set, for training only
    labeller: str = "scene"
    scan_mc: ScanMCConfig = field(default_factory=ScanMCConfig)  # the "scan" labeller's settings
    # make_scene's keyword arguments by scene name: a mesh file's route (as its sampling path),
    # up axis and scale; procedural scenes need none
    scene_params: dict[str, dict[str, Any]] = field(default_factory=dict)


PRESETS: dict[str, dict[str, Any]] = {
    # minutes on 2 cores: for tests, CI and a first look
    "small": {
        "scenes": ["tunnel-0", "office-0", "field-0", "primitives-3"],
        "parents_per_scene": 6,
        "labels": {"children": 50},
    },
    # the paper's protocol on every environment of the split (M = 200)
    "paper": {"scenes": DATASET_SCENES, "parents_per_scene": 150},
    # operating poses on the same environments: level within a few degrees, sensor at the
    # robot's height, heading along the path or across it (another seed: other positions)
    "level": {
        "scenes": DATASET_SCENES,
        "parents_per_scene": 16,
        "seed": 1,
        "labels": {"parent_sigma": [0.3, 0.3, 0.05, 3.0, 3.0, 15.0], "heading": "path"},
    },
    # a distillation set: 108 places of the training families and layouts, each scan labelled by
    # its own estimate (no child is cast in the scene)
    "distill": {"scenes": DISTILL_SCENES, "parents_per_scene": 24, "seed": 10, "labeller": "scan"},
    # randomised places (scenes.composition), each scan labelled by its own estimate: 600 places
    # seen by a VLP-16, 200 by a 32-beam and 200 by a 128-beam sensor, 10 scans each
    "random": {"scenes": COMPOSITION_SCENES[:600], "parents_per_scene": 10, "seed": 20, "labeller": "scan"},
    "random-32": {
        "scenes": COMPOSITION_SCENES[600:800],
        "parents_per_scene": 10,
        "seed": 21,
        "labeller": "scan",
        "lidar": {"model": "hdl32e"},
    },
    "random-128": {
        "scenes": COMPOSITION_SCENES[800:],
        "parents_per_scene": 10,
        "seed": 22,
        "labeller": "scan",
        "lidar": {"model": "os1-128"},
    },
}


def config_for(preset: str | None = None, **overrides: Any) -> DatasetConfig:
    base: dict[str, Any] = {}
    if preset is not None:
        if preset not in PRESETS:
            raise DatasetError(f"unknown preset '{preset}' (choose from {sorted(PRESETS)})")
        base = json.loads(json.dumps(PRESETS[preset]))
    for key, value in overrides.items():
        if value is None:
            continue
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            base[key] = {**base[key], **value}
        else:
            base[key] = value
    return from_dict(DatasetConfig, base)


def shard_prefix(si: int, scene: str) -> str:
    """The start of a scene's shard file names: the scene's name, or for a mesh file its position
    and stem, so that a path makes a plain file name and two meshes of one stem do not share it."""
    if not is_mesh_path(scene):
        return scene
    return f"mesh{si}-" + re.sub(r"[^A-Za-z0-9_.-]", "_", Path(scene).stem)


def _shards(config: DatasetConfig) -> list[tuple[str, int, int, int]]:
    """(shard id, scene index, first parent, last parent + 1) for every shard."""
    out = []
    for si, scene in enumerate(config.scenes):
        for start in range(0, config.parents_per_scene, config.shard_size):
            stop = min(start + config.shard_size, config.parents_per_scene)
            out.append((f"{shard_prefix(si, scene)}-{start // config.shard_size:05d}", si, start, stop))
    return out


_WORKER_CACHE: dict[str, tuple] = {}


def scene_tools(name: str, lidar_config: LidarConfig, params: dict[str, Any] | None = None):
    """(scene, caster, lidar) of a worker process, kept for the next job on the same scene."""
    key = json.dumps([name, params or {}, dataclasses.asdict(lidar_config)], sort_keys=True)
    if key not in _WORKER_CACHE:
        scene = make_scene(name, **(params or {}))
        caster = EmbreeCaster(scene.mesh, threads=1)  # processes give the parallelism
        _WORKER_CACHE.clear()  # one scene at a time keeps worker memory flat
        _WORKER_CACHE[key] = (scene, caster, Lidar(caster, lidar_config))
    return _WORKER_CACHE[key]


def run_shard(config: DatasetConfig, shard: tuple[str, int, int, int]) -> dict[str, Any]:
    """Label the parents of one shard; returns arrays and per-parent failure records."""
    shard_id, si, start, stop = shard
    name = config.scenes[si]
    scene, caster, lidar = scene_tools(name, config.lidar, config.scene_params.get(name))
    rows: dict[str, list] = {k: [] for k in ("points", "poses", "errors", "labels", "index", "children_failed")}
    failures = []
    for i in range(start, stop):
        rng = np.random.default_rng([config.seed, si, i])
        try:
            T = sample_parent_pose(scene, caster, rng, config.labels)
            result = _label(config, lidar, T, rng)
        except (RegistrationError, SamplingError, ScanPatternError) as exc:
            failures.append({"scene": scene.name, "parent": i, "reason": str(exc)})
            continue
        rows["points"].append(result.points)
        rows["poses"].append(result.T_w_s)
        rows["errors"].append(result.errors)
        rows["labels"].append(result.labels)
        rows["index"].append(i)
        rows["children_failed"].append(result.children_failed)
    lengths = np.array([len(p) for p in rows["points"]], dtype=np.int64)
    return {
        "shard": shard_id,
        "scene": np.full(len(lengths), si, dtype=np.int16),
        "index": np.array(rows["index"], dtype=np.int64),
        "lengths": lengths,
        "points": np.concatenate(rows["points"]) if rows["points"] else np.zeros((0, 3), np.float32),
        "poses": np.array(rows["poses"], dtype=np.float64).reshape(-1, 4, 4),
        "errors": np.array(rows["errors"], dtype=np.float32).reshape(-1, 6),
        "labels": np.array(rows["labels"], dtype=np.uint8).reshape(-1, 6),
        "children_failed": np.array(rows["children_failed"], dtype=np.int32),
        "failures": json.dumps(failures),
    }


def _label(config: DatasetConfig, lidar: Lidar, T_w_p: np.ndarray, rng: np.random.Generator) -> ParentLabel:
    """One parent's errors and labels, from its children in the scene or from its scan alone."""
    if config.labeller == "scene":
        return label_parent(lidar, T_w_p, rng, config.labels, config.registration)
    parent = lidar.scan(T_w_p, rng)
    found = scan_errors(
        parent.points, config.lidar, config.registration, config.labels, config.scan_mc, rng, level_rotation_of(T_w_p)
    )
    labels = (found.errors > config.labels.threshold_vector()).astype(np.uint8)
    return ParentLabel(T_w_p, parent.points, found.errors, labels, found.children - len(found.child_errors), 0)


def _settings(config: DatasetConfig, meshes: dict[str, str] | None = None) -> dict[str, Any]:
    """What a resumed run must match. A mesh file's bytes count too: an edited mesh is another
    dataset (`meshes`: their hashes as a manifest holds them; by default read from the files)."""
    settings = json.loads(json.dumps(dataclasses.asdict(config)))
    if not config.scene_params:
        del settings["scene_params"]  # so that datasets made before meshes were taken still resume
    if meshes is None:
        meshes = {name: file_sha256(name) for name in config.scenes if is_mesh_path(name)}
    if meshes:
        settings["mesh_sha256"] = meshes
    return settings


def _stored_settings(stored: dict[str, Any]) -> dict[str, Any]:
    """A manifest's settings with every option it predates at its default (as `comparable_settings`
    does for training): a folder begun before an option existed was made as that default makes it,
    and resumes. Settings no config can read are returned as stored, to be reported as different. The
    scan estimate's continued ground is the exception: a set labelled before it was labelled without it."""
    if isinstance(stored.get("scan_mc"), dict) and "ground_reach" not in stored["scan_mc"]:
        stored = {**stored, "scan_mc": {**stored["scan_mc"], "ground_reach": 0.0}}
    try:
        config = from_dict(DatasetConfig, {k: v for k, v in stored.items() if k != "mesh_sha256"})
    except (TypeError, ValueError):
        return stored
    return _settings(config, stored.get("mesh_sha256") or {})


def _versions() -> dict[str, str]:
    out = {}
    for pkg in ("l3e", "numpy", "small_gicp", "embreex", "trimesh", "pybullet"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            out[pkg] = metadata.version(pkg)
    return out


def check_dataset_config(config: DatasetConfig) -> None:
    """DatasetError for settings no run can use (SceneError for a misspelt scene), before the
    folder, its manifest or any worker exists."""
    for name in config.scenes:
        check_scene_name(name)
    problems = [
        f"scene_params are given for '{name}', which is not among the scenes"
        for name in config.scene_params
        if name not in config.scenes
    ]
    for name in filter(is_mesh_path, config.scenes):
        if not config.scene_params.get(name, {}).get("sampling_paths"):
            problems.append(f"the mesh {name} has no route to sample parents along (--route FILE)")
        else:  # a broken mesh or route fails here, not in every worker
            make_scene(name, **config.scene_params[name])
    problems += value_problems(config)
    if problems:
        raise DatasetError("; ".join(problems))


def value_problems(config: DatasetConfig) -> list[str]:
    """The settings' values no run can use (counts below 1, an unknown labeller or sensor), without
    building a scene: what `check_dataset_config` and a manifest's check (`dataset.manifest_problems`)
    both refuse."""
    problems = [
        f"{name} must be {rule}, got {value}"
        for name, value, ok, rule in [
            ("scenes", config.scenes, len(config.scenes) > 0, "at least one scene"),
            ("parents_per_scene", config.parents_per_scene, config.parents_per_scene >= 1, "at least 1"),
            ("shard_size", config.shard_size, config.shard_size >= 1, "at least 1"),
            ("labels.children", config.labels.children, config.labels.children >= 1, "at least 1"),
            ("labeller", config.labeller, config.labeller in LABELLERS, f"one of {', '.join(LABELLERS)}"),
        ]
        if not ok
    ]
    try:
        get_pattern(config.lidar.model)
    except ValueError as exc:
        problems.append(str(exc))
    return problems


def _open_folder(out: Path, config: DatasetConfig) -> dict[str, Any]:
    """Create the folder or check that it holds a run of the same settings (to resume)."""
    manifest_path = out / "manifest.json"
    settings = _settings(config)
    if manifest_path.exists():
        manifest = json.loads(manifest_path.read_text())
        check_protocol(manifest, out, "resume it")
        if _stored_settings(manifest.get("settings") or {}) != settings:
            raise DatasetError(
                f"{out} holds a dataset made with other settings "
                f"({settings_changed(manifest.get('settings') or {}, settings)}); choose another folder"
            )
        return manifest
    (out / "shards").mkdir(parents=True, exist_ok=True)
    manifest = {
        "format_version": FORMAT_VERSION,
        "protocol": LABEL_PROTOCOL,
        "settings": settings,
        "versions": _versions(),
        "complete": False,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    _write_json(manifest_path, manifest)
    return manifest


def _saved_arrays(arrays: dict[str, Any]) -> Callable[[BinaryIO], None]:
    return lambda fh: np.savez(fh, **arrays)


def _write_json(path: Path, data: dict) -> None:
    _write_atomic(path, lambda fh: fh.write(json.dumps(data, indent=1).encode()))


def generate(
    out_dir: str | Path,
    config: DatasetConfig,
    workers: int = 2,
    backend: str = "local",
    ray_address: str | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Generate (or resume) a dataset; returns the manifest. Finished shards are never redone."""
    out = Path(out_dir)
    check_dataset_config(config)
    fresh = not out.exists()
    with folder_lock(out):
        manifest = _generate(out, config, workers, backend, ray_address, progress)
    if manifest["count"] == 0:
        _nothing_labelled(out, config, manifest, fresh)
    return manifest


def _nothing_labelled(out: Path, config: DatasetConfig, manifest: dict[str, Any], fresh: bool) -> None:
    """Refuse a run that labelled no parent at all, leaving nothing of it behind (the folder, where the
    run made it; else its empty shards and arrays, so that a run with other settings can start there)."""
    reasons = sorted({f["reason"] for f in manifest.get("failures", [])})
    if fresh:
        shutil.rmtree(out, ignore_errors=True)
    else:
        for path in [*(out / "shards").glob("*.npz"), *out.glob("*.npy"), out / "manifest.json"]:
            path.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            (out / "shards").rmdir()  # where it is empty
    raise DatasetError(
        f"no parent of {', '.join(config.scenes)} could be labelled"
        + (f" ({'; '.join(reasons[:3])})" if reasons else "")
        + ": check that the mesh holds surfaces around its route for a scan to see, in metres (--scale); "
        "nothing is kept"
    )


def _generate(
    out: Path, config: DatasetConfig, workers: int, backend: str, ray_address: str | None, progress: bool
) -> dict[str, Any]:
    manifest = _open_folder(out, config)
    todo = [s for s in _shards(config) if not (out / "shards" / f"{s[0]}.npz").exists()]
    total = config.parents_per_scene * len(config.scenes)
    done_before = total - sum(s[3] - s[2] for s in todo)
    bar = tqdm(
        total=total, initial=done_before, desc="labelling parents", unit="parent", disable=not progress, smoothing=0.05
    )
    t0 = time.perf_counter()
    if backend not in JOB_BACKENDS:
        raise DatasetError(f"unknown backend '{backend}' ({', '.join(JOB_BACKENDS)})")
    for result in run_jobs(run_shard, config, todo, workers, backend, ray_address):
        _write_atomic(out / "shards" / f"{result['shard']}.npz", _saved_arrays(result))
        shard = next(s for s in todo if s[0] == result["shard"])
        bar.update(shard[3] - shard[2])
    bar.close()
    manifest = consolidate(out, config, manifest)
    manifest["generation_seconds_last_run"] = round(time.perf_counter() - t0, 1)
    _write_json(out / "manifest.json", manifest)
    return manifest


def consolidate(out: Path, config: DatasetConfig, manifest: dict[str, Any]) -> dict[str, Any]:
    """Join all shards, in shard order, into the memory-mappable arrays; returns the updated
    manifest (the caller writes it)."""
    parts = []
    for shard_id, *_ in _shards(config):
        path = out / "shards" / f"{shard_id}.npz"
        try:
            with np.load(path) as z:
                parts.append({k: z[k] for k in z.files})
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            raise DatasetError(f"shard {path} is unreadable ({exc}); delete it and run again to redo it") from exc
    lengths = np.concatenate([p["lengths"] for p in parts])
    arrays: dict[str, np.ndarray] = {
        "points": np.concatenate([p["points"] for p in parts]).astype(np.float32),
        "offsets": np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        "poses": np.concatenate([p["poses"] for p in parts]),
        "errors": np.concatenate([p["errors"] for p in parts]),
        "labels": np.concatenate([p["labels"] for p in parts]),
        "scene": np.concatenate([p["scene"] for p in parts]),
        "children_failed": np.concatenate([p["children_failed"] for p in parts]),
    }
    for name, arr in arrays.items():
        _write_atomic(out / f"{name}.npy", npy_writer(arr))
    failures = [f for p in parts for f in json.loads(str(p["failures"]))]
    manifest.update(
        {
            "complete": True,
            "count": int(len(lengths)),
            "failures": failures,
            "statistics": label_statistics(arrays["labels"]),
            "scenes": config.scenes,
            "sensor": config.lidar.model,
        }
    )
    return manifest
