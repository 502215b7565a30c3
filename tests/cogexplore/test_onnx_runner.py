"""``cogexplore.onnx_runner``: an ONNX export driven without torch chooses the torch policy's commands
over a real episode, has the same surface, and refuses a broken file in one line."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import onnx.numpy_helper
import pytest

import cogexplore
from cogexplore.onnx_runner import OnnxModelError, OnnxPolicy, load_onnx_policy
from shared.evaluation.protocol import protocol_env_config
from shared.evaluation.setup import setup_evaluation
from shared.learning.checkpoints import load_model
from shared.learning.onnx_export import export_onnx
from shared.learning.onnx_format import MATCH_TOLERANCE, METADATA_KEY
from shared.learning.policy import PolicyError
from shared.sim.env import ExploreEnv
from shared.sim.sensor import DepthCamera

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def torch_policy() -> cogexplore.Policy:
    return cogexplore.load_policy("pretrained", device="cpu")


@pytest.fixture(scope="module")
def onnx_path(torch_policy: cogexplore.Policy, tmp_path_factory) -> Path:
    return export_onnx(torch_policy.model, tmp_path_factory.mktemp("onnx") / "drl.onnx")


@pytest.fixture
def policy(onnx_path: Path) -> OnnxPolicy:
    return load_onnx_policy(onnx_path)


def test_the_runner_imports_no_torch_and_acts_on_a_camera_image(onnx_path: Path) -> None:
    script = f"""
