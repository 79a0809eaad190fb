"""Where the fused estimate's final error on a navigation episode comes from: the registration's,
the legs' and the fusion's error of each step, summed along the route, on straight walking and in
turns apart.

One episode of `l3e policy evaluate` (the planner or the shortest path, steering on the fused
estimate, the fusion's settings as given), with every step's registration, odometry increment,
fused increment and the true increment kept. Per step, in the body frame: the error along the
walk, across it, and of heading (yaw), for the registration (where it converged), the legs and the
fused estimate. Summed over the route, the heading error of the fused increments is the fused
heading's error at the end; an error of heading e at distance d to go costs about e * d across.

Run: python studies/route_drift_budget.py --scene bypass-102 --seed 2 [--policy planner]
     [--odometry-bias yaw,scale] [--attitude tilt] [--no-sweep] [--steer-on truth]
     [--keyframe-distance 4]
"""

from __future__ import annotations

import argparse
from dataclasses import asdict

import numpy as np

from l3e_env.config import FusionSettings
from l3e_env.core.transforms import inverse, yaw_of
from l3e_env.envs import NavigationEnv
from l3e_env.sim.avoidance import FreeHeadings
from policies.context import scene_context
from policies.evaluation import MapSource, make_controller

TURNING = np.radians(0.5)  # rad a step: above this true turn a step is a turn's


def _error(true: np.ndarray, estimate: np.ndarray) -> tuple[float, float, float, float]:
    """(along, across, height, yaw) of estimate against true, two increments in the same body frame."""
    d = estimate[:3, 3] - true[:3, 3]
    return float(d[0]), float(d[1]), float(d[2]), float(yaw_of(inverse(true) @ estimate))


def run_episode(
    scene: str, seed: int, policy: str, settings: FusionSettings, sweep: bool, steer_on: str
) -> dict[str, np.ndarray]:
    """Per step: the true increment's turn, and the (along, across, height, yaw) errors of the
    registration (NaN where none, or where it was onto a keyframe), the odometry and the fused
    increment, all in the body frame."""
    fusion = {**asdict(settings), "enabled": True}
    env = NavigationEnv(scene=scene, fusion=fusion, lidar={"sweep": sweep})
    online = env.fusion
    registrations: list = []
    next_registration = online.registrar.next

    def kept(points: np.ndarray, motion: np.ndarray | None = None):  # type: ignore[no-untyped-def]
        result = next_registration(points, motion)
        registrations.append(result)
        return result

    online.registrar.next = kept  # type: ignore[method-assign]
    ctx = scene_context(scene, settings.detector, None, build=False)
    steer, _ = make_controller(policy, MapSource(scene), 50.0, env.config.odometry, ctx, FreeHeadings())
    _, info = env.reset(seed=seed)
    T_b_s = env.robot.T_b_s
    rows, done = [], False
    truth, fused, odom = info["T_w_b"], info["fused_T_w_b"], info["odom_T_w_b"]
    while not done:
        obstacles = FreeHeadings.obstacles(env.scan.points, T_b_s, env.config.robot)
        pose = info["fused_T_w_b"] if steer_on == "estimate" else info["T_w_b"]
        _, _, terminated, truncated, info = env.step(steer(pose, env.steps, obstacles))
        done = terminated or truncated
        true_step = inverse(truth) @ info["T_w_b"]
        fused_step = inverse(fused) @ info["fused_T_w_b"]
        odom_step = inverse(odom) @ info["odom_T_w_b"]
        reg = registrations[-1]
        reg_err = (np.nan,) * 4
        if reg is not None and reg.converged and reg.span == 1:  # a keyframe's: not a step's error
            reg_err = _error(true_step, T_b_s @ reg.T_target_source @ inverse(T_b_s))
        rows.append(
            [
                yaw_of(true_step),
                *reg_err,
                *_error(true_step, odom_step),
                *_error(true_step, fused_step),
                *info["localizability_mask"][[0, 1, 5]],
            ]
        )
        truth, fused, odom = info["T_w_b"], info["fused_T_w_b"], info["odom_T_w_b"]
    end = inverse(info["T_w_b"]) @ info["fused_T_w_b"]
    env.close()
    table = np.array(rows)
    parts = {"registration": table[:, 1:5], "odometry": table[:, 5:9], "fused": table[:, 9:13]}
    return {"turn": table[:, 0], **parts, "masked": table[:, 13:16], "end": np.array(_error(np.eye(4), end))}


def report(steps: dict[str, np.ndarray]) -> None:
    turning = np.abs(steps["turn"]) > TURNING
    print(f"{len(turning)} steps, {turning.sum()} turning (over {np.degrees(TURNING):.1f} deg a step)")
    print(
        f"{'source':13s} {'part':9s} {'steps':>6s} {'along mm/step':>14s} {'across mm/step':>15s} "
        f"{'z mm/step':>10s} {'yaw mdeg/step':>14s} {'yaw sum deg':>12s}"
    )
    for name in ("registration", "odometry", "fused"):
        for part, which in (("straight", ~turning), ("turning", turning), ("all", np.ones_like(turning))):
            e = steps[name][which]
            e = e[np.isfinite(e).all(1)]
            if not len(e):
                continue
            print(
                f"{name:13s} {part:9s} {len(e):6d} {e[:, 0].mean() * 1e3:14.2f} {e[:, 1].mean() * 1e3:15.2f} "
                f"{e[:, 2].mean() * 1e3:10.2f} {np.degrees(e[:, 3].mean()) * 1e3:14.2f} "
                f"{np.degrees(e[:, 3].sum()):12.2f}"
            )
    masked = steps["masked"].mean(0)
    print(f"masked share: x {masked[0]:.2f}, y {masked[1]:.2f}, yaw {masked[2]:.2f}")
    along, across, height, yaw = steps["end"]
    print(
        f"end: the estimate {along:.2f} m along, {across:.2f} m across, {height:.2f} m in height, "
        f"heading {np.degrees(yaw):.2f} deg off"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bypass-102")
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--policy", default="planner", choices=["planner", "shortest"])
    parser.add_argument("--odometry-bias", default="", help="comma-separated: yaw, z, scale")
    parser.add_argument("--attitude", default="none", choices=["none", "tilt", "full"])
    parser.add_argument("--keyframe-distance", type=float, default=0.0, help="m (default 0: scan to scan)")
    parser.add_argument("--no-sweep", action="store_true", help="scans taken at an instant (no revolution to deskew)")
    parser.add_argument(
        "--steer-on",
        choices=["estimate", "truth"],
        default="estimate",
        help="truth: the same path whatever the estimate (an episode steered on it may end elsewhere)",
    )
    args = parser.parse_args()
    bias = tuple(a for a in args.odometry_bias.split(",") if a)
    settings = FusionSettings(
        odometry_bias=bias, attitude=args.attitude, detector="learned", keyframe_distance=args.keyframe_distance
    )
    report(run_episode(args.scene, args.seed, args.policy, settings, not args.no_sweep, args.steer_on))


if __name__ == "__main__":
    main()
