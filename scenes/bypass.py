"""Bypass: a long smooth gallery as the short way, and a feature-rich way round it, in the spirit of
the paper's mine. The gallery (60-150 m across seeds) leaves ICP nothing to hold along its axis,
so a robot that takes it walks that stretch on leg odometry alone; the way round is at most 1.5x
longer and lined with structure. Whether the detour pays depends on the gallery's length against
the detour's, which the seeds spread.

Seeds 0-99 are for training (maps, PPO), 100 and up for evaluation (EVALUATION_SEEDS): the two
never share a layout.
"""

from __future__ import annotations

import numpy as np
import trimesh

from .geometry import box, cylinder, ground_plane, merge, resample_polyline, seed_spread
from .scene import Scene

TRAINING_SEEDS = range(0, 100)
EVALUATION_SEEDS = range(100, 150)
MAX_DETOUR = 1.5  # the way round is at most this many times the short way's length
APRON = 8.0  # m of open, structured ground before the gallery and after it


def _face(
    rng: np.random.Generator, x0: float, x1: float, y: float, depth: float, facing: int, height: float
) -> list[trimesh.Trimesh]:
    """A wall along x at `y` whose face (towards `facing` = +1 or -1 in y) is broken by buttresses
    and recesses every 2-6 m, so that walking along it holds every axis."""
    parts = [box(((x0 + x1) / 2, y - facing * depth / 2, height / 2), (x1 - x0, depth, height))]
    x = x0 + rng.uniform(0.5, 2.0)
    while x < x1 - 1.0:
        width = rng.uniform(0.4, 1.6)
        out = rng.uniform(0.3, 0.8)
        parts.append(box((x, y + facing * out / 2, height / 2), (width, out, height * rng.uniform(0.6, 1.0))))
        x += rng.uniform(2.0, 6.0)
    return parts


def _clutter(
    rng: np.random.Generator, x0: float, x1: float, y0: float, y1: float, density: float
) -> list[trimesh.Trimesh]:
    """Pillars, boxes and low rocks scattered in the band y0..y1, about `density` per metre of x."""
    parts = []
    for x in np.sort(rng.uniform(x0, x1, int(density * (x1 - x0)))):
        y = rng.uniform(y0, y1)
        kind = rng.integers(3)
        if kind == 0:
            parts.append(cylinder((x, y), rng.uniform(0.15, 0.5), rng.uniform(1.5, 4.0)))
        elif kind == 1:
            size = (rng.uniform(0.5, 2.0), rng.uniform(0.5, 1.5), rng.uniform(0.8, 2.5))
            parts.append(box((x, y, size[2] / 2), size, yaw=rng.uniform(0, np.pi)))
        else:
            rock = trimesh.creation.icosphere(subdivisions=1, radius=rng.uniform(0.4, 0.9))
            rock.vertices *= rng.uniform(0.6, 1.3, 3)
            rock.apply_translation((x, y, 0.1))
            parts.append(rock)
    return parts


def _boundary_and_aprons(rng: np.random.Generator, gx: float, top: float, bottom: float) -> list:
    """Walls round the whole place, buttressed inside, and a few structures on the aprons off the
    routes, so that start and goal are rich places."""
    parts = _face(rng, -APRON - 4, gx + APRON + 4, top, 0.3, -1, 3.0)
    parts.append(box(((gx) / 2, bottom - 0.15, 1.5), (gx + 2 * APRON + 8, 0.3, 3.0)))
    for x in (-APRON - 4, gx + APRON + 4):
        parts.append(box((x, (top + bottom) / 2, 1.5), (0.3, top - bottom, 3.0)))
    for a, b in ((-APRON - 3, -2.5), (gx + 2.5, gx + APRON + 3)):
        parts += _clutter(rng, a, b, bottom + 1.0, top - 1.0, 0.8)
    return parts


