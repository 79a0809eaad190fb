"""The GPU path against the CPU in one run: a checkpoint's probabilities on 100 scans, a short
training's loss curve, and the speed of both.

A GPU machine may have torch and no simulation (no Embree, no trimesh): `prepare` writes, on a machine
with the datasets, the scans and a small training set that `run` needs, into one folder to carry.

    python benchmarks/bench_device.py prepare --out device_check   # here: data/mine-test, data/l3e16
    python benchmarks/bench_device.py run --data device_check --out results   # there: cuda against cpu
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from l3e_env.data.dataset import ARRAYS, LabelDataset, label_statistics  # noqa: E402
from l3e_env.model.classifier import Classifier, ModelConfig  # noqa: E402
from l3e_env.model.training import TrainConfig, train  # noqa: E402

POINTS = 6000  # per carried scan: more than the 4000 the model reads, so that its sampling still draws


def _thin(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return points if len(points) <= POINTS else points[np.sort(rng.choice(len(points), POINTS, replace=False))]


def _subset(source: Path, rows: np.ndarray, out: Path, rng: np.random.Generator) -> None:
    """A dataset folder of `rows` of `source`, each scan thinned to POINTS."""
    data = LabelDataset(source)
    out.mkdir(parents=True, exist_ok=True)
    scans = [_thin(data.scan(int(i)), rng) for i in rows]
    arrays = {k: np.asarray(data.arrays[k])[rows] for k in ARRAYS if k not in ("points", "offsets")}
    arrays["points"] = np.concatenate(scans).astype(np.float32)
    arrays["offsets"] = np.concatenate([[0], np.cumsum([len(s) for s in scans])]).astype(np.int64)
    for name, array in arrays.items():
        np.save(out / f"{name}.npy", array)
    manifest = {**data.manifest, "count": len(rows), "statistics": label_statistics(arrays["labels"])}
    (out / "manifest.json").write_text(json.dumps(manifest))


def prepare(out: Path, scans_from: Path, train_from: Path) -> None:
    rng = np.random.default_rng(0)
    test = LabelDataset(scans_from)
    rows = np.linspace(0, len(test) - 1, 100).astype(int)
    scans = [_thin(test.scan(int(i)), rng) for i in rows]
    out.mkdir(parents=True, exist_ok=True)
    lengths = [len(s) for s in scans]
    np.savez(out / "scans.npz", points=np.concatenate(scans), lengths=lengths, poses=test.poses[rows])
    data = LabelDataset(train_from)
    names = data.manifest["scenes"]
    config = TrainConfig()
    train_rows = [i for i in range(len(data)) if names[data.arrays["scene"][i]] in config.train_scenes]
    val_rows = [i for i in range(len(data)) if names[data.arrays["scene"][i]] in config.validation_scenes]
    picked = [rng.choice(train_rows, 96, replace=False), rng.choice(val_rows, 32, replace=False)]
    picked = np.sort(np.concatenate(picked))
    _subset(train_from, picked, out / "train", rng)
    print(f"written: {out} ({sum(f.stat().st_size for f in out.rglob('*') if f.is_file()) / 1e6:.1f} MB)")


def _scans(folder: Path) -> tuple[list[np.ndarray], np.ndarray]:
    with np.load(folder / "scans.npz") as z:
        points, lengths, poses = z["points"], z["lengths"], z["poses"]
    return np.split(points, np.cumsum(lengths)[:-1]), poses


def _timed(fn, repeat: int = 1) -> tuple[object, float]:
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeat):
        result = fn()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return result, (time.perf_counter() - t0) / repeat


def inference(folder: Path) -> dict:
    """The shipped model's probabilities on the GPU against float32 on the CPU, and the speed of both."""
    scans, poses = _scans(folder)
    cpu, cpu8, gpu = Classifier.load(int8=False), Classifier.load(), Classifier.load(device="cuda")
    gpu.probabilities(scans[:4], poses[:4])  # the first call builds the kernels
    p_cpu, t_cpu = _timed(lambda: cpu.probabilities(scans, poses))
    p_gpu, t_gpu = _timed(lambda: gpu.probabilities(scans, poses), repeat=3)
    _, t_one_cpu = _timed(lambda: [cpu8.predict(s, T) for s, T in zip(scans[:20], poses[:20])])
    _, t_one_gpu = _timed(lambda: [gpu.predict(s, T) for s, T in zip(scans[:20], poses[:20])])
    decisions = (p_cpu > cpu.thresholds) == (p_gpu > gpu.thresholds)
    return {
        "max_abs_probability_difference": float(np.abs(p_cpu - p_gpu).max()),
        "decisions_equal": float(decisions.mean()),
        "batch_of_100_s": {"cpu_float32": round(t_cpu, 3), "cuda": round(t_gpu, 4), "ratio": round(t_cpu / t_gpu, 1)},
        "one_scan_ms": {
            "cpu_int8_one_thread": round(1000 * t_one_cpu / 20, 1),
            "cuda": round(1000 * t_one_gpu / 20, 1),
            "ratio": round(t_one_cpu / t_one_gpu, 1),
        },
    }


def training(folder: Path, out: Path, epochs: int) -> dict:
    """The same short training on the CPU and on the GPU: the two loss curves and the epochs' seconds.
    Without dropout, whose masks come from each device's own random generator: the curves then differ
    by the float rounding of the two devices alone."""
    config = TrainConfig(model=ModelConfig(dropout=0.0), epochs=epochs, samples_per_epoch=96, threads=2)
    curves = {}
    for device in ("cpu", "cuda"):
        run = out / f"train-{device}"
        shutil.rmtree(run, ignore_errors=True)
        train(folder / "train", run, config, progress=False, device=device)
        log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
        curves[device] = {
            "train_loss": [round(r["train_loss"], 5) for r in log],
            "val_loss": [round(r.get("val_loss", float("nan")), 5) for r in log],
            "seconds": [r["seconds"] for r in log],
        }
    a, b = np.array(curves["cpu"]["train_loss"]), np.array(curves["cuda"]["train_loss"])
    speed = np.mean(curves["cpu"]["seconds"][1:]) / max(np.mean(curves["cuda"]["seconds"][1:]), 1e-9)
    return {**curves, "max_relative_loss_difference": float(np.max(np.abs(a - b) / a)), "epoch_ratio": round(speed, 1)}


def run(folder: Path, out: Path, epochs: int) -> None:
    if not torch.cuda.is_available():
        raise SystemExit("no CUDA GPU visible to this torch: run this on a GPU machine")
    out.mkdir(parents=True, exist_ok=True)
    report = {"torch": torch.__version__, "gpu": torch.cuda.get_device_name(0), "inference": inference(folder)}
    print(json.dumps(report["inference"], indent=1), flush=True)
    report["training"] = training(folder, out, epochs)
    print(json.dumps(report["training"], indent=1))
    (out / "device_check.json").write_text(json.dumps(report, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--scans", type=Path, default=Path("data/mine-test"))
    p.add_argument("--train", type=Path, default=Path("data/l3e16"))
    r = sub.add_parser("run")
    r.add_argument("--data", type=Path, required=True)
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--epochs", type=int, default=4)
    args = parser.parse_args()
    if args.command == "prepare":
        prepare(args.out, args.scans, args.train)
    else:
        run(args.data, args.out, args.epochs)


if __name__ == "__main__":
    main()
