"""PPO (stable-baselines3, the `rl` extra) on the fast map environment over seeded fork variants.

A run folder holds `progress.csv` (SB3's CSV log: returns, losses, fps) and the same in TensorBoard
event files (`tensorboard --logdir <run folder>`; written where the `tensorboard` package, part of
the `rl` extra, is installed), `monitor.csv` (one row per episode), `last.pt` (weights, optimiser
state and step count: running the same command again resumes from it), `policy.pt` (the trained
policy's weights) and `policy.json`, which records the network's layout and what the policy
observes, so that a policy of another observation layout is refused by name. Weights are stored as
tensors and read with torch's weights-only loader, so that loading a policy folder never runs code
from it; stable-baselines3's own zip files, whose loader unpickles what they hold, are neither
written nor read."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from l3e_env.config import plain
from l3e_env.core.files import new_folder, write_atomic
from l3e_env.sim.follower import walk_towards

from .context import SceneContext
from .fastenv import FastEnvConfig, MapNavigationEnv, action_layout, as_twist
from .observation import LOOKAHEAD, SECTORS, PolicyView

# the bypass family, where a way round a degenerate gallery pays; the fork stays available by name
TRAIN_VARIANTS = [f"bypass-{s}" for s in range(8)]
EVAL_VARIANTS = [f"bypass-{s}" for s in range(100, 110)]  # never trained on
OBSERVATION = {"layout": "policy-view-2", "size": PolicyView.size, "sectors": SECTORS, "lookahead": list(LOOKAHEAD)}


class PolicyCheckpointError(RuntimeError):
    """A policy file that is missing, unreadable or made for another observation layout."""


def require_sb3():
    try:
        import stable_baselines3
    except ImportError as exc:
        raise RuntimeError("PPO needs stable-baselines3: pip install -e '.[rl]'") from exc
    return stable_baselines3


POLICY_FILE, STATE_FILE, META_FILE, WARM_FILE = "policy.pt", "last.pt", "policy.json", "warm_start.json"
NET_ARCH = [64, 64]
PPO_SETTINGS = {
    "n_steps": 256,
    "batch_size": 256,
    "n_epochs": 10,
    "learning_rate": 3e-4,
    "gamma": 0.99,
    "gae_lambda": 0.95,
    "ent_coef": 0.0,
}


def _save_tensors(path: Path, tensors: dict[str, Any]) -> None:
    import torch

    write_atomic(path, lambda fh: torch.save(tensors, fh))


def _load_tensors(path: Path) -> dict[str, Any]:
    """A file of tensors, read with torch's weights-only loader (it runs no code from the file)."""
    import torch

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - whatever the loader raises, name the file
        # torch's own message advises loading with weights_only=False, which would run code from the file
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        reason = "not a weights-only torch file, or damaged" if first.startswith("Weights only load failed") else first
        raise PolicyCheckpointError(f"{path}: cannot be read as policy weights ({reason})") from exc


def _checked_meta(path: Path, meta: Any) -> dict[str, Any]:
    """policy.json's structure: PolicyCheckpointError naming the file and the key that is missing or wrong."""
    if not isinstance(meta, dict):
        raise PolicyCheckpointError(f"{path}: holds a {type(meta).__name__}, not the mapping train_ppo writes")
    fast_env = meta.get("fast_env")
    repeat = fast_env.get("action_repeat") if isinstance(fast_env, dict) else None
    if isinstance(repeat, bool) or not isinstance(repeat, int) or repeat < 1:
        raise PolicyCheckpointError(
            f"{path}: fast_env.action_repeat must be a whole number of 1 or more, got {repeat!r}"
        )
    detector = meta.get("detector")
    if detector is not None:
        from l3e_env.config.detector_spec import parse_detector

        try:
            parse_detector(detector if isinstance(detector, str) else repr(detector))
        except ValueError as exc:
            raise PolicyCheckpointError(
                f"{path}: detector {detector!r} is no detector this version runs ({exc})"
            ) from None
    arch = meta.get("net_arch", NET_ARCH)
    if not isinstance(arch, list) or not arch or not all(type(n) is int and 0 < n <= 4096 for n in arch):
        raise PolicyCheckpointError(f"{path}: net_arch must be a list of layer widths (1 to 4096), got {arch!r}")
    return meta


def _save_state(model: Any, path: Path) -> None:
    """What resuming needs: the policy's weights, its optimiser's state and the steps taken."""
    _save_tensors(
        path,
        {
            "policy": model.policy.state_dict(),
            "optimizer": model.policy.optimizer.state_dict(),
            "num_timesteps": int(model.num_timesteps),
        },
    )


