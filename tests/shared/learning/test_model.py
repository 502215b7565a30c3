"""Q-network: shapes, preprocessing, dropout, pool-before-ReLU equivalence, supervised sibling."""

import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from shared.config import ConfigError, ModelConfig, SensorConfig
from shared.learning.model import (
    DEPTH_SCALE_M,
    INVERSE_DEPTH_NEAR_M,
    InferenceRunner,
    ModelError,
    QEnsemble,
    QNetwork,
    SupervisedNet,
    architecture_fingerprint,
    copy_conv_weights,
    encode_depth,
    forward_flops,
    layer_summary,
    load_tensors,
    pool3_shape,
    preprocess_depth,
    weights_to_tensors,
)

TINY = SensorConfig(width=40, height=30)
SMALL = ModelConfig(fc1=32, fc2=16)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_paper_shapes_pool3_is_64x15x20():
    torch.manual_seed(0)
    net = QNetwork()
    x = preprocess_depth(np.random.default_rng(0).random((2, 120, 160)).astype(np.float32) * 4)
    assert x.shape == (2, 1, 120, 160)
    assert net.features(x).shape == (2, 64, 15, 20)
    assert net(x).shape == (2, 5)
    assert pool3_shape(SensorConfig()) == (64, 15, 20)


def test_summary_rows_shapes_and_parameter_counts():
    rows = {r["layer"]: r for r in layer_summary(ModelConfig(), SensorConfig())}
    assert rows["conv1"]["output_shape"] == [32, 120, 160] and rows["conv1"]["params"] == 32 * 25 + 32
    assert rows["conv2"]["params"] == 32 * 32 * 25 + 32
    assert rows["conv3"]["params"] == 64 * 32 * 25 + 64
    assert rows["pool3"]["output_shape"] == [64, 15, 20]
    assert rows["fc1"] == {"layer": "fc1", "output_shape": [512], "params": 64 * 15 * 20 * 512 + 512}
    assert rows["fc2"]["output_shape"] == [256]
    assert rows["fc3"]["output_shape"] == [5]
    assert rows["total"]["params"] == sum(r["params"] for n, r in rows.items() if n != "total")


def test_forward_flops_match_hand_count():
    flops = forward_flops(QNetwork())
    assert flops["conv1"] == 2 * 120 * 160 * 32 * 25
    assert flops["conv2"] == 2 * 60 * 80 * 32 * 32 * 25
    assert flops["conv3"] == 2 * 30 * 40 * 64 * 32 * 25
    assert flops["fc1"] == 2 * 19200 * 512


def test_preprocess_metres_and_millimetres_agree_and_keep_zero():
    depth_m = np.array([[0.0, 1.0], [2.5, 9.0]], dtype=np.float32)
    depth_mm = np.array([[0, 1000], [2500, 9000]], dtype=np.uint16)
    a, b = preprocess_depth(depth_m), preprocess_depth(depth_mm)
    assert torch.equal(a, b)
    assert a.shape == (1, 1, 2, 2)
    assert a[0, 0, 0, 0] == 0.0  # no return stays 0
    assert a[0, 0, 0, 1] == pytest.approx(1.0 / DEPTH_SCALE_M)
    assert a[0, 0, 1, 1] == 1.0  # clipped beyond the scale
    assert preprocess_depth(torch.from_numpy(depth_m)).equal(a)
    assert preprocess_depth(np.array([[np.nan, 1.0]], dtype=np.float32))[0, 0, 0, 0] == 0.0


