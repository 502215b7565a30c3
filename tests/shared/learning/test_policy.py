"""Action selection: epsilon schedules, Ape-X per-actor epsilon, greedy and epsilon-greedy."""

import numpy as np
import pytest
import torch

from shared.config import ExploreConfig, ModelConfig, SensorConfig
from shared.learning.model import QNetwork, preprocess_depth
from shared.learning.policy import (
    EpsilonGreedyPolicy,
    EpsilonSchedule,
    PolicyError,
    apex_epsilon,
    greedy_action,
    linear_epsilon,
)

TINY = SensorConfig(width=40, height=30)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def net() -> QNetwork:
    torch.manual_seed(0)
    return QNetwork(ModelConfig(fc1=16, fc2=8, dropout=0.5), TINY)


def test_linear_schedule():
    cfg = ExploreConfig(eps_start=1.0, eps_end=0.1, eps_decay_steps=100)
    assert linear_epsilon(0, cfg) == 1.0
    assert linear_epsilon(50, cfg) == pytest.approx(0.55)
    assert linear_epsilon(100, cfg) == pytest.approx(0.1)
    assert linear_epsilon(10_000, cfg) == pytest.approx(0.1)
    assert linear_epsilon(0, ExploreConfig(eps_decay_steps=0, eps_end=0.2)) == 0.2
    with pytest.raises(PolicyError, match="step"):
        linear_epsilon(-1, cfg)


def test_apex_per_actor_epsilon():
    assert apex_epsilon(0, 8, 0.4, 7.0) == pytest.approx(0.4)
    assert apex_epsilon(7, 8, 0.4, 7.0) == pytest.approx(0.4 ** 8)
    assert apex_epsilon(3, 7, 0.4, 7.0) == pytest.approx(0.4 ** (1 + 7 * 3 / 6))
    assert apex_epsilon(0, 1, 0.3, 7.0) == 0.3
    with pytest.raises(PolicyError, match="actor_index"):
        apex_epsilon(8, 8)
    sched = EpsilonSchedule(ExploreConfig(per_actor=True), actor_index=2, num_actors=5)
    assert sched(0) == sched(10_000) == pytest.approx(0.4 ** (1 + 7 * 2 / 4))
    with pytest.raises(PolicyError):
        EpsilonSchedule(ExploreConfig(per_actor=True), actor_index=5, num_actors=5)


def test_greedy_returns_argmax_and_all_q_values_with_dropout_off():
    n = net()
    n.train()  # the policy must evaluate with dropout off anyway
    policy = EpsilonGreedyPolicy(n)
    depth = np.random.default_rng(0).random((30, 40)).astype(np.float32) * 4
    choice = policy.greedy(depth)
    with torch.no_grad():
        ref = n.eval()(preprocess_depth(depth))[0].numpy()
    np.testing.assert_array_equal(choice.q_values, ref)
    assert choice.action == int(np.argmax(ref)) and not choice.explored
    assert policy.act(depth, step=10**6).action == choice.action  # no schedule: greedy
    assert greedy_action(np.array([1.0, 3.0, 3.0, 0.0, 0.0])) == 1  # ties: lowest index
    with pytest.raises(PolicyError, match="shape"):
        greedy_action(np.zeros(4))


def test_epsilon_greedy_explores_uniformly_and_is_seeded():
    cfg = ExploreConfig(eps_start=1.0, eps_end=0.0, eps_decay_steps=1000)
    depth = np.ones((30, 40), dtype=np.float32)
    p1 = EpsilonGreedyPolicy(net(), EpsilonSchedule(cfg), seed=7)
    actions = np.array([p1.act(depth, step=0).action for _ in range(600)])
    assert np.all(np.abs(np.bincount(actions, minlength=5) / 600 - 0.2) < 0.06)
    p2 = EpsilonGreedyPolicy(net(), EpsilonSchedule(cfg), seed=7)
    assert [p2.act(depth, step=0).action for _ in range(600)] == actions.tolist()
    greedy = p1.greedy(depth).action
    late = [p1.act(depth, step=1000) for _ in range(20)]
    assert all(c.action == greedy and not c.explored and c.epsilon == 0.0 for c in late)
    mid = [p1.act(depth, step=500) for _ in range(600)]
    assert 0.4 < np.mean([c.explored for c in mid]) < 0.6


