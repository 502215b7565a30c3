"""Weights between a torch network and the wire: the one place that turns a QNetwork into a
WeightsMessage and back (raw float tensors, never pickle)."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from shared.learning.model import (
    architecture_fingerprint,
    load_tensors,
    weights_to_tensors,
)
from shared.wire.messages import WeightsMessage


def to_message(net: nn.Module, policy_version: int, learner_epoch: int = 0) -> WeightsMessage:
    """``net``'s state as a WeightsMessage of the learner started at ``learner_epoch`` (float32 on the
    wire, as trained: float16 would overflow past 65504; the wire still reads float16 weights)."""
    tensors = {name: t.float().numpy().astype(np.float32, copy=False) for name, t in weights_to_tensors(net).items()}
    return WeightsMessage(policy_version=policy_version, architecture_fingerprint=architecture_fingerprint(net),
                          tensors=tensors, learner_epoch=learner_epoch)


def load_message(net: nn.Module, message: WeightsMessage) -> None:
    """Load a received WeightsMessage into ``net`` (fingerprint checked first: a message
    for another architecture raises MessageError and leaves ``net`` untouched)."""
    message.check_fingerprint(architecture_fingerprint(net))
    # Received arrays are read-only views of the payload: copy into fresh tensors.
    load_tensors(net, {name: torch.tensor(np.asarray(arr, dtype=np.float32)) for name, arr in message.tensors.items()})
