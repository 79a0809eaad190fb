"""How much of PPO's drift its sideways walking carries: a policy trained with the twist (vx, vy, yaw
rate), evaluated with the full pipeline on bypass variants as trained and with the vy of each action
set to zero at run time, printing per episode the mean |action| and mean action, success, final
error and path length.

Run: python studies/ppo_sideways.py --policy runs/ppo-bypass --scene bypass-100 --scene bypass-101
(the fusion options of docs/results.md's bypass table; two episodes at a time)
"""

from __future__ import annotations

import argparse
from multiprocessing import get_context

import numpy as np


def episode(job: tuple[str, str, bool]) -> tuple:
    folder, scene, zero_vy = job
    import torch

    from l3e_env.config import FusionSettings
    from policies import ppo
    from policies.evaluation import EpisodeJob, EvalOptions, run_episode

    torch.set_num_threads(1)
    actions = []
    as_trained = ppo.PPOPolicy.__call__

    def act(self, obs):
        twist = as_trained(self, obs).copy()
        actions.append(twist.copy())
        if zero_vy:
            twist[1] = 0.0
        return twist

    ppo.PPOPolicy.__call__ = act  # this worker's process only (one task a process)
    settings = FusionSettings(odometry_bias=("yaw", "scale"), attitude="tilt")
    ep = run_episode(EpisodeJob(f"ppo:{folder}", scene, 0, EvalOptions(fusion_settings=settings)))
    a = np.array(actions)
    return scene, zero_vy, ep.success, ep.final_ate, ep.path_length, np.abs(a).mean(0), a.mean(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="runs/ppo-bypass")
    parser.add_argument("--scene", action="append")
    args = parser.parse_args()
    jobs = [(args.policy, s, zero) for s in (args.scene or ["bypass-100", "bypass-101"]) for zero in (False, True)]
    print(f"{'scene':11s} {'vy':>6s} {'success':>7s} {'final m':>7s} {'path m':>7s}  mean |vx vy wz|   mean vx vy wz")
    with get_context("spawn").Pool(2, maxtasksperchild=1) as pool:
        for scene, zero, ok, final, path, size, mean in pool.imap(episode, jobs):
            print(
                f"{scene:11s} {'zero' if zero else 'own':>6s} {str(ok):>7s} {final:7.2f} {path:7.1f}  "
                f"{np.round(size, 3)}  {np.round(mean, 3)}"
            )


if __name__ == "__main__":
    main()
