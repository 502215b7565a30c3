"""The authors' supervised obstacle-avoidance model (Tai et al., IROS 2016), rebuilt in simulation.

:func:`train_supervised` trains ``shared.learning.model.SupervisedNet`` (the Q-network's conv
stack + one fc layer to 5 classes, softmax cross-entropy) on a dataset of expert-labelled depth
images (``shared.expert.dataset``) with Adam, mirrored images as augmentation (a mirrored image's
label is the mirrored command). The model file (format ``cogexplore-supervised``) and the transfer
of its conv layers into a DQN agent (the paper's) live with every other model file in
``shared.learning.checkpoints``. :func:`pretrain` does all of it: data, training, model file.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from shared.config import (
    ACTION_NAMES,
    DEPTH_ENCODINGS,
    MAX_SEED,
    NUM_ACTIONS,
    EnvConfig,
    SensorConfig,
    is_whole,
    mirror_action,
)
from shared.expert.dataset import (
    DriveConfig,
    SupervisedDataset,
    dataset_request,
    open_or_generate,
)
from shared.expert.expert import ExpertConfig, SupervisedError
from shared.files import nearest_existing
from shared.learning.checkpoints import card_path, save_supervised, supervised_model_path
from shared.learning.model import (
    SupervisedNet,
    mirror_images,
    preprocess_depth,
    reduce_allocator_page_faults,
    resolve_device,
)


def _check_seed(seed: Any) -> None:
    # bounded as train.seed is: torch.manual_seed overflows past 2**64, after the data is collected
    if not (is_whole(seed) and 0 <= seed <= MAX_SEED):
        raise SupervisedError(f"seed must be an integer in [0, {MAX_SEED}] (2**53 - 1), got {seed!r}")


MAX_EPOCHS = 10_000
"""The most supervised training epochs: thousands of times the default 3, yet a bound, so that a
mistyped count is refused at once instead of training for ever."""


@dataclass(frozen=True)
class TrainSettings:
    """Supervised training hyperparameters."""

    epochs: int = 3
    batch_size: int = 64
    lr: float = 1e-3
    """Adam learning rate."""
    weight_decay: float = 1e-4
    mirror: bool = True
    """Mirror each batch's images with probability 1/2 (labels mirrored too)."""
    class_balance: float = 0.5
    """Cross-entropy class weights (1 / class frequency) ** class_balance: 0 is the plain loss
    (which, with most labels 'straight', can settle on always answering straight), 1 weighs
    every class equally; in between trades overall accuracy for the turns' accuracy."""
    seed: int = 0
    device: str = "auto"
    depth_encoding: str = "metric"
    """The network's depth input encoding (``ModelConfig.depth_encoding``); a DRL run that copies
    these conv layers must use the same one."""

    def __post_init__(self) -> None:
        _check_seed(self.seed)
        if self.depth_encoding not in DEPTH_ENCODINGS:
            raise SupervisedError(f"depth_encoding must be one of {', '.join(DEPTH_ENCODINGS)}, "
                                  f"got {self.depth_encoding!r}")
        if not (is_whole(self.epochs) and 1 <= self.epochs <= MAX_EPOCHS):
            raise SupervisedError(f"epochs must be an integer in [1, {MAX_EPOCHS}], got {self.epochs!r}")
        if not (isinstance(self.batch_size, int) and 1 <= self.batch_size <= 4096):
            raise SupervisedError(f"batch_size must be an integer in [1, 4096], got {self.batch_size!r}")
        if not (isinstance(self.lr, (int, float)) and 0 < self.lr <= 1):
            raise SupervisedError(f"lr must be in (0, 1], got {self.lr!r}")
        if not (isinstance(self.weight_decay, (int, float)) and 0 <= self.weight_decay < 1):
            raise SupervisedError(f"weight_decay must be in [0, 1), got {self.weight_decay!r}")
        if not (isinstance(self.class_balance, (int, float)) and 0 <= self.class_balance <= 1):
            raise SupervisedError(f"class_balance must be in [0, 1], got {self.class_balance!r}")


