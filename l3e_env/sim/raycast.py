"""Ray casting backends behind one interface: Embree (default) and PyBullet's rayTestBatch."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Protocol

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from l3e_env.core.quiet import import_pybullet
from l3e_env.core.threads import part_threads

if TYPE_CHECKING:  # trimesh and pybullet load slowly: only the meshes' owners need them
    import trimesh


# PyBullet returns 16383 results or none for 16384 rays and raises beyond: stay below.
PYBULLET_MAX_RAYS = 16000


class RayCaster(Protocol):
    def cast(self, origin: np.ndarray, directions: np.ndarray, max_range: float) -> np.ndarray:
        """Distances (float32, N) along unit `directions` from `origin` (world frame), one point (3,)
        or one per ray (N, 3); inf = miss."""
        ...


_POOLS: dict[int, ThreadPoolExecutor] = {}
# a forked child (async vector envs, worker pools) inherits the dict but not the threads
os.register_at_fork(after_in_child=_POOLS.clear)


def _pool(threads: int) -> ThreadPoolExecutor:
    if threads not in _POOLS:
        _POOLS[threads] = ThreadPoolExecutor(threads, thread_name_prefix="embree")
    return _POOLS[threads]


class EmbreeCaster:
    """Intel Embree through embreex: ~10x PyBullet's throughput on one thread.

    embreex releases the GIL while it traces, so a scan is split over `threads` worker threads
    (default: `part_threads()`, up to 2). Vertices are stored relative to the
    mesh centre so float32 keeps sub-millimetre precision in scenes a few hundred metres wide.
    """

    MIN_RAYS_PER_THREAD = 4096

    def __init__(self, mesh: trimesh.Trimesh, threads: int | None = None):
        self.threads = max(1, threads if threads is not None else part_threads())
        self.offset = np.asarray(mesh.bounds, dtype=np.float64).mean(axis=0)
        self.scene = rtcore_scene.EmbreeScene()
        verts = (np.asarray(mesh.vertices, dtype=np.float64) - self.offset).astype(np.float32)
        TriangleMesh(self.scene, verts, np.asarray(mesh.faces, dtype=np.int32))

    def cast(self, origin: np.ndarray, directions: np.ndarray, max_range: float) -> np.ndarray:
        o = (np.asarray(origin, dtype=np.float64) - self.offset).astype(np.float32)
        dirs = np.ascontiguousarray(directions, dtype=np.float32)
        origins = np.broadcast_to(o, dirs.shape)
        tfar = np.full(len(dirs), max_range, dtype=np.float32)
        # a few chunks per thread balance the load: downward beams are cheaper than far ones
        parts = min(self.threads * 4, len(dirs) // self.MIN_RAYS_PER_THREAD) if self.threads > 1 else 1
        if parts <= 1:
            dist = self.scene.run(origins, dirs, dists=tfar, query="DISTANCE")
        else:
            edges = np.linspace(0, len(dirs), parts + 1).astype(int)
            jobs = [
                _pool(self.threads).submit(self.scene.run, origins[a:b], dirs[a:b], dists=tfar[a:b], query="DISTANCE")
                for a, b in zip(edges[:-1], edges[1:])
            ]
            dist = np.concatenate([j.result() for j in jobs])
        dist[dist >= max_range] = np.inf  # Embree returns tfar unchanged on a miss
        return dist


class PyBulletCaster:
    """PyBullet rayTestBatch on a client's bodies, chunked below its per-call limit.

    `collision_mask` selects the bodies rays may hit (the robot's own body is left out by the
    world's collision filter groups).
    """

    def __init__(self, client: int, collision_mask: int = 1, threads: int = 1):
        self.client, self.mask, self.threads = client, collision_mask, threads

    @classmethod
    def for_mesh(cls, mesh: trimesh.Trimesh) -> PyBulletCaster:
        """A caster with its own DIRECT client holding only `mesh` (for tests and benchmarks)."""
        pb = import_pybullet()
        client = pb.connect(pb.DIRECT)
        add_static_mesh(client, mesh)
        return cls(client)

    def cast(self, origin: np.ndarray, directions: np.ndarray, max_range: float) -> np.ndarray:
        dirs = np.asarray(directions, dtype=np.float64)
        origins = np.broadcast_to(np.asarray(origin, dtype=np.float64), dirs.shape)
        out = np.full(len(dirs), np.inf, dtype=np.float32)
        pb = import_pybullet()
        for lo in range(0, len(dirs), PYBULLET_MAX_RAYS):
            chunk = dirs[lo : lo + PYBULLET_MAX_RAYS]
            starts = origins[lo : lo + PYBULLET_MAX_RAYS].copy()
            hits = pb.rayTestBatch(
                starts,
                starts + chunk * max_range,
                numThreads=self.threads,
                collisionFilterMask=self.mask,
                physicsClientId=self.client,
            )
            frac = np.array([h[2] if h[0] >= 0 else np.inf for h in hits], dtype=np.float64)
            out[lo : lo + len(chunk)] = frac * max_range
        return out

    def cast_many(self, origins: np.ndarray, direction: np.ndarray, max_range: float) -> np.ndarray:
        """Distances along one direction from many origins (a few rays: ground sensing)."""
        starts = np.asarray(origins, dtype=np.float64)
        pb = import_pybullet()
        hits = pb.rayTestBatch(
            starts,
            starts + np.asarray(direction) * max_range,
            collisionFilterMask=self.mask,
            physicsClientId=self.client,
        )
        return np.array([h[2] * max_range if h[0] >= 0 else np.inf for h in hits])


# PyBullet copies a mesh shape through a fixed shared-memory command: at most 131 072 vertices and
# 524 288 indices a shape (B3_MAX_NUM_VERTICES, B3_MAX_NUM_INDICES); a larger mesh goes in as
# several shapes of at most this many triangles (3 vertices each at most: under both caps)
MAX_SHAPE_TRIANGLES = 40_000


def add_static_mesh(client: int, mesh: trimesh.Trimesh, max_triangles: int | None = None) -> list[int]:
    """Add `mesh` to a PyBullet client as static concave triangle meshes, one body per piece of at most
    `max_triangles` (default MAX_SHAPE_TRIANGLES; pieces of neighbouring triangles, so each body's box
    stays small); the body ids."""
    pb = import_pybullet()
    max_triangles = max_triangles or MAX_SHAPE_TRIANGLES
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if not len(faces):
        raise RuntimeError("the scene mesh holds no triangle: PyBullet has nothing to stand the robot on")
    bodies = []
    for piece in _pieces(np.asarray(mesh.vertices, dtype=np.float64), faces, max_triangles):
        used, local = np.unique(faces[piece], return_inverse=True)
        shape = pb.createCollisionShape(
            pb.GEOM_MESH,
            vertices=np.asarray(mesh.vertices, dtype=np.float64)[used],
            indices=local.astype(np.int32).ravel(),
            flags=pb.GEOM_FORCE_CONCAVE_TRIMESH,
            physicsClientId=client,
        )
        if shape < 0:
            raise RuntimeError(
                f"PyBullet could not build a collision shape from {len(piece)} of the scene mesh's triangles "
                f"({len(used)} vertices): check the mesh for triangles with repeated or non-finite corners"
            )
        body = pb.createMultiBody(baseMass=0, baseCollisionShapeIndex=shape, physicsClientId=client)
        # static bodies default to Bullet's StaticFilter group (2); rays look for group 1
        pb.setCollisionFilterGroupMask(body, -1, 1, 0xFFFF, physicsClientId=client)
        bodies.append(body)
    return bodies


def _pieces(vertices: np.ndarray, faces: np.ndarray, size: int) -> list[np.ndarray]:
    """The faces' indices in runs of at most `size`, neighbours together: sorted by the cell of a grid
    (about `size` faces a cell on average) their centres fall in, then by their x."""
    if len(faces) <= size:
        return [np.arange(len(faces))]
    centres = vertices[faces].mean(axis=1)
    low, span = centres.min(axis=0), np.ptp(centres, axis=0) + 1e-9
    cells = max(1, int(np.ceil(np.sqrt(len(faces) / size))))
    cell = np.minimum((centres[:, :2] - low[:2]) / span[:2] * cells, cells - 1).astype(np.int64)
    order = np.lexsort((centres[:, 0], cell[:, 1], cell[:, 0]))
    return [order[lo : lo + size] for lo in range(0, len(order), size)]


def make_caster(backend: str, mesh: trimesh.Trimesh, client: int | None = None) -> RayCaster:
    if backend == "embree":
        return EmbreeCaster(mesh)
    if backend == "pybullet":
        return PyBulletCaster(client) if client is not None else PyBulletCaster.for_mesh(mesh)
    raise ValueError(f"unknown ray backend '{backend}' (embree, pybullet)")
