"""Monte-Carlo registration errors estimated from one scan alone.

The labels (labels.py) ray-cast children around a parent in the full scene and register each
to the parent. With only the parent's scan in hand, its range image is the best surface there
is: neighbouring returns of neighbouring beams and columns are joined into triangles, except
across depth jumps, and the children are ray-cast against that mesh. It is physics rather than
learning, so it carries over to scene families no model was trained on, at the cost of up to M
registrations a scan. What the mesh lacks (surfaces the parent did not see) the children miss
too, so the estimate runs somewhat low; `calibration` scales it back (fitted on training scenes).

Most scans are clearly localizable or clearly not on every axis, and a few children settle that;
only an axis near its threshold needs many. So children are drawn in stages (10, 20, 40, ... up
to M) and drawing stops once every axis lies `settle` times the estimate's own spread away from
its threshold. The children are the same draws in the same order, so a scan that goes on to M
gets exactly the estimate of M children.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from l3e_env.config import LidarConfig
from l3e_env.config.labelling import ScanMCConfig
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.patterns import BEAM_TOLERANCE, BeamPattern, get_pattern
from l3e_env.sim.raycast import EmbreeCaster

if TYPE_CHECKING:
    import trimesh

from .labels import LabelConfig, child_offset, registration_error
from .registration import PreparedTarget, RegistrationConfig, RegistrationError, prepare_source, register
from .up import ground_plane


class ScanEstimate(NamedTuple):
    errors: np.ndarray  # (6,) estimated mean registration errors, calibrated
    children: int  # children drawn (registered or not)
    # (registered children, 6) each registered child's errors in draw order, not calibrated: what
    # the estimate's own Monte-Carlo spread, or another calibration, is worked out from
    child_errors: np.ndarray


class ScanPatternError(ValueError):
    """Points that do not lie on the rays of the LiDAR's beam pattern."""


def beams_and_columns(points: np.ndarray, pattern: BeamPattern) -> tuple[np.ndarray, np.ndarray]:
    """The beam and column of each point, from its direction: a scan stored as bare points keeps
    them, since range noise moves a return along its ray only."""
    r = np.linalg.norm(points, axis=1)
    if not (r > 0).all():
        raise ScanPatternError("the scan holds a point at the sensor's origin")
    beam, column, off = pattern.locate(points)
    spacing = pattern.spacing_deg()
    if off.max(initial=0.0) > BEAM_TOLERANCE * spacing:
        raise ScanPatternError(
            f"a point lies {off.max():.2f} deg off the nearest beam of {pattern.name} (beams "
            f"{spacing:.2f} deg apart): give a scan of that sensor, in its own frame, or leave "
            "the sensor to be recognised from the scan"
        )
    return beam, column


def _corner(grid: np.ndarray, down: int, right: int) -> np.ndarray:
    """The grid shifted `down` rows and `right` columns (columns wrap around), one row short."""
    return np.roll(grid, -right, axis=1)[down : down + len(grid) - 1]


def _joined(
    vertex: np.ndarray, ranges: np.ndarray, max_range_ratio: float, keep: np.ndarray | None = None
) -> np.ndarray:
    """The two triangles of each 2 x 2 block of the grid whose three returns exist and whose ranges differ
    by less than `max_range_ratio` (with `keep`, only those that touch a kept cell)."""
    faces = []
    for tri in (((0, 0), (0, 1), (1, 0)), ((0, 1), (1, 1), (1, 0))):
        ids = [_corner(vertex, d, r) for d, r in tri]
        rs = [_corner(ranges, d, r) for d, r in tri]
        hi, lo = np.maximum.reduce(rs), np.minimum.reduce(rs)
        ok = (ids[0] >= 0) & (ids[1] >= 0) & (ids[2] >= 0) & (hi < max_range_ratio * lo)
        if keep is not None:  # only faces that reach behind the foreground
            ok &= np.logical_or.reduce([_corner(keep, d, r) for d, r in tri])
        faces.append(np.stack([i[ok] for i in ids], axis=1))
    return np.concatenate(faces)


def _add_shadow(
    vertices: list, faces: list, vertex: np.ndarray, ranges: np.ndarray, pattern: BeamPattern, ratio: float, deg: float
) -> None:
    """A surface behind each return beside a depth jump, at the farthest range within `deg` of azimuth
    and a beam: taken to go on behind the foreground, where a child that moves sees it."""
    from scipy.ndimage import maximum_filter

    width = 2 * int(round(deg / (360.0 / pattern.n_azimuth))) + 1
    far = maximum_filter(ranges, size=(3, width), mode=("nearest", "wrap"))
    behind = (vertex >= 0) & (far >= ratio * ranges)  # foreground returns beside a far surface
    layer = vertex.copy()
    layer[behind] = sum(map(len, vertices)) + np.arange(behind.sum())
    vertices.append(vertices[0][vertex[behind]] * (far[behind] / ranges[behind])[:, None])
    faces.append(_joined(layer, np.where(behind, far, ranges), ratio, behind))