def _routes(gx: float, centres: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The short way straight through the gallery and the rich way round along the detour's lane."""
    short_route = resample_polyline(np.array([[0.0, 0, 0], [gx, 0, 0]]), 1.0)
    corners = [[0.0, 0.0], [3.0, 0.0], [3.0, centres[0]]]
    for k in range(len(steps)):
        corners += [[steps[k] - 1.5, centres[k]], [steps[k] + 1.5, centres[k + 1]]]
    corners += [[gx - 3.0, centres[-1]], [gx - 3.0, 0.0], [gx, 0.0]]
    return short_route, resample_polyline(np.column_stack([np.array(corners), np.zeros(len(corners))]), 1.0)


def make_bypass(seed: int = 0, gallery_length: float | None = None, detour: float | None = None) -> Scene:
    """Start at the origin facing +x, the goal straight ahead beyond a gallery of `gallery_length` m
    (60-150 m across seeds, unset) whose walls and roof are smooth; the way round runs at y =
    `detour` m (8-18 m, within the 1.5x bound) between a buttressed wall and a band of pillars,
    boxes and rocks, with a dog-leg or two. The gallery's width and height, the detour's shape and
    the clutter's density vary with the seed."""
    rng = np.random.default_rng(seed + 5000)
    length = gallery_length or float(60.0 + 90.0 * seed_spread(seed))
    short = length + 2 * APRON
    # the way round is about short + 2 detour + the dog-legs' steps (up to 4 m)
    detour_max = min(18.0, ((MAX_DETOUR - 1.0) * short - 6.0) / 2)
    detour = detour or float(rng.uniform(8.0, max(8.0, detour_max)))
    half = float(rng.uniform(1.2, 2.0))  # the gallery's half width
    height = float(rng.uniform(2.6, 3.6))
    x0, x1 = APRON, APRON + length
    gx = x1 + APRON
    lane = float(rng.uniform(3.5, 5.0))  # the detour's clear width
    density = float(rng.uniform(0.25, 0.7))
    # the detour's dog-legs: the lane's centre steps by up to 2 m at one or two places
    steps = np.sort(rng.uniform(x0 + 10, x1 - 10, int(rng.integers(1, 3))))
    offsets = rng.uniform(-2.0, 2.0, len(steps))
    knots = np.concatenate([[x0], steps, [x1]])
    centres = detour + np.concatenate([[0.0], np.cumsum(offsets)])
    centres = np.clip(centres, half + 3.0 + lane / 2, None)
    top = float(centres.max() + lane / 2 + 6.0)
    bottom = -half - 6.0
    parts = [ground_plane(-APRON - 4, gx + APRON + 4, bottom - 2, top + 2, cell=10)]
    # the gallery: smooth walls and roof
    for sign in (-1, 1):
        parts.append(box(((x0 + x1) / 2, sign * (half + 0.1), height / 2), (length, 0.2, height)))
    parts.append(box(((x0 + x1) / 2, 0.0, height + 0.1), (length, 2 * half + 0.4, 0.2)))
    # below the gallery: solid to the boundary; above it: a block up to the lane, buttressed on the lane's side
    parts.append(box(((x0 + x1) / 2, (bottom - half - 0.2) / 2, height / 2), (length, -bottom - half - 0.2, height)))
    for k in range(len(centres)):
        a, b = knots[k], knots[k + 1]
        face = float(centres[k] - lane / 2)
        parts.append(box(((a + b) / 2, (half + 0.2 + face) / 2, height / 2), (b - a, face - half - 0.2, height)))
        parts += _face(rng, a, b, face, 0.3, +1, height)
        far = float(centres[k] + lane / 2)
        parts += _clutter(rng, a, b, far + 0.6, far + 3.5, density)
    parts += _boundary_and_aprons(rng, gx, top, bottom)
    short_route, rich = _routes(gx, centres, steps)
    for route in (short_route, rich):  # nothing the clutter put on a route
        _clear(parts, route)
    return Scene.two_ways(
        f"bypass-{seed}",
        merge(parts),
        short_route,
        rich,
        "bypass",
        seed,
        {"corridor": np.array([x0, -half, x1, half]), "detour": np.array([x0, half, x1, top])},
    )


def _clear(parts: list[trimesh.Trimesh], route: np.ndarray, radius: float = 1.0) -> None:
    """Drop the clutter (small parts) whose footprint comes within `radius` m of the route."""
    keep = []
    for part in parts:
        lo, hi = part.bounds[0, :2], part.bounds[1, :2]
        small = float(np.prod(hi - lo)) < 6.0
        nearest = np.clip(route[:, :2], lo, hi)
        if small and np.min(np.linalg.norm(route[:, :2] - nearest, axis=1)) < radius:
            continue
        keep.append(part)
    parts[:] = keep
