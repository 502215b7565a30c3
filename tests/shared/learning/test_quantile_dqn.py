"""QR-DQN (``model.quantiles``): the quantile Huber loss's minimiser, the target distribution, a rare
collision kept in the distribution, and a quantile network acting, fused and exported on its mean."""

from pathlib import Path

import numpy as np
import pytest
import torch

from shared.config import ConfigError, DQNConfig, ModelConfig, SensorConfig, load_preset
from shared.learning.dqn import DQNAgent, quantile_huber_loss, quantile_td_targets
from shared.learning.learner import LearnerCore
from shared.learning.model import ModelError, QEnsemble, QNetwork, preprocess_depth
from shared.learning.onnx_export import export_onnx
from tests.shared.learning.test_dqn import make_batch

TINY = SensorConfig(width=40, height=30)
QUANTILE = ModelConfig(fc1=32, fc2=16, dropout=0.0, quantiles=10)
G = 0.85

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_the_quantile_loss_puts_each_quantile_at_its_midpoint_fraction_of_the_targets():
    samples = torch.tensor(np.random.default_rng(0).exponential(10.0, 400), dtype=torch.float32)
    quantiles = torch.zeros(1, 5, requires_grad=True)
    optimizer = torch.optim.Adam([quantiles], lr=0.5)
    for step in range(1500):
        for group in optimizer.param_groups:  # small final steps: the minimiser, not a walk around it
            group["lr"] = 0.5 * (1 - step / 1500) + 1e-3
        optimizer.zero_grad()
        quantile_huber_loss(quantiles, samples[None], kappa=0.01).sum().backward()
        optimizer.step()
    want = np.quantile(samples.numpy(), [0.1, 0.3, 0.5, 0.7, 0.9])
    assert quantiles.detach()[0].numpy() == pytest.approx(want, abs=0.3)


def test_the_target_distribution_bootstraps_theta_minus_at_the_online_argmax_and_stops_at_a_collision():
    rewards = torch.tensor([[1.0, 1.0], [1.0, -100.0], [2.0, 0.0]])
    n_steps = torch.tensor([2, 2, 1])
    terminated = torch.tensor([False, True, False])
    next_quantiles = torch.arange(3 * 5 * 4, dtype=torch.float32).reshape(3, 5, 4)  # theta^-: command 4 best
    online_q = torch.zeros(3, 5)
    online_q[:, 1] = 1.0  # the online net prefers command 1
    y = quantile_td_targets(rewards, n_steps, terminated, next_quantiles, G, online_q)
    assert y.shape == (3, 4)
    assert y[0].tolist() == pytest.approx((1 + G + G**2 * next_quantiles[0, 1]).tolist())
    assert y[1].tolist() == pytest.approx([1 - 100 * G] * 4)  # a collision: the return in every column
    assert y[2].tolist() == pytest.approx((2 + G * next_quantiles[2, 1]).tolist())
    plain = quantile_td_targets(rewards, n_steps, terminated, next_quantiles, G)  # no Double DQN
    assert plain[0].tolist() == pytest.approx((1 + G + G**2 * next_quantiles[0, 4]).tolist())


def test_a_rare_collision_stays_in_the_distribution_and_its_mean_says_avoid_it():
    """The scene of test_dqn's MSE/Huber test: 'left' always earns +1, 'half-left' +2 but collides
    (-100) one time in five. The quantile loss is Huber-like per quantile, yet the two lowest of ten
    quantiles hold the collision and the mean (the Q-value a policy acts on) is the mean return."""
    batch = make_batch(20, seed=5, terminated=np.ones(20, bool))
    batch.obs[:] = batch.obs[0]
    batch.action[:] = [0] * 10 + [1] * 10
    batch.rewards[:, 0] = [1.0] * 10 + [2.0] * 8 + [-100.0] * 2
    agent = DQNAgent(QUANTILE, TINY, DQNConfig(optimizer="adam", lr=1e-2), device="cpu", seed=0)
    for _ in range(600):  # 300 left the lowest quantiles 7-16 short of -100 on AVX-512 hosts' arithmetic
        metrics = agent.update(batch)
    x = preprocess_depth(batch.obs[:1])
    with torch.no_grad():
        risky = agent.online.return_quantiles(x)[0, 1].numpy()
    # the collision held by the two lowest (a Huber or squared loss would put every value near the mean, -18)
    assert (risky[:2] < -85).all() and risky[2:] == pytest.approx([2] * 8, abs=1), risky
    q = agent.q_values(batch.obs[:1])[0]
    assert q[1] == pytest.approx(-18.4, abs=2) and q[0] == pytest.approx(1.0, abs=0.5)
    assert metrics["td_errors"].shape == (20,) and np.isfinite(metrics["loss"])


