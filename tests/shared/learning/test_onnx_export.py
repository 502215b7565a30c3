"""``export_onnx`` and ``cogexplore model export --onnx``: the exported graph gives the torch network's
Q-values (to ``MATCH_TOLERANCE``) for every previous command and batch size, carries its camera and
provenance, and a broken export never lands on disk."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime
import pytest
import torch

from services.cli import main
from shared.config import NUM_ACTIONS, ModelConfig, load_preset
from shared.learning import onnx_export
from shared.learning.checkpoints import LoadedModel, load_model, load_supervised_model
from shared.learning.model import QEnsemble, QNetwork, preprocess_depth
from shared.learning.onnx_export import check_inputs, export_onnx, q_difference
from shared.learning.onnx_format import (
    MATCH_TOLERANCE,
    METADATA_KEY,
    NO_PREVIOUS_ACTION,
    OnnxModelError,
    OnnxPolicyInfo,
)

REPO = Path(__file__).resolve().parents[3]
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _smoke_net() -> QNetwork:
    """A random network of another shape: the smoke preset's dueling head, metric depth, no previous command."""
    cfg = load_preset("smoke")
    assert cfg.model.dueling and not cfg.model.previous_action and cfg.model.depth_encoding == "metric"
    torch.manual_seed(3)
    return QNetwork(cfg.model, cfg.sensor).eval()


def _ensemble() -> QEnsemble:
    """Two random networks that read the previous command, of different fc widths: a Q-value ensemble."""
    torch.manual_seed(4)
    sensor = load_preset("fast-40x30").sensor
    return QEnsemble([QNetwork(ModelConfig(fc1=fc, fc2=16, previous_action=True, depth_encoding="inverse"), sensor)
                      for fc in (32, 48)]).eval()


@pytest.fixture(scope="module")
def shipped() -> LoadedModel:
    return load_model("pretrained")


def _torch_q(net: QNetwork, depth: np.ndarray, previous: np.ndarray) -> np.ndarray:
    with torch.inference_mode():
        return net(preprocess_depth(depth), previous).numpy()


def _onnx_q(path: Path, depth: np.ndarray, previous: np.ndarray) -> np.ndarray:
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(["q_values"], {"depth_m": depth, "previous_action": previous})[0]


def _assert_the_runner_plays_as_the_torch_policy(path: Path, net: QNetwork | QEnsemble, seed: int) -> None:
    """Two episodes of random images (the second from a later one, after a reset) played by the ONNX
    runner and by ``GreedyPolicy``: the same commands, their Q-values to ``MATCH_TOLERANCE``, and
    ``q_values`` changing nothing the next decision sees."""
    from cogexplore.onnx_runner import load_onnx_policy
    from shared.evaluation.policies import GreedyPolicy

    s = net.sensor_cfg
    runner, greedy = load_onnx_policy(path), GreedyPolicy(net)
    images = np.random.default_rng(seed).uniform(0.3, 4.0, (7, s.height, s.width)).astype(np.float32)
    for episode in range(2):
        runner.reset()
        greedy.reset()
        for image in images[episode * 2:]:
            asked = runner.q_values(image)
            (ours, q), (theirs, q_torch) = runner.decide(image), greedy(image)
            assert ours == theirs and q_difference(q[None], q_torch[None]) <= MATCH_TOLERANCE
            np.testing.assert_array_equal(asked, q)
        assert runner.previous_command == greedy.policy.previous_action


