"""DQN update: hand-computed TD targets, the Caffe lr mapping, target sync, learning rates, updates."""

import numpy as np
import pytest
import torch

from shared.config import (
    MAX_ACTION_HISTORY,
    ConfigError,
    DQNConfig,
    ModelConfig,
    ReplayConfig,
    SensorConfig,
    load_preset,
)
from shared.learning.dqn import (
    DQNAgent,
    DQNError,
    caffe_lr_to_torch,
    lr_factor,
    mirror_batch,
    n_step_returns,
    td_targets,
    update_flops,
)
from shared.learning.model import QNetwork, forward_flops, shift_images
from shared.learning.replay import Batch, ReplayMemory

TINY = SensorConfig(width=40, height=30)
SMALL = ModelConfig(fc1=32, fc2=16, dropout=0.0)
G = 0.85


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def make_batch(b: int = 8, seed: int = 0, terminated=None, n: int = 1) -> Batch:
    rng = np.random.default_rng(seed)
    return Batch(
        obs=rng.integers(300, 4000, (b, 30, 40)).astype(np.uint16),
        action=rng.integers(0, 5, b).astype(np.int64),
        rewards=np.where(rng.random((b, n)) < 0.2, -100.0, 1.0).astype(np.float32),
        n_steps=np.full(b, n, dtype=np.int64),
        terminated=np.zeros(b, bool) if terminated is None else np.asarray(terminated),
        next_obs=rng.integers(300, 4000, (b, 30, 40)).astype(np.uint16),
        previous_action=rng.integers(-1, 5, (b, MAX_ACTION_HISTORY)).astype(np.int64),
        next_previous_action=rng.integers(0, 5, (b, MAX_ACTION_HISTORY)).astype(np.int64),
        weights=np.ones(b, np.float32),
        indices=np.arange(b),
    )


def test_td_targets_hand_computed_terminal_truncated_normal_and_n_step():
    # rows: normal 1-step, collision, truncated (bootstraps like normal), 3-step, 2-step collision
    rewards = torch.tensor([[1, 0, 0], [-100, 0, 0], [1, 0, 0], [1, 1, 1], [1, -100, 0]], dtype=torch.float32)
    n_steps = torch.tensor([1, 1, 1, 3, 2])
    terminated = torch.tensor([False, True, False, False, True])
    next_q = torch.tensor([[0, 2, 1, 0, 0], [50, 50, 50, 50, 50], [3, 0, 0, 0, 0],
                           [0, 0, 0, 0, 4], [9, 9, 9, 9, 9]], dtype=torch.float32)
    y = td_targets(rewards, n_steps, terminated, next_q, G)
    expected = [1 + G * 2, -100, 1 + G * 3, 1 + G + G ** 2 + G ** 3 * 4, 1 + G * -100]
    np.testing.assert_allclose(y.numpy(), expected, rtol=1e-6)
    # Double DQN: argmax from the online net, value from the target net
    online = torch.tensor([[0, 0, 5, 0, 0]] * 5, dtype=torch.float32)
    y2 = td_targets(rewards, n_steps, terminated, next_q, G, next_q_online=online)
    expected2 = [1 + G * 1, -100, 1 + 0, 1 + G + G ** 2 + 0, 1 + G * -100]
    np.testing.assert_allclose(y2.numpy(), expected2, rtol=1e-6)
    # NaN next values of a collision row never leak into its target
    next_q[1] = float("nan")
    assert td_targets(rewards, n_steps, terminated, next_q, G)[1] == -100
    np.testing.assert_allclose(n_step_returns(rewards, n_steps, G).numpy()[3], 1 + G + G ** 2)


def test_caffe_euclidean_gradient_is_half_of_our_mean_squared_error():
    """The documented lr mapping: Caffe 1e-7 == ours 5e-8, checked on real gradients."""
    assert caffe_lr_to_torch(1e-7) == pytest.approx(5e-8)
    torch.manual_seed(0)
    q = torch.randn(4, 5, requires_grad=True)
    a = torch.tensor([0, 3, 1, 4])
    y = torch.randn(4) * 10
    # Caffe DQN: EuclideanLoss over the whole (N, 5) blob, target = own output except taken action
    target_blob = q.detach().clone()
    target_blob[torch.arange(4), a] = y
    caffe = ((q - target_blob) ** 2).sum() / (2 * 4)
    (g_caffe,) = torch.autograd.grad(caffe, q)
    ours = torch.nn.functional.mse_loss(q.gather(1, a[:, None]).squeeze(1), y)
    (g_ours,) = torch.autograd.grad(ours, q)
    torch.testing.assert_close(g_ours * 0.5, g_caffe)


