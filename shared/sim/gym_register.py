"""The Gymnasium ids of the exploration task, registered on import of this module (or of
``shared.sim.env``). Light: the entry points are strings, so nothing heavy loads until ``make``.

    cogexplore/Explore-v0       (H, W) float32 depth in metres (``shared.sim.env.ExploreEnv``)
    cogexplore/ExploreImage-v0  (1, H, W) uint8, near bright: SB3's ``CnnPolicy`` takes it as is
                                (``shared.sim.image_env``)

Gymnasium 1.x has no plugin discovery (v1.0 removed the ``gymnasium.envs`` entry-point group),
so a fresh interpreter names this module in the id or imports it first::

    gym.make("shared.sim.gym_register:cogexplore/Explore-v0")
    import shared.sim.gym_register; gym.make("cogexplore/Explore-v0")
"""

from __future__ import annotations

import gymnasium as gym

from shared.evaluation import PAPER_MAX_STEPS

ENV_ID = "cogexplore/Explore-v0"
IMAGE_ENV_ID = "cogexplore/ExploreImage-v0"
ENTRY_POINTS = {
    ENV_ID: "shared.sim.env:ExploreEnv",
    IMAGE_ENV_ID: "shared.sim.image_env:make_image_env",
}


def register_envs() -> None:
    """Register both ids (idempotent). Their ``TimeLimit`` is the paper's test cap,
    ``PAPER_MAX_STEPS`` (200); ``EnvConfig.max_episode_steps`` (500 by default) is the env's own
    cap, so under ``gym.make`` the earlier of the two truncates, both as ``truncated`` (never
    ``terminated``). An episode longer than 500 steps needs both raised:
    ``gym.make(id, max_episode_steps=n, config=EnvConfig(max_episode_steps=n))``."""
    for env_id, entry_point in ENTRY_POINTS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, max_episode_steps=PAPER_MAX_STEPS)


register_envs()
