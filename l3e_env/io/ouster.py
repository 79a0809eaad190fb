"""Ouster captures, `.osf` and `.pcap`, read scan by scan through `ouster-sdk` with the capture's
own metadata (a `.pcap` carries none: its metadata JSON lies beside it or is given). An optional
dependency installed on its own, without its pins: `pip install --no-deps ouster-sdk==1.0.1` (it
needs only numpy and rosbags, in l3e[bag]; every release pins rosbags and click to versions older
than this project's). The SDK's clouds (XYZLut) are in its sensor frame; the scans come out in the
lidar frame, the frame the beams are in, turned by the metadata's lidar_to_sensor_transform."""

from __future__ import annotations

import atexit
import json
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterable, Iterator
from itertools import chain
from pathlib import Path
from typing import NamedTuple

import numpy as np

from l3e_env.io.recorded import RecordedScan, RecordingError
from l3e_env.sim.patterns import BeamPattern, PatternError, ouster_pattern

CAPTURES = (".osf", ".pcap")
INSTALL = "pip install --no-deps ouster-sdk==1.0.1 (beside l3e[bag])"
TURNED = "read in the SDK's sensor frame, turned into the lidar frame by the capture's metadata"


class CaptureError(RecordingError):
    """An Ouster capture that cannot be read as scans; the message says why."""


def is_capture(path: str | Path) -> bool:
    return Path(path).suffix.lower() in CAPTURES


# the SDK logs a chunk it cannot decode at its warning level too ("Invalid chunk at file offset 0"): a
# warning naming one of these is damage, the others (out-of-order legacy data, sensors taken as
# synchronised) are not
DAMAGE_WORDS = ("invalid", "crc", "corrupt", "fail", "error", "truncat", "bad ", "cannot", "unable")


class _SdkLog:
    """The SDK reports a chunk it cannot decode only in its log, and reads on: the log goes to a
    file of this process, read after each scan, so that a damaged scan is named, not judged."""

    def __init__(self, core) -> None:
        folder = tempfile.mkdtemp(prefix="l3e-ouster-")
        atexit.register(shutil.rmtree, folder, True)
        self.path = Path(folder) / "sdk.log"
        core.init_logger("warning", str(self.path))
        self.read = 0
        self.warned: list[str] = []
        self.errors: list[str] = []

    def _read(self) -> None:
        """What the SDK logged since the last read, sorted into errors and warnings."""
        if not self.path.exists():
            return
        with self.path.open("rb") as log:
            log.seek(self.read)
            text = log.read()
        self.read += len(text)
        for line in text.decode("utf-8", "replace").splitlines():
            message = line.rsplit("] ", 1)[-1].strip()
            if not message:
                continue
            level = line.rsplit("] ", 1)[0].rsplit("[", 1)[-1].lower() if "] " in line else "error"
            benign = level in ("warning", "warn", "info", "debug", "trace") and not any(
                word in message.lower() for word in DAMAGE_WORDS
            )
            (self.warned if benign else self.errors).append(message)

    def news(self) -> list[str]:
        """The errors the SDK logged since the last call, each once, without their time and level; its
        warnings (an out-of-order legacy file, sensors taken as synchronised) wait in `warnings_said`:
        a warning is no damage, the SDK decodes the scans it warns of."""
        self._read()
        said, self.errors = list(dict.fromkeys(self.errors)), []
        return said

    def warnings_said(self) -> list[str]:
        """The warnings logged since the last call, each once."""
        self._read()
        said, self.warned = list(dict.fromkeys(self.warned)), []
        return said


_LOG: _SdkLog | None = None


def _sdk():
    global _LOG
    try:
        import ouster.sdk as sdk
        from ouster.sdk import core
    except ImportError as exc:
        raise CaptureError(f"reading Ouster captures needs ouster-sdk: {INSTALL}") from exc
    if _LOG is None:
        _LOG = _SdkLog(core)
    return sdk, core, _LOG


def _not_a_number(word: str) -> float:
    raise ValueError(f"{word} is no number a sensor writes")