def test_update_uses_target_net_and_syncs_every_c_updates():
    cfg = DQNConfig(target_sync_every=3, optimizer="adam", lr=1e-3)
    agent = DQNAgent(SMALL, TINY, cfg, device="cpu", seed=0)
    target_before = {k: v.clone() for k, v in agent.target.state_dict().items()}
    batch = make_batch()
    for i in range(2):
        m = agent.update(batch)
        assert not m["synced_target"]
    assert all(torch.equal(v, agent.target.state_dict()[k]) for k, v in target_before.items())
    assert not torch.equal(agent.online.fc1.weight, agent.target.fc1.weight)
    m = agent.update(batch)
    assert m["synced_target"] and m["update"] == 3 and m["policy_version"] == 3
    for k, v in agent.online.state_dict().items():
        assert torch.equal(v, agent.target.state_dict()[k])
    assert not agent.target.training and not any(p.requires_grad for p in agent.target.parameters())


def test_update_targets_match_hand_formula_with_the_target_network():
    agent = DQNAgent(SMALL, TINY, DQNConfig(), device="cpu", seed=1)
    batch = make_batch(terminated=[True, False, False, False, False, False, False, False])
    tb = agent.to_tensors(batch)
    with torch.no_grad():
        next_q = agent.target(tb.next_obs)
    y = agent.compute_targets(tb)
    assert y[0] == batch.rewards[0, 0]
    torch.testing.assert_close(y[1:], tb.rewards[1:, 0] + G * next_q[1:].max(1).values)
    # garbage next frames of collision rows do not change their targets
    batch.next_obs[0] = 123
    assert agent.compute_targets(agent.to_tensors(batch))[0] == y[0]


def test_repeated_updates_fit_a_fixed_batch():
    agent = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", lr=1e-2, double_dqn=True,
                                            target_sync_every=10_000), device="cpu", seed=0)
    batch = make_batch(16, terminated=np.arange(16) % 4 == 0)
    first = agent.update(batch)["td_abs_mean"]
    for _ in range(80):
        last = agent.update(batch)
    assert last["td_abs_mean"] < 0.5 * first
    assert last["td_errors"].shape == (16,)


def test_mirror_batch_flips_frames_and_swaps_commands_only_where_asked():
    agent = DQNAgent(SMALL, TINY, DQNConfig(), device="cpu", seed=0)
    tb = agent.to_tensors(make_batch(6, terminated=[True, False] * 3))
    flip = torch.tensor([True, False, True, False, True, False])
    m = mirror_batch(tb, flip)
    for i in range(6):
        want = (lambda x: x.flip(-1)) if flip[i] else (lambda x: x)
        assert torch.equal(m.obs[i], want(tb.obs[i])) and torch.equal(m.next_obs[i], want(tb.next_obs[i]))
        assert m.action[i] == (4 - tb.action[i] if flip[i] else tb.action[i])
        for name in ("previous_action", "next_previous_action"):  # -1 (none) stays none
            before, after = getattr(tb, name)[i], getattr(m, name)[i]  # each command of the history
            assert torch.equal(after, torch.where(flip[i] & (before >= 0), 4 - before, before))
    assert torch.equal(m.rewards, tb.rewards) and torch.equal(m.terminated, tb.terminated)
    assert m.obs.is_contiguous(memory_format=torch.channels_last)


def test_mirror_augment_teaches_the_mirror_image_of_each_transition():
    """'left' always collides in the data; only the mirrored agent learns that 'right' in the
    mirror-image scenes collides too."""
    batch = make_batch(16, seed=4, terminated=np.ones(16, bool))
    batch.action[:] = 0
    batch.rewards[:] = -100.0
    mirrored_obs = torch.from_numpy(batch.obs[:, :, ::-1].copy())
    q_right = {}
    for mirror in (False, True):
        agent = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", lr=1e-2, mirror_augment=mirror), device="cpu",
                         seed=0)
        for _ in range(60):
            agent.update(batch)
        q_right[mirror] = float(agent.q_values(mirrored_obs)[:, 4].mean())
    assert q_right[True] < -50 and q_right[True] < q_right[False] - 30, q_right