def test_guide_action_replaces_the_greedy_choice_not_the_random_one():
    half = EpsilonSchedule(ExploreConfig(eps_start=0.5, eps_end=0.5, eps_decay_steps=0))
    depth = np.ones((30, 40), dtype=np.float32)
    guided, plain = EpsilonGreedyPolicy(net(), half, seed=3), EpsilonGreedyPolicy(net(), half, seed=3)
    guide = (plain.greedy(depth).action + 1) % 5  # never the greedy action
    choices = [(guided.act(depth, guide_action=guide), plain.act(depth)) for _ in range(200)]
    assert 60 < sum(p.explored for _, p in choices) < 140
    for g, p in choices:
        assert g.explored == p.explored  # the same random stream with or without a guide
        assert g.action == (p.action if p.explored else guide)
    with pytest.raises(PolicyError, match="guide_action"):
        guided.act(depth, guide_action=5)


def test_the_policy_feeds_its_last_command_back_and_forgets_it_at_reset():
    torch.manual_seed(0)
    n = QNetwork(ModelConfig(fc1=16, fc2=8, previous_action=True), TINY)
    with torch.no_grad():  # the previous command's weight dominates: the policy repeats itself
        for layer in (n.fc1, n.fc2, n.fc3):
            layer.weight.zero_()
            layer.bias.zero_()
        n.fc3.bias.copy_(torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0]))  # straight without a previous command
        n.fc2.weight[:5, :5] = torch.eye(5)
        n.fc3.weight[:, :5] = 10 * torch.eye(5)
        n.previous_action_fc.weight[:5, :] = 10 * torch.eye(5)
    depth = np.zeros((30, 40), np.float32)
    policy = EpsilonGreedyPolicy(n, EpsilonSchedule(ExploreConfig(eps_start=1.0, eps_end=1.0)), seed=0)
    first = policy.act(depth)  # random: eps 1
    assert policy.previous_action == first.action
    policy.schedule = None
    assert [policy.act(depth).action for _ in range(3)] == [first.action] * 3  # repeats its last command
    policy.reset()
    assert policy.previous_action is None and policy.greedy(depth).action == 2


def test_a_frame_stack_policy_feeds_the_images_it_acted_on_and_forgets_them_at_reset():
    torch.manual_seed(0)
    n = QNetwork(ModelConfig(fc1=16, fc2=8, dropout=0.0, frame_stack=3), TINY)
    seen: list[np.ndarray] = []
    forward = n.forward

    def spy(x, previous_action=None, **kw):
        seen.append(x[:, :, 0, 0].numpy().copy() * 4.0)  # back to metres: one pixel per image
        return forward(x, previous_action, **kw)

    n.forward = spy
    policy = EpsilonGreedyPolicy(n, seed=0)
    frames = [np.full((30, 40), d, np.float32) for d in (1.0, 2.0, 3.0, 3.5)]
    for f in frames:
        policy.greedy(f)
    np.testing.assert_allclose(np.concatenate(seen), [[1, 1, 1], [2, 1, 1], [3, 2, 1], [3.5, 3, 2]])
    # q_values looks without remembering; reset starts the next episode from its own first image
    q = policy.q_values(frames[0])
    np.testing.assert_allclose(seen[-1], [[1, 3.5, 3]])
    np.testing.assert_allclose(policy.greedy(frames[0]).q_values, q)
    policy.reset()
    policy.greedy(frames[2])
    np.testing.assert_allclose(seen[-1], [[3, 3, 3]])
