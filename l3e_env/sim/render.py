"""Top-down pictures of a scene, the robot and its scan, as RGB arrays (no GUI needed)."""

from __future__ import annotations

import numpy as np
import trimesh

from scenes import Scene

BACKGROUND = np.array([250, 250, 247], dtype=np.uint8)
ROUTE, TRAIL, ROBOT, NOSE = (190, 190, 220), (40, 120, 40), (20, 20, 20), (230, 30, 30)
SCAN_LOW, SCAN_HIGH = np.array([30, 90, 230]), np.array([230, 60, 30])  # scan points 1 m below to 3 m above the body
LEGEND_ROWS = 28  # the strip under the plan: scale bar and colour key


def _even(n: int) -> int:
    return n + (n % 2)


def _scale_bar_metres(pixels_per_metre: float, at_most: int) -> float:
    """The longest of 1, 2, 5, 10, 20, 50 ... m that fits in `at_most` pixels."""
    best = 1.0
    for decade in (1, 10, 100, 1000):
        for step in (1, 2, 5):
            if step * decade * pixels_per_metre <= at_most:
                best = float(step * decade)
    return best


def wall_points(mesh: trimesh.Trimesh, count: int = 300_000, seed: int = 0) -> np.ndarray:
    """Points on the steep faces of the mesh (walls, not floors or flat roofs): the floor plan."""
    normals = mesh.face_normals
    steep = np.abs(normals[:, 2]) < 0.6
    if not steep.any():
        return np.zeros((0, 3))
    sub = trimesh.Trimesh(mesh.vertices, mesh.faces[steep], process=False)
    pts, _ = trimesh.sample.sample_surface(sub, count, seed=seed)
    return np.asarray(pts)


def binned_from_above(
    points: np.ndarray, values: np.ndarray, cells: int = 800
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Points seen from above (their first two coordinates) as a grid of square cells, `cells` along
    its longer side: each cell the largest of its points' `values`, NaN where none falls; and the
    grid's extent (left, right, bottom, top) for matplotlib's `imshow(grid, extent=...,
    origin="lower")`. A figure shows a hundred thousand coloured points as such an image in
    milliseconds, where as many coloured markers take matplotlib a second or more to draw."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    if len(xy) == 0:
        return np.full((1, 1), np.nan), (0.0, 1.0, 0.0, 1.0)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    size = max(float(np.max(hi - lo)), 1e-9) / cells
    columns, rows = np.floor((hi - lo) / size).astype(int) + 1
    col, row = np.floor((xy - lo) / size).astype(int).T
    grid = np.full((rows, columns), -np.inf)
    np.maximum.at(grid, (row, col), np.asarray(values, dtype=np.float64))
    grid[np.isneginf(grid)] = np.nan
    return grid, (lo[0], lo[0] + columns * size, lo[1], lo[1] + rows * size)


class TopDownRenderer:
    """Rasterises the floor plan once; each frame then costs a few array writes. Frames have even
    sides (video encoders want them) and a strip under the plan with a scale bar and the colour key."""

    def __init__(self, scene: Scene, max_pixels: int = 640, margin: float = 2.0):
        lo, hi = scene.bounds[0, :2] - margin, scene.bounds[1, :2] + margin
        self.origin = lo
        self.scale = max_pixels / float(np.max(hi - lo))  # pixels per metre
        rows, cols = np.ceil((hi - lo)[::-1] * self.scale).astype(int) + 1
        self.shape = (_even(int(rows)), _even(max(int(cols), 384)))  # the plan: rows (y), cols (x)
        base = np.tile(BACKGROUND, (*self.shape, 1))
        pts = wall_points(scene.mesh)
        if len(pts):
            counts = np.zeros(self.shape, dtype=np.float64)
            r, c = self.to_pixels(pts[:, :2])
            np.add.at(counts, (r, c), 1.0)
            shade = np.clip(counts / max(np.percentile(counts[counts > 0], 60), 1e-9), 0, 1)
            base = (base * (1 - 0.8 * shade[..., None])).astype(np.uint8)
        for route in scene.routes.values():
            self._polyline(base, route[:, :2], ROUTE)
        self.base = np.concatenate([base, self._legend(self.shape[1])])

    def _legend(self, width: int) -> np.ndarray:
        """The strip under the plan: a scale bar and the colour of each thing drawn."""
        from PIL import Image, ImageDraw

        strip = Image.new("RGB", (width, LEGEND_ROWS), tuple(int(v) for v in BACKGROUND))
        draw = ImageDraw.Draw(strip)
        metres = _scale_bar_metres(self.scale, width // 4)
        bar = int(round(metres * self.scale))
        draw.rectangle([6, 16, 6 + bar, 19], fill=(0, 0, 0))
        draw.text((6, 3), f"{metres:g} m", fill=(0, 0, 0))
        x = 16 + max(bar, 40)
        for label, colour in (
            ("route", ROUTE),
            ("trail", TRAIL),
            ("scan low", tuple(SCAN_LOW)),
            ("scan high", tuple(SCAN_HIGH)),
            ("robot", NOSE),
        ):
            draw.rectangle([x, 10, x + 8, 18], fill=tuple(int(v) for v in colour))
            draw.text((x + 11, 8), label, fill=(0, 0, 0))
            x += 17 + int(draw.textlength(label))
        return np.asarray(strip, dtype=np.uint8)

    def to_pixels(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        px = (np.asarray(xy) - self.origin) * self.scale
        col = np.clip(px[:, 0].astype(int), 0, self.shape[1] - 1)
        row = np.clip(self.shape[0] - 1 - px[:, 1].astype(int), 0, self.shape[0] - 1)
        return row, col

    def _polyline(self, img: np.ndarray, xy: np.ndarray, color) -> None:
        if len(xy) < 2:
            return
        seg = np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()
        t = np.linspace(0, 1, max(2, int(seg * self.scale * 2)))
        s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        s = s / max(s[-1], 1e-9)
        dense = np.column_stack([np.interp(t, s, xy[:, 0]), np.interp(t, s, xy[:, 1])])
        r, c = self.to_pixels(dense)
        img[r, c] = color

    def frame(
        self,
        T_w_b: np.ndarray,
        scan_world: np.ndarray | None = None,
        trail: np.ndarray | None = None,
        footprint: tuple[float, float] = (0.9, 0.5),
    ) -> np.ndarray:
        """RGB uint8 image: floor plan, trail, scan points (by height) and the robot footprint, over the
        legend strip."""
        img = self.base.copy()
        if trail is not None and len(trail) > 1:
            self._polyline(img, np.asarray(trail)[:, :2], TRAIL)
        if scan_world is not None and len(scan_world):
            r, c = self.to_pixels(scan_world[:, :2])
            z = scan_world[:, 2] - T_w_b[2, 3]
            t = np.clip((z + 1.0) / 4.0, 0, 1)[:, None]
            img[r, c] = (SCAN_LOW * (1 - t) + SCAN_HIGH * t).astype(np.uint8)
        lx, ly = footprint
        g = np.stack(np.meshgrid(np.linspace(-lx / 2, lx / 2, 12), np.linspace(-ly / 2, ly / 2, 7)), -1).reshape(-1, 2)
        xy = g @ T_w_b[:2, :2].T + T_w_b[:2, 3]
        r, c = self.to_pixels(xy)
        img[r, c] = ROBOT
        nose = T_w_b[:2, 3] + T_w_b[:2, 0] * np.linspace(0, lx, 10)[:, None]
        r, c = self.to_pixels(nose)
        img[r, c] = NOSE
        return img
