"""The classifier beside the registration: a learned detector in a process of its own, judging a scan
while this process registers it and prepares it as the next ICP target.

A step of the pipeline is mostly two pieces of work on the same scan that do not depend on each
other: the classifier (torch, one thread) and the scan's ICP target (small_gicp's normals and k-d
tree). small_gicp holds Python's lock while it works, so a thread cannot run them side by side;
a process can, on a machine with a core to spare (`FusionSettings.detector_process`). The scan
crosses a pipe (about 0.3 MB for a VLP-16 revolution); the answers are the same as the detector's
in this process, to the bit. A process that dies answers UNKNOWN, counted as a detector error.
"""

from __future__ import annotations

import contextlib
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from l3e_env.config import LidarConfig
from l3e_env.config.detector_spec import parse_detector
from l3e_env.core.workers import die_with_parent, process_context

from .detectors import UNKNOWN, Prediction, make_detector, safe_predict

PROCESS_DETECTORS = ("learned",)  # kinds that judge the scan alone (no registration, no scene)


def runs_in_a_process(spec: str) -> bool:
    """Whether a detector of `spec` can judge in a process of its own: it reads the scan alone."""
    return parse_detector(spec).kind in PROCESS_DETECTORS


def _serve(conn: Connection, spec: str, sensor: LidarConfig, seed: int) -> None:
    die_with_parent()
    try:
        detector = make_detector(spec, seed=seed, sensor=sensor)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", detector.name))
    while (job := conn.recv()) is not None:
        points, T_w_s = job
        prediction, failed = safe_predict(detector, points, None, T_w_s)
        conn.send((prediction.probabilities, prediction.mask, prediction.known, failed))


class DetectorProcess:
    """`submit(points, T_w_s)` then `result()` -> (Prediction, failed), as `safe_predict` answers."""

    def __init__(self, spec: str, sensor: LidarConfig, seed: int = 0):
        if not runs_in_a_process(spec):
            raise ValueError(
                f"detector '{spec}' needs the registration or the scene; only {PROCESS_DETECTORS} "
                "judge in a process of their own"
            )
        context = process_context([__name__])
        self._conn, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, spec, sensor, seed), daemon=True)
        self._process.start()
        child.close()
        try:
            kind, said = self._conn.recv()
        except EOFError:
            self.close()
            raise RuntimeError(
                "the detector process ended before it began: a script that makes environments with "
                'detector_process must run its top level under `if __name__ == "__main__":` (the '
                "process imports the script again)"
            ) from None
        if kind == "error":
            self.close()
            raise ValueError(f"the detector process could not make '{spec}': {said}")
        self.name = said
        self._waiting = False

    def submit(self, points: np.ndarray, T_w_s: np.ndarray | None) -> None:
        if self._waiting:
            raise RuntimeError("a scan is still being judged: call result() before the next submit()")
        try:
            self._conn.send((np.ascontiguousarray(points, dtype=np.float32), T_w_s))
            self._waiting = True
        except (OSError, ValueError):  # the process is gone: result() answers UNKNOWN
            self._waiting = False

    def result(self) -> tuple[Prediction, bool]:
        if not self._waiting:
            return UNKNOWN, True
        self._waiting = False
        try:
            probabilities, mask, known, failed = self._conn.recv()
        except (EOFError, OSError):
            return UNKNOWN, True
        return Prediction(probabilities, mask, known), failed

    def close(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self._conn.send(None)
        self._process.join(timeout=5)
        if self._process.is_alive():
            self._process.terminate()
        self._conn.close()

    def __del__(self) -> None:  # an environment dropped without close() leaves no process behind
        process: Any = getattr(self, "_process", None)
        if process is not None and process.is_alive():
            process.terminate()