def test_shift_images_moves_each_frame_by_its_own_draw_and_repeats_the_edges():
    x = torch.arange(2 * 5 * 6, dtype=torch.float32).reshape(2, 1, 5, 6)
    shift = torch.tensor([[0, 2], [-1, 0]])  # frame 0: two columns left; frame 1: one row down
    out = shift_images(x, shift)
    assert out.shape == x.shape and out.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(out[0, 0, :, :4], x[0, 0, :, 2:])  # pixel (i, j) from (i, j + 2)
    assert torch.equal(out[0, 0, :, 4], x[0, 0, :, 5]) and torch.equal(out[0, 0, :, 5], x[0, 0, :, 5])
    assert torch.equal(out[1, 0, 1:], x[1, 0, :4]) and torch.equal(out[1, 0, 0], x[1, 0, 0])
    assert torch.equal(shift_images(x, torch.zeros(2, 2, dtype=torch.int64)), x)


def test_shift_augment_draws_within_its_bound_and_the_targets_read_the_shifted_next_frame():
    assert DQNAgent(SMALL, TINY, DQNConfig(), device="cpu", seed=0).draw_augmentation(make_batch()) is None
    mirror_only = DQNAgent(SMALL, TINY, DQNConfig(mirror_augment=True), device="cpu", seed=0)
    assert mirror_only.draw_augmentation(make_batch()).obs_shift is None
    agent = DQNAgent(SMALL, TINY, DQNConfig(double_dqn=True, shift_augment_px=2), device="cpu", seed=0)
    batch = make_batch(64, seed=5)
    aug = agent.draw_augmentation(batch)
    assert aug.flip is None and aug.obs_shift.shape == aug.next_obs_shift.shape == (64, 2)
    for shift in (aug.obs_shift, aug.next_obs_shift):
        assert set(shift.unique().tolist()) == {-2, -1, 0, 1, 2}
    assert not torch.equal(aug.obs_shift, aug.next_obs_shift)  # each frame its own draw
    prepared = agent.prepare(batch, aug)
    plain = agent.to_tensors(batch)
    assert torch.equal(prepared.tb.obs, shift_images(plain.obs, aug.obs_shift))
    assert torch.equal(prepared.tb.next_obs, shift_images(plain.next_obs, aug.next_obs_shift))
    assert torch.equal(prepared.y, agent.compute_targets(prepared.tb))
    assert not torch.equal(prepared.y, agent.compute_targets(plain))
    for bad in (-1, 9, 1.5, True):
        with pytest.raises(ConfigError, match="shift_augment_px"):
            DQNConfig(shift_augment_px=bad)


def test_mse_weighs_a_rare_collision_and_huber_ignores_it():
    """One scene: 'left' always earns +1; 'half-left' earns +2 but collides (-100) one time in
    five. The mean return (-18.4) says avoid it, which MSE learns; Huber with the rewards
    unclipped learns a median-like +1.75 and prefers the risky command."""
    batch = make_batch(20, seed=5, terminated=np.ones(20, bool))
    batch.obs[:] = batch.obs[0]
    batch.action[:] = [0] * 10 + [1] * 10
    batch.rewards[:, 0] = [1.0] * 10 + [2.0] * 8 + [-100.0] * 2
    q = {}
    for loss in ("mse", "huber"):
        agent = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", lr=1e-2, loss=loss), device="cpu", seed=0)
        for _ in range(60):
            agent.update(batch)
        q[loss] = agent.q_values(torch.from_numpy(batch.obs[:1].copy()))[0, :2].tolist()
    assert q["mse"][1] < q["mse"][0] - 10 and q["mse"][1] == pytest.approx(-18.4, abs=3), q
    assert q["huber"][1] > q["huber"][0] and q["huber"][1] == pytest.approx(1.75, abs=0.5), q


