"""A trial of bad inputs through the `l3e` command, as a new user would give them: damaged and
lying scan files, Ouster metadata outside a sensor's physics, option values of the wrong type or
beyond any practical run (from the command line, --set and --config), tampered datasets, broken
checkpoints and policy records. Each case runs `l3e` in this process and is sorted by how it ends:

- clear: refused with exit status 2 and a message that names the file, option or field given;
- unclear: refused, but the message names none of them;
- traceback: an exception escaped the command;
- silent: the command succeeded (status 0) on input it should refuse;
- ran on: accepted, and still working after a minute (a value that should have been refused);
- left behind: refused, but the folder the command was to write is there (a case that names one).

Run: python studies/bad_inputs.py [--out runs/bad-inputs] [--show unclear,traceback,silent]
Writes cases.jsonl (each case, its outcome and message) and prints the counts.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import signal
import struct
import tempfile
import traceback
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from l3e_env.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
OUSTER = ROOT / "tests" / "data" / "ouster"


@dataclass
class Case:
    kind: str
    name: str
    argv: list[str]
    names: list[str]  # what a clear message names (any of them)
    outcome: str = ""
    message: str = ""
    out: str = ""  # the folder the command writes, where it makes one: a refusal must leave none


class _TooLong(Exception):
    pass


def _alarm(signum, frame) -> None:
    raise _TooLong


def run_case(case: Case, limit: int = 60) -> Case:
    """The case run in this process, stopped after `limit` seconds (a value accepted that starts real work)."""
    out, err = io.StringIO(), io.StringIO()
    signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(limit)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            status = main(case.argv)
    except SystemExit as exc:
        status = exc.code if isinstance(exc.code, int) else 2
    except _TooLong:
        case.outcome, case.message = "ran on", f"accepted and still working after {limit} s"
        return case
    except Exception:  # noqa: BLE001 - what the trial counts
        case.outcome, case.message = "traceback", traceback.format_exc(limit=3)[-600:]
        return case
    finally:
        signal.alarm(0)
    said = (err.getvalue().strip().splitlines() or [""])[-1]
    case.message = said[:400]
    if status == 0:  # a scan no detector can judge is said so and judged unknown, by design
        case.outcome = "clear" if "cannot judge" in out.getvalue() else "silent"
    else:
        case.outcome = "clear" if any(n in err.getvalue() for n in case.names) else "unclear"
        if case.out and Path(case.out).exists():
            case.outcome, case.message = "left behind", f"{case.out} is left after: {case.message}"
    return case


def _pcd(points: np.ndarray, **header: str | None) -> bytes:
    lines = {"VERSION": "0.7", "FIELDS": "x y z", "SIZE": "4 4 4", "TYPE": "F F F", "COUNT": "1 1 1"}
    lines |= {"WIDTH": str(len(points)), "HEIGHT": "1", "POINTS": str(len(points))}
    lines.update(header)
    text = "".join(f"{k} {v}\n" for k, v in lines.items() if v is not None) + "DATA binary\n"
    return text.encode() + points.astype("<f4").tobytes()


def scan_files(tmp: Path) -> Iterator[Case]:
    """Damaged and lying scan files, judged by `l3e judge FILE --detector none`."""
    rng = np.random.default_rng(0)
    points = rng.normal(0, 5, (2000, 3)).astype(np.float32)
    files: dict[str, bytes | Callable[[Path], None]] = {
        "points_more.pcd": _pcd(points, POINTS="1000", WIDTH="1000"),
        "points_fewer_than_data.pcd": _pcd(points, POINTS="3000", WIDTH="3000"),
        "no_points.pcd": _pcd(points, POINTS=None, WIDTH=None),
        "points_negative.pcd": _pcd(points, POINTS="-5", WIDTH="-5"),
        "count_zero.pcd": _pcd(points, COUNT="0 1 1"),
        "no_size.pcd": _pcd(points, SIZE=None),
        "no_type.pcd": _pcd(points, TYPE=None),
        "type_unknown.pcd": _pcd(points, TYPE="Q F F"),
        "no_fields.pcd": _pcd(points, FIELDS="a b c"),
        "huge_points.pcd": _pcd(points, POINTS="1000000000000", WIDTH="1000000000000"),
        "width_height.pcd": _pcd(points, WIDTH="7"),
        "no_data.pcd": b"FIELDS x y z\nSIZE 4 4 4\n",
        "empty.pcd": b"",
        "garbage.pcd": bytes(range(256)) * 10,
        "middle_endian.ply": b"ply\nformat binary_middle_endian 1.0\nelement vertex 3\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + b"\0" * 36,
        "vertex_more.ply": b"ply\nformat ascii 1.0\nelement vertex 100\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n" + b"1 2 3\n" * 10,
        "vertex_negative.ply": b"ply\nformat ascii 1.0\nelement vertex -5\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n" + b"1 2 3\n" * 10,
        "vertex_binary_short.ply": b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + b"\0" * 120,
        "no_header.ply": b"1 2 3\n4 5 6\n",
        "cut.bin": points.tobytes()[:-3],
        "triples.bin": np.c_[points, -np.ones(len(points), np.float32)].tobytes(),
        "text.bin": b"hello world, not floats at all" * 20,
        "letters.csv": b"a,b,c\nd,e,f\n",
        "two_columns.xyz": b"1 2\n3 4\n",
        "ragged.txt": b"1 2 3\n4 5\n6 7 8 9\n",
        "transposed.npy": lambda p: np.save(p, points.T),
        "bool.npy": lambda p: np.save(p, np.ones((100, 3), bool)),
        "complex.npy": lambda p: np.save(p, np.ones((100, 3), complex)),
        "datetime.npy": lambda p: np.save(p, np.zeros((100, 3), "datetime64[D]")),
        "object.npy": lambda p: np.save(p, np.array([[1, "a", None]] * 3, dtype=object), allow_pickle=True),
        "one_dim.npy": lambda p: np.save(p, np.ones(30)),
        "millimetres.npy": lambda p: np.save(p, points * 1e6),
        "nan.npy": lambda p: np.save(p, np.full((100, 3), np.nan)),
        "several.npz": lambda p: np.savez(p, a=points, b=points),
        "garbage.npz": bytes(range(256)) * 4,
        "unknown.las": b"LASF" + b"\0" * 100,
    }
    for name, content in files.items():
        path = tmp / name
        if callable(content):
            content(path)
        else:
            path.write_bytes(content)
        yield Case("scan file", name, ["judge", str(path), "--detector", "eigen:30"], [name])
    yield Case("scan file", "missing", ["judge", str(tmp / "nothere.pcd"), "--detector", "none"], ["nothere.pcd"])


def ouster_metadata(tmp: Path) -> Iterator[Case]:
    """A .pcap beside metadata JSON outside the sensor's physics."""
    pcap = OUSTER / "OS-1-128_v2.3.0_1024x10_lb_n3.pcap"
    good = json.loads((OUSTER / "OS-1-128_v2.3.0_1024x10_lb_n3_metadata.json").read_text())

    def changed(path: list[str], value) -> dict:
        meta = json.loads(json.dumps(good))

        def walk(tree):
            if isinstance(tree, dict):
                for key in list(tree):
                    if key == path[-1]:
                        tree[key] = value
                    else:
                        walk(tree[key])

        walk(meta)
        return meta

    variants = {
        "beam_1e30": changed(["beam_altitude_angles"], [1e30] * 128),
        "azimuths_12": changed(["beam_azimuth_angles"], [0.0] * 12),
        "transform_3": changed(["lidar_to_sensor_transform"], [1, 2, 3]),
        "mode_disagrees": changed(["lidar_mode"], "2048x10"),
        "columns_1e12": changed(["columns_per_frame"], 10**12),
        "pixels_64": changed(["pixels_per_column"], 64),
        "origin_1e9": changed(["lidar_origin_to_beam_origin_mm"], 1e9),
        "altitudes_text": changed(["beam_altitude_angles"], "many"),
    }
    for name, meta in variants.items():
        folder = tmp / f"ouster-{name}"
        folder.mkdir()
        shutil.copy(pcap, folder / "capture.pcap")
        (folder / "capture.json").write_text(json.dumps(meta))
        yield Case(
            "ouster metadata", name, ["judge", str(folder / "capture.pcap"), "--detector", "none"], ["capture.json"]
        )
    for name, text in {"nan": json.dumps(good).replace("36.18", "NaN"), "deep": "[" * 50000 + "]" * 50000}.items():
        folder = tmp / f"ouster-{name}"
        folder.mkdir()
        shutil.copy(pcap, folder / "capture.pcap")
        (folder / "capture.json").write_text(text)
        yield Case(
            "ouster metadata", name, ["judge", str(folder / "capture.pcap"), "--detector", "none"], ["capture.json"]
        )


