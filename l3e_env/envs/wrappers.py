"""Observation wrappers for learning libraries that expect flat vectors."""

from __future__ import annotations

from typing import Any, cast

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class FlatObservation(gym.ObservationWrapper):
    """The navigation environment's observation with its range image and validity mask flattened
    row by row into vectors (beams x width,), the other entries as they are. stable-baselines3's
    MultiInputPolicy takes it without the shape warnings that a 2-D non-image entry draws:

        env = FlatObservation(gym.make("l3e/Fork-v0"))
        model = PPO("MultiInputPolicy", env)
    """

    FLAT = ("ranges", "valid")

    def __init__(self, env: gym.Env):
        super().__init__(env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or any(k not in space.spaces for k in self.FLAT):
            raise ValueError(
                "FlatObservation wraps the navigation environment, whose observation is a Dict with "
                f"{' and '.join(self.FLAT)}"
            )
        flat: dict[str, spaces.Space] = {}
        for key, space_of in space.spaces.items():
            if key in self.FLAT:
                box = cast(spaces.Box, space_of)  # the navigation environment's arrays
                flat[key] = spaces.Box(box.low.reshape(-1), box.high.reshape(-1), (int(np.prod(box.shape)),), box.dtype)
            else:
                flat[key] = space_of
        self.observation_space = spaces.Dict(flat)

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        return {k: (np.asarray(v).reshape(-1) if k in self.FLAT else v) for k, v in observation.items()}
