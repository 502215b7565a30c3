"""An ONNX export records the Q-values its graph gives on the format's self-check inputs, and
``load_onnx_policy`` refuses a file whose weights were damaged since: before, one flipped byte in a
weight loaded without a word and changed the robot's Q-values (only a flip to infinity was caught)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import onnx.numpy_helper
import onnxruntime
import pytest
import torch

from cogexplore.onnx_runner import OnnxModelError, load_onnx_policy
from shared.config import ModelConfig, load_preset
from shared.learning.model import QEnsemble, QNetwork, preprocess_depth
from shared.learning.onnx_export import command_history, export_onnx
from shared.learning.onnx_format import (
    MATCH_TOLERANCE,
    SELF_CHECK_ROWS,
    SELF_CHECK_TOLERANCE,
    OnnxPolicyInfo,
    q_difference,
    self_check_inputs,
)
from tests.cogexplore.test_onnx_runner import _with_metadata
from tests.shared.learning.test_onnx_export import _assert_the_runner_plays_as_the_torch_policy, _ensemble, _smoke_net

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _net(which: str) -> QNetwork | QEnsemble:
    """Small networks of every graph variant: dueling, a previous-command ensemble, quantiles, the
    last three images, the last three commands."""
    if which == "smoke":
        return _smoke_net()
    if which == "ensemble":
        return _ensemble()
    torch.manual_seed(7)
    sensor = load_preset("fast-40x30").sensor
    cfg = {"quantile": ModelConfig(fc1=32, fc2=16, quantiles=4, previous_action=True),
           "frame_stack": ModelConfig(fc1=32, fc2=16, frame_stack=3, depth_encoding="inverse"),
           "history": ModelConfig(fc1=32, fc2=16, previous_action=True, action_history=3)}[which]
    net = QNetwork(cfg, sensor).eval()
    if which == "frame_stack":
        with torch.no_grad():  # older images given weight, as training gives them (they start at zero)
            net.trunk.conv1.weight[:, 1:] += 0.2
    return net


def _file_q(data: bytes, net: QNetwork | QEnsemble) -> np.ndarray:
    depth, previous = self_check_inputs(net.sensor_cfg, net.model_cfg.frame_stack, command_history(net))
    session = onnxruntime.InferenceSession(data, providers=["CPUExecutionProvider"])
    return session.run(["q_values"], {"depth_m": depth, "previous_action": previous})[0]


def _flip_byte(data: bytes, byte: int, bit: int) -> bytes:
    """``data`` with one bit flipped in byte ``byte`` (0: lowest) of the largest weight of a
    convolution (the file's first 4-D tensor), found as raw float32 bytes in the file."""
    proto = onnx.load_from_string(data)
    conv = next(t for t in proto.graph.initializer if t.data_type == onnx.TensorProto.FLOAT and len(t.dims) == 4)
    assert conv.raw_data and data.count(conv.raw_data) == 1
    at = data.index(conv.raw_data) + 4 * int(np.abs(onnx.numpy_helper.to_array(conv)).argmax()) + byte
    damaged = bytearray(data)
    damaged[at] ^= 1 << bit
    return bytes(damaged)


@pytest.mark.parametrize("which", ["smoke", "ensemble", "quantile", "frame_stack", "history"])
def test_a_damaged_weight_is_refused_and_a_sound_file_plays_as_before(which: str, tmp_path: Path) -> None:
    net = _net(which)
    path = export_onnx(net, tmp_path / "sound.onnx")
    data = path.read_bytes()
    info = OnnxPolicyInfo.from_json(onnx.load(str(path)).metadata_props[0].value)
    recorded = np.array(info.self_check_q_values)
    assert recorded.shape == (SELF_CHECK_ROWS, 5)
    np.testing.assert_array_equal(recorded, _file_q(data, net).astype(np.float64))  # the file's own, exactly
    depth, previous = self_check_inputs(net.sensor_cfg, net.model_cfg.frame_stack, command_history(net))
    with torch.inference_mode():
        assert q_difference(recorded, net(preprocess_depth(depth), previous, float32=True).numpy()) <= MATCH_TOLERANCE
    assert len({row.tobytes() for row in recorded}) == SELF_CHECK_ROWS  # twelve different questions
    # (a) a sound file loads and plays as the torch policy
    _assert_the_runner_plays_as_the_torch_policy(path, net, seed=21)
    # (b) the top mantissa bit of one weight (it changes by up to half): Q-values a little off, finite;
    # such a file loaded before
    damaged = tmp_path / "damaged.onnx"
    damaged.write_bytes(_flip_byte(data, byte=2, bit=6))
    moved = q_difference(_file_q(damaged.read_bytes(), net), recorded)
    assert SELF_CHECK_TOLERANCE < moved < 0.1, moved
    with pytest.raises(OnnxModelError, match="its graph no longer gives the Q-values recorded at export") as caught:
        load_onnx_policy(damaged)
    assert "\n" not in str(caught.value) and str(caught.value).startswith(f"{damaged}: ")


def test_a_flip_in_the_last_bits_is_within_float32s_own_rounding_and_loads(tmp_path: Path) -> None:
    net = _smoke_net()
    data = export_onnx(net, tmp_path / "sound.onnx").read_bytes()
    lowest = tmp_path / "lowest.onnx"
    lowest.write_bytes(_flip_byte(data, byte=0, bit=0))  # one float32 step of one weight
    assert q_difference(_file_q(lowest.read_bytes(), net), _file_q(data, net)) < SELF_CHECK_TOLERANCE
    assert load_onnx_policy(lowest).info.self_check_q_values is not None


def test_a_file_from_before_the_self_check_loads_unchecked(tmp_path: Path) -> None:
    path = export_onnx(_ensemble(), tmp_path / "sound.onnx")

    def without(text: str) -> str:
        body = json.loads(text)
        del body["self_check_q_values"]
        return json.dumps(body)

    old = _with_metadata(path, tmp_path / "old.onnx", without)
    policy = load_onnx_policy(old)
    assert policy.info.self_check_q_values is None
    np.testing.assert_array_equal(policy.q_values(np.full((30, 40), 1.5, np.float32)),
                                  load_onnx_policy(path).q_values(np.full((30, 40), 1.5, np.float32)))
    # an old file damaged is not caught: nothing recorded to compare with
    damaged = tmp_path / "old-damaged.onnx"
    damaged.write_bytes(_flip_byte(old.read_bytes(), byte=2, bit=6))
    assert load_onnx_policy(damaged).info.self_check_q_values is None


def _edit(change):
    """A metadata edit: ``change`` applied to its JSON body."""
    def edit(text: str) -> str:
        body = json.loads(text)
        change(body)
        return json.dumps(body)
    return edit


@pytest.mark.parametrize(("name", "edit"), [
    ("rows", lambda b: b["self_check_q_values"].pop()),
    ("columns", lambda b: b["self_check_q_values"][3].append(1.0)),
    ("flat", lambda b: b.update(self_check_q_values=[1.0] * 60)),
    ("text", lambda b: b["self_check_q_values"][0].__setitem__(2, "1.5")),
    ("bool", lambda b: b["self_check_q_values"][0].__setitem__(2, True)),
    ("object", lambda b: b.update(self_check_q_values={"q": 1})),
    # an integer too large for a float (JSON has no limit on digits; Python's own is 4300)
    ("huge", lambda b: b["self_check_q_values"][0].__setitem__(0, 10 ** 400)),
    ("string", lambda b: b.update(self_check_q_values="[[1]]")),
])
def test_a_malformed_self_check_is_a_one_line_error(name: str, edit, tmp_path: Path) -> None:
    path = export_onnx(_smoke_net(), tmp_path / "sound.onnx")
    bad = _with_metadata(path, tmp_path / f"{name}.onnx", _edit(edit))
    said = "metadata is invalid: self_check_q_values must be 12 lists of 5 finite numbers$"
    with pytest.raises(OnnxModelError, match=said) as caught:
        load_onnx_policy(bad)
    assert "\n" not in str(caught.value) and str(caught.value).startswith(f"{bad}: ")


@pytest.mark.parametrize("constant", ["NaN", "Infinity", "1e999"])
def test_a_self_check_value_json_cannot_hold_is_a_one_line_error(constant: str, tmp_path: Path) -> None:
    path = export_onnx(_smoke_net(), tmp_path / "sound.onnx")

    def edit(text: str) -> str:
        body = json.loads(text)
        body["self_check_q_values"][5][1] = "@@"
        return json.dumps(body).replace('"@@"', constant)

    bad = _with_metadata(path, tmp_path / "nan.onnx", edit)
    with pytest.raises(OnnxModelError, match="metadata is not readable JSON") as caught:
        load_onnx_policy(bad)
    assert "\n" not in str(caught.value) and str(caught.value).startswith(f"{bad}: ")


def test_the_self_check_inputs_are_closed_form_and_inside_the_range_gate() -> None:
    sensor = load_preset("fast-40x30").sensor
    depth, previous = self_check_inputs(sensor, 3, 4)
    again, _ = self_check_inputs(sensor, 3, 4)
    assert depth.dtype == np.float32 and depth.shape == (SELF_CHECK_ROWS, 3, 30, 40)
    np.testing.assert_array_equal(depth, again)
    assert not depth[0].any()  # nothing in range
    seen = depth[depth > 0]
    assert seen.min() > sensor.min_range_m and seen.max() < sensor.max_range_m and (depth[1:] == 0).mean() > 0.05
    assert previous.shape == (SELF_CHECK_ROWS, 4) and set(previous[:, 0]) == set(range(-1, 5))
    assert self_check_inputs(sensor, 1, 1)[1].shape == (SELF_CHECK_ROWS,)
