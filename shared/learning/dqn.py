"""The DQN update (Tai & Liu 2016, Algorithm 1) as pure tensors-in, metrics-out code: no I/O.

Target, for a sampled chain of m <= n steps (n = 1 in the paper)::

    y = sum_{k<m} gamma^k r_k                                  if the chain ends in a collision
    y = sum_{k<m} gamma^k r_k + gamma^m max_a' Q(x', a'; theta^-)   otherwise (a truncated episode
                                                                     bootstraps: it is no collision)

With n = 1 this is the paper's y = r_ter on collision and r + gamma max Q(x', .; theta^-) otherwise.
Double DQN takes the argmax with theta (eval mode) and the value with theta^-. theta^- is copied
from theta every ``target_sync_every`` updates. The loss is the batch mean of (y - Q(x, a; theta))^2
(the paper's L = 1/n sum_k (y_k - Q)^2), or the Huber loss, each weighted by importance weights
under prioritised replay. A ``model.quantiles`` network (QR-DQN, Dabney et al. 2018) learns N return
quantiles per command instead: its target is the distribution y_j = sum gamma^k r_k + gamma^m
theta_j(x', a*; theta^-) (the return alone after a collision), a* the Double-DQN argmax of the
quantiles' means, and its loss the quantile Huber loss of the taken command's quantiles against
those N samples. Dropout is on in the online forward pass that is trained, and off when
computing targets (deterministic targets, as at test time).

Learning-rate mapping from the paper's Caffe setup ("learning rate 0.0000001", momentum 0.99)
---------------------------------------------------------------------------------------------
Caffe's EuclideanLoss layer is E = 1/(2N) sum_i ||p_i - t_i||^2, with N = the blob's *num* (the batch
size) and the squared norm summed over all 5 outputs of each sample. A Caffe DQN feeds the whole
(N, 5) Q blob and a target blob equal to the network's own output except at the taken action, so
the 4 other terms vanish: E = 1/(2N) sum_k (y_k - Q(x_k, a_k))^2 and dE/dQ_k = (Q_k - y_k) / N.
Our loss is the paper's formula, L = 1/N sum_k (y_k - Q_k)^2 (PyTorch ``mse_loss`` on the gathered
Q, mean over the batch): dL/dQ_k = 2 (Q_k - y_k) / N, twice Caffe's gradient. (Applying
``mse_loss`` to the full (N, 5) blob instead would divide by 5N: 2/5 of Caffe's gradient.) Caffe's
SGD (V <- mu V - lr grad; W <- W + V) and PyTorch's (b <- mu b + grad; W <- W - lr b) follow the
same trajectory for a fixed lr. Hence Caffe lr eta == PyTorch lr eta / 2 with our loss: the
paper's 1e-7 is ``lr = 5e-8`` here (``caffe_lr_to_torch``), which the ``paper`` preset uses.
This holds for the fc layers exactly; the conv layers' effective rate also depends on the input
scale (an input scaled by s acts like conv1's lr times s^2), and the paper's Caffe input scale is
not stated: we feed depth / 4 m in [0, 1] (shared.learning.model.preprocess_depth). The paper trains the
conv layers slower than the fc layers; ``conv_lr_scale`` (0.1) sets that ratio.
For scale: at initialisation, with momentum 0.99 (an effective rate of 100 lr), 5e-8 moves the fc
weights by about 0.5-4e-5 of their norm per update and the conv weights 10x less: learning over
the paper's 40k updates is plausible, over a few thousand it is slow; the ``fast`` preset (Adam)
is the one meant to learn quickly.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from shared.config import DQNConfig, ModelConfig, SensorConfig, is_finite_number, mask_commands, mirror_action
from shared.errors import CogexploreError
from shared.learning.model import (
    InferenceRunner,
    QNetwork,
    architecture_fingerprint,
    check_weights_fit,
    conv_autocast_dtype,
    forward_flops,
    load_tensors,
    mirror_images,
    preprocess_depth,
    reduce_allocator_page_faults,
    resolve_device,
    shift_images,
    weights_to_tensors,
)
from shared.learning.replay import Batch

CAFFE_EUCLIDEAN_TO_MEAN_MSE = 0.5
"""PyTorch lr per Caffe lr when Caffe's EuclideanLoss (1/2N) becomes our mean squared error (1/N)."""


class DQNError(CogexploreError):
    """A batch or state that does not fit the agent."""


class NonFiniteLoss(DQNError):
    """An update's loss is not finite; nothing was applied. ``non_finite`` marks the samples (B,) whose
    own loss is not finite or alone could overflow the mean (none marked: the demonstrations' margin loss
    is)."""

    def __init__(self, message: str, non_finite: np.ndarray):
        super().__init__(message)
        self.non_finite = non_finite