def test_conv_layers_learn_slower_and_can_be_frozen():
    agent = DQNAgent(SMALL, TINY, DQNConfig(lr=1e-3, conv_lr_scale=0.1), device="cpu", seed=0)
    lrs = {g["name"]: g["lr"] for g in agent.optimizer.param_groups}
    assert lrs == {"fc": pytest.approx(1e-3), "conv": pytest.approx(1e-4)}
    frozen = DQNAgent(SMALL, TINY, DQNConfig(lr=1e-3, conv_lr_scale=0.0), device="cpu", seed=0)
    conv_before = frozen.online.trunk.conv2.weight.clone()
    fc_before = frozen.online.fc1.weight.clone()
    frozen.update(make_batch())
    assert torch.equal(frozen.online.trunk.conv2.weight, conv_before)
    assert not torch.equal(frozen.online.fc1.weight, fc_before)


def test_learning_rates_fall_linearly_to_the_final_scale_and_resume_on_schedule():
    assert [lr_factor(u, 100, 0.1) for u in (0, 50, 100, 500)] == pytest.approx([1.0, 0.55, 0.1, 0.1])
    assert lr_factor(10**6, 0, 0.1) == 1.0  # off: the paper's constant rate
    cfg = DQNConfig(optimizer="adam", lr=1e-3, conv_lr_scale=0.5, lr_decay_updates=4, lr_final_scale=0.25)
    agent = DQNAgent(SMALL, TINY, cfg, device="cpu", seed=0)
    seen = []
    for _ in range(6):
        agent.update(make_batch())
        seen.append({g["name"]: g["lr"] for g in agent.optimizer.param_groups})
        assert agent.lr == seen[-1]["fc"]  # what stats/learner.csv logs
    # the step that makes update u+1 runs at lr_factor(u)
    for u, lrs in enumerate(seen):
        f = lr_factor(u, 4, 0.25)
        assert lrs == {"fc": pytest.approx(1e-3 * f), "conv": pytest.approx(5e-4 * f)}, u
    # a resumed agent carries on from its update count, whatever lr its saved optimizer holds
    tensors, meta = agent.state_tensors()
    resumed = DQNAgent(SMALL, TINY, cfg, device="cpu", seed=1)
    resumed.load_state_tensors(tensors, meta)
    resumed.update(make_batch())
    assert {g["name"]: g["lr"] for g in resumed.optimizer.param_groups} == {
        "fc": pytest.approx(2.5e-4), "conv": pytest.approx(1.25e-4)}
    with pytest.raises(ValueError, match="lr_final_scale"):
        DQNConfig(lr_final_scale=0.0)
    with pytest.raises(ValueError, match="lr_decay_updates"):
        DQNConfig(lr_decay_updates=-1)

def test_a_resumed_agent_trains_at_its_own_configs_rate_not_the_files():
    """`--set dqn.lr=...` on a resume (after a divergence, say) is what config.toml then says: the
    checkpoint's optimiser state loads, its hyper-parameters give way to the agent's config."""
    saved = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", lr=1e-3, conv_lr_scale=0.5), device="cpu", seed=0)
    saved.update(make_batch())
    tensors, meta = saved.state_tensors()
    lowered = DQNConfig(optimizer="adam", lr=1e-5, conv_lr_scale=0.5)
    resumed = DQNAgent(SMALL, TINY, lowered, device="cpu", seed=1)
    resumed.load_state_tensors(tensors, meta)
    assert {g["name"]: g["lr"] for g in resumed.optimizer.param_groups} == {
        "fc": pytest.approx(1e-5), "conv": pytest.approx(5e-6)}
    assert resumed.update_count == 1 and resumed.optimizer.state  # the moments came with it
    # with a schedule, the rate is the schedule's at the resumed update before the first step
    decaying = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", lr=1e-3, conv_lr_scale=0.5, lr_decay_updates=2,
                                               lr_final_scale=0.5), device="cpu", seed=1)
    decaying.load_state_tensors(tensors, meta)
    assert decaying.lr == pytest.approx(1e-3 * lr_factor(1, 2, 0.5))


