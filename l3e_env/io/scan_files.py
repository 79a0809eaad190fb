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


def _pcd_header(path: Path, raw: bytes) -> tuple[dict[str, list[str]], int]:
    """A PCD's header lines by their keyword, and where its data begins."""
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
    return header, offset


def _pcd_count(path: Path, header: dict[str, list[str]]) -> int:
    """The points a PCD header declares: POINTS, which WIDTH x HEIGHT must agree with."""
    n = _pcd_numbers(path, header, "POINTS", 1, None)[0] if "POINTS" in header else None
    shape = [_pcd_numbers(path, header, key, 1, None)[0] for key in ("WIDTH", "HEIGHT") if key in header]
    if n is None and len(shape) < 2:
        raise ScanFileError(
            f"{path}: the PCD header has no POINTS (nor WIDTH and HEIGHT): it does not say how many points it holds"
        )
    n = shape[0] * shape[1] if n is None else n
    if len(shape) == 2 and shape[0] * shape[1] != n:
        raise ScanFileError(
            f"{path}: the PCD header's WIDTH x HEIGHT ({shape[0]} x {shape[1]}) disagrees with its POINTS {n}"
        )
    return n


def _read_pcd(path: Path) -> np.ndarray:
    """PCD's header names the fields; x, y, z are read from ascii or binary data, where the header
    agrees with the data. Hand-written: the libraries that read PCD (open3d, pypcd) are large or
    unmaintained."""
    raw = path.read_bytes()
    header, offset = _pcd_header(path, raw)
    fields = header.get("FIELDS", [])
    if not {"x", "y", "z"} <= set(fields):
        raise ScanFileError(f"{path}: the PCD has fields {fields}, not x, y and z")
    sizes = _pcd_numbers(path, header, "SIZE", len(fields), None)
    types = header.get("TYPE", [])
    if len(types) != len(fields):
        raise ScanFileError(f"{path}: the PCD header's TYPE names {len(types)} types for its {len(fields)} FIELDS")
    counts = _pcd_numbers(path, header, "COUNT", len(fields), 1)
    n = _pcd_count(path, header)
    kind = header["DATA"][0].lower()
    if kind == "ascii":
        if n == 0 and not raw[offset:].strip():  # an empty cloud, as a binary one of no points reads
            return np.zeros((0, 3))
        table = np.loadtxt(raw[offset:].decode("ascii").splitlines(), ndmin=2)
        if table.size and table.shape[1] != sum(counts):
            raise ScanFileError(
                f"{path}: the PCD header describes {sum(counts)} numbers a point and its rows hold {table.shape[1]}"
            )
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
    extra = len(raw) - offset - n * dtype.itemsize
    if extra < 0:
        raise ScanFileError(f"{path}: the PCD is cut short ({len(raw) - offset} bytes of data for {n} points)")
    if extra >= dtype.itemsize or raw[len(raw) - extra :].strip():  # a writer's closing newline is no point
        raise ScanFileError(
            f"{path}: the PCD header says {n} points and its data holds {(len(raw) - offset) / dtype.itemsize:.0f}: "
            "the header disagrees with the data; fix POINTS (and WIDTH, HEIGHT) or save the cloud again"
        )
    data = np.frombuffer(raw, dtype=dtype, count=n, offset=offset)
    return np.stack([data[a][:, 0] for a in "xyz"], axis=1)


def _pcd_numbers(path: Path, header: dict[str, list[str]], key: str, count: int, default: int | None) -> list[int]:
    """`count` whole numbers of a PCD header line (each at least 1, POINTS at least 0), or the default's,
    or ScanFileError naming the line."""
    words = header.get(key, [str(default)] * count if default is not None else [])
    least = 0 if key in ("POINTS", "WIDTH", "HEIGHT") else 1
    if len(words) != count or not all(w.isdigit() and int(w) >= least for w in words):
        raise ScanFileError(
            f"{path}: the PCD header's {key} is {' '.join(words) or 'missing'}; it must be {count} whole "
            f"number(s) of at least {least}"
        )
    return [int(w) for w in words]


PLY_SIZES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}  # fmt: skip
PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