def caffe_lr_to_torch(caffe_lr: float) -> float:
    """The PyTorch learning rate equivalent to a Caffe EuclideanLoss learning rate (see module doc)."""
    return caffe_lr * CAFFE_EUCLIDEAN_TO_MEAN_MSE


def n_step_returns(rewards: torch.Tensor, n_steps: torch.Tensor, gamma: float) -> torch.Tensor:
    """sum_{k < n_steps} gamma^k rewards[:, k] for rewards (B, n) and n_steps (B,)."""
    n = rewards.shape[1]
    k = torch.arange(n, device=rewards.device)
    discounts = torch.pow(torch.full((n,), gamma, dtype=rewards.dtype, device=rewards.device), k)
    mask = k[None, :] < n_steps[:, None]
    return (rewards * discounts * mask).sum(dim=1)


def lr_factor(update_count: int, decay_updates: int, final_scale: float) -> float:
    """The learning-rate multiplier at ``update_count``: 1 falling linearly to ``final_scale`` at
    ``decay_updates``, then constant (1 throughout when ``decay_updates`` is 0)."""
    if decay_updates <= 0:
        return 1.0
    done = min(1.0, max(0, update_count) / decay_updates)
    return 1.0 - (1.0 - final_scale) * done


def td_targets(rewards: torch.Tensor, n_steps: torch.Tensor, terminated: torch.Tensor,
               next_q_target: torch.Tensor, gamma: float,
               next_q_online: torch.Tensor | None = None) -> torch.Tensor:
    """TD targets y (B,) from raw n-step data and next-state Q-values (B, A).

    ``next_q_online`` given: Double DQN (argmax by the online net, value by the target net).
    Rows with ``terminated`` never bootstrap, whatever their next-state values are.
    """
    if next_q_online is not None:
        best = next_q_online.argmax(dim=1, keepdim=True)
        bootstrap = next_q_target.gather(1, best).squeeze(1)
    else:
        bootstrap = next_q_target.max(dim=1).values
    returns, discount = _return_and_discount(rewards, n_steps, gamma, bootstrap)
    return torch.where(terminated, returns, returns + discount * bootstrap)


