"""``cogexplore bench learner``: DQN update time, single-image forward time, FLOP utilisation.

Everything is measured in one process, back to back: the paper network (fp32), a batch of 32
with Double-DQN targets (three forward passes and one backward), one-image greedy inference as
an actor runs it, and the machine's fp32 matmul peak. ``--preset`` (and ``--set``) times a run
configuration's update instead, the one ``cogexplore up`` would train (its image size, network,
batch, bfloat16 convolutions where the CPU has them): its ``ms_per_update`` bounds the learner's
updates per second on this machine (``flop_utilization`` stays against the fp32 peak, so bfloat16
can pass 1). Times are the best of several repeats for the update, the forward and the peak
alike, so that load from other processes on a shared machine depresses all three the same way
and ``flop_utilization`` (achieved over peak) stays comparable; medians are reported too.

The optimisations measured here live in the real code (shared/learning/model.py, shared/learning/dqn.py):
channels-last convolutions, pooling before ReLU, and the glibc allocator setting that stops
activations being page-faulted in on every update. ``baseline=True`` also times a plain
PyTorch version of the same update (NCHW, ReLU before pooling) in the same process; the
allocator setting is process-wide, so that baseline already has it and the reported speedup
leaves its share out (shared/learning/model.py's docstring has the separate-process comparison).
"""

from __future__ import annotations

import argparse
import copy
import platform
import statistics
import time
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F

from services.bench import print_json
from shared.config import (
    DEFAULT_PRESET,
    MAX_ACTION_HISTORY,
    ConfigError,
    DQNConfig,
    ModelConfig,
    RunConfig,
    SensorConfig,
    load_preset,
    parse_override,
)
from shared.learning.dqn import DQNAgent, td_targets, update_flops
from shared.learning.model import (
    InferenceRunner,
    QNetwork,
    forward_flops,
    reduce_allocator_page_faults,
    resolve_device,
)
from shared.learning.replay import Batch


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time(fn: Callable[[], Any], device: torch.device, repeats: int, warmup: int) -> list[float]:
    for _ in range(warmup):
        fn()
    _sync(device)
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        out.append(time.perf_counter() - t0)
    return out


def matmul_peak_gflops(device: torch.device, repeats: int = 5) -> float:
    """Best fp32 GFLOP/s of a square matmul (2048 on CPU, 8192 on CUDA; TF32 off)."""
    n = 8192 if device.type == "cuda" else 2048
    a = torch.randn(n, n, device=device)
    b = torch.randn(n, n, device=device)
    prev = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        best = min(_time(lambda: a @ b, device, repeats, warmup=1))
    finally:
        torch.backends.cuda.matmul.allow_tf32 = prev
    return 2 * n ** 3 / best / 1e9


def synthetic_batch(sensor: SensorConfig, batch_size: int, seed: int = 0, frame_stack: int = 1) -> Batch:
    """A replay-format batch (uint16 mm frames, ~12% collisions; ``frame_stack`` > 1: that many
    frames per sample, as the replay samples them for ``model.frame_stack``)."""
    rng = np.random.default_rng(seed)
    shape = (batch_size, sensor.height, sensor.width) if frame_stack == 1 else \
        (batch_size, frame_stack, sensor.height, sensor.width)
    terminated = rng.random(batch_size) < 0.12
    return Batch(obs=rng.integers(300, 4000, shape).astype(np.uint16),
                 action=rng.integers(0, 5, batch_size).astype(np.int64),
                 rewards=np.where(terminated, -100.0, 1.0).astype(np.float32)[:, None],
                 n_steps=np.ones(batch_size, dtype=np.int64), terminated=terminated,
                 next_obs=rng.integers(300, 4000, shape).astype(np.uint16),
                 previous_action=rng.integers(-1, 5, (batch_size, MAX_ACTION_HISTORY)).astype(np.int64),
                 next_previous_action=rng.integers(0, 5, (batch_size, MAX_ACTION_HISTORY)).astype(np.int64),
                 weights=np.ones(batch_size, dtype=np.float32), indices=np.arange(batch_size))