def _add_beyond(
    vertices: list, faces: list, vertex: np.ndarray, ranges: np.ndarray, pattern: BeamPattern, ratio: float, deg: float
) -> None:
    """The lowest and highest beams' surfaces continued `deg` past them, one beam spacing a row, their
    range growing by the ratio between the edge beam's and the next beam's."""
    elevations = np.sort(pattern.elevations_deg)
    rows = int(np.ceil(deg / pattern.spacing_deg()))
    points = vertices[0]
    for edge, inner in ((0, 1), (-1, -2)):
        ids, growth = vertex[edge], ranges[edge] / np.where(ranges[inner] > 0, ranges[inner], np.inf)
        ok = (ids >= 0) & (growth > 1 / ratio) & (growth < ratio)
        last = points[np.where(ok, ids, 0)]
        azimuth = np.arctan2(last[:, 1], last[:, 0])
        step = np.deg2rad(elevations[edge] - elevations[inner])
        elevation = np.arctan2(last[:, 2], np.hypot(last[:, 0], last[:, 1]))
        grid, grid_ranges = [vertex[edge]], [ranges[edge]]
        for k in range(1, rows + 1):
            r = ranges[edge] * growth**k
            el = elevation + k * step
            ray = np.stack([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)], axis=1)
            index = np.full(len(ids), -1, dtype=np.int64)
            index[ok] = sum(map(len, vertices)) + np.arange(ok.sum())
            vertices.append((ray * r[:, None])[ok])
            grid.append(index)
            grid_ranges.append(np.where(ok, r, 0.0))
        stack, stack_ranges = np.stack(grid), np.stack(grid_ranges)
        if edge == 0:  # rows run from the lowest up
            stack, stack_ranges = stack[::-1], stack_ranges[::-1]
        fresh = np.ones_like(stack, dtype=bool)
        fresh[-1 if edge == 0 else 0] = False
        faces.append(_joined(stack, stack_ranges, ratio, fresh))


def range_image_mesh(
    points: np.ndarray,
    pattern: BeamPattern,
    max_range_ratio: float = 1.5,
    shadow_deg: float = 0.0,
    beyond_deg: float = 0.0,
) -> trimesh.Trimesh:
    """The scan's points as vertices, each 2 x 2 block of neighbouring beams and columns (columns
    wrap around) as two triangles where all three returns exist and their ranges differ by less
    than `max_range_ratio`. With `shadow_deg`, a surface behind each return beside a depth jump,
    at the farthest range within that many degrees of azimuth and a beam: a child that moves sees
    into the foreground's shadow, as it would in the scene, where the scan alone has no surface.
    With `beyond_deg`, the surfaces at the lowest and highest beams are continued that far beyond
    them, their range growing by the ratio between the last two beams' (a child pitched or rolled
    sees past the scan's field of view)."""
    points = np.asarray(points, dtype=np.float64)
    # neighbours by the returns' own azimuths: the beams of a staggered sensor (an Ouster's) fire
    # degrees apart at one encoder column, and joining those would fold the mesh (scanmc then
    # read x in a 64-beam tunnel as 0.3-0.5 m against the label's 0.04-0.07 m)
    beam, column = beams_and_columns(points, replace(pattern, azimuth_offsets_deg=()))
    shape = (pattern.n_beams, pattern.n_azimuth)
    vertex = np.full(shape, -1, dtype=np.int64)
    vertex[beam, column] = np.arange(len(points))
    beside = (np.roll(vertex, -1, axis=1)[beam, column] >= 0).mean() if len(points) else 0.0
    if beside < 0.5:  # a full revolution has a return in the next column beside nearly every return
        raise ScanPatternError(
            f"only {beside:.0%} of the scan's returns have one beside them: the scan is thinned "
            "or sampled, and the estimate needs every return of a revolution"
        )
    ranges = np.zeros(shape)
    ranges[beam, column] = np.linalg.norm(points, axis=1)
    order = np.argsort(pattern.elevations_deg)  # rows from the lowest beam up, so that rows k, k+1 neighbour
    vertex, ranges = vertex[order], ranges[order]
    vertices, faces = [points], [_joined(vertex, ranges, max_range_ratio)]
    if shadow_deg > 0:
        _add_shadow(vertices, faces, vertex, ranges, pattern, max_range_ratio, shadow_deg)
    if beyond_deg > 0 and pattern.n_beams > 2:
        _add_beyond(vertices, faces, vertex, ranges, pattern, max_range_ratio, beyond_deg)
    import trimesh  # loads slowly: only the scan estimate builds a mesh

    return trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False)