def _check_metadata(path: Path, metadata: str | Path | None) -> None:
    """CaptureError naming a .pcap's metadata file (the one given, else those the SDK would take beside
    it) where it is not a JSON object describing a sensor's beams (fields that disagree or lie outside
    the sensor's physics named), checked before the SDK sizes its buffers from it: the SDK's own
    message names neither the file nor the fix, and a column count of 1e12 exhausts memory there."""
    candidates = [Path(metadata)] if metadata else sorted(path.parent.glob(f"{path.stem}*.json"))
    for meta in candidates:
        try:
            found = json.loads(meta.read_text(), parse_constant=_not_a_number)
        except RecursionError as exc:
            raise CaptureError(
                f"{meta}: the metadata of {path.name} is nested too deep to be a sensor's metadata"
            ) from exc
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise CaptureError(
                f"{meta}: the metadata of {path.name} is not readable JSON ({exc}); give the sensor's metadata "
                "as the Ouster SDK writes it"
            ) from exc
        if not isinstance(found, dict):
            raise CaptureError(f"{meta}: the metadata of {path.name} is not a JSON object")
        try:
            ouster_pattern(meta.name, found)
        except (PatternError, RecursionError) as exc:
            raise CaptureError(f"{meta}: the metadata of {path.name} does not describe a sensor: {exc}") from exc


def read_capture(
    path: str | Path,
    metadata: str | Path | None = None,
    every: int = 1,
    start: float | None = None,
    end: float | None = None,
    sensor_index: int | None = None,
    one_sensor: bool = False,
) -> Iterator[RecordedScan]:
    """The scans of an Ouster capture, every `every`-th of each sensor, between `start` and `end`
    seconds after its first scan, as (N, 3) points in the lidar frame with their beams (`rings`) and
    their sensor's pattern from the metadata (an .osf's own; a .pcap's `metadata` JSON, else the one
    beside it). An .osf may hold several sensors: each scan comes with its own sensor's pattern and
    `sensor <i>` in its name, or only sensor `sensor_index`'s scans; `one_sensor` refuses a capture of
    several without an index (what reads one sensor's beams). A capture that cannot be opened, or
    holds no scan, raises CaptureError here; a scan the SDK could not decode gives a RecordedScan with
    its `error`, and the next one is read."""
    if every < 1:
        raise CaptureError(f"every must be at least 1, got {every}")
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: no such capture")
    if path.stat().st_size == 0:
        raise CaptureError(f"{path}: the file is empty; give an Ouster .osf or .pcap that holds scans")
    sdk, core, log = _sdk()
    log.news()
    log.warnings_said()
    source = _open(sdk, path, metadata)
    infos = list(source.sensor_info)
    chosen = _chosen_sensors(path, infos, sensor_index, one_sensor)
    sensors = {i: _sensor(path, infos, i, core) for i in chosen}
    frames = ((i, found[i]) for found in source for i in chosen if i < len(found) and found[i] is not None)
    first = next(frames, None)
    if first is None:
        said = log.news()
        why = (
            f"the SDK: {'; '.join(said)}; the file is damaged"
            if said
            else f"its {path.stat().st_size} bytes hold no whole revolution for this metadata: the file is cut "
            "short, or the metadata is another sensor's"
            if path.suffix.lower() == ".pcap"
            else "the capture is empty"
        )
        raise CaptureError(f"{path}: holds no scan ({why})")
    return _scans(chain([first], frames), path, sensors, len(infos) > 1, core, log, (every, start, end))


def _open(sdk, path: Path, metadata: str | Path | None):
    """The SDK's source of the capture, or CaptureError naming the problem and its fix."""
    if path.suffix.lower() == ".pcap":
        _check_metadata(path, metadata)
    try:
        # an .osf carries its metadata; a .pcap's is the one given, else the SDK's find beside it
        given = {"meta": [str(metadata)]} if metadata and path.suffix.lower() == ".pcap" else {}
        return sdk.open_source(str(path), **given)
    except Exception as exc:  # noqa: BLE001 - the SDK raises several kinds; name the file and the problem
        detail = str(exc).rpartition("more details:")[2].strip() or str(exc)
        hint = (
            f"; put its metadata JSON beside it as {path.stem}.json (the SDK looks for {path.stem}*.json "
            "there), or give it to l3e judge with --sensor"
            if "metadata" in detail.lower()
            else ""
        )
        raise CaptureError(f"{path}: cannot be read as an Ouster capture: {detail}{hint}") from exc