def _return_and_discount(rewards: torch.Tensor, n_steps: torch.Tensor, gamma: float,
                         like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each chain's n-step return and gamma^m (B,), in ``like``'s dtype and device."""
    discount = torch.pow(torch.tensor(gamma, dtype=like.dtype, device=like.device), n_steps.to(like.dtype))
    return n_step_returns(rewards.to(like.dtype), n_steps, gamma), discount


def quantile_td_targets(rewards: torch.Tensor, n_steps: torch.Tensor, terminated: torch.Tensor,
                        next_quantiles_target: torch.Tensor, gamma: float,
                        next_q_online: torch.Tensor | None = None) -> torch.Tensor:
    """QR-DQN's target distribution (B, N): the n-step return plus gamma^m times each return
    quantile (B, A, N) of theta^- at the next state's command, that command the argmax of the
    online net's Q-values ``next_q_online`` (Double DQN) or else of theta^-'s own quantile means.
    Rows with ``terminated`` are the return alone in every column."""
    chooser = next_q_online if next_q_online is not None else next_quantiles_target.mean(dim=2)
    best = chooser.argmax(dim=1)
    bootstrap = next_quantiles_target[torch.arange(len(best), device=best.device), best]  # (B, N)
    returns, discount = _return_and_discount(rewards, n_steps, gamma, bootstrap)
    return torch.where(terminated[:, None], returns[:, None].expand_as(bootstrap),
                       returns[:, None] + discount[:, None] * bootstrap)


def quantile_huber_loss(quantiles: torch.Tensor, targets: torch.Tensor, kappa: float) -> torch.Tensor:
    """Per-sample quantile Huber loss (B,) of predicted quantiles (B, N) at the midpoints
    tau_i = (2i + 1) / 2N against target samples (B, M) (Dabney et al. 2018, eq. 10): for each pair,
    |tau_i - 1{u < 0}| * Huber_kappa(u) / kappa with u = target_j - quantile_i, averaged over the
    targets and summed over the quantiles. Its minimiser puts quantile i at the tau_i-quantile of
    the targets."""
    n = quantiles.shape[1]
    tau = (torch.arange(n, dtype=quantiles.dtype, device=quantiles.device) + 0.5) / n
    u = targets[:, None, :] - quantiles[:, :, None]  # (B, N, M)
    huber = F.huber_loss(u, torch.zeros_like(u), reduction="none", delta=kappa)
    weight = (tau[None, :, None] - (u.detach() < 0).to(u.dtype)).abs()
    return (weight * huber / kappa).mean(dim=2).sum(dim=1)


def set_margin_loss(q_all: torch.Tensor, allowed: torch.Tensor, margin: float) -> tuple[torch.Tensor, float]:
    """Mean over samples of max(0, max_{a not allowed} Q(s, a) + margin - max_{a allowed} Q(s, a)):
    zero once the best allowed command (``allowed``: (B, A) bool, each row with some allowed and
    some not) leads every other by ``margin``; and the share of samples whose argmax is allowed.
    With one allowed command a_E this is DQfD's large-margin loss (Hester et al. 2018),
    max_a [Q(s, a) + margin * (a != a_E)] - Q(s, a_E)."""
    best_allowed = q_all.masked_fill(~allowed, float("-inf")).max(dim=1).values
    best_other = q_all.masked_fill(allowed, float("-inf")).max(dim=1).values
    loss = F.relu(best_other + float(margin) - best_allowed).mean()
    agreement = float(allowed.gather(1, q_all.detach().argmax(dim=1, keepdim=True)).float().mean())
    return loss, agreement


def large_margin_loss(q_all: torch.Tensor, label: torch.Tensor, margin: float) -> tuple[torch.Tensor, float]:
    """DQfD's large-margin loss: :func:`set_margin_loss` with the labelled command (a
    demonstration's, or the expert's) the one allowed; the share is of argmaxes that are the label."""
    return set_margin_loss(q_all, F.one_hot(label, q_all.shape[1]).bool(), margin)


@dataclass
class TensorBatch:
    """A replay Batch on the agent's device, preprocessed."""

    obs: torch.Tensor
    action: torch.Tensor
    rewards: torch.Tensor
    n_steps: torch.Tensor
    terminated: torch.Tensor
    next_obs: torch.Tensor
    weights: torch.Tensor
    previous_action: torch.Tensor  # (B, J) int64 commands before obs, most recent first; -1: none
    next_previous_action: torch.Tensor  # (B, J) int64
    demo: torch.Tensor | None = None  # (B,) bool: demonstration samples (never mirrored)
    expert_action: torch.Tensor | None = None  # (B,) int64 labelled command (large-margin loss), -1: none
    safe: torch.Tensor | None = None  # (B, A) bool commands with a way out (safe-set margin loss); no row: none


def mirror_batch(tb: TensorBatch, flip: torch.Tensor) -> TensorBatch:
    """``tb`` with the transitions where ``flip`` (B,) is true mirrored left-right: both frames
    flipped horizontally and the commands swapped (left <-> right, half-left <-> half-right), the
    previous ones too. Rewards, returns and episode ends are those of the mirror-image transition
    unchanged."""
    def mirror(action: torch.Tensor) -> torch.Tensor:
        rows = flip.reshape(-1, *([1] * (action.dim() - 1)))  # (B,) or (B, J) commands
        return torch.where(rows & (action >= 0), mirror_action(action), action)

    return dataclasses.replace(tb, obs=mirror_images(tb.obs, flip), next_obs=mirror_images(tb.next_obs, flip),
                               action=mirror(tb.action), previous_action=mirror(tb.previous_action),
                               next_previous_action=mirror(tb.next_previous_action),
                               expert_action=None if tb.expert_action is None else mirror(tb.expert_action),
                               safe=None if tb.safe is None else
                               torch.where(flip[:, None], tb.safe.flip(dims=[1]), tb.safe))


@dataclass(frozen=True)
class Augmentation:
    """One update's random draws for its batch: which samples are mirrored (``dqn.mirror_augment``)
    and by how many pixels each frame moves (``dqn.shift_augment_px``; (B, 2) (dy, dx), the
    frame before and the frame after each drawn on its own, as DrQ does)."""

    flip: torch.Tensor | None = None
    obs_shift: torch.Tensor | None = None
    next_obs_shift: torch.Tensor | None = None

    def apply(self, tb: TensorBatch) -> TensorBatch:
        if self.flip is not None:
            tb = mirror_batch(tb, self.flip)
        if self.obs_shift is not None:
            tb = dataclasses.replace(tb, obs=shift_images(tb.obs, self.obs_shift),
                                     next_obs=shift_images(tb.next_obs, self.next_obs_shift))
        return tb


@dataclass
class PreparedBatch:
    """A TensorBatch, augmented, and its TD targets: all an update needs but the gradient step."""

    tb: TensorBatch
    y: torch.Tensor  # (B,) TD targets, or (B, N) target return samples for a model.quantiles network