def test_a_quantile_network_acts_fuses_and_exports_on_the_mean_of_its_quantiles(tmp_path: Path):
    torch.manual_seed(0)
    nets = [QNetwork(QUANTILE, TINY).eval() for _ in range(2)]
    x = preprocess_depth(np.random.default_rng(1).uniform(0.3, 4.0, (3, 30, 40)).astype(np.float32))
    previous = torch.tensor([0, 2, 4])
    with torch.no_grad():
        q = nets[0](x, previous)
        assert q.shape == (3, 5)
        assert torch.allclose(q, nets[0].return_quantiles(x, previous).mean(dim=2))
        ensemble = QEnsemble(nets).eval()
        fused = ensemble(x, previous)  # no autograd: the members run as one network
    with torch.enable_grad():
        unfused = ensemble(x, previous).detach()
    assert ensemble._fused is not None and torch.allclose(fused, unfused, atol=1e-4)
    assert torch.allclose(unfused, (q + nets[1](x, previous).detach()) / 2, atol=1e-5)
    assert export_onnx(nets[0], tmp_path / "q.onnx").exists()  # refuses to write unless onnxruntime agrees
    with pytest.raises(ModelError, match="return_quantiles needs"):
        QNetwork(ModelConfig(fc1=32, fc2=16), TINY).return_quantiles(x)


def test_a_pipelined_learner_trains_a_quantile_network_and_repeats_exactly():
    """The learner service's core (replay, the TD-target thread) with quantiles; its state restores
    a fresh agent exactly (what a checkpoint saves)."""
    cfg = load_preset("smoke").with_overrides({"model.quantiles": 8, "model.dueling": False,
                                               "train.warmup_transitions": 16, "replay.capacity": 256,
                                               "dqn.mirror_augment": True})
    weights = []
    for _ in range(2):
        core = LearnerCore(cfg, device="cpu", pipeline=True)
        try:
            rng = np.random.default_rng(0)
            for i in range(64):
                end = i % 9 == 8
                core.add_transition("s", rng.uniform(0.3, 4.0, (30, 40)).astype(np.float32), int(rng.integers(5)),
                                    -100.0 if end else 1.0,
                                    None if end else rng.uniform(0.3, 4.0, (30, 40)).astype(np.float32), end, False)
            start = {n: t.clone() for n, t in core.agent.online.state_dict().items()}
            for _ in range(12):
                assert core.train_step() is not None
            loss, _ = core.recent()
            assert np.isfinite(loss) and core.updates == 12
            weights.append(core.agent.online.state_dict())
            assert not torch.equal(weights[-1]["fc3.weight"], start["fc3.weight"])
            assert weights[-1]["fc3.weight"].shape == (5 * 8, cfg.model.fc2)
            restored = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu")
            restored.load_state_tensors(*core.agent.state_tensors())
            depth = rng.uniform(0.3, 4.0, (3, 30, 40)).astype(np.float32)
            assert np.array_equal(restored.q_values(depth, [0, 1, 2]), core.agent.q_values(depth, [0, 1, 2]))
        finally:
            core.close()
    assert all(torch.equal(weights[0][n], weights[1][n]) for n in weights[0])


@pytest.mark.parametrize("fields, bad", [
    ({"quantiles": 1}, "quantiles"), ({"quantiles": 201}, "quantiles"), ({"quantiles": -1}, "quantiles"),
    ({"quantiles": 8.0}, "quantiles"), ({"quantiles": True}, "quantiles"),
    ({"quantiles": 8, "dueling": True}, "dueling"),
])
def test_bad_quantile_settings_are_refused_naming_the_field(fields, bad):
    with pytest.raises(ConfigError, match=bad):
        ModelConfig(**fields)


@pytest.mark.parametrize("kappa", [0.0, -1.0, float("nan"), 1001.0])
def test_a_bad_quantile_kappa_is_refused(kappa):
    with pytest.raises(ConfigError, match="quantile_kappa"):
        DQNConfig(quantile_kappa=kappa)
