"""The up direction of a scan from its own ground, for scans whose tilt nobody measured (a user's
files without an IMU): the plane under the sensor that holds the most returns whose own surface lies
along it (a wall's rings cut by a slanted plane do not count), among planes within MAX_TILT_DEG of
the sensor's own z. Registration's `ground_plane` assumes a sensor within a few
degrees of level (it fits heights over x and y); a scan tilted 20-30 deg needs a fit that does not.
Hand-written: a RANSAC over a few hundred planes of a thinned scan is a few lines of numpy, and
the libraries that offer one (Open3D, pyransac3d) would be a heavy or unkept dependency for it."""

from __future__ import annotations

import numpy as np

MAX_TILT_DEG = 45.0  # the ground's normal lies within this of the sensor's z
MIN_BELOW = 0.3  # m: the sensor stands at least this far above its ground
BAND = 0.05  # m: a return this close to the plane is the ground's
MIN_SHARE = 0.02  # the ground holds at least this share of the thinned returns
MIN_RETURNS = 30  # and at least this many (a level surface under the sensor: a floor, or a table indoors)
VOXEL = 0.2  # m: the scan is thinned to one point a voxel first
TRIES = 500
COUNTED = 20_000  # thinned returns (a random sample of them) the planes are counted on
SCORED = 4000  # of which every tried plane is scored on the first; the FINALISTS best on them all
FINALISTS = 8
NEIGHBOURS = 8  # a return's own surface normal: the plane fitted to its nearest thinned returns
ALONG_DEG = 20.0  # a return counts for a plane where its own normal lies within this of the plane's


def ground_up(points: np.ndarray, seed: int = 0) -> tuple[np.ndarray, float] | None:
    """The ground plane's unit normal (pointing at the sensor: up) in the sensor's frame and the share of
    the thinned returns on it; None where no plane under the sensor holds MIN_SHARE of them."""
    found = ground_plane(points, seed)
    return None if found is None else (found[0], found[2])


def ground_plane(points: np.ndarray, seed: int = 0) -> tuple[np.ndarray, float, float] | None:
    """The ground plane n.p = d under the sensor (n its unit normal pointing up, at the sensor; d < 0)
    and the share of the thinned returns on it; None where no plane holds MIN_SHARE of them."""
    cloud = _thinned(np.asarray(points, dtype=np.float64))
    if len(cloud) < 30:
        return None
    rng = np.random.default_rng(seed)
    # the planes are tried on a sample of the thinned returns (their own normals are the cost)
    picked = cloud[rng.permutation(len(cloud))[:COUNTED]]  # in random order: any first few are a sample
    normals = _normals(cloud, picked)
    cos_tilt, cos_along = np.cos(np.radians(MAX_TILT_DEG)), np.cos(np.radians(ALONG_DEG))
    # the planes are drawn through returns under the sensor whose own surface could be ground
    below = picked[(picked[:, 2] < -MIN_BELOW) & (np.abs(normals[:, 2]) > cos_tilt)]
    if len(below) < 3:
        return None
    a, b, c = np.moveaxis(below[rng.integers(0, len(below), (TRIES, 3))], 1, 0)
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = n / np.maximum(norm, 1e-12) * np.where(n[:, 2:] >= 0, 1.0, -1.0)  # turned towards the sensor's z
    d = np.einsum("ij,ij->i", n, a)  # planes n.p = d; the sensor (origin) lies -d above each
    keep = (norm[:, 0] > 1e-9) & (n[:, 2] >= cos_tilt) & (-d >= MIN_BELOW)
    if not keep.any():
        return None
    n, d = n[keep], d[keep]
    # every plane scored on the sample's first returns at once, the best few counted on all of it
    scores = _on_plane(picked[:SCORED], normals[:SCORED], n, d, cos_along).sum(axis=0)
    few = np.argsort(-scores, kind="stable")[:FINALISTS]
    counts = _on_plane(picked, normals, n[few], d[few], cos_along).sum(axis=0)
    best, share = int(few[int(np.argmax(counts))]), float(counts.max()) / len(picked)
    if share < MIN_SHARE or share * len(cloud) < MIN_RETURNS:
        return None
    normal, offset = _refined(cloud, n[best], float(d[best]))
    return normal, offset, share


def _on_plane(points: np.ndarray, normals: np.ndarray, n: np.ndarray, d: np.ndarray, cos_along: float) -> np.ndarray:
    """(returns, planes): whether each return lies within BAND of each plane n.p = d with its own
    surface along it."""
    return (np.abs(points @ n.T - d) < BAND) & (np.abs(normals @ n.T) > cos_along)


def _thinned(points: np.ndarray) -> np.ndarray:
    """One point a VOXEL cube (the first of each), finite points only."""
    points = points[np.isfinite(points).all(axis=1)]
    if not len(points):
        return points
    cells = np.floor(points / VOXEL).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    if np.prod(span.astype(np.float64)) < 2**62:  # one integer a cell: far quicker than unique rows
        _, first = np.unique(np.ravel_multi_index(cells.T, span), return_index=True)
    else:
        _, first = np.unique(cells, axis=0, return_index=True)
    return points[np.sort(first)]


def _normals(cloud: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The unit normal (unsigned) of the cloud's surface at each point of `at`, from its NEIGHBOURS
    nearest returns of the cloud."""
    from scipy.spatial import cKDTree

    k = min(NEIGHBOURS, len(cloud))
    _, near = cKDTree(cloud).query(at, k)
    hood = cloud[near] - cloud[near].mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("nki,nkj->nij", hood, hood))[1][:, :, 0]


def _refined(cloud: np.ndarray, n: np.ndarray, d: float) -> tuple[np.ndarray, float]:
    """The plane n.p = d refitted (least squares, twice) to the returns within BAND of it."""
    for _ in range(2):
        near = cloud[np.abs(cloud @ n - d) < BAND]
        if len(near) < 3:
            break
        centre = near.mean(axis=0)
        normal = np.linalg.svd(near - centre, full_matrices=False)[2][-1]
        n = normal if normal @ n >= 0 else -normal
        d = float(n @ centre)
    return n, d
