"""A drive, or a set of judged scans, as a Rerun recording (`.rrd`): the scene's mesh once, the true
path and each fused row's estimate growing step by step, the scan of each step in the world frame at
the estimate's pose coloured by its flags, each axis's probability and flag, and each row's error, on
the time lines `step` and `sim_time`, with a default layout. Open one with `rerun FILE.rrd`.

The only module of the project that imports rerun-sdk (the `viewer` extra): nothing else needs it.
Entities (docs/rerun.md): world/scene, world/truth, world/estimate/<row>, world/scan, world/map and
world/plan (a navigation episode's), flags/<axis>/probability, flags/<axis>/flagged, error/<row>; a
judged file's scan under scans/<name>."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from l3e_env.core.points import random_subset
from l3e_env.localizability.labels import AXES

if TYPE_CHECKING:
    import trimesh

SEND_EVERY = 100  # steps a drive's recording holds before it writes them (a killed run's file has those written)
MAX_SCAN_POINTS = 3000  # a logged scan is a random subset of at most this many of its points (the file's size)
FREE = (90, 200, 90)  # a scan whose axes are all localizable
FLAGGED = (230, 60, 50)  # a scan with a flagged axis
UNJUDGED = (160, 160, 160)
PATH_COLOURS = [(240, 240, 240), (60, 140, 250), (250, 170, 40), (170, 90, 230), (40, 200, 200), (230, 90, 160)]


class RerunMissing(RuntimeError):
    """rerun-sdk is not installed: the message says how to install it."""


def rerun_available() -> bool:
    try:
        import rerun  # noqa: F401
    except ImportError:
        return False
    return True


def _rerun() -> Any:
    try:
        import rerun
    except ImportError as exc:
        raise RerunMissing(
            "--rerun writes a Rerun recording with rerun-sdk, which is not installed: pip install 'l3e[viewer]'"
        ) from exc
    return rerun


def check_rerun() -> None:
    """RerunMissing, saying how to install rerun-sdk, where it is not installed."""
    _rerun()


def open_command(path: str | Path) -> str:
    """The line that opens a recording (the viewer comes with rerun-sdk)."""
    return f"rerun {path}"


@dataclass(frozen=True)
class StepLog:
    """What one step shows: its index and time, the true pose, each row's estimate (body poses, 4x4),
    the scan (sensor frame) with the pose it is placed at, and the flags of the row that placed it."""

    step: int
    seconds: float
    truth: np.ndarray
    estimates: dict[str, np.ndarray]
    scan: np.ndarray | None = None
    T_w_s: np.ndarray | None = None
    probabilities: np.ndarray | None = None
    mask: np.ndarray | None = None


class DriveLog:
    """A recording written step by step into `path` (a new file; the folder is made)."""

    def __init__(self, path: str | Path, name: str, rows: list[str], seed: int = 0):
        rr = _rerun()
        self.rr, self.path, self.rows = rr, Path(path), list(rows)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("l3e", recording_id=name)
        self.rec.save(str(self.path), default_blueprint=_blueprint(rr, self.rows))
        self.rng = np.random.default_rng(seed)
        self.last: dict[str, np.ndarray] = {}
        self.pending: list[StepLog] = []

    def scene(self, mesh: trimesh.Trimesh) -> None:
        """The scene's mesh, once (static: on every time line)."""
        self.rec.log(
            "world/scene",
            self.rr.Mesh3D(
                vertex_positions=np.asarray(mesh.vertices, np.float32),
                triangle_indices=np.asarray(mesh.faces, np.uint32),
                albedo_factor=(150, 150, 160, 255),
            ),
            static=True,
        )

    def map(self, positions: np.ndarray, flagged: np.ndarray) -> None:
        """A localizability map, once: its positions (N, 3) coloured from green (every axis localizable
        there, in every heading) to red (every axis flagged), by the share flagged (N,)."""
        share = np.clip(np.nan_to_num(np.asarray(flagged, float)), 0.0, 1.0)[:, None]
        colours = (np.array(FREE) * (1 - share) + np.array(FLAGGED) * share).astype(np.uint8)
        points = self.rr.Points3D(np.asarray(positions, np.float32), colors=colours, radii=0.08)
        self.rec.log("world/map", points, static=True)

    def plan(self, route: np.ndarray) -> None:
        """A planned route (ground points (K, 3)), once, drawn a little above the ground."""
        line = (np.asarray(route, np.float64)[:, :3] + np.array([0.0, 0.0, 0.1])).astype(np.float32)
        self.rec.log("world/plan", self.rr.LineStrips3D([line], colors=[(250, 220, 40)], radii=0.05), static=True)

    def step(self, s: StepLog) -> None:
        """Kept, and written with the others every SEND_EVERY steps and at close."""
        self.pending.append(s)
        if len(self.pending) >= SEND_EVERY:
            self._send()

    def _send(self) -> None:
        """The pending steps as columns, one call an entity (docs/decisions.md, "Processes and files")."""
        steps, self.pending = self.pending, []
        if not steps:
            return
        rr, rec = self.rr, self.rec
        names = list(dict.fromkeys(name for s in steps for name in s.estimates))
        for i, name in enumerate(["truth", *names]):
            have = [s for s in steps if name == "truth" or name in s.estimates]
            entity = "world/truth" if name == "truth" else f"world/estimate/{_entity(name)}"
            poses = np.stack([s.truth if name == "truth" else s.estimates[name] for s in have])
            here = poses[:, :3, 3].astype(np.float32)
            before = np.vstack([self.last.get(entity, here[0])[None], here[:-1]])
            self.last[entity] = here[-1]
            colour = PATH_COLOURS[i % len(PATH_COLOURS)]
            strips = rr.LineStrips3D.columns(
                strips=list(np.stack([before, here], axis=1)), colors=[colour] * len(have), radii=[0.04] * len(have)
            )
            rec.send_columns(entity, indexes=self._times(have), columns=strips)
            if name != "truth":
                error = np.linalg.norm(poses[:, :3, 3] - np.stack([s.truth[:3, 3] for s in have]), axis=1)
                rec.send_columns(f"error/{_entity(name)}", self._times(have), rr.Scalars.columns(scalars=error))
        scanned = [s for s in steps if s.scan is not None and s.T_w_s is not None]
        if scanned:
            world = [self._shown(s) for s in scanned]
            colours = [UNJUDGED if s.mask is None else FLAGGED if np.any(s.mask) else FREE for s in scanned]
            points = rr.Points3D.columns(positions=np.concatenate(world)).partition([len(w) for w in world])
            looks = rr.Points3D.columns(colors=colours, radii=[0.03] * len(scanned))
            rec.send_columns("world/scan", self._times(scanned), [*points, *looks])
        flagged = [s for s in steps if s.probabilities is not None and s.mask is not None]
        if flagged:
            probabilities = np.array([np.asarray(s.probabilities, float) for s in flagged])
            masks = np.array([np.asarray(s.mask, float) for s in flagged])
            for a, axis in enumerate(AXES):
                for what, values in (("probability", probabilities), ("flagged", masks)):
                    column = rr.Scalars.columns(scalars=values[:, a])
                    rec.send_columns(f"flags/{axis}/{what}", self._times(flagged), column)

    def _times(self, steps: list[StepLog]) -> list:
        return [
            self.rr.TimeColumn("step", sequence=[s.step for s in steps]),
            self.rr.TimeColumn("sim_time", duration=[s.seconds for s in steps]),
        ]

    def _shown(self, s: StepLog) -> np.ndarray:
        """The step's scan, a random subset of its points, in the world frame."""
        assert s.scan is not None and s.T_w_s is not None
        points = random_subset(np.asarray(s.scan)[:, :3], MAX_SCAN_POINTS, self.rng)
        return (points @ s.T_w_s[:3, :3].T + s.T_w_s[:3, 3]).astype(np.float32)

    def close(self) -> Path:
        self._send()
        self.rec.flush()
        self.rec.disconnect()
        return self.path


