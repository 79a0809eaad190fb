"""Surface normals in closed form: the smallest eigenvector of a 3x3 scatter, one point at a time.

A scatter's eigenvectors by numpy's batched eigh cost more in per-call overhead than in arithmetic
on the few thousand matrices a scan has; the trigonometric solution of the characteristic cubic,
compiled, costs microseconds. The classifier's constraint layer (its voxels' 3x3x3 blocks) and the
registration's target (each voxel's k nearest neighbours, as small_gicp estimates them) both use it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def smallest_eigenvector(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unit eigenvector of the smallest eigenvalue, smallest, middle eigenvalue) of symmetric
    (N, 3, 3) matrices, in closed form (see closed_form_normal)."""
    c = np.asarray(c, dtype=np.float64)
    return _smallest_eigenvectors(np.stack([c[:, i, j] for i, j in _UPPER]))


_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # the six distinct entries, in this order


@njit(cache=True, nogil=True)
def closed_form_normal(a: float, e: float, f: float, b: float, g: float, d: float) -> tuple[float, ...]:
    """(nx, ny, nz, smallest, middle eigenvalue) of [[a, e, f], [e, b, g], [f, g, d]]: the
    trigonometric solution of the characteristic cubic, and the eigenvector as the longest cross
    product of two rows of C - smallest I (it is orthogonal to every row)."""
    q = (a + b + d) / 3
    a0, b0, d0 = a - q, b - q, d - q
    p = max(math.sqrt((a0 * a0 + b0 * b0 + d0 * d0 + 2 * (e * e + f * f + g * g)) / 6), 1e-12)
    det = a0 * (b0 * d0 - g * g) - e * (e * d0 - g * f) + f * (e * g - b0 * f)  # of C - q I
    phi = math.acos(min(max(det / (2 * p**3), -1.0), 1.0)) / 3
    largest = q + 2 * p * math.cos(phi)
    smallest = q + 2 * p * math.cos(phi + 2 * math.pi / 3)
    middle = 3 * q - largest - smallest
    a1, b1, d1 = a - smallest, b - smallest, d - smallest
    x, y, z = e * g - f * b1, f * e - a1 * g, a1 * b1 - e * e  # rows 0 x 1
    longest = x * x + y * y + z * z
    x2, y2, z2 = e * d1 - f * g, f * f - a1 * d1, a1 * g - e * f  # rows 0 x 2
    if x2 * x2 + y2 * y2 + z2 * z2 > longest:
        x, y, z, longest = x2, y2, z2, x2 * x2 + y2 * y2 + z2 * z2
    x2, y2, z2 = b1 * d1 - g * g, g * f - e * d1, e * g - b1 * f  # rows 1 x 2
    if x2 * x2 + y2 * y2 + z2 * z2 > longest:
        x, y, z, longest = x2, y2, z2, x2 * x2 + y2 * y2 + z2 * z2
    length = max(math.sqrt(longest), 1e-12)
    return x / length, y / length, z / length, smallest, middle


@njit(cache=True, nogil=True)
def _smallest_eigenvectors(entries: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """smallest_eigenvector of the (6, N) distinct entries, in _UPPER's order."""
    n = entries.shape[1]
    normal, smallest, middle = np.empty((n, 3)), np.empty(n), np.empty(n)
    for i in range(n):
        a, e, f, b, g, d = entries[:, i]
        nx, ny, nz, smallest[i], middle[i] = closed_form_normal(a, e, f, b, g, d)
        normal[i, 0], normal[i, 1], normal[i, 2] = nx, ny, nz
    return normal, smallest, middle


@njit(cache=True, nogil=True)
def neighbourhood_normals(points: np.ndarray, neighbours: np.ndarray, which: np.ndarray, normals: np.ndarray) -> None:
    """normals[i] = the smallest eigenvector of the scatter of points[neighbours[k]] about their mean,
    for each i = which[k]: each point's normal from its k nearest neighbours (itself among them), the
    moments summed about the mean as small_gicp's normal estimation does. Fewer than three
    neighbours (a negative index: none found) give a zero normal, as small_gicp marks it invalid.
    The scatter is summed about the mean, as small_gicp sums it, so that the registration's normals
    are its own to rounding; the constraint layer's raw moments (l3e_env.model.constraints) stay
    as the shipped model was fitted on them."""
    for k in range(len(which)):
        count = 0
        sx = sy = sz = 0.0
        for u in neighbours[k]:
            if u >= 0:
                count += 1
                sx += points[u, 0]
                sy += points[u, 1]
                sz += points[u, 2]
        i = which[k]
        if count < 3:
            normals[i, 0] = normals[i, 1] = normals[i, 2] = 0.0
            continue
        mx, my, mz = sx / count, sy / count, sz / count
        cxx = cxy = cxz = cyy = cyz = czz = 0.0
        for u in neighbours[k]:
            if u >= 0:
                x, y, z = points[u, 0] - mx, points[u, 1] - my, points[u, 2] - mz
                cxx += x * x
                cxy += x * y
                cxz += x * z
                cyy += y * y
                cyz += y * z
                czz += z * z
        nx, ny, nz, _, _ = closed_form_normal(
            cxx / count, cxy / count, cxz / count, cyy / count, cyz / count, czz / count
        )
        normals[i, 0], normals[i, 1], normals[i, 2] = nx, ny, nz