def test_inverse_depth_encoding_is_monotone_keeps_no_return_and_is_inside_the_network():
    depth_m = np.array([[0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 9.0]], dtype=np.float32)
    x = preprocess_depth(depth_m)
    assert torch.equal(encode_depth(x, "metric"), x)
    inv = encode_depth(x, "inverse")[0, 0, 0].tolist()
    assert inv[0] == 0.0  # no return: free space, as far as it gets
    assert inv[1] == inv[2] == 1.0  # at and inside the near distance: capped
    for d, v in zip(depth_m[0, 3:], inv[3:]):
        assert v == pytest.approx(INVERSE_DEPTH_NEAR_M / min(d, DEPTH_SCALE_M))
    assert all(a > b for a, b in zip(inv[2:6], inv[3:6]))  # nearer is always larger, up to the range
    assert inv[6] == inv[5]  # beyond the 4 m scale: clipped, as in the metric input
    with pytest.raises(ModelError, match="unknown depth encoding"):
        encode_depth(x, "log")

    # the encoding is part of the network: same weights, different Q-values and fingerprints
    torch.manual_seed(0)
    metric = QNetwork(SMALL, TINY).eval()
    inverse = QNetwork(ModelConfig(fc1=32, fc2=16, depth_encoding="inverse"), TINY).eval()
    load_tensors(inverse, weights_to_tensors(metric))
    batch = preprocess_depth(np.random.default_rng(5).random((2, 30, 40)).astype(np.float32) * 4)
    with torch.no_grad():
        assert not torch.allclose(metric(batch), inverse(batch))
        assert torch.allclose(inverse(batch), metric(encode_depth(batch, "inverse")))
    assert architecture_fingerprint(metric) != architecture_fingerprint(inverse)
    with pytest.raises(ModelError, match="trained on 'metric' depth input"):
        copy_conv_weights(SupervisedNet(TINY), inverse)
    copy_conv_weights(SupervisedNet(TINY, "inverse"), inverse)
    with pytest.raises(ConfigError, match="depth_encoding"):
        ModelConfig(depth_encoding="disparity")


def test_preprocess_rejects_bad_shapes():
    with pytest.raises(ModelError, match=r"\(H, W\), \(B, H, W\) or \(B, K, H, W\)"):
        preprocess_depth(np.zeros((1, 1, 1, 4, 4), dtype=np.float32))
    with pytest.raises(ModelError, match=r"\(H, W\), \(B, H, W\) or \(B, K, H, W\)"):
        preprocess_depth(np.zeros(4, dtype=np.float32))
    with pytest.raises(ModelError, match="numpy array or torch tensor"):
        preprocess_depth([[1.0]])
    net = QNetwork(SMALL, TINY)
    with pytest.raises(ModelError, match="network input must be"):
        net(torch.zeros(1, 1, 120, 160))


def test_dropout_only_in_training():
    torch.manual_seed(0)
    net = QNetwork(ModelConfig(fc1=64, fc2=32, dropout=0.5), TINY)
    x = preprocess_depth(np.random.default_rng(1).random((4, 30, 40)).astype(np.float32) * 3)
    net.eval()
    assert torch.equal(net(x), net(x))
    net.train()
    assert not torch.equal(net(x), net(x))


def test_pool_then_relu_equals_paper_order_values_and_gradients():
    torch.manual_seed(0)
    net = QNetwork(SMALL, TINY)
    x = preprocess_depth(np.random.default_rng(2).random((3, 30, 40)).astype(np.float32) * 4)
    t = net.trunk

    def paper_order(x):
        for conv in (t.conv1, t.conv2, t.conv3):
            x = F.max_pool2d(F.relu(conv(x)), 2)
        return x

    ours = t(x)
    ref = paper_order(x)
    assert torch.allclose(ours, ref, atol=1e-6)
    g1 = torch.autograd.grad(ours.square().sum(), t.conv1.weight)[0]
    g2 = torch.autograd.grad(paper_order(x).square().sum(), t.conv1.weight)[0]
    assert torch.allclose(g1, g2, rtol=1e-4, atol=1e-6)


def test_tiny_sensor_and_dueling_head():
    net = QNetwork(ModelConfig(fc1=32, fc2=16, dueling=True), TINY).eval()
    x = preprocess_depth(np.ones((2, 30, 40), dtype=np.float32))
    assert net.features(x).shape == (2, 64, 3, 5)
    q = net(x)
    assert q.shape == (2, 5)
    h = net.features(x).flatten(1)
    h = F.relu(net.fc2(F.relu(net.fc1(h))))
    adv = net.advantage(h)
    # Q - V is the advantage with zero mean over actions
    assert torch.allclose(q - net.value(h), adv - adv.mean(1, keepdim=True), atol=1e-5)
    assert pool3_shape(SensorConfig(width=17, height=8)) == (64, 1, 2)  # odd sizes floor