def confusion_matrix(true: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """(5, 5) counts: row = expert label, column = predicted command."""
    m = np.zeros((NUM_ACTIONS, NUM_ACTIONS), np.int64)
    np.add.at(m, (np.asarray(true, np.int64), np.asarray(pred, np.int64)), 1)
    return m


def classification_metrics(true: np.ndarray, pred: np.ndarray) -> dict[str, Any]:
    """Accuracy, per-class accuracy (recall; None for a class with no example), balanced accuracy
    (mean over the classes present: chance is 1/5 whatever the label distribution) and the
    confusion matrix."""
    cm = confusion_matrix(true, pred)
    support = cm.sum(axis=1)
    per_class = {name: (float(cm[i, i] / support[i]) if support[i] else None) for i, name in enumerate(ACTION_NAMES)}
    present = [v for v in per_class.values() if v is not None]
    total = int(support.sum())
    return {"accuracy": float(np.trace(cm) / total) if total else 0.0,
            "balanced_accuracy": float(np.mean(present)) if present else 0.0,
            "per_class_accuracy": per_class, "support": {n: int(s) for n, s in zip(ACTION_NAMES, support)},
            "confusion_matrix": cm.tolist(), "frames": total}


def predict(net: SupervisedNet, depth_mm: np.ndarray, indices: np.ndarray | None = None,
            batch_size: int = 256) -> np.ndarray:
    """Predicted commands (argmax of the logits, eval mode) for frames of (N, H, W) depth."""
    device = next(net.parameters()).device
    idx = np.arange(len(depth_mm)) if indices is None else np.asarray(indices)
    out = np.empty(len(idx), np.int64)
    was_training = net.training
    net.eval()
    try:
        with torch.inference_mode():
            for i in range(0, len(idx), batch_size):
                chunk = np.sort(idx[i:i + batch_size])  # sorted: sequential reads from the memmap
                order = np.argsort(np.argsort(idx[i:i + batch_size]))
                logits = net(preprocess_depth(np.asarray(depth_mm[chunk]), device))
                out[i:i + len(chunk)] = logits.argmax(dim=1).cpu().numpy()[order]
    finally:
        net.train(was_training)
    return out


def train_supervised(dataset: SupervisedDataset, settings: TrainSettings | None = None, *,
                     progress: bool = True) -> tuple[SupervisedNet, dict[str, Any]]:
    """Train a SupervisedNet on the dataset's train split; returns it (eval mode) and its model
    card (data size, label distribution, test accuracy, per-class accuracy, confusion matrix, and
    ``majority_accuracy``: the test accuracy of always answering the training split's most common
    label, ``majority_command``). SupervisedError at the first batch whose loss is not finite."""
    from tqdm import tqdm

    s = settings or TrainSettings()
    reduce_allocator_page_faults()
    device = resolve_device(s.device)
    train_idx, test_idx = dataset.split()
    if len(train_idx) == 0 or len(test_idx) == 0:
        raise SupervisedError(f"{dataset.root}: the split has {len(train_idx)} train and {len(test_idx)} test frames")
    torch.manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    net = SupervisedNet(dataset.sensor_cfg, s.depth_encoding).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=s.lr, weight_decay=s.weight_decay)
    labels_all = np.asarray(dataset.labels)
    freq = np.bincount(labels_all[train_idx], minlength=NUM_ACTIONS).astype(np.float64)
    if s.mirror:
        freq = (freq + freq[::-1]) / 2  # what the mirrored batches see on average
    freq = np.maximum(freq, 1.0) / freq.sum()
    weights = (1.0 / (NUM_ACTIONS * freq)) ** s.class_balance
    class_weights = torch.tensor(weights / (weights * freq).sum(), dtype=torch.float32, device=device)
    steps_per_epoch = math.ceil(len(train_idx) / s.batch_size)
    started = time.monotonic()
    history: list[dict[str, float]] = []
    net.train()
    with tqdm(total=s.epochs * steps_per_epoch, desc="train SL", unit="batch", disable=not progress) as bar:
        for epoch in range(s.epochs):
            perm = rng.permutation(train_idx)
            loss_sum, correct, seen = 0.0, 0, 0
            for b in range(steps_per_epoch):
                idx = np.sort(perm[b * s.batch_size:(b + 1) * s.batch_size])
                x = preprocess_depth(np.asarray(dataset.depth_mm[idx]), device)
                y = torch.from_numpy(labels_all[idx].astype(np.int64)).to(device)
                if s.mirror:
                    flip = torch.from_numpy(rng.random(len(idx)) < 0.5).to(device)
                    x = mirror_images(x, flip)
                    y = torch.where(flip, mirror_action(y), y)
                logits = net(x)
                loss = F.cross_entropy(logits, y, weight=class_weights)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                batch_loss = float(loss.detach())
                if not math.isfinite(batch_loss):  # every later step is NaN: stop before the model is written
                    raise SupervisedError(f"the training loss is {batch_loss} at epoch {epoch + 1}, batch {b + 1}: "
                                          f"training diverged at lr {s.lr}; try a lower --lr")
                loss_sum += batch_loss * len(idx)
                correct += int((logits.detach().argmax(1) == y).sum())
                seen += len(idx)
                bar.update(1)
                bar.set_postfix(epoch=epoch + 1, loss=f"{loss_sum / seen:.3f}", acc=f"{correct / seen:.3f}")
            test = classification_metrics(labels_all[test_idx], predict(net, dataset.depth_mm, test_idx))
            history.append({"epoch": epoch + 1, "train_loss": loss_sum / seen, "train_accuracy": correct / seen,
                            "test_accuracy": test["accuracy"], "test_balanced_accuracy": test["balanced_accuracy"]})
    seconds = time.monotonic() - started
    net.eval()
    test = classification_metrics(labels_all[test_idx], predict(net, dataset.depth_mm, test_idx))
    counts = dataset.label_counts()
    # The baseline beside the test accuracy: the training split's most common label, answered on the test split.
    majority = int(np.argmax(np.bincount(labels_all[train_idx], minlength=NUM_ACTIONS)))
    card = {
        "model": "SupervisedNet (ConvTrunk + fc to 5 classes, softmax)",
        "data": {"root": str(dataset.root), "frames": len(dataset), "train_frames": len(train_idx),
                 "test_frames": len(test_idx), "episodes": int(dataset.manifest["episodes"]),
                 "test_episodes": len(dataset.manifest["test_episodes"]), "worlds": dataset.manifest["worlds"],
                 "speed_table": dataset.manifest.get("speed_table"),
                 "label_counts": counts},
        "training": {**asdict(s), "seconds": round(seconds, 2), "class_weights": weights.tolist(),
                     "history": history},
        "test": test,
        "accuracy": test["accuracy"],
        "balanced_accuracy": test["balanced_accuracy"],
        "majority_command": ACTION_NAMES[majority],
        "majority_accuracy": float(np.mean(labels_all[test_idx] == majority)),
        "per_class_accuracy": test["per_class_accuracy"],
        "confusion_matrix": test["confusion_matrix"],
        "classes": list(ACTION_NAMES),
    }
    return net, json.loads(json.dumps(card))  # plain JSON types, as the model file stores it


