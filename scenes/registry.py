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
from .mesh_io import is_mesh_path, scene_from_mesh
from .mine import make_mine
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


def scene_family(name: str) -> str:
    """The family of a scene name: 'cave' for 'cave-3' and for 'cave'; a mesh file's stem for its path."""
    if is_mesh_path(name):
        return Path(name).stem
    return name.partition("-")[0]


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


def canonical_scene_name(name: str) -> str:
    """A mesh file by its absolute path, as datasets, recordings and checkpoints name it for good
    (a relative path would change meaning with the folder a command runs in); other names as given."""
    return str(Path(name).resolve()) if is_mesh_path(name) else name


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


# The paper's protocol: training draws on at least 15 distinct environments, meshed caves among
# them, and the mine's mesh is the test. Rock galleries span smooth to rough walls: without them
# every tube in training is a smooth, non-localizable one, and a model learns "tube = degenerate"
# instead of looking at the walls; caves and chambers give it rough closed rooms (the quarry).
# Pipe racks are held out as well: a family unlike every training one (no tube, no room, no plain),
# so that "a family never seen" stays measured beside the mine (HELDOUT_SCENES, a dataset of its own).
GALLERIES = [f"gallery-{s}" for s in range(8)]
TRAIN_SCENES = (
    [f"tunnel-{s}" for s in range(4)]
    + [f"primitives-{s}" for s in range(5)]
    + [
        "field-0",
        "field-1",
        "office-0",
        "office-1",
        "office-2",
        "fork-0",
        "fork-1",
        *GALLERIES,
        "cave-0",
        "cave-1",
        "cave-2",
        "cave-3",
        "chamber-0",
        "chamber-1",
        "chamber-2",
        "chamber-3",
    ]
)
VALIDATION_SCENES = ["tunnel-7", "primitives-7", "office-5", "field-3", "gallery-9", "cave-5", "chamber-5"]
TEST_SCENES = ["mine-0", "mine-1", "mine-2"]
HELDOUT_SCENES = [f"piperack-{s}" for s in range(6)]
# A distillation set's scenes (labelled by the scan's own estimate, `l3e dataset generate --preset
# distill`): the training families and procedural layouts at seeds no split uses, so that many
# more places than the Monte-Carlo labels can afford are seen; never a test or held-out family.
DISTILL_FAMILIES = ["tunnel", "primitives", "field", "office", "fork", "gallery", "cave", "chamber", "layout"]
DISTILL_SCENES = [f"{family}-{s}" for s in range(10, 22) for family in DISTILL_FAMILIES]
# Randomised places (scenes.composition), labelled by their own estimate for training only: a family no
# split uses, so that their seeds are their own; 1 000 places, cut in three for three sensors
# (`l3e dataset generate --preset random`, `random-32`, `random-128`)
COMPOSITION_SCENES = [f"composition-{s}" for s in range(1000)]
# The order of scenes in a dataset matters (parent i of the s-th scene is seeded by (seed, s, i)):
# scenes added to the split later are appended, so that earlier ones keep their labels.
DATASET_SCENES = TRAIN_SCENES + VALIDATION_SCENES + TEST_SCENES[:1]