def _entity(name: str) -> str:
    """A row's name as one entity path part ('eigen:30' -> 'eigen_30', 'odometry only' -> 'odometry_only')."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def _log_flags(rec: Any, rr: Any, prefix: str, probabilities: np.ndarray, mask: np.ndarray) -> None:
    """Each axis's score and flag at the recording's time, under prefix/<axis>/probability|flagged."""
    for axis, p, flagged in zip(AXES, probabilities, mask):
        rec.log(f"{prefix}/{axis}/probability", rr.Scalars(float(p)))
        rec.log(f"{prefix}/{axis}/flagged", rr.Scalars(float(flagged)))


def _blueprint(rr: Any, rows: list[str]) -> Any:
    """The default layout: the 3-D view (paths kept from the start, the scan of the moment) beside the
    flags over time above each row's error."""
    import rerun.blueprint as rrb

    whole_drive = rrb.VisibleTimeRanges(
        [
            rrb.VisibleTimeRange(
                timeline, start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.cursor_relative()
            )
            for timeline in ("step", "sim_time")
        ]
    )
    paths = ["world/truth", *(f"world/estimate/{_entity(r)}" for r in rows)]
    world = rrb.Spatial3DView(
        origin="world",
        name="drive",
        overrides={path: [whole_drive] for path in paths},
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            world,
            rrb.Vertical(
                rrb.TimeSeriesView(origin="flags", name="flags (probability, flagged)"),
                rrb.TimeSeriesView(origin="error", name="error against the truth (m)"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def log_judged(path: str | Path, judgements: list) -> Path:
    """Judged scans (experiments.judge.Judgement, with the points they keep to be `shown`) as one
    recording: each scan its own entity scans/<name>, in its level frame, coloured by its flags (any
    detector's), and each detector's scores under flags/<detector>/<axis>, on the time line `scan`."""
    rr = _rerun()
    rec = rr.RecordingStream("l3e", recording_id="judged")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    rec.save(str(path))
    seen: set[str] = set()
    for k, judged in enumerate(judgements):
        rec.set_time("scan", sequence=k)
        entity = _entity(Path(judged.path).name)
        entity = entity if entity not in seen else f"{entity}_{k}"  # the same file twice: two entities
        seen.add(entity)
        known = {name: p for name, p in judged.predictions.items() if p.known}
        flagged = any(np.any(p.mask) for p in known.values())
        if judged.shown is not None:
            colour = FLAGGED if flagged else FREE if known else UNJUDGED
            rec.log(f"scans/{entity}", rr.Points3D(judged.shown, colors=[colour], radii=0.03))
        for detector, p in known.items():
            _log_flags(rec, rr, f"flags/{_entity(detector)}", p.probabilities, p.mask)
    rec.flush()
    rec.disconnect()
    return Path(path)


def log_drive(path: str | Path, mesh: trimesh.Trimesh, drive: Any, results: list, dt: float) -> Path:
    """A recorded drive (a DriveRecord: truth, scans, the sensor's mount) and its fused rows (each with
    its trajectory, masks and probabilities) as a recording; the scan of each step is placed by, and
    coloured with the flags of, the first row that has a detector (else the first row: the legs).
    Returns the file."""
    shown = next((r for r in results if not r.name.startswith("odometry")), results[0])
    log = DriveLog(path, f"{drive.scene}-seed-{drive.seed}", [r.name for r in results], drive.seed)
    log.scene(mesh)
    for k, truth in enumerate(drive.ground_truth):
        judged = 0 < k <= len(shown.masks)
        log.step(
            StepLog(
                k,
                k * dt,
                truth,
                {r.name: r.trajectory[k] for r in results if k < len(r.trajectory)},
                drive.scans[k] if k < len(drive.scans) else None,
                shown.trajectory[k] @ drive.T_b_s if k < len(shown.trajectory) else None,
                np.asarray(shown.probabilities[k - 1]) if judged else None,
                np.asarray(shown.masks[k - 1]) if judged else None,
            )
        )
    return log.close()
