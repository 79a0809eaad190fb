"""Procedural and imported scenes (geometry only, trimesh): meshes, sampling paths, routes."""

from .mesh_io import file_sha256, is_mesh_path, load_mesh, load_route, scene_from_mesh
from .registry import (
    COMPOSITION_SCENES,
    DATASET_SCENES,
    DISTILL_SCENES,
    HELDOUT_SCENES,
    TEST_SCENES,
    TRAIN_SCENES,
    VALIDATION_SCENES,
    canonical_scene_name,
    check_scene_name,
    list_scenes,
    make_scene,
    scene_family,
)
from .scene import Scene, SceneError, validate_mesh

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
