"""A Q-network (or a Q-value ensemble) as an ONNX file that a robot computer runs without torch
(``cogexplore model export --onnx``; the runner is ``cogexplore.onnx_runner``, the file's contract
``shared.learning.onnx_format``).

The graph is traced from :class:`_ExportGraph`, which has fixed tensor inputs and no Python branch
on their values, so the trace is the whole computation for every input. Every export is checked
before it lands on disk: onnxruntime runs the serialised file on random range-gated images with
every previous command, at batch sizes 1 and 12, and on the format's ``self_check_inputs``, against
the network's forward; a mismatch raises :class:`OnnxModelError` and leaves no file behind. The
self-check's Q-values, as onnxruntime gives them for the file's graph, go into its metadata for the
runner to compare with its own.
"""

from __future__ import annotations

import copy
import dataclasses
import io
import os
import warnings
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime
import torch
import torch.nn.functional as F
from torch import nn

from shared.config import NUM_ACTIONS, load_preset
from shared.depth import range_gate
from shared.evaluation.setup import setup_evaluation
from shared.files import write_atomically
from shared.learning.checkpoints import LoadedModel, weights_sha256
from shared.learning.model import (
    QEnsemble,
    QNetwork,
    command_values,
    most_commands_read,
    newest_images,
    preprocess_depth,
)
from shared.learning.onnx_format import (
    DEPTH_INPUT,
    MATCH_TOLERANCE,
    METADATA_KEY,
    NO_PREVIOUS_ACTION,
    PREVIOUS_ACTION_INPUT,
    Q_OUTPUT,
    SELF_CHECK_TOLERANCE,
    OnnxModelError,
    OnnxPolicyInfo,
    q_difference,
    self_check_inputs,
)

OPSET = 17
"""ONNX opset of the graph (onnxruntime has run it since 1.11)."""
CHECK_IMAGES_PER_COMMAND = 2
"""Random images per previous command (-1..4) in the check of an export."""


class _ExportGraph(nn.Module):
    """``QNetwork.forward`` (or ``QEnsemble.forward``: the mean over its members) on explicit
    tensors: metres in (``preprocess_depth``, the one place depth becomes network input), (B, N, H, W)
    for networks that read the last N images (``model.frame_stack``; each member reads the newest it
    takes), and the previous command as an int64 index with -1 for none: (B,), or (B, K) for networks
    that read the last K commands (``command_history``), most recent first.

    Its head repeats ``QNetwork.head`` with the one-hot built by comparison with ``arange``, which
    traces to plain ops (``previous_action_input`` branches on values to validate them); the check
    of every export against the network's forward is what keeps the two the same."""

    def __init__(self, net: QNetwork | QEnsemble):
        super().__init__()
        self.members = nn.ModuleList(net.members if isinstance(net, QEnsemble) else [net])
        self.register_buffer("commands", torch.arange(NUM_ACTIONS, dtype=torch.int64), persistent=False)

    def forward(self, depth_m: torch.Tensor, previous_action: torch.Tensor) -> torch.Tensor:
        x = preprocess_depth(depth_m)
        history = previous_action if previous_action.dim() == 2 else previous_action[:, None]
        q = [self._member_q(net, newest_images(x, net.model_cfg.frame_stack), history) for net in self.members]
        return q[0] if len(q) == 1 else torch.stack(q).mean(0)

    def _member_q(self, net: QNetwork, x: torch.Tensor, history: torch.Tensor) -> torch.Tensor:
        # the trunk, not features(): its shape check is the graph's fixed input shape here
        pool3 = net.trunk(x)
        h = net.fc1(torch.flatten(pool3.contiguous(), 1))
        if net.previous_action_fc is not None:
            # -1 (none) equals no command: a zero row, as previous_action_input gives it
            k = net.model_cfg.action_history
            one_hot = (history[:, :k, None] == self.commands[None, None, :]).to(h.dtype)
            h = h + net.previous_action_fc(one_hot.reshape(-1, NUM_ACTIONS * k))
        h = F.relu(h)
        h = F.relu(net.fc2(h))  # dropout: off in eval mode, so not in the graph
        if net.model_cfg.dueling:
            advantage = net.advantage(h)
            return net.value(h) + advantage - advantage.mean(dim=1, keepdim=True)
        return command_values(net.fc3(h), net.model_cfg.quantiles)


def export_onnx(model: LoadedModel | QNetwork, path: str | os.PathLike[str], *, label: str | None = None,
                extra: Mapping[str, Any] | None = None) -> Path:
    """Write ``model`` (a loaded model, or a bare network) as an ONNX policy file at ``path``.

    ``label`` names it (default: the loaded model's label, else ``network``); ``extra`` is JSON-able
    metadata kept in the file (a model card, the checkpoints averaged). The control period is the
    model's run's (the paper preset's for a bare network or a weights export), as
    ``cogexplore.load_policy`` has it. Raises OnnxModelError, writing nothing, when onnxruntime's
    Q-values differ from torch's by more than ``MATCH_TOLERANCE``. Returns the path."""
    path = Path(path)
    data = onnx_file_bytes(model, path, label=label, extra=extra)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda tmp: tmp.write_bytes(data))
    return path