GROUND_FACES = np.array([[0, 1, 2], [0, 2, 3]])
# m: the continued ground lies this far under the fitted plane, so that where the scan's own floor is
# meshed its noisy returns are what a child sees (a plane through them cut it, and a closed room's z
# errors rose by a half); beyond them the ground the scene has, a centimetre low
GROUND_BELOW = 0.01


def continued_ground(points: np.ndarray, reach: float) -> np.ndarray | None:
    """The four corners (4, 3) of a square `reach` m to each side on the scan's fitted ground plane
    (localizability.up.ground_plane), GROUND_BELOW under it; None where no ground plane is found. A hole
    where the scan's ground returns lie would leave the gaps between its unjoined far rings open, and
    open ground lost z again (studies/scan_mc_open_ground.py)."""
    found = ground_plane(points)
    if found is None:
        return None
    n, d, _ = found
    u = np.cross(n, (1.0, 0.0, 0.0) if abs(n[0]) < 0.9 else (0.0, 1.0, 0.0))
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    centre = n * (d - GROUND_BELOW)
    return np.array([centre + reach * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])


def scan_surface(points: np.ndarray, pattern: BeamPattern, config: ScanMCConfig) -> trimesh.Trimesh:
    """What the children are cast against: the scan's range-image mesh (range_image_mesh) and its ground
    continued (continued_ground); RegistrationError where no two returns join into a surface."""
    mesh = range_image_mesh(points, pattern, config.max_range_ratio, config.shadow_deg, config.beyond_deg)
    if len(mesh.faces) == 0:
        raise RegistrationError("no two neighbouring returns of the scan could be joined into a surface")
    if config.ground_reach > 0 and (ground := continued_ground(points, config.ground_reach)) is not None:
        faces = np.vstack([mesh.faces, len(mesh.vertices) + GROUND_FACES])
        mesh = type(mesh)(np.vstack([mesh.vertices, ground]), faces, process=False)
    return mesh


def scan_errors(
    points: np.ndarray,
    lidar: LidarConfig,
    registration: RegistrationConfig,
    labels: LabelConfig,
    config: ScanMCConfig,
    rng: np.random.Generator,
    R_l_s: np.ndarray | None = None,
) -> ScanEstimate:
    """The scan's estimated mean registration errors (metres, radians), as labels.py computes
    them in the full scene, in the scan's level frame (`R_l_s`, from the up direction:
    `core.transforms.level_rotation`; None takes the sensor as level), times the calibration, from
    as many children as settle every axis against `labels`' thresholds. Raises RegistrationError
    where the scan itself cannot be registered, or more than half of the children cannot."""
    if config.column_stride < 1:
        raise ValueError(f"the scan estimate casts every k-th column, k >= 1, got {config.column_stride}")
    if config.children < 1 or config.first < 1:
        raise ValueError(
            f"the scan estimate needs at least one child, got children={config.children} first={config.first}"
        )
    if not config.settle >= 0 or len(config.spread) != 6 or len(config.calibration) != 6:
        raise ValueError(
            f"scan estimate settings: settle must be >= 0 (got {config.settle}), spread and calibration "
            f"six numbers each (got {len(config.spread)} and {len(config.calibration)})"
        )
    points = np.asarray(points, dtype=np.float64)
    target = PreparedTarget(points, registration)  # checks shape, NaN and size first
    pattern = get_pattern(lidar.model)
    mesh = scan_surface(points, pattern, config)
    cast = replace(pattern, n_azimuth=pattern.n_azimuth // config.column_stride) if config.column_stride > 1 else None
    sensor = Lidar(EmbreeCaster(mesh, threads=1), lidar, cast)
    sigma, thresholds = labels.sigma_vector("child"), labels.threshold_vector()
    R_l_s = np.eye(3) if R_l_s is None else np.asarray(R_l_s, dtype=np.float64)
    calibration, spread = np.asarray(config.calibration), np.asarray(config.spread)
    errors: list[np.ndarray] = []
    drawn, stage = 0, min(config.first, config.children)
    while True:
        for _ in range(stage - drawn):
            T_p_c = child_offset(rng, sigma, R_l_s)
            child = sensor.scan(T_p_c, rng)
            try:
                result = register(prepare_source(child.points, registration), target, registration, with_hessian=False)
            except RegistrationError:
                continue
            errors.append(registration_error(result.T_target_source, T_p_c, labels.error_frame, R_l_s))
        drawn = stage
        if len(errors) < max(1, drawn // 2):
            raise RegistrationError(
                f"{drawn - len(errors)} of {drawn} children of the scan's own surface could not be registered"
            )
        estimate = np.mean(errors, axis=0) * calibration
        margin = np.abs(np.log(np.maximum(estimate, 1e-12) / thresholds))
        settled = config.settle > 0 and (margin >= config.settle * spread * np.sqrt(20 / drawn)).all()
        if drawn >= config.children or settled:
            return ScanEstimate(estimate, drawn, np.array(errors))
        stage = min(2 * drawn, config.children)
