"""Shipped models and deployment exports: ``cogexplore model export`` (float16, model card),
``pretrained[:drl|:sl]`` resolution, and the shipped files evaluating out of the box."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from services.cli import main
from shared.config import ModelConfig, SensorConfig, load_preset
from shared.evaluation.results import validate_results_json
from shared.learning.checkpoints import (
    PRETRAINED_DIR,
    PRETRAINED_FILES,
    CheckpointError,
    CheckpointManager,
    load_exported_weights,
    load_model,
    pretrained_path,
)
from shared.errors import CogexploreError
from shared.learning.dqn import DQNAgent

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_model_export_half_precision_keeps_the_greedy_policy(tmp_path: Path, capsys) -> None:
    cfg = load_preset("paper")
    agent = DQNAgent(ModelConfig(fc1=64, fc2=32), SensorConfig(width=80, height=60), cfg.dqn, device="cpu", seed=3)
    agent.update_count = agent.policy_version = 321
    CheckpointManager(tmp_path / "run" / "checkpoints").save(agent, config=cfg.to_dict())
    card = tmp_path / "card.json"
    card.write_text(json.dumps({"world": "paper-indoor", "updates": 321}))

    outs = {}
    for half in (False, True):
        out = tmp_path / f"w-{half}.safetensors"
        argv = ["model", "export", str(tmp_path / "run"), "--out", str(out), "--card", str(card)]
        assert main(argv + (["--half"] if half else [])) == 0
        printed = json.loads(capsys.readouterr().out)
        assert printed["policy_version"] == 321 and printed["half"] is half and printed["bytes"] == out.stat().st_size
        outs[half] = out
    assert outs[True].stat().st_size < 0.55 * outs[False].stat().st_size

    full, meta = load_exported_weights(outs[False])
    half, half_meta = load_exported_weights(outs[True])
    assert half_meta["card"] == {"world": "paper-indoor", "updates": 321} and half_meta["policy_version"] == 321
    assert all(t.dtype == torch.float32 for t in half.state_dict().values())  # cast back on load
    depth = torch.from_numpy(np.random.default_rng(0).uniform(0, 4, (64, 1, 60, 80)).astype(np.float32) / 4)
    with torch.no_grad():
        q_full, q_half = full(depth), half(depth)
    assert torch.allclose(q_full, q_half, atol=1e-2 * q_full.abs().max().item() + 1e-4)
    assert (q_full.argmax(1) == q_half.argmax(1)).float().mean() >= 0.95

    # a card is stored as standard JSON, which has no NaN: refused before anything is written
    out = tmp_path / "nan.safetensors"
    for text in ('{"accuracy": NaN}', '{"n": 1e999}', "[" * 100_000):
        card.write_text(text)
        assert main(["model", "export", str(tmp_path / "run"), "--out", str(out), "--card", str(card)]) == 2
        assert "--card" in capsys.readouterr().err and not out.exists()
    # and an export whose policy version was forged is no model
    from shared.learning.checkpoints import load_model, load_tensors_file, save_tensors_file

    tensors, meta = load_tensors_file(outs[False], "cogexplore-weights")
    for version in ("abc", -12345, 1.7):
        save_tensors_file(out, tensors, {k: v for k, v in meta.items() if k != "digest"} | {"policy_version": version})
        with pytest.raises(CogexploreError, match="policy_version"):
            load_model(out)


def test_model_export_averages_several_checkpoints(tmp_path: Path, capsys) -> None:
    cfg = load_preset("tiny")
    paths = []
    for seed, version in ((1, 100), (2, 200), (3, 300)):
        agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=seed)
        agent.update_count = agent.policy_version = version
        paths.append(CheckpointManager(tmp_path / f"run{seed}").save(agent, config=cfg.to_dict()))
    out = tmp_path / "avg.safetensors"
    assert main(["model", "export", *map(str, paths), "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["averaged"] == 3 and printed["policy_version"] == 300
    avg, meta = load_exported_weights(out)
    assert [a["policy_version"] for a in meta["averaged_from"]] == [100, 200, 300]
    nets = [load_model(p).net for p in paths]
    for name, t in avg.state_dict().items():
        want = sum(n.state_dict()[name] for n in nets) / 3
        assert torch.allclose(t, want, atol=1e-6), name

    other = load_preset("tiny").with_overrides({"model.fc1": 24})
    agent = DQNAgent(other.model, other.sensor, other.dqn, device="cpu")
    odd = CheckpointManager(tmp_path / "odd").save(agent, config=other.to_dict())
    assert main(["model", "export", str(paths[0]), str(odd), "--out", str(tmp_path / "x.safetensors")]) == 2
    assert "different architectures" in capsys.readouterr().err
    assert not (tmp_path / "x.safetensors").exists()


def test_model_export_errors_are_clear(tmp_path: Path, capsys) -> None:
    out = tmp_path / "w.safetensors"
    assert main(["model", "export", str(tmp_path / "nothing"), "--out", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err
    cfg = load_preset("tiny")
    agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu")
    CheckpointManager(tmp_path / "ckpts").save(agent, config=cfg.to_dict())
    for text, message in (("{not json", "Expecting property name"), ("[1, 2]", "must hold a JSON object")):
        (tmp_path / "card.json").write_text(text)
        assert main(["model", "export", str(tmp_path / "ckpts"), "--out", str(out), "--card",
                     str(tmp_path / "card.json")]) == 2
        assert message in capsys.readouterr().err
    assert not out.exists()


def test_pretrained_names_resolve_to_shipped_files() -> None:
    assert pretrained_path("runs/x/checkpoints") is None and pretrained_path(Path("pretrained.safetensors")) is None
    drl = PRETRAINED_DIR / PRETRAINED_FILES["drl"]
    assert pretrained_path("pretrained") == pretrained_path("pretrained:drl") == drl
    assert pretrained_path("pretrained:sl") == PRETRAINED_DIR / "sl.safetensors"
    with pytest.raises(CheckpointError, match="unknown shipped model 'pretrained:big'.*pretrained:sl"):
        pretrained_path("pretrained:big")
    with pytest.raises(CheckpointError, match="unknown shipped model"):
        load_model("pretrained:big")


def test_shipped_models_carry_their_card_and_evaluate_out_of_the_box(tmp_path: Path) -> None:
    """`cogexplore evaluate --checkpoint pretrained` on a fresh install: both shipped models load
    from the package, say where they came from, and run the protocol on the reference world."""
    card_md = (PRETRAINED_DIR / "MODEL_CARD.md").read_text()
    drl = load_model("pretrained")
    assert drl.kind == "weights" and drl.path == PRETRAINED_DIR / "drl.safetensors"
    _, meta = load_exported_weights(drl.path)
    card = meta["card"]
    # an ensemble of four runs: the card names each member, in the file's order
    assert card["world"] == "paper-indoor" and drl.policy_version > 0
    assert [m["updates"] for m in card["members"]] == [e["policy_version"] for e in drl.ensemble_of]
    assert [m["run"] for m in card["members"]] == [e["label"].split("@")[0] for e in drl.ensemble_of]
    for evaluation in (card["eval"]["protocol_robust"], card["eval"]):  # robust first, the paper's beside
        assert f"{evaluation['paper-indoor']['mean_steps']:.1f}" in card_md

    out = tmp_path / "drl.json"
    assert main(["evaluate", "--checkpoint", "pretrained", "--starts", "1", "--episodes-per-start", "1",
                 "--max-steps", "10", "--json", str(out), "--device", "cpu", "--quiet"]) == 0
    results = validate_results_json(out.read_text())
    assert results.meta["world"] == "paper-indoor" and results.meta["policy_version"] == drl.policy_version
    assert results.meta["sensor"]["width"] == drl.net.sensor_cfg.width

    out = tmp_path / "sl.json"
    assert main(["evaluate", "--policy", "sl", "--checkpoint", "pretrained", "--starts", "1",
                 "--episodes-per-start", "1", "--max-steps", "10", "--json", str(out), "--device", "cpu",
                 "--quiet"]) == 0
    results = validate_results_json(out.read_text())
    assert results.meta["policy"] == "sl" and len(results.episodes) == 1


@pytest.mark.parametrize("preset", ["fast-40x30", "fast-80x60", "robust-40x30"])
def test_fast_recipes_start_from_the_shipped_sl_model(preset: str) -> None:
    """The fast and robust recipes start from the shipped supervised model (`pretrained:sl`; conv
    weights fit any image size), and the 40 x 30 ones build the shipped DRL model's architecture
    and camera, so the model card's recipe reproduces it (the default preset's camera is the
    shipped one, noise included: tests/shared/test_config.py)."""
    from shared.learning.checkpoints import init_agent_conv, load_supervised
    from shared.learning.model import architecture_fingerprint

    cfg = load_preset(preset)
    assert cfg.train.init_conv_from == "pretrained:sl"
    agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=0)
    meta = init_agent_conv(agent, cfg.train.init_conv_from)
    sl_net, _ = load_supervised(PRETRAINED_DIR / "sl.safetensors")
    for mine, theirs in zip(agent.online.trunk.parameters(), sl_net.trunk.parameters(), strict=True):
        assert torch.equal(mine, theirs)
    for mine, target in zip(agent.online.parameters(), agent.target.parameters(), strict=True):
        assert torch.equal(mine, target)
    if preset.endswith("40x30"):  # the architecture and camera of the shipped models
        shipped = load_model("pretrained").net
        for member in shipped.members:  # the shipped DRL model is an ensemble of four runs of one recipe
            assert architecture_fingerprint(agent.online) == architecture_fingerprint(member)
        # (the stored sensor as the code reads it: fields added since then take their defaults)
        assert SensorConfig(**meta["sensor"]) == cfg.sensor.noise_free() == shipped.sensor_cfg.noise_free()
