"""The paper's main field test: an outdoor yard, a long smooth mine tunnel, a quarry cavern."""

from __future__ import annotations

import numpy as np

from .geometry import box, ground_plane, merge, polar_profile, resample_polyline, smooth_noise, sweep
from .scene import Scene


def _yard(rng: np.random.Generator, seed: int, yard: float) -> list:
    """The yard's ground and its buildings and containers (jittered for seeds other than 0)."""
    parts = [ground_plane(-yard, 0.5, -30, 30, cell=15)]
    for cx, cy, sx, sy, sz in [
        (-32, -9, 8, 5, 4),
        (-20, 10, 6, 4, 3),
        (-12, -8, 6, 2.5, 2.6),
        (-27, 12, 3, 6, 5),
        (-6, 9, 2.5, 6, 2.6),
        (-40, 3, 4, 4, 3),
    ]:
        j = rng.uniform(-1, 1, 2) if seed else np.zeros(2)
        parts.append(box((cx + j[0], cy + j[1], sz / 2), (sx, sy, sz), yaw=rng.uniform(-0.3, 0.3) if seed else 0.0))
    return parts


def _cliff(tunnel_width: float, height: float) -> list:
    """The cliff face around the portal: a rectangular opening of the tunnel's width and height."""
    cliff_h, half = 18.0, tunnel_width / 2
    return [
        box((-0.5, -(30 + half) / 2, cliff_h / 2), (1.0, 30 - half, cliff_h)),
        box((-0.5, (30 + half) / 2, cliff_h / 2), (1.0, 30 - half, cliff_h)),
        box((-0.5, 0, (height + cliff_h) / 2), (1.0, 2 * half, cliff_h - height)),
    ]


def _tunnel_and_quarry(
    rng: np.random.Generator, tunnel_length: float, tunnel_width: float, cavern_r: float, cavern_len: float
):
    """The horseshoe tunnel morphing over 6 m into the rough quarry cavern, closed at its end."""
    height, half = tunnel_width, tunnel_width / 2
    s = np.arange(0.0, tunnel_length + cavern_len + 1e-9, 1.0)
    angles = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rho_t, cz_t = polar_profile("horseshoe", angles, tunnel_width, height)
    u = np.clip((s - tunnel_length) / 6.0, 0, 1)  # 6 m transition
    bulge = np.sin(np.clip((s - tunnel_length) / cavern_len, 0, 1) * np.pi) ** 0.6
    radius = np.maximum(bulge * cavern_r, 0.15 * half)  # cavern cross-section radius
    rho = rho_t[None, :] * (1 - u[:, None]) + (u * radius)[:, None]
    cz = cz_t * (1 - u) + u * 0.35 * radius
    path = np.column_stack([s, 0 * s, 0 * s])
    noise = smooth_noise(rng, 0.9, wavelengths=(3.0, 10.0))
    tunnel_noise = lambda pts: noise(pts) * np.clip((pts[:, 0] - tunnel_length) / 6.0, 0.02, 1.0)  # noqa: E731
    return sweep(path, angles, rho, cz, noise=tunnel_noise, close_end=True)


def make_mine(seed: int = 0, tunnel_length: float = 100.0, tunnel_width: float = 4.5) -> Scene:
    """Yard on x < 0 with buildings and containers; a portal in a cliff face at x = 0; a
    horseshoe tunnel to x = tunnel_length; a noisy quarry cavern about 30 m across behind it."""
    rng = np.random.default_rng(seed + 3000)
    yard, half = 45.0, tunnel_width / 2
    cavern_r, cavern_len = 15.0, 34.0
    parts = _yard(rng, seed, yard) + _cliff(tunnel_width, tunnel_width)
    parts.append(_tunnel_and_quarry(rng, tunnel_length, tunnel_width, cavern_r, cavern_len))
    goal_x = tunnel_length + cavern_len * 0.6
    route = resample_polyline(np.array([[-38.0, 0.5, 0], [-16.0, 0.5, 0], [-4.0, 0, 0], [goal_x, 0, 0]]), 1.0)
    regions = {
        "yard": np.array([-yard, -30, 0.0, 30]),
        "tunnel": np.array([0.0, -half, tunnel_length, half]),
        "quarry": np.array([tunnel_length + 6, -cavern_r, tunnel_length + cavern_len, cavern_r]),
    }
    paths = [
        route,
        resample_polyline(np.array([[-30.0, -3, 0], [-30, 4, 0], [-10, 3, 0], [-10, -3, 0]]), 1.0),
        resample_polyline(np.array([[tunnel_length + 8, -6, 0], [tunnel_length + 20, 6, 0]]), 1.0),
    ]
    return Scene(
        name=f"mine-{seed}",
        mesh=merge(parts),
        sampling_paths=paths,
        start=np.array((route[0, 0], route[0, 1], 0.0)),
        goal=route[-1, :2],
        routes={"main": route},
        family="mine",
        seed=seed,
        regions=regions,
    )