def test_supervised_net_shares_trunk_and_conv_weights_copy():
    torch.manual_seed(0)
    q = QNetwork(SMALL, TINY)
    sl = SupervisedNet(TINY)
    x = preprocess_depth(np.random.default_rng(3).random((2, 30, 40)).astype(np.float32) * 4)
    assert sl(x).shape == (2, 5)
    assert not torch.equal(q.features(x), sl.features(x))
    copy_conv_weights(sl, q)
    assert torch.equal(q.features(x), sl.features(x))
    with pytest.raises(ModelError, match="no ConvTrunk"):
        copy_conv_weights(torch.nn.Linear(2, 2), q)


def test_weights_round_trip_and_mismatch_errors():
    torch.manual_seed(0)
    a, b = QNetwork(SMALL, TINY), QNetwork(SMALL, TINY)
    tensors = weights_to_tensors(a)
    assert all(t.is_contiguous() for t in tensors.values())
    load_tensors(b, tensors)
    x = preprocess_depth(np.ones((1, 30, 40), dtype=np.float32))
    assert torch.equal(a.eval()(x), b.eval()(x))
    other = QNetwork(ModelConfig(fc1=64, fc2=16), TINY)
    assert architecture_fingerprint(other) != architecture_fingerprint(a)
    with pytest.raises(ModelError, match="fc1.weight"):
        load_tensors(other, tensors)
    with pytest.raises(ModelError, match="missing"):
        load_tensors(b, {k: v for k, v in tensors.items() if k != "fc3.bias"})


def test_inference_runner_matches_eval_forward_and_restores_mode():
    torch.manual_seed(0)
    net = QNetwork(SMALL, TINY)
    net.train()
    runner = InferenceRunner(net)
    depth = np.random.default_rng(4).random((30, 40)).astype(np.float32) * 4
    q = runner.q_values(depth)
    assert q.shape == (5,) and q.dtype == np.float32
    assert net.training
    with torch.no_grad():
        ref = net.eval()(preprocess_depth(depth))[0].numpy()
    np.testing.assert_array_equal(q, ref)
    assert runner.q_values(np.stack([depth, depth])).shape == (2, 5)


def test_previous_action_input_changes_q_and_none_means_no_previous_command():
    torch.manual_seed(0)
    net = QNetwork(ModelConfig(fc1=32, fc2=16, previous_action=True), TINY).eval()
    plain = QNetwork(SMALL, TINY)
    assert architecture_fingerprint(net) != architecture_fingerprint(plain)  # weights never mix
    assert [r["layer"] for r in layer_summary(net=net)].count("previous_action_fc") == 1
    x = preprocess_depth(np.random.default_rng(1).random((5, 30, 40)).astype(np.float32) * 4)
    with torch.no_grad():
        none, minus_one = net(x), net(x, torch.full((5,), -1))
        each = net(x, torch.arange(5))
        single = net(x[:1], 3)
    assert torch.equal(none, minus_one)
    assert not torch.allclose(each, none)
    torch.testing.assert_close(single[0], net(x[:1], torch.tensor([3]))[0])
    runner = InferenceRunner(net)
    depth = np.random.default_rng(2).random((30, 40)).astype(np.float32) * 4
    assert not np.allclose(runner.q_values(depth, 0), runner.q_values(depth, 4))
    np.testing.assert_array_equal(runner.q_values(depth), runner.q_values(depth, None))
    for bad in (5, -2, torch.arange(3)):
        with pytest.raises(ModelError, match="previous_action"):
            net(x, bad)
    with pytest.raises(ConfigError, match="previous_action"):
        ModelConfig(previous_action=1)