BAD_VALUES = {
    "list": "[1, 2]",
    "map": "{a: 1}",
    "huge": "1e300",
    "negative": "-5",
    "nan": ".nan",
    "text": "lots",
    "bool": "true",
}
THRESHOLD_LISTS = ("taus", "kappas", "eigen")  # options that take a detector's thresholds, one or several
OPTION_COMMANDS = {  # a command line that would run, and its options to spoil
    ("ate", "--scene", "tunnel-0"): ["seeds", "seed", "workers", "max-steps", "scale", "keyframe-distance", "out"],
    ("judge", "x.npy"): ["workers", "every", "start", "end", "json", "sensor-index", "detector"],
    ("dataset", "generate", "--out", "OUT"): ["parents", "children", "workers", "seed", "preset"],
    ("train", "--dataset", "DATA", "--out", "OUT"): ["epochs", "lr", "threads", "samples-per-epoch", "config"],
    ("record", "--out", "OUT.bag"): ["imu-rate", "max-steps", "seed"],
    ("demo",): ["scale", "out"],
    ("policy", "map"): ["resolution", "workers", "out"],
    ("policy", "plan"): ["resolution", "lam", "workers"],
    ("policy", "evaluate"): ["episodes", "workers", "lam", "stop-radius", "resolution"],
    ("policy", "train", "--out", "OUT"): ["timesteps", "envs", "seed"],
    ("sweep", "--scene", "tunnel-0"): ["taus", "kappas", "detector-every", "keyframe-distance"],
    ("adapt", "--scans", "SCANS", "--out", "OUT"): [
        "every",
        "max-scans",
        "children",
        "epochs",
        "samples-per-epoch",
        "lr",
        "workers",
        "replay-share",
        "seed",
    ],
    ("evaluate", "--other", "DATA"): ["eigen", "scan-mc", "cascade", "workers", "draws"],
    ("fit-constraints", "--dataset", "DATA"): ["beta", "levels"],
}