def run_record(out: str | Path) -> dict[str, Any]:
    """A run folder's policy.json (what `train_ppo` writes after each stage); {} before the first."""
    meta_file = Path(out) / "policy.json"
    return json.loads(meta_file.read_text()) if meta_file.exists() else {}


def resumed_config(out: str | Path, **given: float | bool | None) -> FastEnvConfig:
    """The fast environment's settings for a stage in `out`: each option given wins; one not given
    is the run's own where the folder holds a stage already (so a second stage trains as the first
    did), else the default."""
    own = run_record(out).get("fast_env") or {}
    default = FastEnvConfig()
    chosen: dict[str, Any] = {k: own.get(k, getattr(default, k)) if v is None else v for k, v in given.items()}
    return FastEnvConfig(**chosen)


def _has_tensorboard() -> bool:
    import importlib.util

    return importlib.util.find_spec("tensorboard") is not None


def teacher_action(obs: np.ndarray, sideways: bool = True) -> np.ndarray:
    """The planner's choice as a twist: walk towards the observation's localizability-aware path
    direction (downhill on the planner's cost-to-go) as the route follower walks towards its
    look-ahead point (l3e_env.sim.follower.walk_towards). A function of
    the observation alone, so that the network can hold it exactly. In the action layout of
    `sideways` (fastenv.action_layout): the teacher never walks sideways."""
    aware = np.asarray(obs, dtype=np.float64)[..., PolicyView.aware]
    forward, turn = walk_towards(np.arctan2(aware[..., 1], aware[..., 0]))
    parts = [forward, np.zeros_like(turn), turn] if sideways else [forward, turn]
    return np.stack(parts, -1).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class WarmStart:
    """Behaviour cloning before PPO: the teacher (teacher_action) walks every training scene
    `episodes` times with Gaussian noise of `noise` on its executed twist, so that the states off
    its path are seen too, each labelled with the teacher's own twist (as DAgger labels them); the
    network's mean action is fitted to the labels and its value to the discounted returns for
    `epochs` passes, and its exploration noise starts at `std`. PPO from random weights on the
    long bypass variants wandered without learning to arrive; from here it starts at the planner's
    behaviour."""

    episodes: int = 4
    noise: float = 0.4
    epochs: int = 30
    std: float = 0.2


