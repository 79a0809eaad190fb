"""Geometric primitives as in the paper's dataset: planes, walls, boxes, cylinders, pipes."""

from __future__ import annotations

import numpy as np
import trimesh

from .geometry import box, ground_plane, merge, polar_profile, resample_polyline, sweep
from .scene import Scene

KINDS = ("plane", "walls", "box_room", "cylinder_room", "pipe")


def make_primitive(seed: int = 0, kind: str | None = None) -> Scene:
    """One primitive environment; the kind cycles with the seed unless given.

    plane: x, y, yaw free; walls (two parallel walls, no roof): along-wall axis free;
    box_room: all constrained; cylinder_room: yaw free; pipe (round, the floor too): along-axis and
    the turn about the axis free, which the sensor below the axis sees as roll and a sideways shift.
    """
    rng = np.random.default_rng(seed + 2000)
    name = f"primitives-{seed}" if kind in (None, KINDS[seed % len(KINDS)]) else f"primitives-{seed}:{kind}"
    kind = kind or KINDS[seed % len(KINDS)]
    if kind == "plane":
        mesh = ground_plane(-150, 150, -150, 150, cell=50)
        path = np.array([[-20.0, 0, 0], [20.0, 0, 0]])
    elif kind == "walls":
        w, h = rng.uniform(3, 8), rng.uniform(2, 5)
        walls = [box((0, s * w / 2, h / 2), (300, 0.2, h)) for s in (-1, 1)]
        mesh = merge([ground_plane(-150, 150, -20, 20, cell=50)] + walls)
        path = np.array([[-30.0, 0, 0], [30.0, 0, 0]])
    elif kind == "box_room":
        lx, ly, h = rng.uniform(6, 20), rng.uniform(6, 20), rng.uniform(2.5, 6)
        mesh = trimesh.creation.box(extents=(lx, ly, h))
        mesh.apply_translation((0, 0, h / 2))
        path = np.array([[-lx / 4, -ly / 4, 0], [lx / 4, ly / 4, 0]])
    elif kind == "cylinder_room":
        r, h = rng.uniform(4, 12), rng.uniform(3, 8)
        mesh = trimesh.creation.cylinder(radius=r, height=h, sections=96)
        mesh.apply_translation((0, 0, h / 2))
        path = np.array([[-r / 3, 0, 0], [r / 3, 0, 0]])
    elif kind == "pipe":
        d = rng.uniform(3, 7)
        s = np.linspace(-150, 150, 61)
        angles = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        rho, _ = polar_profile("circular", angles, d, d)
        # centred d/2 above the route, so that its floor is round: a turn about its axis is free
        mesh = sweep(np.column_stack([s, 0 * s, 0 * s]), angles, np.tile(rho, (len(s), 1)), np.full(len(s), d / 2))
        path = np.array([[-30.0, 0, 0], [30.0, 0, 0]])
    else:
        raise ValueError(f"unknown primitive kind '{kind}' (choose from {KINDS})")
    route = resample_polyline(path, 1.0)
    return Scene.along_route(name, trimesh.Trimesh(mesh.vertices, mesh.faces, process=False), route, "primitives", seed)