def option_values(tmp: Path, data: Path) -> Iterator[Case]:
    """Every spoilt option value through --set, and a few through --config."""
    (tmp / "scans").mkdir(exist_ok=True)  # a place's scans for `l3e adapt`: a few random clouds
    for k in range(3):
        np.save(tmp / "scans" / f"scan-{k}.npy", np.random.default_rng(k).normal(size=(2000, 3)) * 5)
    for command, options in OPTION_COMMANDS.items():
        base = [str(tmp / "out") if a == "OUT" else str(tmp / "out.bag") if a == "OUT.bag" else a for a in command]
        base = [str(data) if a == "DATA" else str(tmp / "scans") if a == "SCANS" else a for a in base]
        for option in options:
            for kind, value in BAD_VALUES.items():
                if option in ("out", "json", "config") and kind not in ("list", "map", "bool"):
                    continue  # any text names a file or folder
                if option in THRESHOLD_LISTS and kind in ("list", "huge"):
                    continue  # several thresholds, and one that flags every axis, are values they take
                if kind in ("list", "map", "bool") or option in ("detector", "preset"):
                    argv = [*base, "--set", f"{option}={value}"]
                else:
                    argv = [*base, f"--{option}={value}"]
                yield Case("option", f"{' '.join(command[:2])} {option}={kind}", argv, [option])
    binary = tmp / "binary.yaml"
    binary.write_bytes(bytes(range(256)))
    tagged = tmp / "tagged.yaml"
    tagged.write_text('seeds: !!python/object/apply:os.system ["echo ran"]\n')
    listed = tmp / "listed.yaml"
    listed.write_text("[1, 2]\n")
    train_typed = tmp / "train.yaml"
    train_typed.write_text('batch_size: "8"\n')
    for path in (binary, tagged, listed):
        yield Case("option file", path.name, ["ate", "--config", str(path)], [path.name])
    argv = ["train", "--config", str(train_typed), "--dataset", str(tmp), "--out", str(tmp / "run")]
    yield Case("option file", "train batch_size text", argv, ["train.yaml"])


