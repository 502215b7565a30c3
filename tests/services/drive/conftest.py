"""The drive tests' shipped policy and its camera's image from paper-indoor's first start."""

import pytest

from cogexplore import load_policy
from shared.sim.env import ExploreEnv


@pytest.fixture(scope="module")
def policy():
    return load_policy("pretrained", device="cpu")


@pytest.fixture(scope="module")
def start_image(policy):
    """The network's own camera image from paper-indoor's first start (nearest obstacle > 0.55 m)."""
    env = ExploreEnv(world="paper-indoor", speed_table="test", start_index=0, sensor=policy.sensor)
    depth, info = env.reset(seed=0)
    env.close()
    assert info["min_depth_m"] > 0.6
    return depth