@pytest.mark.parametrize("which", ["pretrained", "smoke", "ensemble"])
def test_the_export_gives_torchs_q_values_for_every_previous_command_and_batch(
        which: str, shipped: LoadedModel, tmp_path: Path) -> None:
    model = {"pretrained": shipped, "smoke": _smoke_net(), "ensemble": _ensemble()}[which]
    net = model.net if isinstance(model, LoadedModel) else model
    path = export_onnx(model, tmp_path / f"{which}.onnx")
    depth, _ = check_inputs(net, seed=11)  # other images than the export's own check
    for previous in range(NO_PREVIOUS_ACTION, NUM_ACTIONS):
        commands = np.full(len(depth), previous, dtype=np.int64)
        want, got = _torch_q(net, depth, commands), _onnx_q(path, depth, commands)
        assert got.shape == (len(depth), NUM_ACTIONS) and got.dtype == np.float32
        assert q_difference(got, want) <= MATCH_TOLERANCE, (which, previous, q_difference(got, want))
        np.testing.assert_array_equal(got.argmax(1), want.argmax(1))
    mixed = np.arange(len(depth), dtype=np.int64) % (NUM_ACTIONS + 1) - 1  # -1..4 within one batch
    for rows in (slice(None), slice(3, 4), slice(0, 7)):  # batch sizes 12, 1, 7
        assert q_difference(_onnx_q(path, depth[rows], mixed[rows]), _torch_q(net, depth[rows], mixed[rows])) \
            <= MATCH_TOLERANCE
    if which == "pretrained":
        # the shipped model's Q-values are large: the relative tolerance is ~1e-3 absolute, not looser than float32
        assert 10 < np.abs(_torch_q(net, depth, mixed)).max() < 200
    # the shipped model reads the previous command (the one-hot reaches the graph); the smoke net has the same
    # input and ignores it
    first = [_onnx_q(path, depth[:1], np.array([c])) for c in (0, 4)]
    assert np.allclose(*first) == (which == "smoke")


def test_networks_that_read_several_commands_export_a_history_input_and_the_runner_keeps_it(tmp_path: Path) -> None:
    torch.manual_seed(5)
    sensor = load_preset("fast-40x30").sensor
    # the last command only, and the last three: the file's input holds the most any member reads
    net = QEnsemble([QNetwork(ModelConfig(fc1=32, fc2=16, previous_action=True, action_history=k,
                                          depth_encoding="inverse"), sensor) for k in (1, 3)]).eval()
    path = export_onnx(net, tmp_path / "history.onnx")
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.shape[1:] for i in session.get_inputs() if i.name == "previous_action"] == [[3]]
    depth, histories = check_inputs(net, seed=12)
    assert histories.shape == (len(depth), 3)
    assert q_difference(_onnx_q(path, depth, histories), _torch_q(net, depth, histories)) <= MATCH_TOLERANCE
    # an older command changes the values (the history reaches the graph)
    older = histories.copy()
    older[:, 2] = (older[:, 2] + 2) % NUM_ACTIONS
    assert not np.allclose(_onnx_q(path, depth, older), _onnx_q(path, depth, histories))
    # the runner remembers the commands it chose as the torch policy does, and forgets them on reset
    _assert_the_runner_plays_as_the_torch_policy(path, net, seed=13)


def test_networks_that_read_several_images_export_a_stack_input_and_the_runner_remembers_them(
        tmp_path: Path) -> None:
    torch.manual_seed(6)
    sensor = load_preset("fast-40x30").sensor
    # one image and the last three: the file's input holds the most any member reads, each the newest
    nets = [QNetwork(ModelConfig(fc1=32, fc2=16, previous_action=True, frame_stack=k, depth_encoding="inverse"),
                     sensor) for k in (1, 3)]
    with torch.no_grad():  # older images given weight, as training gives them (they start at zero)
        nets[1].trunk.conv1.weight[:, 1:] += 0.2
    net = QEnsemble(nets).eval()
    path = export_onnx(net, tmp_path / "stack.onnx")
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.shape[1:] for i in session.get_inputs() if i.name == "depth_m"] == [[3, sensor.height, sensor.width]]
    depth, previous = check_inputs(net, seed=14)
    assert depth.shape[1] == 3
    assert q_difference(_onnx_q(path, depth, previous), _torch_q(net, depth, previous)) <= MATCH_TOLERANCE
    older = depth.copy()
    older[:, 2] = older[:, 1]  # the oldest image reaches the graph
    assert not np.allclose(_onnx_q(path, older, previous), _onnx_q(path, depth, previous))
    # the runner remembers the images it acted on as the torch policy does, and forgets them on reset
    _assert_the_runner_plays_as_the_torch_policy(path, net, seed=15)