def demonstrations(
    contexts: list[SceneContext], config: FastEnvConfig, warm: WarmStart, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(observations, teacher twists, discounted returns) from the teacher's noisy walks."""
    rng = np.random.default_rng(seed)
    observations, actions, returns = [], [], []
    gamma = PPO_SETTINGS["gamma"]
    for ctx in contexts:
        env = MapNavigationEnv([ctx], config)
        for _ in range(warm.episodes):
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
            rewards, done = [], False
            while not done:
                label = teacher_action(obs, config.sideways)
                observations.append(obs)
                actions.append(label)
                act = np.clip(label + rng.normal(0.0, warm.noise, len(label)), -1.0, 1.0)
                obs, reward, terminated, truncated, _ = env.step(act)
                rewards.append(reward)
                done = terminated or truncated
            to_go, running = np.zeros(len(rewards)), 0.0
            for k in range(len(rewards) - 1, -1, -1):
                running = rewards[k] + gamma * running
                to_go[k] = running
            returns.append(to_go)
    return np.array(observations, np.float32), np.array(actions, np.float32), np.concatenate(returns).astype(np.float32)


def clone(
    policy: Any, observations: np.ndarray, actions: np.ndarray, returns: np.ndarray, warm: WarmStart, seed: int = 0
) -> float:
    """Fit an SB3 ActorCriticPolicy's mean action to `actions` and its value to `returns`; returns
    the final mean squared error of the actions."""
    import torch

    generator = torch.Generator().manual_seed(seed)
    obs, act, ret = (torch.as_tensor(a) for a in (observations, actions, returns))
    optimiser = torch.optim.Adam(policy.parameters(), lr=1e-3)
    error = float("nan")
    for _ in range(warm.epochs):
        order, errors = torch.randperm(len(obs), generator=generator), []
        for batch in order.split(256):
            distribution = policy.get_distribution(obs[batch]).distribution
            action_error = ((distribution.mean - act[batch]) ** 2).mean()
            value_error = ((policy.predict_values(obs[batch]).squeeze(-1) - ret[batch]) ** 2).mean()
            optimiser.zero_grad()
            (action_error + 1e-3 * value_error).backward()
            optimiser.step()
            errors.append(action_error.item())
        error = float(np.mean(errors))
    with torch.no_grad():
        policy.log_std.fill_(float(np.log(warm.std)))
    return error


@dataclasses.dataclass(frozen=True)
class PPOTraining:
    """How long and how PPO trains: `timesteps` in all (a resumed run goes on to them), over `n_envs`
    environments, seeded by `seed`; a new run starts from `warm`'s behaviour cloning of the planner's
    choice (None: from random weights)."""

    timesteps: int = 300_000
    seed: int = 0
    n_envs: int = 4
    warm: WarmStart | None = WarmStart()


def train_ppo(
    out: str | Path,
    contexts: list[SceneContext],
    detector: str = "learned",
    training: PPOTraining = PPOTraining(),
    config: FastEnvConfig | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Train (or resume) a PPO policy on the scenes' cached maps (made with `detector`, which
    evaluation reads back from policy.json); returns the summary written there."""
    require_sb3()
    import torch
    from stable_baselines3.common.logger import configure

    out = Path(out)
    torch.set_num_threads(1)
    config = config or FastEnvConfig()
    last = out / STATE_FILE
    with new_folder(out):  # a run refused while it is set up leaves no folder; once it learns, it is kept
        model = _ppo_model(out, contexts, config, training)
        if last.exists():
            _resume(model, last)
        elif training.warm is not None:
            observations, actions, returns = demonstrations(contexts, config, training.warm, training.seed)
            cloned = clone(model.policy, observations, actions, returns, training.warm, training.seed)
            record = {**dataclasses.asdict(training.warm), "samples": len(observations), "action_mse": cloned}
            (out / WARM_FILE).write_text(json.dumps(record, indent=2))
    model.set_logger(configure(str(out), ["csv", *(["tensorboard"] if _has_tensorboard() else [])]))
    done = model.num_timesteps
    if training.timesteps > done:
        model.learn(
            training.timesteps - done,
            callback=[_progress(model, last, training.timesteps, progress)],
            reset_num_timesteps=False,
        )
    _save_state(model, last)
    _save_tensors(out / POLICY_FILE, model.policy.state_dict())
    return _write_record(out, model, contexts, detector, training, config, done)


def _ppo_model(out: Path, contexts: list[SceneContext], config: FastEnvConfig, training: PPOTraining) -> Any:
    """A PPO model over `n_envs` fast environments of the scenes, their episodes logged to a monitor
    file of this run's own (monitor.csv, then resume-1.monitor.csv, ...: SB3 wants the suffix)."""
    sb3 = require_sb3()
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

    runs = len(list(out.glob("*monitor.csv")))
    monitor = out / ("monitor.csv" if runs == 0 else f"resume-{runs}.monitor.csv")
    venv = VecMonitor(DummyVecEnv([lambda: MapNavigationEnv(contexts, config)] * training.n_envs), str(monitor))
    venv.seed(training.seed)
    return sb3.PPO(
        "MlpPolicy", venv, seed=training.seed, device="cpu", policy_kwargs={"net_arch": NET_ARCH}, **PPO_SETTINGS
    )


def _resume(model: Any, last: Path) -> None:
    """The policy, its optimiser and the steps taken from a run's last state (weights only)."""
    state = _load_tensors(last)
    try:
        model.policy.load_state_dict(state["policy"])
        model.policy.optimizer.load_state_dict(state["optimizer"])
        model.num_timesteps = int(state["num_timesteps"])
    except (KeyError, RuntimeError, ValueError, TypeError) as exc:
        raise PolicyCheckpointError(
            f"{last}: not the state of a run of this network ({exc}); train into another folder"
        ) from exc


def _progress(model: Any, last: Path, timesteps: int, progress: bool) -> Any:
    """A callback that shows a progress bar and saves the run's state every 20 000 steps."""
    from stable_baselines3.common.callbacks import BaseCallback

    done = model.num_timesteps

    class Bar(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = tqdm(total=timesteps, initial=done, desc="PPO", unit="step", disable=not progress)

        def _on_step(self) -> bool:
            self.bar.update(self.training_env.num_envs)
            if self.num_timesteps % 20_000 < self.training_env.num_envs:
                _save_state(model, last)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return Bar()


def _write_record(
    out: Path,
    model: Any,
    contexts: list[SceneContext],
    detector: str,
    training: PPOTraining,
    config: FastEnvConfig,
    done: int,
) -> dict[str, Any]:
    """policy.json: the layouts, the scenes and maps, the fast environment, and each stage's steps (a run
    resumed on other variants, a curriculum, keeps the record of every stage)."""
    scenes = [c.scene.name for c in contexts]
    history = run_record(out).get("history", [])
    history.append({"scenes": scenes, "from_timestep": int(done), "to_timestep": int(model.num_timesteps)})
    summary = {
        "observation": OBSERVATION,
        "action": list(action_layout(config.sideways)),
        "net_arch": NET_ARCH,
        "scenes": scenes,
        "detector": detector,
        "timesteps": int(model.num_timesteps),
        "warm_start": json.loads((out / WARM_FILE).read_text()) if (out / WARM_FILE).exists() else None,
        "seed": training.seed,
        "fast_env": plain(dataclasses.asdict(config)),
        "history": history,
    }
    (out / META_FILE).write_text(json.dumps(summary, indent=2))
    return summary


def recorded_detector(folder: str | Path, default: str) -> str:
    """The detector a policy folder's policy.json says its policy was trained with, checked (else
    `default` where the folder has no policy.json); PolicyCheckpointError naming the file."""
    meta_path = Path(folder) / META_FILE
    if not meta_path.exists():
        return default
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError) as exc:
        raise PolicyCheckpointError(f"{meta_path}: cannot be read ({exc})") from exc
    return str(_checked_meta(meta_path, meta).get("detector", default))


class PPOPolicy:
    """A trained policy: observation in, normalised twist out (deterministic). Built from the folder's
    policy.json (the network's layout) and policy.pt (its weights, read as tensors only)."""

    def __init__(self, path: str | Path):
        require_sb3()
        from gymnasium import spaces
        from stable_baselines3.common.policies import ActorCriticPolicy

        path = Path(path)
        folder = path.parent if path.is_file() else path
        weights, meta_path = folder / POLICY_FILE, folder / META_FILE
        if not weights.exists() or not meta_path.exists():
            old = (
                " (its policy.zip is not read: loading it could run code from it; train the policy again)"
                if (folder / "policy.zip").exists()
                else ""
            )
            raise PolicyCheckpointError(
                f"{folder}: no {POLICY_FILE} with {META_FILE} beside it{old} (train one with `l3e policy train`)"
            )
        try:
            self.meta = _checked_meta(meta_path, json.loads(meta_path.read_text()))
        except (OSError, ValueError) as exc:
            raise PolicyCheckpointError(f"{meta_path}: cannot be read ({exc})") from exc
        if self.meta.get("observation") != json.loads(json.dumps(OBSERVATION)):
            raise PolicyCheckpointError(
                f"{folder}: trained on observation {self.meta.get('observation')}, this "
                f"version gives {OBSERVATION}; retrain it"
            )
        layouts = {action_layout(sideways): sideways for sideways in (False, True)}
        if tuple(self.meta.get("action", ())) not in layouts:
            raise PolicyCheckpointError(
                f"{folder}: trained with actions {self.meta.get('action')}, this version "
                f"takes {' or '.join(str(list(a)) for a in layouts)}; retrain it"
            )
        self.sideways = layouts[tuple(self.meta["action"])]
        self.policy = ActorCriticPolicy(
            spaces.Box(-np.inf, np.inf, (PolicyView.size,), np.float32),
            spaces.Box(-1.0, 1.0, (len(self.meta["action"]),), np.float32),
            lambda _: 0.0,
            net_arch=list(self.meta.get("net_arch", NET_ARCH)),
        )
        tensors = _load_tensors(weights)
        if not isinstance(tensors, dict):
            raise PolicyCheckpointError(f"{weights}: holds a {type(tensors).__name__}, not a network's weights")
        broken = [k for k, t in tensors.items() if hasattr(t, "isfinite") and not bool(t.isfinite().all())]
        if broken:
            raise PolicyCheckpointError(f"{weights}: non-finite weights in {', '.join(broken[:3])}: retrain the policy")
        try:
            self.policy.load_state_dict(tensors)
        except (RuntimeError, TypeError, ValueError) as exc:
            raise PolicyCheckpointError(f"{weights}: not the weights of this network ({exc})") from exc
        self.policy.set_training_mode(False)
        self.action_repeat = int(self.meta["fast_env"]["action_repeat"])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The normalised twist (vx, vy, yaw rate)."""
        action, _ = self.policy.predict(obs, deterministic=True)
        return as_twist(action, self.sideways).astype(np.float32)
