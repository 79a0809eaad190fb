"""Scene names without geometry: which names are mesh files, a name's family, and the split of the
environments into training and test. Nothing here loads trimesh, so that a model can be trained on
datasets of these scenes where no scene can be built."""

from __future__ import annotations

from pathlib import Path

FORMATS = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off")


def is_mesh_path(name: str | Path) -> bool:
    """Whether a scene name is a mesh file to load (by its suffix) rather than a procedural family."""
    return str(name).lower().endswith(FORMATS)


def scene_family(name: str) -> str:
    """The family of a scene name: 'cave' for 'cave-3' and for 'cave'; a mesh file's stem for its path."""
    if is_mesh_path(name):
        return Path(name).stem
    return name.partition("-")[0]


def canonical_scene_name(name: str) -> str:
    """A mesh file by its absolute path, as datasets, recordings and checkpoints name it for good
    (a relative path would change meaning with the folder a command runs in); other names as given."""
    return str(Path(name).resolve()) if is_mesh_path(name) else name


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
