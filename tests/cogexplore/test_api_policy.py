"""``cogexplore.load_policy`` and ``Policy``: the shipped model on depth images of any resolution,
checked against the project's own observation path (the env's camera and the evaluator's policy)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import cogexplore
from shared.config import SPEED_TABLES
from shared.evaluation.policies import GreedyPolicy
from shared.evaluation.protocol import protocol_env_config
from shared.evaluation.setup import setup_evaluation
from shared.learning.checkpoints import PRETRAINED_DIR
from shared.learning.policy import PolicyError
from shared.sim.env import ExploreEnv
from shared.sim.sensor import DepthCamera

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def policy() -> cogexplore.Policy:
    return cogexplore.load_policy("pretrained", device="cpu")


@pytest.fixture(scope="module")
def scenes(policy: cogexplore.Policy) -> list[dict[str, np.ndarray]]:
    """At every start pose of the policy's world: the env's own observation (40 x 30) and the same
    view rendered by the same camera model at other resolutions."""
    setup = setup_evaluation(None, model=policy.model)
    env = ExploreEnv(protocol_env_config(setup.env_cfg, setup.world, 200), policy.sensor)
    cameras = {size: DepthCamera(env.model, dataclasses.replace(policy.sensor, width=size[0], height=size[1]))
               for size in ((640, 480), (160, 120), (120, 90))}
    out = []
    try:
        for start in range(len(env.world.starts)):
            obs, _ = env.reset(seed=0, options={"start_index": start})
            out.append({"env": obs, **{size: cam.capture(env.data) for size, cam in cameras.items()}})
    finally:
        env.close()
    return out


def test_the_shipped_model_loads_with_its_camera_and_commands(policy: cogexplore.Policy) -> None:
    assert policy.model.path == PRETRAINED_DIR / "drl.safetensors"
    assert (policy.sensor.width, policy.sensor.height) == (40, 30) and policy.model.net.model_cfg.previous_action
    assert policy.command_names == cogexplore.COMMAND_NAMES == ("left", "half-left", "straight", "half-right", "right")
    angular, linear = SPEED_TABLES["test"]
    assert policy.twist(0) == cogexplore.Command(linear, angular[0]) and policy.twist(0).angular_rps > 0  # left
    assert policy.twist(2) == (0.25, 0.0) and policy.twist(4, "train") == (0.32, -1.4)
    assert policy.control_period_s > 0 and "drl@" in repr(policy)


def test_act_at_any_resolution_gives_the_command_of_the_env_observation(
        policy: cogexplore.Policy, scenes: list[dict[str, np.ndarray]]) -> None:
    reference = GreedyPolicy(policy.model.net)  # what `cogexplore evaluate` runs on the env's images
    for i, scene in enumerate(scenes):
        obs = scene["env"]
        reference.reset()
        want, want_q = reference(obs)
        # The env's image at the network's size is taken as it is.
        np.testing.assert_array_equal(policy.observation(obs), obs)
        # An odd multiple (3x) puts a source pixel centre on every network pixel centre: exact.
        np.testing.assert_allclose(policy.observation(scene[(120, 90)]), obs, atol=1e-6)
        for size in ((640, 480), (160, 120)):
            seen = policy.observation(scene[size])
            close = np.isclose(seen, obs, rtol=1e-4, atol=1e-4)
            # Only pixels whose centre lies on an edge (a 1-in-16 chance for each edge at 640 x 480,
            # 1 in 4 at 160 x 120) or at the range limit may take the other side; the rest is exact.
            assert close.mean() >= (0.96 if size == (640, 480) else 0.85), (i, size, close.mean())
        for image in (obs, scene[(640, 480)], scene[(120, 90)]):
            policy.reset()
            q = policy.q_values(image)
            assert policy.act(image) == want, (i, image.shape)
            np.testing.assert_allclose(q, want_q, atol=0.05 * np.abs(want_q).max())
    assert len({int(np.argmax(GreedyPolicy(policy.model.net)(s["env"])[1])) for s in scenes}) >= 3  # not constant


def test_no_return_nan_inf_and_beyond_range_read_alike(policy: cogexplore.Policy,
                                                     scenes: list[dict[str, np.ndarray]]) -> None:
    image = scenes[0][(640, 480)].copy()
    missing = image == 0
    assert missing.any()
    for fill in (np.nan, np.inf, 9.0):  # beyond the camera's 4 m: the simulated camera reports no return
        other = np.where(missing, fill, image)
        np.testing.assert_array_equal(policy.observation(other), policy.observation(image))
        policy.reset()
        q = policy.q_values(other)
        policy.reset()
        np.testing.assert_array_equal(q, policy.q_values(image))
    millimetres = np.rint(image * 1000).astype(np.uint16)
    np.testing.assert_allclose(policy.observation(millimetres), policy.observation(image), atol=6e-4)
    assert policy.observation(image[..., None]).shape == (30, 40)


def test_millimetres_in_a_float_image_are_refused_not_read_as_no_return(policy: cogexplore.Policy,
                                                                       scenes: list[dict[str, np.ndarray]]) -> None:
    # Every pixel read as beyond the range: the network chose its blind command whatever the scene.
    image = scenes[0][(640, 480)]
    with pytest.raises(PolicyError, match=r"typical depth is \d+ m: millimetres in a float image\?"):
        policy.act((image * 1000).astype(np.float32))
    far = image.copy()  # metres beyond the camera on some pixels are no return, as before
    far[: far.shape[0] // 8] = 150.0
    np.testing.assert_array_equal(policy.observation(far), policy.observation(np.where(far > 100, 0.0, far)))


def test_the_previous_command_is_remembered_until_reset(policy: cogexplore.Policy,
                                                        scenes: list[dict[str, np.ndarray]]) -> None:
    image = scenes[3]["env"]
    policy.reset()
    assert policy.previous_command is None
    fresh = policy.q_values(image)
    assert policy.previous_command is None  # q_values changes nothing
    first = policy.act(image)
    assert policy.previous_command == first
    after = policy.q_values(image)
    assert not np.allclose(after, fresh)  # the network reads the previous command
    reference = GreedyPolicy(policy.model.net)
    reference(image)
    np.testing.assert_allclose(after, reference(image)[1], rtol=1e-6)
    policy.reset()
    assert policy.previous_command is None
    np.testing.assert_array_equal(policy.q_values(image), fresh)
    assert policy(image) == first  # a Policy is a callable depth -> command


@pytest.mark.parametrize(("depth", "message"), [
    (np.zeros((0, 0)), "empty"),
    (np.zeros((30, 0)), "empty"),
    (np.ones(40), r"one \(H, W\) depth image, got shape \(40,\)"),
    (np.ones((2, 30, 40)), r"got shape \(2, 30, 40\)"),
    (np.ones((480, 848)), "848 x 480 pixels; the network's camera is 40 x 30"),
    (np.ones((30, 40), dtype=np.int64), "float metres"),
    (-np.ones((30, 40)), "negative"),
    (np.where(np.arange(40) == 3, -np.inf, np.ones((30, 40))), "too near to measure.*stop the robot"),
    ([[1.0, 2.0], [3.0]], "array of depths"),
])
def test_bad_images_are_clear_errors(policy: cogexplore.Policy, depth, message: str) -> None:
    for call in (policy.act, policy.q_values, policy.observation):
        with pytest.raises(PolicyError, match=message):
            call(depth)
    assert issubclass(PolicyError, cogexplore.CogexploreError)


def test_bad_sources_and_commands_are_clear_errors(policy: cogexplore.Policy, tmp_path) -> None:
    with pytest.raises(cogexplore.CogexploreError, match="does not exist"):
        cogexplore.load_policy(tmp_path / "nothing-here")
    with pytest.raises(cogexplore.CogexploreError, match="unknown shipped model"):
        cogexplore.load_policy("pretrained:big")
    with pytest.raises(PolicyError, match="source must be"):
        cogexplore.load_policy(3)
    for command, message in ((5, "index in 0..4"), (True, "index in 0..4"), (1.0, "index in 0..4")):
        with pytest.raises(PolicyError, match=message):
            policy.twist(command)
    with pytest.raises(PolicyError, match="unknown speed table"):
        policy.twist(0, "fast")
    with pytest.raises(PolicyError, match="unknown speed table"):
        policy.twist(0, [])
    for device, message in ((None, "device must be"), ("meta", "runs on 'cpu' or 'cuda'"),
                            ("mps", "runs on 'cpu' or 'cuda'"), ("cuda:7", "CUDA")):
        with pytest.raises(cogexplore.CogexploreError, match=message):
            cogexplore.load_policy("pretrained", device=device)


def test_tensors_and_big_endian_millimetres_are_images_too(policy: cogexplore.Policy, scenes) -> None:
    import torch

    image = scenes[0][(160, 120)]
    want = policy.observation(image)
    np.testing.assert_array_equal(policy.observation(torch.tensor(image, requires_grad=True)), want)
    millimetres = np.round(image * 1000).astype(np.uint16)
    np.testing.assert_array_equal(policy.observation(millimetres.astype(">u2")), policy.observation(millimetres))


def test_masked_pixels_are_no_return(policy: cogexplore.Policy, scenes) -> None:
    # np.asarray drops a masked array's mask: the invalid pixels a driver masked were read as the depths
    # left under the mask (here 0.3 m: a wall in front of the robot).
    image = scenes[0][(160, 120)]
    invalid = np.zeros(image.shape, bool)
    invalid[:, 40:120] = True
    want = policy.observation(np.where(invalid, np.nan, image))
    assert not np.array_equal(want, policy.observation(np.where(invalid, 0.3, image)))
    np.testing.assert_array_equal(policy.observation(np.ma.masked_array(np.where(invalid, 0.3, image), invalid)), want)
    millimetres = np.ma.masked_array(np.round(np.where(invalid, 0.3, image) * 1000).astype(np.uint16), invalid)
    np.testing.assert_array_equal(policy.observation(millimetres),
                                  policy.observation(np.where(invalid, 0, millimetres.data).astype(np.uint16)))

def test_weights_that_give_nan_are_refused_not_driven_as_command_0(tmp_path) -> None:
    # Finite weights so large that fc3 overflows: argmax of the non-finite Q-values is command 0, a
    # full-speed turn.
    import torch

    from shared.config import ModelConfig, SensorConfig
    from shared.learning.checkpoints import export_weights
    from shared.learning.model import QNetwork

    net = QNetwork(ModelConfig(fc1=16, fc2=8), SensorConfig(width=40, height=30))
    with torch.no_grad():
        params = dict(net.named_parameters())
        params["fc2.weight"].zero_()
        params["fc2.bias"].fill_(1.0)  # every fc2 unit 1, whatever the image: fc3's row 0 sums past float32
        params["fc3.weight"][0].fill_(3e38)
        params["fc3.bias"][0] = 3e38
    export_weights(tmp_path / "huge.safetensors", net, 7)
    broken = cogexplore.load_policy(tmp_path / "huge.safetensors", device="cpu")
    image = np.full((30, 40), 2.0, np.float32)
    for call in (broken.act, broken.q_values):
        with pytest.raises(PolicyError, match="not finite"):
            call(image)
    assert broken.previous_command is None  # the overflow's argmax is not remembered


def test_a_weights_file_holding_nan_is_refused_when_it_loads(tmp_path) -> None:
    # The digest only proves the bytes are the writer's: a file written with a NaN weight (by hand, or an
    # older cogexplore) is refused with one line at load_policy, not played by `cogexplore evaluate`.
    import torch

    from shared.config import ModelConfig, SensorConfig
    from shared.learning.checkpoints import CheckpointError, export_weights, load_tensors_file, save_tensors_file
    from shared.learning.model import QNetwork

    net = QNetwork(ModelConfig(fc1=16, fc2=8), SensorConfig(width=40, height=30))
    good = export_weights(tmp_path / "good.safetensors", net, 7)
    tensors, meta = load_tensors_file(good, "cogexplore-weights")
    for value in (float("nan"), float("inf")):
        tensors["fc3.bias"][0] = value
        save_tensors_file(tmp_path / "nan.safetensors", tensors, {k: v for k, v in meta.items() if k != "digest"})
        with pytest.raises(cogexplore.CogexploreError, match="fc3.bias holds NaN or infinite values"):
            cogexplore.load_policy(tmp_path / "nan.safetensors", device="cpu")
    with torch.no_grad():
        dict(net.named_parameters())["fc3.bias"][0] = float("nan")
    with pytest.raises(CheckpointError, match="not written: weight fc3.bias is not finite"):
        export_weights(tmp_path / "diverged.safetensors", net)
    assert not (tmp_path / "diverged.safetensors").exists()