def _plain_update_fn(agent: DQNAgent, batch: Batch) -> Callable[[], None]:
    """The same Double-DQN update in plain eager PyTorch: NCHW, ReLU then pool."""
    online = copy.deepcopy(agent.online).to(memory_format=torch.contiguous_format)
    target = copy.deepcopy(agent.target).to(memory_format=torch.contiguous_format)
    opt = torch.optim.SGD(online.parameters(), lr=agent.cfg.lr, momentum=agent.cfg.momentum)
    tb = agent.to_tensors(batch)
    obs, nxt = tb.obs.contiguous(), tb.next_obs.contiguous()

    def q(net: QNetwork, x: torch.Tensor) -> torch.Tensor:
        t = net.trunk
        for conv in (t.conv1, t.conv2, t.conv3):
            x = F.max_pool2d(F.relu(conv(x)), 2)
        return net.head(x)

    def step() -> None:
        with torch.no_grad():
            online.eval()
            y = td_targets(tb.rewards, tb.n_steps, tb.terminated, q(target, nxt), agent.cfg.gamma,
                           q(online, nxt))
            online.train()
        qa = q(online, obs).gather(1, tb.action[:, None]).squeeze(1)
        loss = F.mse_loss(qa, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


def run(device: str = "auto", batch_size: int = 32, repeats: int = 8, forward_repeats: int = 60,
        threads: int | None = None, baseline: bool = False, seed: int = 0,
        config: RunConfig | None = None, preset: str | None = None) -> dict[str, Any]:
    """Time the learner's hot paths; returns a JSON-ready dict (see the module docstring).
    ``config``: time that run configuration's update (its sensor, network, batch and DQN options:
    mirrored batches, bfloat16 convolutions, quantiles...) instead of the paper network's; ``preset``:
    its name, for the result (None: the paper network)."""
    if config is not None and baseline:
        raise ConfigError("--baseline times the paper network's plain update only: leave out --preset and --set")
    allocator_tuned = reduce_allocator_page_faults()
    dev = resolve_device(device)
    if threads is not None:
        torch.set_num_threads(threads)
    if config is None:
        sensor, model, dqn = SensorConfig(), ModelConfig(), DQNConfig(double_dqn=True, batch_size=batch_size)
    else:
        sensor, model, dqn = config.sensor, config.model, config.dqn
        batch_size = dqn.batch_size
    agent = DQNAgent(model, sensor, dqn, device=dev, seed=seed)
    batch = synthetic_batch(sensor, batch_size, seed, frame_stack=model.frame_stack)
    flops = update_flops(agent.online, batch_size, double_dqn=dqn.double_dqn,
                         conv_trainable=dqn.conv_lr_scale > 0)
    fwd_flops = sum(forward_flops(agent.online).values())

    peaks = [matmul_peak_gflops(dev)]
    update_s = _time(lambda: agent.update(batch), dev, repeats, warmup=2)
    runner = InferenceRunner(agent.online)
    depth_m = np.random.default_rng(seed).random((sensor.height, sensor.width)).astype(np.float32) * 4
    forward_s = _time(lambda: runner.q_values(depth_m), dev, forward_repeats, warmup=5)
    peaks.append(matmul_peak_gflops(dev))
    peak = max(peaks)
    best_update, best_forward = min(update_s), min(forward_s)
    result: dict[str, Any] = {
        "device": str(dev),
        "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor()
        or platform.machine(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "allocator_tuned": allocator_tuned,
        "preset": preset,
        "image": [sensor.height, sensor.width],
        "batch_size": batch_size,
        "double_dqn": dqn.double_dqn,
        "conv_precision": str(agent.online.conv_autocast or torch.float32).removeprefix("torch."),
        "ms_per_update": best_update * 1e3,
        "ms_per_update_median": statistics.median(update_s) * 1e3,
        "forward_ms": best_forward * 1e3,
        "forward_ms_median": statistics.median(forward_s) * 1e3,
        "flops_per_update": flops,
        "flops_per_forward": fwd_flops,
        "achieved_gflops": flops / best_update / 1e9,
        "peak_gflops": peak,
        "peak_gflops_runs": peaks,
        "flop_utilization": flops / best_update / 1e9 / peak,
        "forward_flop_utilization": fwd_flops / best_forward / 1e9 / peak,
        "updates": repeats,
    }
    if baseline:
        plain = _time(_plain_update_fn(agent, batch), dev, repeats, warmup=2)
        result["baseline_ms_per_update"] = min(plain) * 1e3
        result["speedup_vs_baseline"] = min(plain) / best_update
    return result


def run_command(args: argparse.Namespace) -> int:
    """``cogexplore bench learner``."""
    preset = args.preset or (DEFAULT_PRESET if args.overrides else None)
    config = load_preset(preset).with_overrides(dict(parse_override(o) for o in args.overrides)) if preset else None
    result = run(device=args.device, repeats=args.repeats, threads=args.threads, baseline=args.baseline,
                 config=config, preset=preset)
    print_json(result, args.json)
    return 0
