"""Randomised places for training: compositions of open ground, corridors, halls and rooms.

A seed draws a walk of 3-5 legs, cuts it into stretches of 8-35 m and gives each stretch a space of
its own kind and size: open ground, a corridor or a hall (a tube of rectangular or vaulted section,
roofed or open to the sky), or a room (a short wide tube closed by end walls with a door in each).
Then it scatters parts over and beside the walk at a random density and scale: walls, pillars,
boxes, rock, beams overhead and slopes; the spaces' surfaces are roughened by an amount drawn from
smooth concrete to rock. Sizes, counts, roughness and the mixture are all drawn, so that no two
places share a plan and no family's generator is copied (the test and held-out families least of
all): a network trained on these places cannot learn a generator's habits, only what each part
constrains.
"""

from __future__ import annotations

import numpy as np
import trimesh

from .geometry import box, merge, polar_profile, resample_polyline, smooth_noise, sweep
from .layout import beside, ground_surface, keeps_clear, piece, walk_legs
from .scene import Scene

SPACES = ("open", "corridor", "hall", "room")
PARTS = ("box", "pillar", "rock", "wall", "beam", "slope")
SPACING = 0.5  # m between the walk's points (layout.walk_legs)


def _stretches(rng: np.random.Generator, walk: np.ndarray) -> list[np.ndarray]:
    """The walk cut into consecutive stretches of 8-35 m (sharing their end points)."""
    cuts = [0]
    while cuts[-1] < len(walk) - 1:
        cuts.append(min(len(walk) - 1, cuts[-1] + int(rng.uniform(8, 35) / SPACING)))
    return [walk[a : b + 1] for a, b in zip(cuts[:-1], cuts[1:])]


def _size(rng: np.random.Generator, kind: str, scale: float) -> tuple[float, float]:
    """Width and height of a space of `kind`, scaled; a corridor leaves the robot at least 1.8 m."""
    low, high = {
        "corridor": ((1.8, 2.2), (5.0, 5.0)),
        "hall": ((8.0, 4.0), (30.0, 12.0)),
        "room": ((4.0, 2.5), (16.0, 5.0)),
    }[kind]
    width, height = rng.uniform(low, high) * scale
    return max(float(width), 1.8), max(float(height), 2.2)


def _roofless(tube: trimesh.Trimesh, floor: float, height: float) -> trimesh.Trimesh:
    """The tube without the faces of its roof (facing down, high above the floor): walls open to the sky."""
    centres, normals = tube.triangles_center, tube.face_normals
    keep = ~((np.abs(normals[:, 2]) > 0.6) & (centres[:, 2] > floor + 0.6 * height))
    return trimesh.Trimesh(tube.vertices, tube.faces[keep], process=False)


def _end_walls(stretch: np.ndarray, width: float, height: float, door: float) -> list[trimesh.Trimesh]:
    """A wall across each end of a stretch, with a door of `door` m where the walk passes."""
    walls = []
    for end, inner in ((0, 1), (-1, -2)):
        d = stretch[end, :2] - stretch[inner, :2]
        yaw = float(np.arctan2(d[1], d[0])) + np.pi / 2  # across the walk
        across = np.array([np.cos(yaw), np.sin(yaw)])
        side = (width / 2 + 0.5 - door / 2) / 2  # each half from the door's edge to beyond the tube's wall
        for sign in (-1.0, 1.0):
            centre = stretch[end, :2] + sign * across * (door / 2 + side)
            walls.append(box((centre[0], centre[1], stretch[end, 2] + height / 2), (2 * side, 0.3, height), yaw=yaw))
    return walls


def _space(rng: np.random.Generator, stretch: np.ndarray, scale: float) -> list[trimesh.Trimesh]:
    """The enclosure of one stretch of the walk (none for open ground)."""
    kind = str(rng.choice(SPACES, p=[0.3, 0.3, 0.2, 0.2]))
    if kind == "open" or len(stretch) < 4:
        return []
    width, height = _size(rng, kind, scale)
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    rho, centre = polar_profile(str(rng.choice(["rectangular", "horseshoe"])), angles, width, height)
    roughness = float(np.exp(rng.uniform(np.log(0.003), np.log(0.5))))
    noise = smooth_noise(rng, roughness, wavelengths=(0.8, 8.0))
    tube = sweep(stretch, angles, np.tile(rho, (len(stretch), 1)), np.full(len(stretch), centre), noise=noise)
    if kind != "room" and rng.random() < 0.3:
        tube = _roofless(tube, float(stretch[:, 2].min()), height)
    if kind != "room":
        return [tube]
    return [tube, *_end_walls(stretch, width, height, float(rng.uniform(1.2, 2.5)))]