def _chosen_sensors(path: Path, infos: list, index: int | None, one: bool) -> list[int]:
    """The indices of the sensors whose scans are read, or CaptureError naming the choice to make."""
    if not infos:
        raise CaptureError(f"{path}: holds no sensor's metadata (cut short, or not an Ouster capture)")
    products = ", ".join(f"{i}: {getattr(info, 'prod_line', '') or 'a sensor'}" for i, info in enumerate(infos))
    if index is not None:
        if not 0 <= index < len(infos):
            raise CaptureError(
                f"{path}: holds {len(infos)} sensor(s) ({products}); --sensor-index {index} is none of them"
            )
        return [index]
    if one and len(infos) > 1:
        raise CaptureError(
            f"{path}: holds the scans of {len(infos)} sensors ({products}); pick one with --sensor-index"
        )
    return list(range(len(infos)))


class _Sensor(NamedTuple):
    pattern: BeamPattern
    lut: Callable[[np.ndarray], np.ndarray]  # the SDK's XYZLut


def _sensor(path: Path, infos: list, i: int, core) -> _Sensor:
    """Sensor i's pattern (named after the capture, and the sensor where it holds several) and lookup."""
    name = path.stem if len(infos) == 1 else f"{path.stem}-sensor{i}"
    try:
        pattern = ouster_pattern(name, json.loads(infos[i].to_json_string()))
    except (PatternError, KeyError, TypeError, ValueError) as exc:
        raise CaptureError(f"{path}: the metadata of sensor {i} does not describe its beams: {exc}") from exc
    return _Sensor(pattern, core.XYZLut(infos[i]))


def _scans(
    frames: Iterator,
    path: Path,
    sensors: dict[int, _Sensor],
    several: bool,
    core,
    log: _SdkLog,
    window: tuple[int, float | None, float | None],
) -> Iterator[RecordedScan]:
    """Each (sensor index, frame) as a RecordedScan: every `every`-th scan of each sensor, between
    `start` and `end` seconds after the first scan of any."""
    every, start, end = window
    began, counts = None, dict.fromkeys(sensors, 0)
    warned: set[str] = set()
    for i, scan in frames:
        said = log.news()  # the SDK decodes a scan while it is read: what it logged belongs to this one
        for warning in set(log.warnings_said()) - warned:  # once per file, beside its scans: no damage
            warned.add(warning)
            warnings.warn(f"{path.name}: the Ouster SDK warns: {warning}", stacklevel=2)
        k = counts[i]
        counts[i] += 1
        stamps = np.asarray(scan.timestamp)
        stamp = float(stamps[stamps > 0][0]) * 1e-9 if (stamps > 0).any() else None
        began = began if began is not None or stamp is None else stamp
        after = None if stamp is None or began is None else stamp - began
        if k % every or (start is not None and after is not None and after < start):
            continue
        if end is not None and after is not None and after > end:
            if not several:
                break
            continue
        name = f"{path.name} {'sensor ' + str(i) + ' ' if several else ''}#{k}"
        valid = int((np.asarray(scan.status) & 1).sum())  # columns the sensor sent
        if valid < scan.w:
            name += f" (a part revolution: {valid} of {scan.w} columns)"
        pattern = sensors[i].pattern
        if said:
            yield RecordedScan(
                name,
                stamp,
                None,
                f"{name}: the SDK could not decode it ({'; '.join(said)}); the capture is damaged",
                pattern=pattern,
            )
            continue
        ranges = scan.field(core.ChanField.RANGE)
        kept = ranges > 0  # no return: the SDK puts it at the beam's origin, not at the lidar's
        points = pattern.from_sensor_frame(sensors[i].lut(ranges)[kept].astype(np.float64))
        rings = np.nonzero(kept)[0].astype(np.int64)
        yield RecordedScan(
            name, stamp, points, rings=rings, pattern=pattern, frame=TURNED if pattern.lidar_to_sensor else None
        )


def expand_captures(sources: Iterable, metadata: str | Path | None = None, sensor_index: int | None = None) -> Iterator:
    """The sources with each Ouster capture among them replaced by its scans (of every sensor, or of
    `sensor_index`'s; one that cannot be read by a RecordedScan naming why), the others as they are."""
    for source in sources:
        if isinstance(source, (str, Path)) and is_capture(source):
            try:
                yield from read_capture(source, metadata, sensor_index=sensor_index)
            except CaptureError as exc:
                yield RecordedScan(str(source), None, None, str(exc))
        else:
            yield source