class DQNAgent:
    """Online and target Q-networks, optimiser and counters: the core of every learner.

    ``update(batch)`` does one gradient step and returns metrics; ``weights()`` exports the
    online weights as CPU tensors for weight messages; ``policy_version`` changes whenever the
    online weights do (each update, each load), so actors can tell new weights from old.
    ``seed`` seeds torch's global generator (weight initialisation, dropout masks); checkpoints
    save and restore that generator so a resumed run draws the same masks.
    """

    def __init__(self, model_cfg: ModelConfig | None = None, sensor_cfg: SensorConfig | None = None,
                 dqn_cfg: DQNConfig | None = None, device: str | torch.device = "auto",
                 seed: int | None = None):
        reduce_allocator_page_faults()
        self.model_cfg = model_cfg or ModelConfig()
        self.sensor_cfg = sensor_cfg or SensorConfig()
        self.cfg = dqn_cfg or DQNConfig()
        self.device = resolve_device(device)
        if seed is not None:
            torch.manual_seed(seed)
        self.online = QNetwork(self.model_cfg, self.sensor_cfg).to(self.device)
        # the updates' conv arithmetic; the policies acting on these weights run float32
        self.online.conv_autocast = conv_autocast_dtype(self.cfg.conv_precision, self.device)
        self.target = copy.deepcopy(self.online)
        self.target.eval()
        for p in self.target.parameters():
            p.requires_grad_(False)
        self.fingerprint = architecture_fingerprint(self.online)
        self.optimizer = self._make_optimizer()
        self.update_count = 0
        self.policy_version = 0
        self.target_version = 0  # bumped whenever theta^- is written (sync, state load): copies can skip it
        self._runner = InferenceRunner(self.online)

    def _make_optimizer(self) -> torch.optim.Optimizer:
        cfg = self.cfg
        conv, head = self.online.conv_parameters(), self.online.head_parameters()
        groups: list[dict[str, Any]] = [{"params": head, "lr": cfg.lr, "name": "fc"}]
        if cfg.conv_lr_scale > 0:
            groups.append({"params": conv, "lr": cfg.lr * cfg.conv_lr_scale, "name": "conv"})
        else:
            # frozen representation: no conv weight gradients at all (saves a third of backward)
            for p in conv:
                p.requires_grad_(False)
        # fused: one kernel over all parameters (Adam's step: 0.4 ms instead of 2.9 ms on one CPU
        # core, an eighth of a bfloat16 update), the same arithmetic as the per-tensor loop
        if cfg.optimizer == "sgd":
            return torch.optim.SGD(groups, lr=cfg.lr, momentum=cfg.momentum, fused=True)
        return torch.optim.Adam(groups, lr=cfg.lr, fused=True)

    @property
    def lr(self) -> float:
        """The fully connected layers' learning rate now (the first parameter group's)."""
        return float(self.optimizer.param_groups[0]["lr"])

    def _set_lr(self, factor: float) -> None:
        # From the config, not from the groups: a restored optimizer state brings its own lr.
        for group in self.optimizer.param_groups:
            scale = self.cfg.conv_lr_scale if group.get("name") == "conv" else 1.0
            group["lr"] = self.cfg.lr * scale * factor

    # ------------------------------------------------------------------ data
    def to_tensors(self, batch: Batch) -> TensorBatch:
        if len(batch) < 1:
            raise DQNError("empty batch")
        stack = self.model_cfg.frame_stack
        want = (self.sensor_cfg.height, self.sensor_cfg.width) if stack == 1 else \
            (stack, self.sensor_cfg.height, self.sensor_cfg.width)
        if batch.obs.shape[1:] != want or batch.next_obs.shape[1:] != want:
            raise DQNError(f"batch frames {batch.obs.shape[1:]} do not fit the sensor and model.frame_stack {want}"
                           + (" (sample the replay with frames=model.frame_stack)" if stack > 1 else ""))
        dev = self.device
        return TensorBatch(
            obs=preprocess_depth(batch.obs, dev),
            action=torch.as_tensor(batch.action, dtype=torch.int64, device=dev),
            rewards=torch.as_tensor(batch.rewards, dtype=torch.float32, device=dev),
            n_steps=torch.as_tensor(batch.n_steps, dtype=torch.int64, device=dev),
            terminated=torch.as_tensor(batch.terminated, dtype=torch.bool, device=dev),
            next_obs=preprocess_depth(batch.next_obs, dev),
            weights=torch.as_tensor(batch.weights, dtype=torch.float32, device=dev),
            previous_action=torch.as_tensor(batch.previous_action, dtype=torch.int64, device=dev),
            next_previous_action=torch.as_tensor(batch.next_previous_action, dtype=torch.int64, device=dev),
            demo=None if batch.demo is None else torch.as_tensor(batch.demo, dtype=torch.bool, device=dev),
            expert_action=None if batch.expert_action is None or not (batch.expert_action >= 0).any() else
            torch.as_tensor(batch.expert_action, dtype=torch.int64, device=dev),
            safe=None if batch.safe_commands is None or not batch.safe_commands.any() else
            torch.as_tensor(mask_commands(batch.safe_commands), device=dev),
        )

    # ------------------------------------------------------------------ update
    @torch.no_grad()
    def compute_targets(self, tb: TensorBatch, online: QNetwork | None = None,
                        target: QNetwork | None = None) -> torch.Tensor:
        """TD targets y (B,) with theta^- (and theta, eval mode, for Double DQN). ``online`` and
        ``target`` replace the agent's own two nets (a :class:`shared.learning.pipeline.TargetPipeline`
        passes its copies, which no update writes to while it reads them)."""
        online = self.online if online is None else online
        target = self.target if target is None else target
        quantiles = self.model_cfg.quantiles > 0
        next_q_target = (target.return_quantiles if quantiles else target)(tb.next_obs, tb.next_previous_action)
        next_q_online = None
        if self.cfg.double_dqn:
            was_training = online.training
            online.eval()
            try:
                next_q_online = online(tb.next_obs, tb.next_previous_action)
            finally:
                online.train(was_training)
        targets = quantile_td_targets if quantiles else td_targets
        return targets(tb.rewards, tb.n_steps, tb.terminated, next_q_target, self.cfg.gamma, next_q_online)

    def draw_augmentation(self, batch: Batch | TensorBatch) -> Augmentation | None:
        """This update's mirror flips and pixel shifts for ``batch`` (None with neither
        ``mirror_augment`` nor ``shift_augment_px``): drawn from torch's global generator, the one a
        checkpoint restores, so they are always drawn here, on the thread that trains, in the same
        order as the dropout masks."""
        n = len(batch.action)
        flip = obs_shift = next_obs_shift = None
        if self.cfg.mirror_augment:
            flip = torch.rand(n, device=self.device) < 0.5
            if batch.demo is not None:
                # A demonstration commits to one of two mirror-image manoeuvres; in a symmetric
                # scene (paper-indoor's start 6 sees an exactly symmetric dead end) its mirror
                # would teach the other turn on the same image, and the two would tie.
                flip &= ~torch.as_tensor(batch.demo, dtype=torch.bool, device=self.device)
        px = self.cfg.shift_augment_px
        if px > 0:
            obs_shift, next_obs_shift = torch.randint(-px, px + 1, (2, n, 2), device=self.device)
        if flip is None and obs_shift is None:
            return None
        return Augmentation(flip, obs_shift, next_obs_shift)

    def prepare(self, batch: Batch | TensorBatch, augmentation: Augmentation | None,
                online: QNetwork | None = None, target: QNetwork | None = None) -> PreparedBatch:
        """The part of an update that needs no gradient: tensors, the augmentation drawn by
        :meth:`draw_augmentation` and TD targets (see :meth:`compute_targets` for ``online``/``target``)."""
        tb = batch if isinstance(batch, TensorBatch) else self.to_tensors(batch)
        if augmentation is not None:
            tb = augmentation.apply(tb)
        return PreparedBatch(tb, self.compute_targets(tb, online, target))

    def update(self, batch: Batch | TensorBatch) -> dict[str, Any]:
        """One gradient step on ``batch``; syncs theta^- every C updates. Returns metrics.

        Metrics: update (count after this step), policy_version, loss, q_mean (taken actions),
        target_mean, td_abs_mean, grad_norm, synced_target, and td_errors (numpy (B,), y - Q)
        for prioritised replay.
        """
        return self.apply(self.prepare(batch, self.draw_augmentation(batch)))

    def apply(self, prepared: PreparedBatch) -> dict[str, Any]:
        """The gradient step of :meth:`update` on a prepared batch (its targets already computed)."""
        tb, y = prepared.tb, prepared.y
        self.online.train()
        if self.model_cfg.quantiles:
            taken = self.online.return_quantiles(tb.obs, tb.previous_action)  # (B, A, N)
            q_all = taken.mean(dim=2)
            taken = taken[torch.arange(len(tb.action), device=taken.device), tb.action]  # (B, N)
            per_sample = quantile_huber_loss(taken, y, self.cfg.quantile_kappa)
            q, y = taken.mean(dim=1), y.mean(dim=1)  # the Q-value and its target, for the metrics
        else:
            q_all = self.online(tb.obs, tb.previous_action)
            q = q_all.gather(1, tb.action[:, None]).squeeze(1)
            per_sample = (F.smooth_l1_loss(q, y, reduction="none", beta=1.0) if self.cfg.loss == "huber"
                          else (q - y).square())
        loss = (per_sample * tb.weights).mean()
        label_metrics: dict[str, float] = {}
        if tb.expert_action is not None and self.cfg.demo_weight > 0:
            labelled = tb.expert_action >= 0  # demonstrations and the expert's labels
            margin_loss, agreement = large_margin_loss(q_all[labelled], tb.expert_action[labelled],
                                                       self.cfg.demo_margin)
            loss = loss + self.cfg.demo_weight * margin_loss
            label_metrics = {"label_margin_loss": float(margin_loss.detach()), "label_agreement": agreement}
        if tb.safe is not None and self.cfg.safe_weight > 0:
            # only where the mark tells commands apart: all-safe and none-safe rows carry no contrast
            marked = tb.safe.any(dim=1) & ~tb.safe.all(dim=1)
            if bool(marked.any()):
                safe_loss, agreement = set_margin_loss(q_all[marked], tb.safe[marked], self.cfg.safe_margin)
                loss = loss + self.cfg.safe_weight * safe_loss * (marked.float().mean())
                label_metrics.update(safe_margin_loss=float(safe_loss.detach()), safe_agreement=agreement)
        if not torch.isfinite(loss):
            # The offenders: a sample whose own loss is not finite, or so large that it alone can
            # overflow the batch mean (a Huber loss stays finite where the squared error does not).
            limit = torch.finfo(per_sample.dtype).max / len(per_sample)
            offenders = ~torch.isfinite(per_sample) | (per_sample.abs() > limit)
            raise NonFiniteLoss(f"non-finite loss {loss.item()} at update {self.update_count + 1}",
                                offenders.cpu().numpy())
        if self.cfg.lr_decay_updates > 0:
            self._set_lr(lr_factor(self.update_count, self.cfg.lr_decay_updates, self.cfg.lr_final_scale))
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        params = [p for p in self.online.parameters() if p.grad is not None]
        if self.cfg.grad_clip_norm > 0:
            grad_norm = torch.nn.utils.clip_grad_norm_(params, self.cfg.grad_clip_norm)
        else:
            grad_norm = torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in params]))
        self.optimizer.step()
        self.update_count += 1
        self.policy_version += 1
        synced = self.update_count % self.cfg.target_sync_every == 0
        if synced:
            self.sync_target()
        td = (y - q).detach()
        return {
            "update": self.update_count,
            "policy_version": self.policy_version,
            "loss": float(loss.detach()),
            "q_mean": float(q.detach().mean()),
            "target_mean": float(y.mean()),
            "td_abs_mean": float(td.abs().mean()),
            "grad_norm": float(grad_norm),
            "synced_target": synced,
            "td_errors": td.cpu().numpy(),
            **label_metrics,
        }

    def sync_target(self) -> None:
        """theta^- <- theta."""
        with torch.no_grad():
            for pt, po in zip(self.target.parameters(), self.online.parameters()):
                pt.copy_(po)
        self.target_version += 1

    # ------------------------------------------------------------------ acting and weights
    def q_values(self, depth: Any, previous_action: Any = None) -> np.ndarray:
        """Greedy-time Q-values of the online net (dropout off) for (H, W) or (B, H, W) depth
        (and the previous commands, for a ``model.previous_action`` net)."""
        return self._runner.q_values(depth, previous_action)

    def weights(self) -> dict[str, torch.Tensor]:
        """Online weights as CPU tensors (for weight messages and exports)."""
        return weights_to_tensors(self.online)

    def load_weights(self, tensors: dict[str, torch.Tensor], sync_target: bool = True) -> None:
        """Replace the online weights (e.g. pretrained); bumps policy_version."""
        load_tensors(self.online, tensors)
        if sync_target:
            self.sync_target()
        self.policy_version += 1

    # ------------------------------------------------------------------ state for checkpoints
    def state_tensors(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """(tensors, JSON-able metadata) that restore this agent exactly (see shared.learning.checkpoints).

        Tensors: ``online.*``, ``target.*``, ``optim.<param index>.<key>``, ``rng.torch``
        (and ``rng.cuda``); the metadata holds counters, optimiser hyperparameters and configs.
        """
        tensors = {f"online.{k}": v for k, v in weights_to_tensors(self.online).items()}
        tensors.update({f"target.{k}": v for k, v in weights_to_tensors(self.target).items()})
        opt = self.optimizer.state_dict()
        scalars: dict[str, dict[str, Any]] = {}
        for idx, st in opt["state"].items():
            for key, val in st.items():
                if isinstance(val, torch.Tensor):
                    # contiguous NCHW: safetensors has no strides (momentum buffers follow the
                    # weights' channels-last layout on the device)
                    tensors[f"optim.{idx}.{key}"] = val.detach().to("cpu").contiguous()
                else:
                    scalars.setdefault(str(idx), {})[key] = val
        tensors["rng.torch"] = torch.get_rng_state()
        if self.device.type == "cuda":
            tensors["rng.cuda"] = torch.cuda.get_rng_state(self.device)
        meta = {
            "update_count": self.update_count,
            "policy_version": self.policy_version,
            "fingerprint": self.fingerprint,
            "optimizer": {"type": type(self.optimizer).__name__, "param_groups": opt["param_groups"],
                          "scalars": scalars},
            "model": asdict(self.model_cfg), "sensor": asdict(self.sensor_cfg),
            "dqn": asdict(self.cfg),
        }
        return tensors, meta

    def load_state_tensors(self, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
        """Inverse of ``state_tensors``; refuses state of another architecture or optimiser, or a tensor or
        optimiser hyper-parameter that does not fit, before anything of the agent changes."""
        if meta.get("fingerprint") != self.fingerprint:
            raise DQNError(f"state is for architecture {meta.get('fingerprint')}, this agent is "
                           f"{self.fingerprint}")
        opt_meta = meta["optimizer"]
        if opt_meta["type"] != type(self.optimizer).__name__:
            raise DQNError(f"state has a {opt_meta['type']} optimiser, this agent uses "
                           f"{type(self.optimizer).__name__}")
        online = {k[7:]: v for k, v in tensors.items() if k.startswith("online.")}
        target = {k[7:]: v for k, v in tensors.items() if k.startswith("target.")}
        check_weights_fit(self.online, online)
        check_weights_fit(self.target, target)
        state = self._optimizer_state(tensors, opt_meta)
        self._check_param_groups(opt_meta["param_groups"])
        update_count, policy_version = int(meta["update_count"]), int(meta["policy_version"])
        rngs = {"rng.torch": torch.get_rng_state()}
        if self.device.type == "cuda":
            rngs["rng.cuda"] = torch.cuda.get_rng_state(self.device)
        for name, now in rngs.items():
            if name in tensors:
                _check_fits(name, tensors[name], now.shape, now.dtype)
        # all checked: from here on nothing refuses, so a misfit never leaves the agent half loaded
        # The agent's config sets the hyper-parameters, not the file: a run resumed with `--set dqn.lr=...`
        # (after a divergence, say) trains at the rate its saved config.toml now says.
        own_groups = [{k: v for k, v in g.items() if k != "params"} for g in self.optimizer.param_groups]
        self.optimizer.load_state_dict({"state": state, "param_groups": opt_meta["param_groups"]})
        for group, own in zip(self.optimizer.param_groups, own_groups):
            group.update(own)
        load_tensors(self.online, online)
        load_tensors(self.target, target)
        self.target_version += 1
        self.update_count = update_count
        self.policy_version = policy_version
        self._set_lr(lr_factor(update_count, self.cfg.lr_decay_updates, self.cfg.lr_final_scale))
        if "rng.torch" in tensors:
            torch.set_rng_state(tensors["rng.torch"])
        if "rng.cuda" in tensors and self.device.type == "cuda":
            torch.cuda.set_rng_state(tensors["rng.cuda"], self.device)

    def _check_param_groups(self, saved_groups: list[dict[str, Any]]) -> None:
        """DQNError unless each saved optimiser group holds this agent's group's hyper-parameters, each
        a sane value: ``load_state_dict`` takes them unchecked, and an lr that is a string, NaN or
        negative, or betas that are no pair, failed only in the first step or trained on nonsense.
        Their values give way to the agent's own config's on loading, so numbers are checked for range
        only (a value out of range marks a damaged file); flags and names must be this agent's own."""
        for i, (saved, own) in enumerate(zip(saved_groups, self.optimizer.param_groups)):
            where = f"state's optimiser group {i} ({own.get('name')})"
            keys, own_keys = set(saved) - {"params"}, set(own) - {"params"}
            if keys != own_keys:
                key = sorted(map(str, keys ^ own_keys))[0]
                raise DQNError(f"{where}: {'no' if key in own_keys else 'an unknown'} hyper-parameter {key!r} "
                               "(a damaged or hand-made checkpoint?)")
            for key in sorted(own_keys):
                wanted = _hyperparameter_misfit(key, saved[key], own[key])
                if wanted is not None:
                    raise DQNError(f"{where}: {key} is {saved[key]!r}, not {wanted} (a damaged or hand-made "
                                   "checkpoint?)")

    def _optimizer_state(self, tensors: dict[str, torch.Tensor], opt_meta: dict[str, Any]) -> dict[int, dict[str, Any]]:
        """The optimiser state that ``state_tensors`` saved, for ``optimizer.load_state_dict``: each
        tensor checked against its parameter (its shape and dtype; ``step`` a float32 scalar), since
        torch casts any dtype silently (a complex one loses its imaginary part) and a fused step on a
        moment of another shape corrupts the process's memory."""
        params = [p for g in self.optimizer.param_groups for p in g["params"]]
        saved_groups = opt_meta["param_groups"]
        saved_sizes = [len(g["params"]) for g in saved_groups]
        own_sizes = [len(g["params"]) for g in self.optimizer.param_groups]
        if saved_sizes != own_sizes:
            raise DQNError(f"state's optimiser groups hold {saved_sizes} parameters, this agent's {own_sizes}")
        param_of = dict(zip((i for g in saved_groups for i in g["params"]), params))  # as load_state_dict maps them
        state: dict[int, dict[str, Any]] = {}
        for key, val in tensors.items():
            if not key.startswith("optim."):
                continue
            idx, _, name = key[6:].partition(".")
            param = param_of.get(int(idx)) if idx.isascii() and idx.isdigit() else None
            if param is None or not name:
                raise DQNError(f"{key}: optimiser state of no parameter of this agent")
            if name == "step":
                _check_fits(key, val, (), torch.float32)
            else:
                _check_fits(key, val, param.shape, param.dtype)
                # our parameters' layout (channels-last) for the moments, before the optimiser copies
                # them: keeps the resumed update bit-identical to the uninterrupted one
                val = val.to(self.device).contiguous(memory_format=_memory_format(param))
            state.setdefault(int(idx), {})[name] = val
        for idx, vals in opt_meta["scalars"].items():
            state.setdefault(int(idx), {}).update(vals)
        return state


def _check_fits(name: str, t: torch.Tensor, shape: tuple[int, ...] | torch.Size, dtype: torch.dtype) -> None:
    """DQNError unless the saved tensor ``name`` has exactly this shape and dtype."""
    if tuple(t.shape) != tuple(shape) or t.dtype != dtype:
        raise DQNError(f"{name}: {t.dtype} of shape {tuple(t.shape)}, this agent wants {dtype} of shape "
                       f"{tuple(shape)} (a damaged or hand-made checkpoint?)")


def _hyperparameter_misfit(key: str, value: Any, own: Any) -> str | None:
    """What optimiser hyper-parameter ``key`` should be where ``value`` is not that, else None; the
    agent's own value ``own`` tells its kind. The bounds are torch's own (and momentum's the config's)."""
    if isinstance(own, (tuple, list)):  # Adam's betas
        fits = (isinstance(value, (tuple, list)) and len(value) == len(own)
                and all(is_finite_number(b) and 0 <= b < 1 for b in value))
        return None if fits else f"{len(own)} numbers in [0, 1)"
    if is_finite_number(own):  # lr, eps, weight_decay, momentum, dampening
        if key == "momentum":
            return None if is_finite_number(value) and 0 <= value < 1 else "a number in [0, 1)"
        return None if is_finite_number(value) and value >= 0 else "a finite number >= 0"
    # flags (amsgrad, nesterov, fused, ...) and the group's name: how this agent computes, not hyper-parameters
    return None if type(value) is type(own) and value == own else f"{own!r} as this agent's"


def _memory_format(t: torch.Tensor) -> torch.memory_format:
    if t.dim() == 4 and t.is_contiguous(memory_format=torch.channels_last):
        return torch.channels_last
    return torch.contiguous_format


def update_flops(net: QNetwork, batch_size: int, double_dqn: bool = True,
                 conv_trainable: bool = True) -> int:
    """Multiply-add FLOPs of one update: target (and Double-DQN online) forwards on next_obs, the
    training forward on obs, and its backward (weight gradients everywhere; input gradients
    everywhere except conv1, whose input needs none). Pooling and ReLU are not counted."""
    per_layer = forward_flops(net)
    fwd = sum(per_layer.values())
    conv1 = per_layer.get("conv1", 0)
    if conv_trainable:
        backward = 2 * fwd - conv1
    else:
        conv = sum(v for k, v in per_layer.items() if k.startswith("conv"))
        backward = 2 * (fwd - conv)
    nograd_forwards = 2 if double_dqn else 1
    return int(batch_size * (fwd * (1 + nograd_forwards) + backward))

