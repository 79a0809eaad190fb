"""Scan files in a sensor's frame, read as (N, 3) points: numpy, KITTI .bin, PLY, PCD and text."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

FORMATS = {
    ".npy": "numpy (N, >=3)",
    ".npz": "numpy archive ('points' or its only array)",
    ".bin": "KITTI float32 x y z intensity",
    ".ply": "PLY",
    ".pcd": "PCD (ascii or binary)",
    ".xyz": "text x y z ...",
    ".txt": "text x y z ...",
    ".csv": "comma-separated x,y,z,...",
}


class ScanFileError(ValueError):
    """A scan file that cannot be read as points."""


def _read_pcd(path: Path) -> np.ndarray:
    """PCD's header names the fields; x, y, z are read from ascii or binary data. Hand-written:
    the libraries that read PCD (open3d, pypcd) are large or unmaintained."""
    raw = path.read_bytes()
    header: dict[str, list[str]] = {}
    offset = 0
    while "DATA" not in header:
        end = raw.find(b"\n", offset)
        if end < 0:
            raise ScanFileError(f"{path}: the PCD header has no DATA line")
        words = raw[offset:end].decode("ascii", "replace").split()
        offset = end + 1
        if words and not words[0].startswith("#"):
            header[words[0].upper()] = words[1:]
    fields = header.get("FIELDS", [])
    if not {"x", "y", "z"} <= set(fields):
        raise ScanFileError(f"{path}: the PCD has fields {fields}, not x, y and z")
    sizes = [int(s) for s in header.get("SIZE", [])]
    types, counts = header.get("TYPE", []), [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
    n = (
        int(header["POINTS"][0])
        if "POINTS" in header
        else int(header.get("WIDTH", ["0"])[0]) * int(header.get("HEIGHT", ["1"])[0])
    )
    kind = header["DATA"][0].lower()
    if kind == "ascii":
        table = np.loadtxt(raw[offset:].decode("ascii").splitlines(), ndmin=2)
        if len(table) != n:  # a file cut short, or rows added: either way not the cloud the header describes
            raise ScanFileError(
                f"{path}: the PCD header says {n} points and the file holds {len(table)} rows; "
                "the file is cut short or damaged"
            )
        columns = np.cumsum([0] + counts)
        return np.stack([table[:, columns[fields.index(a)]] for a in "xyz"], axis=1)
    if kind != "binary":
        raise ScanFileError(f"{path}: PCD data '{kind}' is not read; save it as ascii or binary")
    codes = {
        ("F", 4): "<f4",
        ("F", 8): "<f8",
        ("I", 1): "<i1",
        ("I", 2): "<i2",
        ("I", 4): "<i4",
        ("I", 8): "<i8",
        ("U", 1): "<u1",
        ("U", 2): "<u2",
        ("U", 4): "<u4",
        ("U", 8): "<u8",
    }
    try:
        dtype = np.dtype([(f, codes[t, s], (c,)) for f, t, s, c in zip(fields, types, sizes, counts)])
    except KeyError as exc:
        raise ScanFileError(f"{path}: PCD field type {exc} is not read") from exc
    if len(raw) - offset < n * dtype.itemsize:
        raise ScanFileError(f"{path}: the PCD is cut short ({len(raw) - offset} bytes of data for {n} points)")
    data = np.frombuffer(raw, dtype=dtype, count=n, offset=offset)
    return np.stack([data[a][:, 0] for a in "xyz"], axis=1)


def _check_ply_header(path: Path) -> None:
    """ScanFileError where the file does not open with a PLY header that declares its vertices (a
    header is text up to `end_header`; trimesh's own errors on a broken one name no cause)."""
    with open(path, "rb") as f:
        head = f.read(65536)
    lines = head.split(b"end_header")[0].splitlines() if b"end_header" in head else []
    if (
        not lines
        or lines[0].strip() != b"ply"
        or not any(line.split()[:2] == [b"element", b"vertex"] for line in lines)
    ):
        raise ScanFileError(
            f"{path}: not a PLY point cloud: its header must open with 'ply', declare 'element vertex N' "
            "and close with 'end_header'"
        )


TRIPLES_FIX = "if it holds x y z float32 triples, save them as .npy (numpy.save) and give that"


def _read_kitti_bin(path: Path) -> np.ndarray:
    """KITTI's x y z intensity float32 quadruples. x y z triples whose length happens to divide by 16
    read as quadruples too, their coordinates then taken for intensities: a fourth float that is
    negative on more than 1% of the points is no intensity, and the file is refused."""
    size = path.stat().st_size
    if size % 16:  # np.fromfile would drop a cut-off tail silently
        raise ScanFileError(
            f"{path}: {size} bytes, not whole x y z intensity float32 quadruples (KITTI .bin: 16 bytes a "
            f"point); {TRIPLES_FIX}"
        )
    points = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    negative = float(np.mean(points[:, 3] < 0)) if len(points) else 0.0
    if negative > 0.01:
        raise ScanFileError(
            f"{path}: the fourth float of {negative:.0%} of the points is negative, so it is no KITTI intensity "
            f"and the file is not x y z intensity quadruples; {TRIPLES_FIX}"
        )
    return points


def read_scan(path: str | Path) -> np.ndarray:
    """(N, 3) float64 points of a scan file, as written (NaN kept: `judge_scans` drops them)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ScanFileError(
            f"{path}: unknown scan format '{suffix}'; read: " + ", ".join(f"{k} ({v})" for k, v in FORMATS.items())
        )
    if not path.is_file():
        raise ScanFileError(f"{path}: no such file")
    try:
        if suffix == ".npy":
            points = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as archive:
                names = list(archive.keys())
                if "points" not in names and len(names) != 1:
                    raise ScanFileError(f"{path}: holds {names}; name the points array 'points'")
                points = archive["points" if "points" in names else names[0]]
        elif suffix == ".bin":
            points = _read_kitti_bin(path)
        elif suffix == ".ply":
            import trimesh

            _check_ply_header(path)
            points = np.asarray(trimesh.load(path, process=False).vertices)
        elif suffix == ".pcd":
            points = _read_pcd(path)
        else:
            with warnings.catch_warnings():  # an empty file is no points, judged "unknown" as any too-small scan
                warnings.simplefilter("ignore", UserWarning)
                points = np.loadtxt(path, delimiter="," if suffix == ".csv" else None, ndmin=2)
    except ScanFileError:
        raise
    except Exception as exc:  # noqa: BLE001 - whatever the reader raises, name the file and the problem
        raise ScanFileError(f"{path}: cannot be read as {FORMATS[suffix]}: {exc}") from exc
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ScanFileError(f"{path}: points of shape {points.shape}, not (N, 3) or more columns")
    if points.shape[0] in (3, 4) and points.shape[1] > points.shape[0]:  # x, y, z (, intensity) as rows
        raise ScanFileError(
            f"{path}: points of shape {points.shape}: a scan is (N, 3) or (N, 4), one point a row; "
            f"this looks like its transpose (save points.T)"
        )
    return points[:, :3].astype(np.float64)
