"""PPO (stable-baselines3, the `rl` extra) on the fast map environment over seeded fork variants.

A run folder holds `progress.csv` (SB3's CSV log: returns, losses, fps), `monitor.csv` (one row
per episode), `checkpoints/`, `last.zip` (resumed by running the same command again) and
`policy.zip` with `policy.json`, which records what the policy observes so that a policy of
another observation layout is refused by name."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from l3e_env.config import plain

from .context import SceneContext
from .fastenv import FastEnvConfig, MapNavigationEnv
from .observation import LOOKAHEAD, SECTORS, PolicyView

TRAIN_VARIANTS = [f"fork-{s}" for s in range(7)]
EVAL_VARIANTS = [f"fork-{s}" for s in range(100, 110)]  # never trained on
OBSERVATION = {"layout": "policy-view-2", "size": PolicyView.size, "sectors": SECTORS, "lookahead": list(LOOKAHEAD)}


class PolicyCheckpointError(RuntimeError):
    """A policy file that is missing, unreadable or made for another observation layout."""


def _sb3():
    try:
        import stable_baselines3
    except ImportError as exc:
        raise RuntimeError("PPO needs stable-baselines3: pip install -e '.[rl]'") from exc
    return stable_baselines3


# what a run trained before each of these options existed was trained with (policy.json records
# every FastEnvConfig field since): no cost for walking sideways
FAST_ENV_BEFORE_OPTIONS = {"lateral_drift": 0.0}


def run_record(out: str | Path) -> dict[str, Any]:
    """A run folder's policy.json (what `train_ppo` writes after each stage); {} before the first."""
    meta_file = Path(out) / "policy.json"
    return json.loads(meta_file.read_text()) if meta_file.exists() else {}


def resumed_config(out: str | Path, **given: float | None) -> FastEnvConfig:
    """The fast environment's settings for a stage in `out`: each option given wins; one not given
    is the run's own where the folder holds a stage already (so a second stage trains as the first
    did), else the default."""
    own = run_record(out).get("fast_env")
    own = {**FAST_ENV_BEFORE_OPTIONS, **own} if own is not None else {}
    default = FastEnvConfig()
    return FastEnvConfig(**{k: own.get(k, getattr(default, k)) if v is None else v for k, v in given.items()})


def train_ppo(out: str | Path, contexts: list[SceneContext], detector: str = "learned", timesteps: int = 300_000,
              seed: int = 0, n_envs: int = 4, config: FastEnvConfig | None = None,
              progress: bool = True) -> dict[str, Any]:
    """Train (or resume) a PPO policy on the scenes' cached maps (made with `detector`, which
    evaluation reads back from policy.json); returns the summary written there."""
    sb3 = _sb3()
    import torch
    from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback
    from stable_baselines3.common.logger import configure
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    config = config or FastEnvConfig()
    scenes = [c.scene.name for c in contexts]

    last = out / "last.zip"
    # one episode log per run: monitor.csv, then resume-1.monitor.csv, ... (SB3 wants the suffix)
    runs = len(list(out.glob("*monitor.csv")))
    monitor = out / ("monitor.csv" if runs == 0 else f"resume-{runs}.monitor.csv")
    venv = VecMonitor(DummyVecEnv([lambda: MapNavigationEnv(contexts, config)] * n_envs), str(monitor))
    venv.seed(seed)
    if last.exists():
        model = sb3.PPO.load(last, env=venv, device="cpu")
    else:
        model = sb3.PPO("MlpPolicy", venv, n_steps=256, batch_size=256, n_epochs=10, learning_rate=3e-4, gamma=0.99,
                        gae_lambda=0.95, ent_coef=0.0, seed=seed, device="cpu", policy_kwargs={"net_arch": [64, 64]})
    model.set_logger(configure(str(out), ["csv"]))
    done = model.num_timesteps

    class Bar(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = tqdm(total=timesteps, initial=done, desc="PPO", unit="step", disable=not progress)

        def _on_step(self) -> bool:
            self.bar.update(self.training_env.num_envs)
            if self.num_timesteps % 20_000 < self.training_env.num_envs:
                model.save(last)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    if timesteps > done:
        model.learn(timesteps - done, callback=[Bar(), CheckpointCallback(50_000, str(out / "checkpoints"), "ppo")],
                    reset_num_timesteps=False)
    model.save(last)
    model.save(out / "policy.zip")
    # a run resumed on other variants (a curriculum) keeps the record of every stage
    history = run_record(out).get("history", [])
    history.append({"scenes": scenes, "from_timestep": int(done), "to_timestep": int(model.num_timesteps)})
    summary = {"observation": OBSERVATION, "scenes": scenes, "detector": detector,
               "timesteps": int(model.num_timesteps),
               "seed": seed, "fast_env": plain(dataclasses.asdict(config)), "history": history}
    (out / "policy.json").write_text(json.dumps(summary, indent=2))
    return summary


class PPOPolicy:
    """A trained policy: observation in, normalised twist out (deterministic)."""

    def __init__(self, path: str | Path):
        sb3 = _sb3()
        path = Path(path)
        zip_path = path / "policy.zip" if path.is_dir() else path
        meta_path = zip_path.with_name("policy.json")
        if not zip_path.exists() or not meta_path.exists():
            raise PolicyCheckpointError(f"{path}: no policy.zip with policy.json beside it (train one with "
                                        f"`l3e policy train`)")
        self.meta = json.loads(meta_path.read_text())
        if self.meta.get("observation") != json.loads(json.dumps(OBSERVATION)):
            raise PolicyCheckpointError(f"{zip_path}: trained on observation {self.meta.get('observation')}, this "
                                        f"version gives {OBSERVATION}; retrain it")
        try:
            self.model = sb3.PPO.load(zip_path, device="cpu")
        except Exception as exc:  # noqa: BLE001 - SB3 raises many kinds for a broken zip
            raise PolicyCheckpointError(f"{zip_path}: cannot be loaded as a PPO policy ({exc})") from exc
        if self.model.observation_space.shape != (PolicyView.size,):
            raise PolicyCheckpointError(f"{zip_path}: observation shape {self.model.observation_space.shape}, "
                                        f"expected ({PolicyView.size},)")
        self.action_repeat = int(self.meta["fast_env"]["action_repeat"])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        action, _ = self.model.predict(obs, deterministic=True)
        return np.clip(np.asarray(action, dtype=np.float32), -1, 1)