def onnx_file_bytes(model: LoadedModel | QNetwork, path: str | os.PathLike[str], *, label: str | None = None,
                    extra: Mapping[str, Any] | None = None) -> bytes:
    """The bytes :func:`export_onnx` writes to ``path`` (named in its errors), checked against torch;
    for a caller that writes them with other files (``model export --onnx F --out G``)."""
    path = Path(path)
    if isinstance(model, LoadedModel):
        net, source, version = model.net, str(model.path), model.policy_version
        label = label or model.label
        extra = {**({"averaged_from": list(model.averaged_from)} if model.averaged_from else {}),
                 **({"ensemble_of": list(model.ensemble_of)} if model.ensemble_of else {}), **dict(extra or {})}
    elif isinstance(model, (QNetwork, QEnsemble)):
        net, source, version = model, label or "network", 0
        label = label or "network"
    else:
        raise OnnxModelError(f"export_onnx takes a LoadedModel, a QNetwork or a QEnsemble, "
                             f"got {type(model).__name__}")
    if not isinstance(net, (QNetwork, QEnsemble)):
        raise OnnxModelError(f"only a Q-network exports to ONNX; {source} holds a {type(net).__name__}")
    # a CPU float32 copy in eval mode: the caller's network (maybe on CUDA, maybe training) is left as it is
    net = copy.deepcopy(net).to("cpu", torch.float32).eval()
    # the camera itself, as setup_evaluation gives it: a run's training noise is no part of the model
    info = OnnxPolicyInfo(sensor=net.sensor_cfg.noise_free(), model=net.model_cfg,
                          control_period_s=_control_period_s(model),
                          label=label, source=source, policy_version=int(version), weights_sha256=weights_sha256(net),
                          cogexplore_version=_cogexplore_version(), extra=dict(extra or {}))
    try:
        text = info.to_json()
    except (TypeError, ValueError) as exc:  # json.dumps: keys of mixed types, an extra that holds itself
        raise OnnxModelError(f"{path}: not written: its metadata is not JSON: {exc}") from None
    # read back as the runner will, before anything is written: a NaN in ``extra`` or ``label`` is no JSON
    OnnxPolicyInfo.from_json(text, f"{path}: not written")
    data = _serialise(net, info)
    _check_against_torch(net, data, path)
    return data


def _graph_inputs(net: QNetwork | QEnsemble) -> tuple[np.ndarray, np.ndarray]:
    """The format's self-check inputs for this network's graph."""
    return self_check_inputs(net.sensor_cfg.noise_free(), net.model_cfg.frame_stack, command_history(net))


def _control_period_s(model: LoadedModel | QNetwork) -> float:
    if isinstance(model, LoadedModel):  # the rule Policy.control_period_s follows
        return float(setup_evaluation(None, model=model).env_cfg.control_period_s)
    return float(load_preset("paper").env.control_period_s)  # setup_evaluation's default without a run


def _cogexplore_version() -> str:
    # importlib.metadata, not cogexplore.version: shared/ does not import the API above it
    try:
        return metadata.version("cogexplore")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def command_history(net: QNetwork | QEnsemble) -> int:
    """How many previous commands the file's ``previous_action`` input holds per image: the most
    any member reads (``model.action_history``); 1 (shape (B,)) for networks that read one or none."""
    return most_commands_read(net.members if isinstance(net, QEnsemble) else [net])