def _beam(rng: np.random.Generator, walk: np.ndarray, height, scale: float) -> list[trimesh.Trimesh]:
    """A horizontal beam 2.9-7 m over the ground, at any angle to the walk."""
    xy, heading = beside(rng, walk, 0.0, 6.0 * scale)
    width, depth = (float(v) for v in rng.uniform(0.15, 0.6, 2))
    size = (float(rng.uniform(3, 30) * scale), width, depth)
    z = float(height(xy)[0]) + float(rng.uniform(2.9, 7.0))
    return [box((xy[0], xy[1], z), size, yaw=heading + float(rng.uniform(-np.pi / 2, np.pi / 2)))]


def _slope(rng: np.random.Generator, walk: np.ndarray, height, scale: float) -> list[trimesh.Trimesh]:
    """A ramp (a plate tilted by 5-35 deg) standing on the ground beside the walk."""
    xy, heading = beside(rng, walk, 2.0, 2.0 + 10.0 * scale)
    length, width = float(rng.uniform(3, 12) * scale), float(rng.uniform(2, 8) * scale)
    pitch, yaw = float(np.radians(rng.uniform(5, 35))), heading + float(rng.uniform(-np.pi, np.pi))
    plate = trimesh.creation.box(extents=(length, width, 0.2))
    plate.apply_transform(trimesh.transformations.rotation_matrix(pitch, (0, 1, 0)))
    plate.apply_transform(trimesh.transformations.rotation_matrix(yaw, (0, 0, 1)))
    z0 = float(height(xy)[0]) - 0.1
    return [plate.apply_translation((xy[0], xy[1], z0 + length / 2 * np.sin(pitch)))]


def _parts(rng: np.random.Generator, walk: np.ndarray, height, scale: float) -> list[trimesh.Trimesh]:
    """Parts scattered over and beside the walk at a drawn density and spread; none that stands on it."""
    density = float(rng.choice([0.0, 0.5, 2.0, 5.0], p=[0.15, 0.3, 0.3, 0.25]))  # parts per 10 m of walk
    spread = float(np.exp(rng.uniform(np.log(1.5), np.log(20.0)))) * scale
    mix = rng.dirichlet(np.ones(len(PARTS)))  # each place its own mixture of parts
    length = SPACING * (len(walk) - 1)
    out: list[trimesh.Trimesh] = []
    for _ in range(int(rng.poisson(density * length / 10))):
        kind = str(rng.choice(PARTS, p=mix))
        if kind == "beam":
            out += _beam(rng, walk, height, scale)
        elif kind == "slope":
            out += _slope(rng, walk, height, scale)
        else:
            xy, heading = beside(rng, walk, 1.5, 1.5 + spread)
            out += piece(rng, kind, xy, heading, float(height(xy)[0]) - 0.3, walk)
    return [part for part in out if keeps_clear(part, walk, height)]


def make_composition(seed: int = 0) -> Scene:
    """One randomised place (see the module's text); the walk is its route and sampling path."""
    rng = np.random.default_rng(seed + 31000)
    walk = walk_legs(rng)
    lo, hi = walk[:, :2].min(axis=0) - 35, walk[:, :2].max(axis=0) + 35
    ground, height = ground_surface(rng, lo, hi)
    walk[:, 2] = height(walk[:, :2])
    scale = float(np.exp(rng.uniform(np.log(0.6), np.log(1.6))))  # the place's size, every part alike
    parts = [ground]
    for stretch in _stretches(rng, walk):
        parts += _space(rng, stretch, scale)
    parts += _parts(rng, walk, height, scale)
    route = resample_polyline(walk, 1.0)
    return Scene.along_route(f"composition-{seed}", merge(parts), route, "composition", seed)
