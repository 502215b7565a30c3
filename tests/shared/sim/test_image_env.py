"""cogexplore/ExploreImage-v0: a uint8 image Stable-Baselines3's CnnPolicy takes, and trains on."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from shared.learning.model import INVERSE_DEPTH_NEAR_M
from shared.sim.gym_register import IMAGE_ENV_ID
from shared.sim.image_env import DepthImageObservation
from shared.sim.world import SceneBuilder, StartPose

SMALL_SENSOR = {"width": 48, "height": 36}  # NatureCNN's smallest image is 36 x 36


def _wall_ahead(distance_m: float):
    """A tall wall ``distance_m`` ahead of the start's camera, across the whole view."""
    b = SceneBuilder("wall", (-1.0, -4.0, 8.0, 4.0))
    b.wall(distance_m + 0.05, -4.0, distance_m + 0.05, 4.0, thickness=0.1, height=3.0)
    return b.build("wall", [StartPose(0.0, 0.0, 0.0)])


def test_the_observation_is_an_sb3_image():
    from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first

    env = gym.make(IMAGE_ENV_ID, world="box-room")
    space = env.observation_space
    assert space == gym.spaces.Box(0, 255, (1, 120, 160), np.uint8)
    assert is_image_space(space, check_channels=True) and is_image_space_channels_first(space)
    obs, _ = env.reset(seed=0)
    assert obs in space and obs.flags.c_contiguous
    obs, *_ = env.step(2)
    assert obs in space
    env.close()


@pytest.mark.parametrize("distance_m, value", [
    (INVERSE_DEPTH_NEAR_M * 0.8, 255),  # nearer than the encoding's 0.5 m: saturated
    (1.0, round(255 * INVERSE_DEPTH_NEAR_M / 1.0)),
    (2.0, round(255 * INVERSE_DEPTH_NEAR_M / 2.0)),
])
def test_near_is_bright_as_in_the_inverse_depth_encoding(distance_m, value):
    # a collision distance below the nearest wall's: a start that sees a collision is refused
    env = DepthImageObservation(gym.make("cogexplore/Explore-v0", world=_wall_ahead(distance_m), start_index=0,
                                         collision_distance_m=0.3, sensor={"width": 40, "height": 30}).unwrapped)
    obs, _ = env.reset(seed=0)
    assert obs[0, 15, 20] == pytest.approx(value, abs=1)  # the centre pixel looks straight at the wall
    env.close()


def test_no_return_is_dark():
    b = SceneBuilder("empty", (-1.0, -1.0, 1.0, 1.0))
    env = DepthImageObservation(gym.make("cogexplore/Explore-v0", world=b.build("empty", [StartPose(0, 0, 0)]),
                                         sensor={"width": 40, "height": 30}).unwrapped)
    obs, _ = env.reset(seed=0)
    assert obs[0, :10].max() == 0  # above the horizon: nothing within range
    assert obs[0, -1].min() > 0  # the floor just ahead
    env.close()


def test_sb3_dqn_cnn_policy_trains_on_it(one_torch_thread):
    from stable_baselines3 import DQN
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(IMAGE_ENV_ID, n_envs=1, seed=0, env_kwargs={"world": "box-room", "sensor": SMALL_SENSOR})
    model = DQN("CnnPolicy", venv, learning_starts=50, buffer_size=500, batch_size=16, train_freq=4,
                target_update_interval=100, learning_rate=1e-3, seed=0, device="cpu",
                policy_kwargs={"features_extractor_kwargs": {"features_dim": 64}})
    batch = model.q_net.obs_to_tensor(venv.reset())[0]
    assert venv.get_images()[0].shape[2] == 3  # make_vec_env asks for rgb_array first; it gets it
    with torch.no_grad():
        q_before = model.q_net(batch).clone()
    target_before = [p.detach().clone() for p in model.q_net_target.parameters()]
    model.learn(total_timesteps=300)
    assert model.num_timesteps == 300
    logged = model.logger.name_to_value
    assert logged["train/n_updates"] >= (300 - 50) // 4 and np.isfinite(logged["train/loss"])
    # every step not a collision pays +1: the Q-values climb from their initial ~0
    with torch.no_grad():
        q_after = model.q_net(batch)
    assert q_after.mean() > q_before.mean() + 0.5
    # the target network was synced (every 100 steps)
    assert any(not torch.equal(a, b) for a, b in zip(target_before, model.q_net_target.parameters()))
    venv.close()