def _check_ply_header(path: Path) -> None:
    """ScanFileError where the file does not open with a PLY header that declares its vertices, or
    where the header disagrees with the data after it (the rows of an ascii file, the bytes of a binary
    one): trimesh reads what the header says, and names no cause where the two disagree."""
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
    words = [line.decode("ascii", "replace").split() for line in lines]
    kind = next((w[1] for w in words if w[:1] == ["format"] and len(w) > 1), None)
    if kind not in PLY_FORMATS:
        raise ScanFileError(f"{path}: PLY format {kind!r} is not read; save it as one of {', '.join(PLY_FORMATS)}")
    _check_ply_properties(path, words)
    elements: list[list] = []  # [name, count, bytes a row or None where a row holds a list]
    for w in words:
        if w[:1] == ["element"]:
            if len(w) != 3 or not w[2].isdigit():
                raise ScanFileError(
                    f"{path}: the PLY header's '{' '.join(w)}' must name an element and a count of at least 0"
                )
            elements.append([w[1], int(w[2]), 0])
        elif w[:1] == ["property"] and elements and elements[-1][2] is not None:
            elements[-1][2] = (
                None if w[1:2] == ["list"] else elements[-1][2] + PLY_SIZES.get(w[1] if len(w) > 1 else "", 0)
            )
    data = path.stat().st_size - (head.index(b"end_header") + len(b"end_header"))
    if kind == "ascii":
        with open(path, "rb") as f:
            f.seek(head.index(b"end_header") + len(b"end_header"))
            rows = sum(1 for line in f if line.strip())
        if rows != sum(e[1] for e in elements):
            raise ScanFileError(
                f"{path}: the PLY header declares {' + '.join(f'{e[1]} {e[0]}' for e in elements)} rows and the file "
                f"holds {rows}: the header disagrees with the data"
            )
        return
    sized = [e for e in elements if e[2] is not None]
    needed = sum(e[1] * e[2] for e in sized) if len(sized) == len(elements) else None
    first = elements[0][1] * elements[0][2] if elements[0][2] is not None else 0
    if (needed is not None and not 0 <= data - needed <= 2) or data < first:  # after the header, a line end
        raise ScanFileError(
            f"{path}: the PLY header declares {' + '.join(f'{e[1]} {e[0]}' for e in elements)} and the file holds "
            f"{data} bytes of data: the header disagrees with the data"
        )


def _check_ply_properties(path: Path, words: list[list[str]]) -> None:
    """ScanFileError naming a property of a type PLY does not have, or vertices without x, y and z."""
    vertex: list[str] = []  # the vertex element's property names
    in_vertex = False
    for w in words:
        if w[:1] == ["element"]:
            in_vertex = w[1:2] == ["vertex"]
        elif w[:1] == ["property"]:
            types = w[2:4] if w[1:2] == ["list"] else w[1:2]
            unknown = [t for t in types if t not in PLY_SIZES]
            if unknown or len(w) < (5 if w[1:2] == ["list"] else 3):
                raise ScanFileError(
                    f"{path}: the PLY header's '{' '.join(w)}' is no property: PLY's types are "
                    f"{', '.join(sorted(PLY_SIZES))}"
                )
            if in_vertex:
                vertex.append(w[-1])
    if not {"x", "y", "z"} <= set(vertex):
        raise ScanFileError(f"{path}: the PLY's vertices have the properties {vertex}, not x, y and z")


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
            points = np.asarray(getattr(trimesh.load(path, process=False), "vertices", np.zeros((0, 3))))
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
    if points.dtype.names and {"x", "y", "z"} <= set(points.dtype.names):  # a structured cloud's fields
        points = np.stack([points[a].ravel() for a in "xyz"], axis=1)
    if points.dtype.kind not in "fiu":
        raise ScanFileError(
            f"{path}: holds {points.dtype} values, not real numbers (float or integer x y z; a structured "
            "array needs fields x, y and z)"
        )
    if points.ndim != 2 or points.shape[1] < 3:
        raise ScanFileError(f"{path}: points of shape {points.shape}, not (N, 3) or more columns")
    if points.shape[0] in (3, 4) and points.shape[1] > points.shape[0]:  # x, y, z (, intensity) as rows
        raise ScanFileError(
            f"{path}: points of shape {points.shape}: a scan is (N, 3) or (N, 4), one point a row; "
            f"this looks like its transpose (save points.T)"
        )
    return points[:, :3].astype(np.float64)