def datasets(tmp: Path, folder: Path) -> Iterator[Case]:
    """A dataset's manifest and arrays tampered, read by `l3e dataset stats`."""

    def manifest(change: Callable[[dict], None]) -> Callable[[Path], None]:
        def apply(d: Path) -> None:
            m = json.loads((d / "manifest.json").read_text())
            change(m)
            (d / "manifest.json").write_text(json.dumps(m))

        return apply

    def array(name: str, change: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], None]:
        return lambda d: np.save(d / f"{name}.npy", change(np.load(d / f"{name}.npy")))

    tamperings = {
        "format 99": manifest(lambda m: m.update(format_version=99)),
        "settings null": manifest(lambda m: m.update(settings=None)),
        "scenes numbers": manifest(lambda m: m.update(scenes=[5])),
        "count text": manifest(lambda m: m.update(count="four")),
        "labels 7": array("labels", lambda a: np.where(a == 1, 7, a).astype(np.uint8)),
        "labels nan": array("labels", lambda a: np.full(a.shape, np.nan)),
        "labels short": array("labels", lambda a: a[:-1]),
        "offsets scaled": array("offsets", lambda a: a * 2),
        "scene -1": array("scene", lambda a: np.full_like(a, -1)),
        "points 2 columns": array("points", lambda a: a[:, :2]),
        "manifest gone": lambda d: (d / "manifest.json").unlink(),
        "manifest binary": lambda d: (d / "manifest.json").write_bytes(bytes(range(256))),
    }
    for name, tamper in tamperings.items():
        copy = tmp / f"data-{name.replace(' ', '-')}"
        shutil.copytree(folder, copy)
        tamper(copy)
        yield Case("dataset", name, ["dataset", "stats", str(copy)], [copy.name])


def checkpoints_and_policies(tmp: Path) -> Iterator[Case]:
    """Bytes as a checkpoint; a policy record that lies."""
    for name, content in {
        "random.pt": bytes(range(256)) * 8,
        "empty.pt": b"",
        "zip.pt": b"PK\x03\x04" + b"\0" * 60,
    }.items():
        (tmp / name).write_bytes(content)
        yield Case("checkpoint", name, ["judge", "x.npy", "--detector", f"learned:{tmp / name}"], [name])
    np.save(tmp / "x.npy", np.random.default_rng(0).normal(0, 5, (3000, 3)))
    for name, meta in {"detector 5": {"detector": 5}, "detector bogus": {"detector": "bogus"}, "list": [1]}.items():
        folder = tmp / f"policy-{name.replace(' ', '-')}"
        folder.mkdir()
        (folder / "policy.json").write_text(json.dumps(meta))
        (folder / "policy.pt").write_bytes(struct.pack("<i", 0))
        argv = ["policy", "evaluate", "--policy", f"ppo:{folder}", "--episodes", "1", "--out", str(tmp / "eval")]
        yield Case("policy", name, argv, ["policy.json", "policy.pt", folder.name])


def _ply(properties: str, rows: str) -> bytes:
    head = f"ply\nformat ascii 1.0\nelement vertex {len(rows.splitlines())}\n{properties}end_header\n"
    return (head + rows).encode()


def third_pass(tmp: Path, data: Path) -> Iterator[Case]:
    """The inputs the third pass over rough edges named: lying headers and degenerate scans, a route far
    out, options given where they mean nothing, a manifest whose settings lie, and failed commands that
    must leave no folder."""
    rng = np.random.default_rng(1)
    rows = "".join(f"{x:.3f} {y:.3f} {z:.3f}\n" for x, y, z in rng.normal(0, 5, (200, 3)))
    files: dict[str, bytes | Callable[[Path], None]] = {
        "points_zero_ascii.pcd": b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\n"
        b"HEIGHT 1\nPOINTS 0\nDATA ascii\n",
        "property_quux.ply": _ply("property quux x\nproperty float y\nproperty float z\n", rows),
        "no_z.ply": _ply(
            "property float x\nproperty float y\n", "".join(" ".join(r.split()[:2]) + "\n" for r in rows.splitlines())
        ),
        "one_place.npy": lambda p: np.save(p, np.tile([[2.0, 1.0, 0.5]], (500, 1))),
        "one_line.npy": lambda p: np.save(p, np.linspace(-5, 5, 500)[:, None] * np.array([[1.0, 0.5, -0.2]])),
    }
    for name, content in files.items():
        path = tmp / name
        path.write_bytes(content) if isinstance(content, bytes) else content(path)
        yield Case("scan file", name, ["judge", str(path), "--detector", "eigen:30"], [name])
    yield Case("option", "sensor-index on a .npy", ["judge", "x.npy", "--sensor-index", "5"], ["sensor-index"])
    yield Case("option", "soft-labels -1", ["train", "--dataset", str(data), "--out", str(tmp / "soft"),
               "--soft-labels", "-1"], ["soft-labels"], out=str(tmp / "soft"))  # fmt: skip
    pcap = tmp / "cut.pcap"
    pcap.write_bytes((OUSTER / "OS-1-128_v2.3.0_1024x10_lb_n3.pcap").read_bytes()[:100])
    meta = OUSTER / "OS-1-128_v2.3.0_1024x10_lb_n3_metadata.json"
    yield Case("capture", "pcap cut to 100 bytes", ["judge", str(pcap), "--sensor", str(meta)], ["cut.pcap"])
    import trimesh

    trimesh.creation.box([10, 4, 0.2]).apply_translation([0, 0, -0.1]).export(tmp / "slab.obj")
    trimesh.creation.box([1.5, 1.5, 0.2]).apply_translation([0, 0, -0.1]).export(tmp / "tiny.obj")
    for name, mesh, route in (
        ("far", "slab.obj", "1e300 0 0\n-1e300 0 0\n"),
        ("no parent", "tiny.obj", "-0.5 0 0\n0.5 0 0\n"),
    ):
        (tmp / f"{name}.txt").write_text(route)
        argv = ["dataset", "generate", "--scenes", str(tmp / mesh), "--route", str(tmp / f"{name}.txt"),
                "--out", str(tmp / f"gen-{name}"), "--parents", "2", "--children", "5", "--quiet"]  # fmt: skip
        yield Case("mesh", f"route {name}", argv, [f"{name}.txt", mesh, "parent"], out=str(tmp / f"gen-{name}"))
    argv = ["policy", "plan", "--scene", "fork-0", "--goal", "1000", "1000", "--out", str(tmp / "plan")]
    yield Case("policy", "goal outside the grid", argv, ["goal"], out=str(tmp / "plan"))
    yield from _lying_manifests(tmp, data)