def test_a_command_history_network_reads_its_last_commands_most_recent_first():
    torch.manual_seed(0)
    net = QNetwork(ModelConfig(fc1=32, fc2=16, previous_action=True, action_history=3), TINY).eval()
    one = QNetwork(ModelConfig(fc1=32, fc2=16, previous_action=True), TINY)
    assert architecture_fingerprint(net) != architecture_fingerprint(one)
    assert net.previous_action_fc.in_features == 15
    assert [r for r in layer_summary(net=net) if r["layer"] == "previous_action_fc"][0]["params"] == 15 * 32
    x = preprocess_depth(np.random.default_rng(1).random((2, 30, 40)).astype(np.float32) * 4)
    with torch.no_grad():
        q = lambda prev: net(x, torch.tensor(prev))  # noqa: E731
        # older commands change the values; columns past the history are not read; missing ones read as none
        assert not torch.allclose(q([[1, 0, -1], [1, 0, -1]]), q([[1, 4, -1], [1, 4, -1]]))
        assert not torch.allclose(q([[1, 0, 2], [1, 0, 2]]), q([[1, 0, -1], [1, 0, -1]]))
        torch.testing.assert_close(q([[1, 0, 2, 4, 4], [3, 3, 3, 0, 0]]), q([[1, 0, 2], [3, 3, 3]]))
        torch.testing.assert_close(q([[1, 0], [2, -1]]), q([[1, 0, -1], [2, -1, -1]]))
        torch.testing.assert_close(q([1, 2]), q([[1, -1, -1], [2, -1, -1]]))  # (B,): the last command only
        torch.testing.assert_close(net(x), q([[-1] * 3] * 2))
    with pytest.raises(ModelError, match="previous_action"):
        net(x, torch.tensor([[1, 5, 0], [0, 0, 0]]))
    for bad in (0, 9, True):
        with pytest.raises(ConfigError, match="action_history"):
            ModelConfig(previous_action=True, action_history=bad)
    with pytest.raises(ConfigError, match="action_history"):
        ModelConfig(action_history=2)  # a history of commands the network does not read


@pytest.mark.parametrize("cfg", [ModelConfig(fc1=32, fc2=16, previous_action=True, depth_encoding="inverse"),
                                 ModelConfig(fc1=32, fc2=16, previous_action=True, action_history=4),
                                 ModelConfig(fc1=32, fc2=16, dueling=True)],
                         ids=["previous-command", "command-history", "dueling"])
def test_an_ensemble_acting_runs_its_members_as_one_network_with_the_same_q_values(cfg):
    torch.manual_seed(0)
    nets = [QNetwork(cfg, TINY).eval() for _ in range(3)]
    ensemble = QEnsemble(nets).eval()
    x = preprocess_depth(np.random.default_rng(1).uniform(0.3, 4.0, (4, 30, 40)).astype(np.float32))
    for previous in (None, 2, [0, 4, -1, 1], [[0, 1, 2, 3], [4, 4, -1, -1], [2, -1, -1, -1], [1, 3, 1, 3]]):
        with torch.no_grad():  # a plain loop over the members, with autograd on
            mean = torch.stack([n(x, previous) for n in nets]).mean(0)
        with torch.inference_mode():
            fused = ensemble(x, previous)
        assert ensemble._fused is not None  # the fused path ran
        torch.testing.assert_close(fused, mean, rtol=1e-5, atol=1e-5)
    # new weights in a member (a state dict loaded in place) reach the fused network
    with torch.no_grad():
        nets[1].fc2.bias.add_(1.0)
    with torch.inference_mode():
        after = ensemble(x, 2)
    torch.testing.assert_close(after, torch.stack([n(x, 2) for n in nets]).mean(0).detach(), rtol=1e-5, atol=1e-5)
    assert not torch.allclose(after, fused)
    with torch.inference_mode(), pytest.raises(ModelError, match="network input"):
        ensemble(torch.zeros(1, 1, 48, 64))


