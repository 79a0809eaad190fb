"""Scene names, seeded variants and the split of environments into training and test."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from .bypass import make_bypass
from .cave import make_cave
from .chamber import make_chamber
from .composition import make_composition
from .field import make_field
from .fork import make_fork
from .gallery import make_gallery
from .layout import make_layout
from .mesh_io import scene_from_mesh
from .mine import make_mine
from .names import is_mesh_path
from .office import make_office
from .piperack import make_piperack
from .primitives import make_primitive
from .scene import Scene, SceneError
from .tunnel import make_tunnel
from .yard import make_yard

BUILDERS: dict[str, Callable[..., Scene]] = {
    "tunnel": make_tunnel,
    "field": make_field,
    "office": make_office,
    "cave": make_cave,
    "primitives": make_primitive,
    "mine": make_mine,
    "fork": make_fork,
    "gallery": make_gallery,
    "yard": make_yard,
    "chamber": make_chamber,
    "piperack": make_piperack,
    "layout": make_layout,
    "bypass": make_bypass,
    "composition": make_composition,
}


def list_scenes() -> list[str]:
    return sorted(BUILDERS)


def make_scene(name: str, seed: int = 0, **params) -> Scene:
    """Build a scene by family name ('tunnel', 'mine', ...) or 'family-seed' ('cave-3').

    A path to a mesh file is accepted too (see scenes.mesh_io.scene_from_mesh).
    """
    check_scene_name(name)
    if is_mesh_path(name):
        return scene_from_mesh(name, **params)
    family, _, suffix = name.partition("-")
    if suffix:
        seed = int(suffix)
    return BUILDERS[family](seed=seed, **params)


def check_scene_name(name: str) -> str:
    """The name if make_scene would accept it, else SceneError; builds nothing, so that a command
    can refuse a misspelt scene before it creates folders or starts workers."""
    if is_mesh_path(name):
        if not Path(name).is_file():
            raise SceneError(f"mesh file not found: {name}")
        return name
    family, _, suffix = name.partition("-")
    if suffix and not suffix.isdigit():
        raise SceneError(f"scene name '{name}': expected 'family' or 'family-<seed>'")
    if family not in BUILDERS:
        raise SceneError(f"unknown scene '{name}'; known scenes: {', '.join(list_scenes())}")
    return name
