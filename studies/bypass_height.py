"""Where does the bypass's height error at the goal come from?

One planner episode of `l3e policy evaluate` (the default estimator, the learned detector, the
robot steering on its estimate), traced step by step: the fused estimate's height error against the
truth, the ground's slope under the robot, whether the detector held z (in the level frame), and
whether ICP was used. The height error's growth is summed by what was under the robot (level ground
or a slope, z flagged or held) and printed with the steps where it grew most.

Run: python studies/bypass_height.py [--scene bypass-104] [--seed 4] [--odometry-bias yaw,scale,z]
     [--attitude none] [--keyframe-distance 0] [--ground none]
"""

from __future__ import annotations

import argparse
from dataclasses import asdict

import numpy as np

from l3e_env.config import FusionSettings
from l3e_env.envs import NavigationEnv
from l3e_env.sim.avoidance import FreeHeadings
from policies.evaluation import BackOff, MapSource, make_controller


def trace(scene: str, seed: int, settings: FusionSettings) -> dict[str, np.ndarray]:
    """Per step: true and fused z, the true pitch (the slope walked), z masked, ICP used."""
    env = NavigationEnv(
        scene=scene, arrival="estimate", fusion={**asdict(settings), "enabled": True, "detector": "learned"}
    )
    source = MapSource(scene)
    ctx = source.context()
    local = FreeHeadings()
    steer, _ = make_controller("planner", source, 50.0, env.config.odometry, ctx, local)
    controller = BackOff(steer)
    _, info = env.reset(seed=seed)
    imu_pitch: list[float] = []  # the nine-axis unit's own pitch error on each reading (deg)
    if env.attitude is not None:
        unit, measure = env.attitude, env.attitude.measure

        def recorded(R_w_b: np.ndarray, dt: float) -> np.ndarray:
            R = measure(R_w_b, dt)
            imu_pitch.append(float(np.degrees(np.arcsin(-R[2, 0]) - np.arcsin(-R_w_b[2, 0]))))
            return R

        unit.measure = recorded  # type: ignore[method-assign]
    rows = []
    done = False
    while not done:
        obstacles = FreeHeadings.obstacles(env.scan.points, env.robot.T_b_s, env.config.robot)
        _, _, terminated, truncated, info = env.step(controller(info["fused_T_w_b"], env.steps, obstacles))
        controller.observe(info["blocked"])
        done = terminated or truncated
        T, F = info["T_w_b"], info["fused_T_w_b"]
        pitch = float(np.degrees(np.arcsin(-T[2, 0])))
        fused_pitch = float(np.degrees(np.arcsin(-F[2, 0])))
        mask = info["localizability_mask"]
        rows.append(
            (T[2, 3], F[2, 3], pitch, bool(mask[2]), T[0, 3], T[1, 3], bool(mask[0] or mask[1]), fused_pitch - pitch)
        )
    counts = info["fusion_counts"]
    env.close()
    table = np.array(rows, dtype=np.float64)
    return {
        "true_z": table[:, 0],
        "fused_z": table[:, 1],
        "pitch": table[:, 2],
        "z_masked": table[:, 3].astype(bool),
        "xy": table[:, 4:6],
        "icp_failed": np.array([counts["icp_failed"]]),
        "xy_masked": table[:, 6].astype(bool),
        "pitch_error": table[:, 7],
        "imu_pitch_error": np.array(imu_pitch[-len(table) :] if imu_pitch else [np.nan] * len(table)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bypass-104")
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument("--odometry-bias", default=",".join(FusionSettings().odometry_bias), help="e.g. yaw,scale,z")
    parser.add_argument("--attitude", default=FusionSettings().attitude)
    parser.add_argument("--keyframe-distance", type=float, default=FusionSettings().keyframe_distance)
    parser.add_argument("--ground", default=FusionSettings().ground)
    args = parser.parse_args()
    bias = tuple(a for a in args.odometry_bias.split(",") if a)
    settings = FusionSettings(
        odometry_bias=bias, attitude=args.attitude, keyframe_distance=args.keyframe_distance, ground=args.ground
    )
    print(
        f"odometry bias states {bias or 'none'}, attitude {args.attitude}, keyframes {args.keyframe_distance:g} m, "
        f"ground {args.ground}"
    )
    t = trace(args.scene, args.seed, settings)
    error = t["fused_z"] - t["true_z"]
    growth = np.diff(np.r_[0.0, error])
    sloped = np.abs(t["pitch"]) > 2.0
    print(f"{args.scene} seed {args.seed}: {len(error)} steps, final height error {error[-1]:+.3f} m")
    print(f"  ICP failed on {int(t['icp_failed'][0])} steps; z flagged on {t['z_masked'].mean():.1%} of steps")
    walked = np.r_[0.0, np.linalg.norm(np.diff(t["xy"], axis=0), axis=1)]
    from_pitch = -float(np.sum(np.radians(t["pitch_error"]) * walked))  # nose down (pitch > 0) walks down
    print(
        f"  the estimate's pitch error: mean {t['pitch_error'].mean():+.3f} deg (sd {t['pitch_error'].std():.3f}); "
        f"walked {walked.sum():.1f} m; the height it tilts the walk by: {from_pitch:+.3f} m"
    )
    imu_from_pitch = -float(np.sum(np.radians(t["imu_pitch_error"]) * walked))
    print(
        f"  the IMU's own pitch error: mean {t['imu_pitch_error'].mean():+.3f} deg "
        f"(sd {t['imu_pitch_error'].std():.3f}); the height it would tilt the walk by: {imu_from_pitch:+.3f} m"
    )
    for name, where in (
        ("level ground", ~sloped),
        ("slopes over 2 deg", sloped),
        ("z flagged", t["z_masked"]),
        ("x or y flagged", t["xy_masked"]),
        ("x and y held", ~t["xy_masked"]),
    ):
        print(f"  {name:18s} {where.mean():6.1%} of steps, height error grown {growth[where].sum():+.3f} m")
    window = 50
    sums = np.convolve(growth, np.ones(window), mode="valid")
    for k in np.argsort(np.abs(sums))[::-1][:3]:
        x, y = t["xy"][k + window // 2]
        print(
            f"  steps {k}-{k + window}: {sums[k]:+.3f} m at ({x:.1f}, {y:.1f}), true z {t['true_z'][k]:.2f} to "
            f"{t['true_z'][k + window - 1]:.2f}, pitch {t['pitch'][k : k + window].mean():+.1f} deg mean"
        )


if __name__ == "__main__":
    main()