def _check_writable(folder: Path) -> None:
    """SupervisedError unless a file can be made in ``folder`` (or, where it is missing, in the
    nearest folder above it, under which ``save_supervised`` makes it): a read-only folder was
    found by the last write, after the data and the training, and as a traceback."""
    at = nearest_existing(folder)
    try:
        with tempfile.TemporaryFile(dir=at):  # a real write: a read-only mount, no permission, not a folder
            pass
    except OSError as exc:
        raise SupervisedError(f"{folder}: the model cannot be written there ({at}: {exc.strerror or exc})") from None


@dataclass
class PretrainResult:
    """What :func:`pretrain` produced."""

    model_path: Path
    card: dict[str, Any]
    dataset: SupervisedDataset
    data_reused: bool
    seconds: dict[str, float] = field(default_factory=dict)


def pretrain(out: str | Path, *, worlds: Sequence[str], frames: int, sensor_cfg: SensorConfig,
             env_cfg: EnvConfig, data_dir: str | Path | None = None, settings: TrainSettings | None = None,
             expert_cfg: ExpertConfig | None = None, drive_cfg: DriveConfig | None = None, seed: int = 0,
             test_fraction: float = 0.2, progress: bool = True) -> PretrainResult:
    """Generate (or reuse) the data, train, and write the model and its card to ``out``."""
    out = supervised_model_path(out)  # refused now, not after the data and the training
    _check_seed(seed)
    settings = settings or TrainSettings(seed=seed)
    resolve_device(settings.device)  # a device this machine lacks fails now, not after collecting the data
    data_dir = Path(data_dir) if data_dir is not None else out.with_name(out.name.removesuffix(".safetensors") + "-data")
    for path in (out, card_path(out)):  # written at the end: refused now, not after the data and the training
        if path.is_dir() or path.resolve() == data_dir.resolve():  # resolved: x/../sl.safetensors is it too
            raise SupervisedError(f"{path} is {'a folder' if path.is_dir() else 'the dataset folder (--data)'}: "
                                  "the model and its card need a file of their own")
    _check_writable(out.parent)
    request = dataset_request(worlds, frames, sensor_cfg, env_cfg, expert_cfg or ExpertConfig(),
                              drive_cfg or DriveConfig(), seed, test_fraction)
    t0 = time.monotonic()
    dataset, reused = open_or_generate(data_dir, request, progress=progress)
    t1 = time.monotonic()
    net, card = train_supervised(dataset, settings, progress=progress)
    t2 = time.monotonic()
    card["data"]["generated_seconds"] = dataset.manifest.get("seconds")
    card["data"]["reused"] = reused
    card["data"]["request"] = request
    save_supervised(out, net, card)
    return PretrainResult(out, card, dataset, reused, {"data": t1 - t0, "train": t2 - t1})