def _serialise(net: QNetwork | QEnsemble, info: OnnxPolicyInfo) -> bytes:
    s, images = net.sensor_cfg, net.model_cfg.frame_stack
    history = command_history(net)
    previous_shape = (2,) if history == 1 else (2, history)
    example = (torch.zeros(2, images, s.height, s.width),
               torch.full(previous_shape, NO_PREVIOUS_ACTION, dtype=torch.int64))
    buffer = io.BytesIO()
    batch = {0: "batch"}
    with warnings.catch_warnings():
        # torch 2.9+ calls the TorchScript exporter legacy; it is the one that traces this small graph in
        # about a second without onnxscript's torch.export path
        warnings.simplefilter("ignore", DeprecationWarning)
        with torch.no_grad():
            torch.onnx.export(_ExportGraph(net).eval(), example, buffer, input_names=[DEPTH_INPUT, PREVIOUS_ACTION_INPUT],
                              output_names=[Q_OUTPUT], opset_version=OPSET, dynamo=False,
                              dynamic_axes={DEPTH_INPUT: batch, PREVIOUS_ACTION_INPUT: batch, Q_OUTPUT: batch})
    proto = onnx.load_from_string(buffer.getvalue())
    if PREVIOUS_ACTION_INPUT not in {i.name for i in proto.graph.input}:
        # the trace drops an input no op reads (a net without model.previous_action): put it back, so every
        # export takes the same two inputs and a runner needs no case for it
        proto.graph.input.append(onnx.helper.make_tensor_value_info(PREVIOUS_ACTION_INPUT, onnx.TensorProto.INT64,
                                                                    ["batch"]))  # history > 1 is always read
    proto.producer_name, proto.producer_version = "cogexplore", info.cogexplore_version
    proto.doc_string = (f"cogexplore Q-network {info.label}: {DEPTH_INPUT} float32 (B, {images}, {s.height}, "
                        f"{s.width}) metres, {'newest first, ' if images > 1 else ''}range-gated, 0 = no return; "
                        f"{PREVIOUS_ACTION_INPUT} int64 "
                        f"{'(B,)' if history == 1 else f'(B, {history}), most recent first'}, -1 = none -> "
                        f"{Q_OUTPUT} float32 (B, {NUM_ACTIONS}); greedy command = argmax")
    # the metadata is no input of the graph: its Q-values are the file's, whatever the metadata says
    depth, previous = _graph_inputs(net)
    q = onnxruntime.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"]).run(
        [Q_OUTPUT], {DEPTH_INPUT: depth, PREVIOUS_ACTION_INPUT: previous})[0]
    # float32 to float (exact) to JSON (repr, exact): the file holds the bits onnxruntime gave
    info = dataclasses.replace(info, self_check_q_values=tuple(tuple(float(v) for v in row) for row in q))
    onnx.helper.set_model_props(proto, {METADATA_KEY: info.to_json()})
    onnx.checker.check_model(proto, full_check=True)
    return proto.SerializeToString()


def check_inputs(net: QNetwork | QEnsemble, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Random range-gated depth images (B, N, H, W) (N: ``model.frame_stack``) with no-return holes and
    one empty stack, and every previous command (-1..4) ``CHECK_IMAGES_PER_COMMAND`` times (B,), or as
    the first of (B, K) random command histories (``command_history``): what an export is checked on."""
    s = net.sensor_cfg
    rng = np.random.default_rng(seed)
    commands = np.tile(np.arange(NO_PREVIOUS_ACTION, NUM_ACTIONS, dtype=np.int64), CHECK_IMAGES_PER_COMMAND)
    depth = rng.uniform(0.0, 1.1 * s.max_range_m, (len(commands), net.model_cfg.frame_stack, s.height, s.width))
    depth[rng.random(depth.shape) < 0.2] = 0.0
    depth[0] = 0.0  # nothing in range at all
    history = command_history(net)
    if history > 1:
        older = rng.integers(NO_PREVIOUS_ACTION, NUM_ACTIONS, (len(commands), history - 1))
        commands = np.concatenate([commands[:, None], older], axis=1)
    return range_gate(depth, s.min_range_m, s.max_range_m), commands


def _check_against_torch(net: QNetwork | QEnsemble, data: bytes, path: Path) -> None:
    depth, previous = check_inputs(net)
    with torch.inference_mode():  # float32 convs, as the graph and every acting network run them (not a
        # learner's dqn.conv_precision, whose bfloat16 rounding the graph does not repeat)
        reference = net(preprocess_depth(depth), previous, float32=True).numpy()
    if not np.isfinite(reference).all():
        raise OnnxModelError(f"{path}: not written: the network's Q-values are not finite (diverged weights?)")
    session = onnxruntime.InferenceSession(data, providers=["CPUExecutionProvider"])
    for rows in (slice(None), slice(1, 2)):  # the whole batch, and the runner's batch of one
        q = session.run([Q_OUTPUT], {DEPTH_INPUT: depth[rows], PREVIOUS_ACTION_INPUT: previous[rows]})[0]
        error = q_difference(q, reference[rows])
        if not error <= MATCH_TOLERANCE:  # NaN fails too
            raise OnnxModelError(f"{path}: not written: onnxruntime's Q-values differ from torch's by {error:.2g} "
                                 f"(relative), more than {MATCH_TOLERANCE:g}")
    # the self-check's values are the torch network's too, and the file's own (read back as the runner reads them)
    depth, previous = _graph_inputs(net)
    with torch.inference_mode():
        reference = net(preprocess_depth(depth), previous, float32=True).numpy()
    q = session.run([Q_OUTPUT], {DEPTH_INPUT: depth, PREVIOUS_ACTION_INPUT: previous})[0]
    recorded = OnnxPolicyInfo.from_json(session.get_modelmeta().custom_metadata_map[METADATA_KEY]).self_check_q_values
    error = q_difference(q, reference)
    if not error <= MATCH_TOLERANCE:
        raise OnnxModelError(f"{path}: not written: onnxruntime's self-check Q-values differ from torch's by "
                             f"{error:.2g} (relative), more than {MATCH_TOLERANCE:g}")
    if not q_difference(q, np.array(recorded)) <= SELF_CHECK_TOLERANCE:
        raise OnnxModelError(f"{path}: not written: onnxruntime's self-check Q-values differ from those it recorded")