def test_the_file_describes_its_network(shipped: LoadedModel, tmp_path: Path) -> None:
    import onnx

    import cogexplore

    path = export_onnx(shipped, tmp_path / "drl.onnx", extra={"card": {"robot": "turtlebot"}})
    proto = onnx.load(str(path))
    assert proto.opset_import[0].version >= 17 and proto.producer_name == "cogexplore"
    props = {p.key: p.value for p in proto.metadata_props}
    info = OnnxPolicyInfo.from_json(props[METADATA_KEY])
    policy = cogexplore.load_policy("pretrained", device="cpu")
    assert info.sensor == policy.sensor == shipped.net.sensor_cfg.noise_free() and info.model == shipped.net.model_cfg
    assert info.control_period_s == policy.control_period_s == 0.5
    assert (info.label, info.policy_version, info.weights_sha256) == (
        shipped.label, shipped.policy_version, shipped.weights_sha256)
    assert info.source == str(shipped.path) and info.cogexplore_version == cogexplore.__version__
    # the shipped model is an ensemble of four networks, each a mean of four checkpoints: the file says which
    assert [len(m["averaged_from"]) for m in shipped.ensemble_of] == [4, 4, 4, 4]
    assert info.extra == {"ensemble_of": list(shipped.ensemble_of), "card": {"robot": "turtlebot"}}
    body = json.loads(props[METADATA_KEY])
    assert body["sensor"]["hfov_deg"] == 57.0 and body["model"]["depth_encoding"] == "inverse"
    assert body["model"]["previous_action"] is True and body["format"] == "cogexplore-onnx"


def test_a_mismatching_or_diverged_export_never_lands_on_disk(tmp_path: Path, monkeypatch) -> None:
    net = _smoke_net()
    path = tmp_path / "model.onnx"
    path.write_bytes(b"the previous export")
    forward = onnx_export._ExportGraph.forward
    # the graph drifting from QNetwork.forward (what the check is for): Q-values 0.1% off
    monkeypatch.setattr(onnx_export._ExportGraph, "forward", lambda self, d, p: forward(self, d, p) * 1.001)
    with pytest.raises(OnnxModelError, match="not written: onnxruntime's Q-values differ from torch's by"):
        export_onnx(net, path)
    monkeypatch.undo()
    with torch.no_grad():
        net.fc2.weight[0, 0] = float("nan")
    with pytest.raises(OnnxModelError, match="not finite"):
        export_onnx(net, path)
    assert path.read_bytes() == b"the previous export" and sorted(p.name for p in tmp_path.iterdir()) == ["model.onnx"]
    with pytest.raises(OnnxModelError, match="takes a LoadedModel, a QNetwork or a QEnsemble"):
        export_onnx("pretrained", path)  # type: ignore[arg-type]
    with pytest.raises(OnnxModelError, match="only a Q-network exports to ONNX; .*sl.safetensors holds a SupervisedNet"):
        export_onnx(load_supervised_model("pretrained"), path)


def test_a_learners_bfloat16_network_exports_as_the_float32_network_it_acts_with(tmp_path: Path) -> None:
    # dqn.conv_precision = bfloat16 (or auto on a GPU) trains the convs in bfloat16; acting, and the graph,
    # run them in float32: the export is checked against that, not refused for bfloat16's rounding
    net = _smoke_net()
    net.conv_autocast = torch.bfloat16
    path = export_onnx(net, tmp_path / "bf16.onnx")
    depth, previous = check_inputs(net, seed=5)
    with torch.inference_mode():
        acting = net(preprocess_depth(depth), previous, float32=True).numpy()
    assert q_difference(_onnx_q(path, depth, previous), acting) <= MATCH_TOLERANCE
    assert net.conv_autocast == torch.bfloat16  # the caller's network is left as it was