def test_importance_weights_scale_each_sample():
    a = DQNAgent(SMALL, TINY, DQNConfig(lr=1e-3), device="cpu", seed=0)
    b = DQNAgent(SMALL, TINY, DQNConfig(lr=1e-3), device="cpu", seed=0)
    before = a.online.fc3.weight.clone()
    batch = make_batch(4)
    zero_w = Batch(**{**batch.__dict__, "weights": np.array([1, 0, 0, 0], np.float32)})
    only_first = Batch(**{k: (v[:1] if isinstance(v, np.ndarray) else v) for k, v in batch.__dict__.items()})
    ma = a.update(zero_w)
    mb = b.update(only_first)
    # the zero-weight samples add nothing: a quarter of the one-sample loss and SGD step
    assert ma["loss"] == pytest.approx(mb["loss"] / 4, rel=1e-5)
    torch.testing.assert_close((a.online.fc3.weight - before) * 4, b.online.fc3.weight - before)


def test_bad_batches_and_divergence_raise_clear_errors():
    agent = DQNAgent(SMALL, TINY, DQNConfig(), device="cpu", seed=0)
    big = make_batch()
    wrong = Batch(**{**big.__dict__, "obs": np.zeros((8, 120, 160), np.uint16)})
    with pytest.raises(DQNError, match="do not fit the sensor"):
        agent.update(wrong)
    nan = Batch(**{**big.__dict__, "rewards": np.full((8, 1), np.nan, np.float32)})
    with pytest.raises(DQNError, match="non-finite loss"):
        agent.update(nan)


def test_weights_export_and_load_bump_policy_version():
    a = DQNAgent(SMALL, TINY, DQNConfig(), device="cpu", seed=0)
    b = DQNAgent(SMALL, TINY, DQNConfig(), device="cpu", seed=1)
    b.load_weights(a.weights())
    assert b.policy_version == 1
    depth = np.random.default_rng(0).random((30, 40)).astype(np.float32) * 4
    np.testing.assert_array_equal(a.q_values(depth), b.q_values(depth))
    assert torch.equal(b.target.fc1.weight, a.online.fc1.weight)


def test_update_flops_formula():
    net = QNetwork()
    f = forward_flops(net)
    fwd = sum(f.values())
    assert update_flops(net, 32, double_dqn=True) == 32 * (3 * fwd + 2 * fwd - f["conv1"])
    assert update_flops(net, 32, double_dqn=False) == 32 * (2 * fwd + 2 * fwd - f["conv1"])
    assert 60e9 < update_flops(net, 32) < 70e9


def test_smoke_preset_runs_50_updates_end_to_end_on_replay():
    cfg = load_preset("smoke")
    agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=cfg.train.seed)
    mem = ReplayMemory(cfg.replay, (cfg.sensor.height, cfg.sensor.width), seed=0)
    rng = np.random.default_rng(0)
    obs = rng.random((cfg.sensor.height, cfg.sensor.width)).astype(np.float32) * 4
    for t in range(200):
        term = rng.random() < 0.1
        nxt = rng.random(obs.shape).astype(np.float32) * 4
        mem.add(0, obs, int(rng.integers(5)), -100.0 if term else 1.0, None if term else nxt, term)
        obs = rng.random(obs.shape).astype(np.float32) * 4 if term else nxt
    for _ in range(cfg.train.total_updates):
        batch = mem.sample(cfg.dqn.batch_size, cfg.dqn.n_step)
        m = agent.update(batch)
        mem.update_priorities(batch.indices, m["td_errors"])
    assert agent.update_count == 50 and np.isfinite(m["loss"])


def test_replay_config_capacity_reaches_hundreds_of_thousands():
    mem = ReplayMemory(ReplayConfig(capacity=300_000), (120, 160))
    assert mem.bytes_per_transition < 1.2 * 120 * 160 * 2


def test_a_previous_action_network_learns_a_value_that_only_the_previous_command_explains():
    """Same image, same command: a collision follows only when the previous command was 'left'.
    The plain network cannot tell the rows apart; the previous-action network can."""
    batch = make_batch(16)
    batch.obs[:] = batch.obs[0]
    batch.action[:] = 2
    prev = np.arange(16) % 5
    batch.previous_action[:] = -1
    batch.previous_action[:, 0] = prev
    batch.terminated[:] = prev == 0
    batch.rewards[:, 0] = np.where(prev == 0, -100.0, 1.0)
    q = {}
    for previous in (False, True):
        model = ModelConfig(fc1=32, fc2=16, dropout=0.0, previous_action=previous)
        agent = DQNAgent(model, TINY, DQNConfig(optimizer="adam", lr=1e-2, gamma=0.0), device="cpu", seed=0)
        for _ in range(150):
            agent.update(batch)
        q[previous] = agent.q_values(batch.obs[:5], np.arange(5))[:, 2]
    assert np.ptp(q[False]) < 1.0  # one value for all rows: the mean, about -19
    assert q[True][0] < -80 and np.all(np.abs(q[True][1:] - 1.0) < 5)