def test_an_ensemble_acting_on_an_empty_batch_gives_no_rows_as_one_network_does():
    nets = [QNetwork(SMALL, TINY).eval() for _ in range(2)]
    for net in (nets[0], QEnsemble(nets).eval()):  # the fused path inferred -1 from 0 elements
        assert InferenceRunner(net).q_values(np.zeros((0, 30, 40), np.float32)).shape == (0, 5)


def test_only_networks_that_read_the_same_camera_and_depth_are_averaged():
    from shared.learning.model import average_weights

    # 47 x 31 pools to pool3's 5 x 3 as 40 x 30 does: the same shapes, another camera
    for other in (SensorConfig(width=47, height=31), dataclasses.replace(TINY, hfov_deg=90.0),
                  dataclasses.replace(TINY, max_range_m=8.0)):
        with pytest.raises(ModelError, match="different cameras or depth: sensor"):
            average_weights([QNetwork(SMALL, TINY), QNetwork(SMALL, other)])
    inverse = dataclasses.replace(SMALL, depth_encoding="inverse")
    with pytest.raises(ModelError, match="member 0 model.depth_encoding = 'inverse' against 'metric'"):
        average_weights([QEnsemble([QNetwork(SMALL, TINY), QNetwork(SMALL, TINY)]),
                         QEnsemble([QNetwork(inverse, TINY), QNetwork(inverse, TINY)])])
    # training noise, dropout and the renderer (ray-cast or GL, which agree to 2 cm: a run may resume
    # with the other) are no part of what a network reads
    noisy = dataclasses.replace(TINY, noise_std_m=0.01, backend="gl" if TINY.backend != "gl" else "raycast")
    mean = average_weights([QNetwork(SMALL, TINY), QNetwork(dataclasses.replace(SMALL, dropout=0.2), noisy)])
    assert set(mean) == set(weights_to_tensors(QNetwork(SMALL, TINY)))
    QEnsemble([QNetwork(SMALL, TINY), QNetwork(SMALL, noisy)])  # an ensemble takes them too


def test_networks_of_different_command_histories_still_run_fused():
    torch.manual_seed(0)
    nets = [QNetwork(ModelConfig(fc1=32, fc2=16, previous_action=True, action_history=k), TINY).eval()
            for k in (1, 4, 2)]
    ensemble = QEnsemble(nets).eval()
    x = preprocess_depth(np.random.default_rng(1).uniform(0.3, 4.0, (2, 30, 40)).astype(np.float32))
    for previous in (None, [3, 1], [[0, 1, 2, 3, 4], [4, -1, -1, -1, -1]]):
        with torch.inference_mode():
            fused = ensemble(x, previous)
            mean = torch.stack([n(x, previous) for n in nets]).mean(0)
        assert ensemble._fused is not None and [g.action_history for g in ensemble._fused] == [4]
        torch.testing.assert_close(fused, mean, rtol=1e-5, atol=1e-5)


def test_an_ensemble_of_different_heads_plays_the_member_mean_one_fused_group_per_head():
    """Scalar and quantile heads, different fc widths, one and three images: each config runs as one
    network and the ensemble is the mean over members, not over groups."""
    torch.manual_seed(0)
    quantile = ModelConfig(fc1=32, fc2=16, previous_action=True, quantiles=8)
    nets = [QNetwork(cfg, TINY).eval() for cfg in
            (SMALL, quantile, ModelConfig(fc1=16, fc2=8), SMALL, dataclasses.replace(quantile, frame_stack=3))]
    x = preprocess_depth(np.random.default_rng(1).uniform(0.3, 4.0, (2, 3, 30, 40)).astype(np.float32))
    ensemble = QEnsemble(nets).eval()
    with torch.inference_mode():
        fused = ensemble(x, [1, 3])
    assert [len(g.members) for g in ensemble._fused] == [2, 2, 1]
    mean = torch.stack([n(x[:, :n.model_cfg.frame_stack], [1, 3]) for n in nets]).mean(0).detach()
    torch.testing.assert_close(fused, mean, rtol=1e-5, atol=1e-5)
    with torch.enable_grad():  # one network after the other
        torch.testing.assert_close(ensemble(x, [1, 3]).detach(), mean, rtol=1e-5, atol=1e-5)
    with torch.no_grad():  # new weights in one group's member reach its fused copy
        nets[4].fc1.bias.add_(1.0)
        torch.testing.assert_close(ensemble(x, [1, 3]),
                                   torch.stack([n(x[:, :n.model_cfg.frame_stack], [1, 3]) for n in nets]).mean(0))