def test_model_export_writes_the_onnx_file_beside_or_instead_of_the_weights(tmp_path: Path) -> None:
    onnx_path, weights = tmp_path / "robot" / "drl.onnx", tmp_path / "drl.safetensors"
    proc = subprocess.run([sys.executable, "-m", "services.cli", "model", "export", "pretrained", "--onnx",
                           str(onnx_path), "--out", str(weights)], cwd=REPO, capture_output=True, text=True, timeout=300,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["onnx"] == {"out": str(onnx_path), "bytes": onnx_path.stat().st_size}
    shipped = load_model("pretrained").policy_version
    assert report["out"] == str(weights) and weights.is_file() and report["policy_version"] == shipped
    from cogexplore.onnx_runner import load_onnx_policy

    assert load_onnx_policy(onnx_path).label == f"drl@{shipped}"


@pytest.mark.parametrize(("argv", "message"), [
    (["pretrained"], "give --out FILE.safetensors"),
    (["pretrained", "--onnx", "x.onnx", "--half"], "--half stores the --out weights"),
    # A destination that is a folder: a traceback before, and an 11 MB temporary file left beside it.
    (["pretrained", "--onnx", "dest"], "Is a directory"),
    (["pretrained", "--out", "dest"], "Is a directory"),
])
def test_model_export_option_errors_are_one_line(argv: list[str], message: str, tmp_path: Path, capsys,
                                                  monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "dest").mkdir()
    assert main(["model", "export", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and [p.name for p in tmp_path.iterdir()] == ["dest"]
    assert not list((tmp_path / "dest").iterdir())


def test_a_half_export_refused_for_overflow_writes_no_onnx_file_either(tmp_path: Path, capsys) -> None:
    # --out F --half --onnx G: the ONNX file was written first, then float16 refused the weights,
    # and a failed command left G behind
    from shared.learning.checkpoints import CheckpointManager
    from shared.learning.dqn import DQNAgent

    cfg = load_preset("tiny")
    agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=0)
    with torch.no_grad():
        agent.online.fc3.bias[0] = 1e5  # float32 holds it, float16 does not
    ckpt = CheckpointManager(tmp_path / "ck").save(agent, config=cfg.to_dict())
    out, onnx_path = tmp_path / "w.safetensors", tmp_path / "m.onnx"
    assert main(["model", "export", str(ckpt), "--out", str(out), "--half", "--onnx", str(onnx_path)]) == 2
    assert "not finite in float16" in capsys.readouterr().err
    assert not out.exists() and not onnx_path.exists()


def test_metadata_the_runner_cannot_read_is_never_written(tmp_path: Path) -> None:
    # Before, a NaN in extra (or label) was written as JSON's non-standard NaN: an export that passed
    # every check and that load_onnx_policy then refused on the robot; keys of mixed types were a TypeError.
    from cogexplore.onnx_runner import load_onnx_policy

    net = _smoke_net()
    path = tmp_path / "model.onnx"
    for kwargs, message in (({"extra": {"card": {"score": float("nan")}}}, "not readable JSON"),
                            ({"label": float("nan")}, "not readable JSON"),
                            ({"extra": {1: "a", "b": 2}}, "metadata is not JSON")):
        with pytest.raises(OnnxModelError, match=f"^{re.escape(str(path))}: not written: .*{message}"):
            export_onnx(net, path, **kwargs)
        assert not path.exists()
    assert load_onnx_policy(export_onnx(net, path, extra={"card": {"score": 1.5}})).info.extra == \
        {"card": {"score": 1.5}}