def test_a_command_history_network_learns_a_value_that_only_an_older_command_explains():
    """Same image, same command, same last command: a collision follows only when the command two
    steps back was 'left'. A network that reads one command cannot tell the rows apart; one that
    reads two can."""
    batch = make_batch(16)
    batch.obs[:] = batch.obs[0]
    batch.action[:] = 2
    older = np.arange(16) % 5
    batch.previous_action[:] = -1
    batch.previous_action[:, 0] = 2
    batch.previous_action[:, 1] = older
    batch.terminated[:] = older == 0
    batch.rewards[:, 0] = np.where(older == 0, -100.0, 1.0)
    q = {}
    for history in (1, 2):
        model = ModelConfig(fc1=32, fc2=16, dropout=0.0, previous_action=True, action_history=history)
        agent = DQNAgent(model, TINY, DQNConfig(optimizer="adam", lr=1e-2, gamma=0.0), device="cpu", seed=0)
        for _ in range(150):
            agent.update(batch)
        q[history] = agent.q_values(batch.obs[:5], batch.previous_action[:5])[:, 2]
    assert np.ptp(q[1]) < 1.0
    assert q[2][0] < -80 and np.all(np.abs(q[2][1:] - 1.0) < 5)


def test_conv_precision_is_validated_and_resolved():
    from shared.config import ConfigError
    from shared.learning.model import bfloat16_is_native, conv_autocast_dtype

    with pytest.raises(ConfigError, match="conv_precision"):
        DQNConfig(conv_precision="fp16")
    cpu = torch.device("cpu")
    assert conv_autocast_dtype("float32", cpu) is None
    assert conv_autocast_dtype("bfloat16", cpu) is torch.bfloat16
    assert conv_autocast_dtype("auto", cpu) is (torch.bfloat16 if bfloat16_is_native(cpu) else None)


def test_bfloat16_convs_train_close_to_float32_and_act_in_float32():
    # The same weights and batch: bfloat16 conv arithmetic gives targets and a gradient step close
    # to float32's, weights and optimiser stay float32, and acting ignores the learner's precision.
    agents = {p: DQNAgent(SMALL, TINY, DQNConfig(lr=1e-3, momentum=0.0, double_dqn=True, conv_precision=p),
                          device="cpu", seed=3) for p in ("float32", "bfloat16")}
    f32, b16 = agents["float32"], agents["bfloat16"]
    assert b16.online.conv_autocast is torch.bfloat16 and b16.target.conv_autocast is torch.bfloat16
    assert f32.online.conv_autocast is None
    batch = make_batch(32, seed=5)
    y32 = f32.prepare(batch, None).y
    y16 = b16.prepare(batch, None).y
    assert not torch.equal(y32, y16)  # the convolutions really ran in bfloat16
    torch.testing.assert_close(y16, y32, rtol=0.02, atol=0.05)
    depth = np.random.default_rng(1).uniform(0.3, 4.0, (30, 40)).astype(np.float32)
    np.testing.assert_array_equal(b16.q_values(depth, 2), f32.q_values(depth, 2))  # acting: float32 both
    before = {n: p.detach().clone() for n, p in b16.online.named_parameters()}
    m16, m32 = b16.update(batch), f32.update(batch)
    assert np.isfinite(m16["loss"]) and abs(m16["loss"] - m32["loss"]) <= 0.02 * abs(m32["loss"])
    # plain SGD: each step is the gradient, whose direction bfloat16 keeps
    steps = {p: torch.cat([(q.detach() - before[n]).flatten() for n, q in a.online.named_parameters()])
             for p, a in agents.items()}
    assert all(q.dtype == torch.float32 for q in b16.online.parameters())
    assert torch.nn.functional.cosine_similarity(steps["bfloat16"], steps["float32"], dim=0) > 0.98