import sys
import numpy as np
import cogexplore.onnx_runner
assert "torch" not in sys.modules
policy = cogexplore.load_onnx_policy({str(onnx_path)!r})
command = policy.act(np.full((480, 640), 2.0, dtype=np.float32))
assert 0 <= command < 5 and policy.previous_command == command
heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "mujoco", "zenoh", "rerun", "onnx"))
assert not heavy, heavy
"""
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120,
                          check=False)
    assert proc.returncode == 0, proc.stderr


def test_it_chooses_the_torch_policys_commands_over_a_real_episode(torch_policy: cogexplore.Policy,
                                                                    policy: OnnxPolicy) -> None:
    setup = setup_evaluation(None, model=torch_policy.model)
    assert setup.world == "paper-indoor"
    env = ExploreEnv(protocol_env_config(setup.env_cfg, setup.world, 200), torch_policy.sensor)
    camera = DepthCamera(env.model, dataclasses.replace(torch_policy.sensor, width=640, height=480))
    commands = []
    try:
        obs, _ = env.reset(seed=0, options={"start_index": 6})
        torch_policy.reset()
        policy.reset()
        for _step in range(30):
            q_torch, q_onnx = torch_policy.q_values(obs), policy.q_values(obs)
            assert np.abs(q_onnx - q_torch).max() <= MATCH_TOLERANCE * max(1.0, np.abs(q_torch).max())
            big = camera.capture(env.data)  # the same view from a 640 x 480 camera, resized by both alike
            np.testing.assert_array_equal(policy.observation(big), torch_policy.observation(big))
            command = torch_policy.act(obs)
            assert policy.act(obs) == command and policy.previous_command == torch_policy.previous_command
            commands.append(command)
            obs, _reward, terminated, truncated, _info = env.step(command)
            assert not (terminated or truncated)  # the shipped model survives these 30 steps
    finally:
        env.close()
    assert len(set(commands)) >= 3  # it steers and goes straight: not one easy command all along


def test_it_has_the_torch_policys_surface(torch_policy: cogexplore.Policy, policy: OnnxPolicy,
                                         onnx_path: Path) -> None:
    assert cogexplore.OnnxPolicy is OnnxPolicy and cogexplore.load_onnx_policy is load_onnx_policy
    label = f"drl@{load_model('pretrained').policy_version}"
    assert policy.label == torch_policy.label == label and policy.sensor == torch_policy.sensor
    assert policy.control_period_s == torch_policy.control_period_s
    assert policy.command_names == torch_policy.command_names == cogexplore.COMMAND_NAMES
    for command in range(5):
        for table in ("test", "train"):
            assert policy.twist(command, table) == torch_policy.twist(command, table)
    assert policy.path == onnx_path and label in repr(policy) and "40x30" in repr(policy)
    image = np.full((30, 40), 1.5, dtype=np.float32)
    policy.reset()
    fresh = policy.q_values(image)
    assert policy.previous_command is None and fresh.shape == (5,) and fresh.dtype == np.float32
    command, q = policy.decide(image)
    np.testing.assert_array_equal(q, fresh)
    assert command == int(np.argmax(fresh)) == policy.previous_command
    assert not np.allclose(policy.q_values(image), fresh)  # the previous command is read
    policy.reset()
    np.testing.assert_array_equal(policy.q_values(image), fresh)
    assert policy(image) == command


@pytest.mark.parametrize(("depth", "message"), [
    (np.zeros((0, 0)), "empty"),
    (np.ones((2, 30, 40)), r"got shape \(2, 30, 40\)"),
    (np.ones((480, 848)), "848 x 480 pixels; the network's camera is 40 x 30"),
    (np.ones((30, 40), dtype=np.int64), "float metres"),
    (-np.ones((30, 40)), "negative"),
])
def test_bad_images_and_commands_are_the_torch_policys_errors(policy: OnnxPolicy, depth, message: str) -> None:
    for call in (policy.act, policy.q_values, policy.observation, policy.decide):
        with pytest.raises(PolicyError, match=message):
            call(depth)
    with pytest.raises(PolicyError, match="index in 0..4"):
        policy.twist(5)


def _with_metadata(src: Path, dst: Path, edit) -> Path:
    proto = onnx.load(str(src))
    entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
    entry.value = edit(entry.value)
    onnx.save(proto, str(dst))
    return dst


def _with_graph(src: Path, dst: Path, edit) -> Path:
    proto = onnx.load(str(src))
    edit(proto.graph)
    onnx.save(proto, str(dst))
    return dst


def nan_bias(graph) -> None:
    """The last bias (the Q head's) NaN: the file loads, its metadata and signature are right."""
    bias = [t for t in graph.initializer if len(t.dims) == 1 and t.dims[0] == 5][-1]
    values = onnx.numpy_helper.to_array(bias).copy()
    values[0] = np.nan
    bias.CopyFrom(onnx.numpy_helper.from_array(values, bias.name))


def batch_of_two(graph) -> None:
    """Every input's batch axis fixed to 2: the signature check reads axes 1.. only."""
    for value in graph.input:
        value.type.tensor_type.shape.dim[0].dim_value = 2


def test_a_broken_or_foreign_file_is_a_one_line_error(onnx_path: Path, tmp_path: Path) -> None:
    data = onnx_path.read_bytes()
    truncated = tmp_path / "truncated.onnx"
    truncated.write_bytes(data[: len(data) // 3])
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(np.random.default_rng(0).bytes(4096))
    identity = onnx.helper.make_model(onnx.helper.make_graph(
        [onnx.helper.make_node("Identity", ["x"], ["y"])], "foreign",
        [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
        [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])]))
    foreign = tmp_path / "foreign.onnx"
    onnx.save(identity, str(foreign))

    def resized(text: str) -> str:
        body = json.loads(text)
        body["sensor"].update(width=80, height=60)
        return json.dumps(body)

    cases = {
        tmp_path / "missing.onnx": "no such ONNX file",
        truncated: "not a readable ONNX model",
        garbage: "not a readable ONNX model",
        foreign: "not a cogexplore ONNX export",
        _with_metadata(onnx_path, tmp_path / "json.onnx", lambda t: t[:-5]): "metadata is not readable JSON",
        _with_metadata(onnx_path, tmp_path / "version.onnx", lambda t: t.replace('"version": 1', '"version": 9')):
            "version 9",
        _with_metadata(onnx_path, tmp_path / "field.onnx", lambda t: t.replace('"control_period_s"', '"period"')):
            "metadata is invalid: missing 'control_period_s'",
        _with_metadata(onnx_path, tmp_path / "size.onnx", resized): "not the 80 x 60 policy its metadata describes",
        _with_metadata(onnx_path, tmp_path / "huge.onnx", lambda t: re.sub(r'"policy_version": \d+',
                                                                          '"policy_version": 1e999', t)):
            "metadata is not readable JSON",
        _with_metadata(onnx_path, tmp_path / "text.onnx", lambda t: re.sub(r'"control_period_s": [0-9.]+',
                                                                          '"control_period_s": "0.5"', t)):
            "control_period_s must be a number",
        # dict() made a list of pairs a mapping, and failed on others with its own words
        _with_metadata(onnx_path, tmp_path / "extra.onnx", lambda t: json.dumps({**json.loads(t), "extra": [[1, 2]]})):
            "metadata is invalid: extra must be a JSON object, got list",
        _with_graph(onnx_path, tmp_path / "nan.onnx", nan_bias): "Q-values that are not finite",
        _with_graph(onnx_path, tmp_path / "batch2.onnx", batch_of_two): "the graph fails",
    }
    for path, message in cases.items():
        with pytest.raises(OnnxModelError, match=message) as caught:
            load_onnx_policy(path)
        assert "\n" not in str(caught.value) and str(path) in str(caught.value), path
    for threads in (0, 100_000, 2**31):
        with pytest.raises(PolicyError, match="threads"):
            load_onnx_policy(onnx_path, threads=threads)
    assert issubclass(OnnxModelError, cogexplore.CogexploreError)


def test_load_policy_and_evaluate_send_an_onnx_file_to_its_runner(onnx_path: Path, tmp_path: Path, capsys) -> None:
    # Before: "is neither a checkpoint nor a weights export: ... not a readable safetensors file
    # (partial or corrupt?)", twice, of a sound export.
    from services.cli import main

    shouting = tmp_path / "DRL.ONNX"
    shouting.write_bytes(onnx_path.read_bytes())
    said = r"is an ONNX export: it runs without torch, through cogexplore.load_onnx_policy or `cogexplore drive --onnx`"
    for source in (onnx_path, str(shouting)):
        with pytest.raises(cogexplore.CogexploreError, match=said):
            cogexplore.load_policy(source, device="cpu")
    assert main(["evaluate", "--checkpoint", str(onnx_path), "--world", "box-room", "--episodes-per-start", "1"]) == 2
    err = capsys.readouterr().err
    assert re.search(said, err) and err.count("\n") == 1, err


def test_evaluate_plays_an_onnx_policy_as_the_torch_policy_of_its_network(torch_policy: cogexplore.Policy,
                                                                         policy: OnnxPolicy) -> None:
    # Before, an ONNX policy was played as a foreign controller: through the paper's 160 x 120
    # camera, resized down, and labelled "OnnxPolicy" (145.0 against the torch policy's 160.0).
    kwargs = dict(protocol="paper", episodes_per_start=1, starts=[0, 5], max_steps=40)
    ours, theirs = cogexplore.evaluate(policy, **kwargs), cogexplore.evaluate(torch_policy, **kwargs)
    assert [(e.start_index, e.steps, e.terminated) for e in ours.episodes] == \
           [(e.start_index, e.steps, e.terminated) for e in theirs.episodes]
    assert ours.meta["model"] == theirs.meta["model"] == torch_policy.label
    assert ours.meta["policy_version"] == theirs.meta["policy_version"] > 0
    assert ours.meta["sensor"]["width"] == 40


def test_metadata_that_is_not_text_is_a_one_line_error(onnx_path: Path, tmp_path: Path) -> None:
    # a damaged byte in the metadata: onnxruntime's UnicodeDecodeError came out as a traceback
    proto = onnx.load(str(onnx_path))
    onnx.helper.set_model_props(proto, {**{p.key: p.value for p in proto.metadata_props}, "note": "@" * 16})
    data = proto.SerializeToString()
    assert data.count(b"@" * 16) == 1
    damaged = tmp_path / "bytes.onnx"
    damaged.write_bytes(data.replace(b"@" * 16, b"\xcc" * 16))
    with pytest.raises(OnnxModelError, match="metadata is not UTF-8 text") as caught:
        load_onnx_policy(damaged)
    assert "\n" not in str(caught.value) and str(damaged) in str(caught.value)
