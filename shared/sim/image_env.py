"""``cogexplore/ExploreImage-v0``: the exploration task with a uint8 image observation, the
form Stable-Baselines3's ``CnnPolicy`` (and most Atari-style pixel agents) take as is.

The observation is ``Box(0, 255, (1, H, W), uint8)``, channel-first, so SB3's
``is_image_space`` accepts it and its policies divide by 255. Depth is encoded as the project's
network sees it with ``ModelConfig.depth_encoding = 'inverse'`` (``shared.learning.model``):
``0.5 m / depth`` capped at 1, so near obstacles are bright (255 at 0.5 m and nearer), a return at
4 m is 32 and no return is 0.

SB3's ``NatureCNN`` (8x8 stride 4, 4x4 stride 2, 3x3 stride 1) needs images of at least 36 x 36
pixels: the default sensor (160 x 120) fits, the ``tiny`` and ``smoke`` presets' 40 x 30 does not.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from shared.learning.model import encode_depth, preprocess_depth
from shared.sim.env import ExploreEnv

IMAGE_DEPTH_ENCODING = "inverse"


class DepthImageObservation(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """An :class:`ExploreEnv`'s (H, W) depth in metres as a (1, H, W) uint8 image, near bright."""

    def __init__(self, env: gym.Env):
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.ObservationWrapper.__init__(self, env)
        height, width = env.observation_space.shape
        self.observation_space = gym.spaces.Box(0, 255, (1, height, width), np.uint8)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        encoded = encode_depth(preprocess_depth(observation), IMAGE_DEPTH_ENCODING)[0].numpy()
        return np.rint(encoded * 255).astype(np.uint8, order="C")


def make_image_env(**kwargs: Any) -> DepthImageObservation:
    """The entry point of ``cogexplore/ExploreImage-v0``: ``ExploreEnv(**kwargs)`` (its config,
    sensor, render mode and field overrides) with :class:`DepthImageObservation`."""
    return DepthImageObservation(ExploreEnv(**kwargs))