def test_a_frame_stack_network_reads_its_images_as_channels_and_starts_from_a_one_image_trunk():
    torch.manual_seed(0)
    stack = QNetwork(ModelConfig(fc1=32, fc2=16, frame_stack=3, previous_action=True), TINY)
    images = np.random.default_rng(1).random((2, 3, 30, 40)).astype(np.float32) * 4
    x = preprocess_depth(images)
    assert x.shape == (2, 3, 30, 40) and stack(x).shape == (2, 5)
    with pytest.raises(ModelError, match=r"\(B, 3, 30, 40\).*stacks"):
        stack(preprocess_depth(images[:, 0]))
    assert layer_summary(net=stack)[0]["output_shape"] == [3, 30, 40]
    assert forward_flops(stack)["conv1"] == 3 * forward_flops(QNetwork(SMALL, TINY))["conv1"]
    # the supervised (one-image) conv layers: the current image keeps them, the older ones start at zero
    sl = SupervisedNet(TINY)
    copy_conv_weights(sl, stack)
    torch.testing.assert_close(stack.features(x), sl.features(x[:, :1]))
    older = x.clone()
    older[:, 1:] = 0.5
    stack.eval()  # dropout off
    assert torch.equal(stack(older), stack(x))  # until training gives them weight, older images change nothing
    with torch.no_grad():
        stack.trunk.conv1.weight[:, 1:] += 0.1
    assert not torch.allclose(stack(older), stack(x))
    # with a network that reads one image, the ensemble takes three and gives it the newest
    one = QNetwork(ModelConfig(fc1=32, fc2=16, previous_action=True), TINY).eval()
    mixed = QEnsemble([one, stack])
    assert mixed.model_cfg.frame_stack == 3
    with torch.no_grad():  # fused: the one-image network's conv1 padded with zero weights
        torch.testing.assert_close(mixed(x, [2, 0]), (one(x[:, :1], [2, 0]) + stack(x, [2, 0])) / 2)
    assert mixed._fused is not None
    torch.testing.assert_close(mixed(x, [2, 0]), (one(x[:, :1], [2, 0]) + stack(x, [2, 0])) / 2)  # unfused
    with pytest.raises(ModelError, match=r"network input must be \(B, 3, 30, 40\) \(the ensemble"):
        mixed(x[:, :1])
    pair = QEnsemble([stack, QNetwork(ModelConfig(fc1=32, fc2=16, frame_stack=3, previous_action=True), TINY)]).eval()
    with torch.no_grad():  # fused
        fused = pair(x, [1, 4])
    torch.testing.assert_close(fused, torch.stack([m(x, [1, 4]) for m in pair.members]).mean(0))


def test_a_network_too_large_for_a_machine_is_refused_naming_its_fields(monkeypatch) -> None:
    # each field in its range, together 34 GB of fc1: torch's allocator failed with a traceback
    with pytest.raises(ModelError, match=r"fc1 would have 8,589,934,592 weights .*lower sensor.width/height or model.fc1"):
        QNetwork(ModelConfig(fc1=8192), SensorConfig(width=1024, height=1024))
    import shared.learning.model as model

    paper = QNetwork().fc1.weight.numel()
    monkeypatch.setattr(model, "MAX_FC1_WEIGHTS", paper)  # the limit itself is allowed
    assert QNetwork().fc1.weight.numel() == paper
    monkeypatch.setattr(model, "MAX_FC1_WEIGHTS", paper - 1)
    with pytest.raises(ModelError, match="fc1 would have"):
        QNetwork()