def _lying_manifests(tmp: Path, data: Path) -> Iterator[Case]:
    """A dataset whose manifest's settings lie, or whose points are NaN, given to `l3e evaluate --other`."""

    def settings(change: Callable[[dict], None]) -> Callable[[Path], None]:
        def apply(d: Path) -> None:
            m = json.loads((d / "manifest.json").read_text())
            change(m["settings"])
            (d / "manifest.json").write_text(json.dumps(m))

        return apply

    tamperings: dict[str, Callable[[Path], object]] = {
        "children float": settings(lambda s: s["labels"].update(children=4.5)),
        "parents text": settings(lambda s: s.update(parents_per_scene="two")),
        "scenes int": settings(lambda s: s.update(scenes=3)),
        "scenes text": settings(lambda s: s.update(scenes="tunnel-0")),
        "lidar unknown": settings(lambda s: s["lidar"].update(model="vlp99")),
        "manifest list": lambda d: (d / "manifest.json").write_text("[1, 2]"),
        "points nan": lambda d: np.save(d / "points.npy", np.full_like(np.load(d / "points.npy"), np.nan)),
    }
    for name, tamper in tamperings.items():
        copy = tmp / f"lying-{name.replace(' ', '-')}"
        shutil.copytree(data, copy)
        tamper(copy)
        argv = ["evaluate", "--other", str(copy), "--out", str(tmp / f"eval-{copy.name}")]
        yield Case("dataset", name, argv, [copy.name], out=str(tmp / f"eval-{copy.name}"))


def main_trial() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/bad-inputs")
    parser.add_argument("--show", default="unclear,traceback,silent,ran on")
    args = parser.parse_args()
    from l3e_env.data.generation import config_for, generate

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    out = out.resolve()
    with tempfile.TemporaryDirectory() as folder, contextlib.chdir(folder):  # what a case writes stays there
        tmp = Path(folder)
        tiny = tmp / "tiny"
        generate(tiny, config_for(None, scenes=["tunnel-0", "office-0"], parents_per_scene=2, shard_size=2,
                                  labels={"children": 8}), workers=1, progress=False)  # fmt: skip
        cases = [
            *scan_files(tmp),
            *ouster_metadata(tmp),
            *option_values(tmp, tiny),
            *datasets(tmp, tiny),
            *checkpoints_and_policies(tmp),
            *third_pass(tmp, tiny),
        ]
        done = [run_case(c) for c in cases]
    with (out / "cases.jsonl").open("w") as f:
        for c in done:
            f.write(json.dumps(asdict(c)) + "\n")
    counts: dict[str, int] = {}
    for c in done:
        counts[c.outcome] = counts.get(c.outcome, 0) + 1
    print(f"{len(done)} cases: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    for c in done:
        if c.outcome in args.show.split(","):
            print(f"- {c.outcome}: {c.kind} {c.name}: {' '.join(c.argv)[:120]}\n    {c.message[-300:]}")


if __name__ == "__main__":
    main_trial()
