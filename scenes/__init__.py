"""Procedural and imported scenes (geometry only, trimesh): meshes, sampling paths, routes.

The names and the split (`names`) load at once; everything that builds geometry loads when a name of
it is first used, so that reading a dataset of these scenes or training on it needs no trimesh."""

from __future__ import annotations

from importlib import import_module
from typing import Any

from .names import (
    COMPOSITION_SCENES,
    DATASET_SCENES,
    DISTILL_SCENES,
    HELDOUT_SCENES,
    TEST_SCENES,
    TRAIN_SCENES,
    VALIDATION_SCENES,
    canonical_scene_name,
    is_mesh_path,
    scene_family,
)

_GEOMETRY = {
    "file_sha256": ".mesh_io",
    "load_mesh": ".mesh_io",
    "load_route": ".mesh_io",
    "scene_from_mesh": ".mesh_io",
    "check_scene_name": ".registry",
    "list_scenes": ".registry",
    "make_scene": ".registry",
    "Scene": ".scene",
    "SceneError": ".scene",
    "validate_mesh": ".scene",
}


def __getattr__(name: str) -> Any:
    if name not in _GEOMETRY:
        raise AttributeError(f"module 'scenes' has no attribute '{name}'")
    return getattr(import_module(_GEOMETRY[name], __name__), name)


__all__ = [
    "Scene",
    "SceneError",
    "make_scene",
    "check_scene_name",
    "canonical_scene_name",
    "list_scenes",
    "scene_family",
    "load_mesh",
    "load_route",
    "file_sha256",
    "scene_from_mesh",
    "is_mesh_path",
    "validate_mesh",
    "TRAIN_SCENES",
    "VALIDATION_SCENES",
    "TEST_SCENES",
    "HELDOUT_SCENES",
    "DATASET_SCENES",
    "DISTILL_SCENES",
    "COMPOSITION_SCENES",
]
