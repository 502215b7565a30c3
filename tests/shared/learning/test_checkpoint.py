"""Checkpoints: round trip, exact resume, atomicity, corrupt files, pruning, weights export."""

import dataclasses
import json
import os
import re

import numpy as np
import pytest
import torch

from shared.config import DQNConfig, ModelConfig, ReplayConfig, RunConfig, SensorConfig
from shared.learning.checkpoints import (
    CheckpointError,
    CheckpointManager,
    export_weights,
    load_checkpoint,
    load_exported_weights,
    pretrained_path,
    save_checkpoint,
)
from shared.learning.dqn import DQNAgent
from shared.learning.model import QEnsemble, architecture_fingerprint
from shared.learning.replay import ReplayMemory

TINY = SensorConfig(width=40, height=30)
MODEL = ModelConfig(fc1=32, fc2=16, dropout=0.5)  # dropout on: resume must restore the RNG too


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def setup(dqn: DQNConfig, seed: int = 0):
    agent = DQNAgent(MODEL, TINY, dqn, device="cpu", seed=seed)
    mem = ReplayMemory(ReplayConfig(capacity=64, prioritized=True), (30, 40), seed=seed)
    return agent, mem


def fill(mem: ReplayMemory, n: int = 80) -> None:
    rng = np.random.default_rng(1)
    obs = rng.random((30, 40)).astype(np.float32) * 4
    for t in range(n):
        term = t % 9 == 8
        nxt = rng.random((30, 40)).astype(np.float32) * 4
        mem.add("a", obs, t % 5, -100.0 if term else 1.0, None if term else nxt, term)
        obs = rng.random((30, 40)).astype(np.float32) * 4 if term else nxt


def step(agent: DQNAgent, mem: ReplayMemory) -> dict:
    batch = mem.sample(8, n_step=2)
    m = agent.update(batch)
    mem.update_priorities(batch.indices, m["td_errors"])
    return m


@pytest.mark.parametrize("dqn", [DQNConfig(target_sync_every=3, lr=1e-4),
                                 DQNConfig(optimizer="adam", lr=1e-3, double_dqn=True, n_step=2)],
                         ids=["sgd", "adam"])
def test_resume_gives_exactly_the_same_next_updates(tmp_path, dqn):
    agent, mem = setup(dqn)
    fill(mem)
    for _ in range(4):
        step(agent, mem)
    path = save_checkpoint(tmp_path / "c.safetensors", agent, replay=mem,
                           config=RunConfig().to_dict(), extra={"env_steps": 80})
    # continue without interruption ...
    straight = [step(agent, mem) for _ in range(3)]
    # ... and from the checkpoint in fresh objects (different seeds: everything must come from disk)
    agent2, mem2 = setup(dqn, seed=123)
    ck = load_checkpoint(path)
    ck.restore(agent2, mem2)
    assert ck.extra == {"env_steps": 80} and ck.config["dqn"]["gamma"] == 0.85
    resumed = [step(agent2, mem2) for _ in range(3)]
    for a, b in zip(straight, resumed):
        assert a["loss"] == b["loss"] and a["synced_target"] == b["synced_target"]
        np.testing.assert_array_equal(a["td_errors"], b["td_errors"])
    for (k, v), v2 in zip(agent.online.state_dict().items(), agent2.online.state_dict().values()):
        assert torch.equal(v, v2), k
    for v, v2 in zip(agent.target.state_dict().values(), agent2.target.state_dict().values()):
        assert torch.equal(v, v2)
    assert agent2.update_count == agent.update_count == 7
    assert agent2.policy_version == agent.policy_version


def test_files_are_safetensors_with_json_metadata_never_pickle(tmp_path):
    agent, _ = setup(DQNConfig())
    path = save_checkpoint(tmp_path / "c.safetensors", agent)
    raw = path.read_bytes()
    header_len = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8:8 + header_len])
    meta = json.loads(header["__metadata__"]["cogexplore"])
    assert meta["format"] == "cogexplore-checkpoint" and meta["agent"]["update_count"] == 0
    assert "online.fc1.weight" in header and "target.fc1.weight" in header and "rng.torch" in header
    assert b"\x80\x04" not in raw[:16]  # no pickle protocol marker


def test_manager_keeps_last_k_and_points_latest_at_the_newest(tmp_path):
    agent, mem = setup(DQNConfig())
    fill(mem)
    cm = CheckpointManager(tmp_path, keep=2)
    assert cm.latest() is None and cm.load_latest() is None
    for _ in range(4):
        step(agent, mem)
        cm.save(agent, replay=mem)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert len(names) == 5 and names[-1] == "latest"
    assert names[1] == "ckpt-000000003.safetensors" and names[0].startswith("ckpt-000000003.replay-")
    assert names[3] == "ckpt-000000004.safetensors" and names[2].startswith("ckpt-000000004.replay-")
    assert cm.latest().name == "ckpt-000000004.safetensors"
    assert cm.load().update_count == 4
    # re-saving the same update (a final save right after a periodic one) replaces both files
    fill(mem, 5)
    cm.save(agent, replay=mem)
    assert len(list(tmp_path.glob("ckpt-000000004.replay-*"))) == 1
    agent2, mem2 = setup(DQNConfig(), seed=5)
    cm.load().restore(agent2, mem2)
    assert mem2.transitions_added == mem.transitions_added


def test_a_damaged_latest_pointer_falls_back_to_the_newest_checkpoint_that_loads(tmp_path):
    from shared.learning.checkpoints import load_model

    agent, _ = setup(DQNConfig())
    cm = CheckpointManager(tmp_path / "run" / "checkpoints")
    for count in (1, 2):
        agent.update_count = count
        cm.save(agent)
    newest = cm.path_for(2)
    for damaged in (b"\xff\xfe\x00 not text", b"foo\n", b"\x00" * 32):
        (cm.directory / "latest").write_bytes(damaged)
        assert cm.load_latest().path == newest and "latest" in cm.skipped[0]
        for source in (cm.directory, tmp_path / "run"):
            assert load_model(source).path == newest
    (cm.directory / "latest").unlink()
    (cm.directory / "latest").mkdir()  # a folder in its place
    assert cm.load_latest().path == newest and load_model(cm.directory).path == newest


def test_a_huge_latest_pointer_is_refused_unread(tmp_path):
    """``latest`` holds one file name: 8 MiB there (a checkpoint copied over it, a runaway writer) is
    refused by its size, in one short line, not read into memory and quoted whole in the error."""
    agent, _ = setup(DQNConfig())
    cm = CheckpointManager(tmp_path / "checkpoints")
    agent.update_count = 1
    good = cm.save(agent)
    with open(cm.directory / "latest", "r+b") as pointer:
        pointer.truncate(8 << 20)  # the good name, then zeros (a sparse file)
    with pytest.raises(CheckpointError) as refused:
        cm.latest()
    message = str(refused.value)
    assert "cannot be read" in message and "too large: 8,388,608 bytes, over the limit of 4,096" in message
    assert len(message) < 300 and "\n" not in message
    assert cm.load_latest().path == good and "too large" in cm.skipped[0]


def test_non_finite_weights_are_never_loaded_nor_written(tmp_path):
    """A checkpoint whose weights hold a NaN (its digest recomputed: the bytes are the writer's) is skipped
    by a resume and refused by load_model; an export never writes one, float16's overflow included."""
    from shared.learning.checkpoints import load_model, load_tensors_file, save_tensors_file

    agent, _ = setup(DQNConfig())
    cm = CheckpointManager(tmp_path)
    agent.update_count = 1
    good = cm.save(agent)
    tensors, meta = load_tensors_file(good, "cogexplore-checkpoint")
    tensors["online.fc1.bias"][3] = float("nan")
    agent.update_count = 2
    forged = cm.save(agent)
    save_tensors_file(forged, tensors, {k: v for k, v in meta.items() if k != "digest"})
    assert cm.load_latest().path == good and "online.fc1.bias holds NaN or infinite values" in cm.skipped[0]
    with pytest.raises(CheckpointError, match="online.fc1.bias holds NaN or infinite values"):
        load_model(forged)
    with torch.no_grad():
        agent.online.fc3.bias[0] = 1e5  # finite in float32, infinite in float16
    export_weights(tmp_path / "w32.safetensors", agent.online)
    with pytest.raises(CheckpointError, match="fc3.bias is not finite in float16"):
        export_weights(tmp_path / "w16.safetensors", agent.online, half=True)
    with torch.no_grad():
        agent.online.fc3.bias[0] = float("inf")
    with pytest.raises(CheckpointError, match="fc3.bias is not finite .diverged"):
        export_weights(tmp_path / "inf.safetensors", agent.online)
    assert sorted(p.name for p in tmp_path.glob("*.safetensors") if not p.name.startswith("ckpt-")) == [
        "w32.safetensors"]  # neither w16 nor inf


def test_diverged_weights_are_refused_and_every_saved_checkpoint_stays(tmp_path):
    """A real update at an absurd learning rate overflows a weight while its loss is finite. Saved through
    a manager that keeps one checkpoint, it was written (no loader takes it) and the good one pruned:
    nothing of the run loaded any more. Now it is refused, naming the tensor, before any file is written."""
    from shared.learning.checkpoints import NonFiniteWeights

    agent, mem = setup(DQNConfig(optimizer="sgd", lr=1e-4))
    fill(mem)
    cm = CheckpointManager(tmp_path, keep=1)
    step(agent, mem)
    good = cm.save(agent, replay=mem, extra={"note": "good"})
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def refused(diverged: DQNAgent, tensor: str) -> None:
        with pytest.raises(NonFiniteWeights) as refusal:
            cm.save(diverged, replay=mem)
        assert isinstance(refusal.value, CheckpointError) and str(refusal.value) == (
            f"{cm.path_for(diverged.update_count)}: not written: {tensor} holds NaN or infinite values at update "
            f"{diverged.update_count} (diverged weights)")
        # latest, the good checkpoint and its replay as they were, byte for byte; no file of the refused one
        assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
        assert cm.load_latest().path == good and cm.load().extra == {"note": "good"} and not cm.skipped

    for group in agent.optimizer.param_groups:
        group["lr"] = 3e38  # lr x gradient overflows float32
    step(agent, mem)
    overflowed = [n for n, p in agent.online.named_parameters() if not bool(torch.isfinite(p).all())]
    assert overflowed
    refused(agent, f"online.{overflowed[0]}")
    # finite weights, a NaN in the optimiser's state (the next step spreads it to the weights)
    agent, _ = setup(DQNConfig(optimizer="adam"))
    step(agent, mem)
    agent.update_count = 5
    agent.optimizer.state[agent.optimizer.param_groups[0]["params"][0]]["exp_avg"].view(-1)[0] = float("nan")
    refused(agent, "optim.0.exp_avg")


def test_only_the_newest_checkpoints_keep_their_replay_and_an_older_one_resumes_without(tmp_path, caplog):
    from shared.learning.learner import LearnerCore, resume_from

    agent, mem = setup(DQNConfig())
    fill(mem)
    cm = CheckpointManager(tmp_path, keep=10)  # a learning curve's worth of checkpoints
    for _ in range(4):
        step(agent, mem)
        cm.save(agent, replay=mem)
    assert [p.name for p in cm.checkpoints()] == [f"ckpt-00000000{u}.safetensors" for u in (1, 2, 3, 4)]
    assert sorted(p.name[:14] for p in tmp_path.glob("*.replay-*")) == ["ckpt-000000003", "ckpt-000000004"]
    agent2, mem2 = setup(DQNConfig(), seed=5)
    cm.load(cm.path_for(3)).restore(agent2, mem2)
    assert mem2.transitions_added == mem.transitions_added
    old = cm.load(cm.path_for(1))
    with pytest.raises(CheckpointError, match="replay memory was not kept"):
        old.restore(agent2, mem2)
    old.restore(agent2)  # the agent alone restores exactly
    assert agent2.update_count == 1

    # A run whose only checkpoint left lost its replay resumes its network with an empty replay.
    for u in (2, 3, 4):
        cm.path_for(u).unlink()
    (tmp_path / "latest").write_text(cm.path_for(1).name + "\n")
    cfg = RunConfig(sensor=TINY, model=MODEL, replay=ReplayConfig(capacity=64))
    core = LearnerCore(cfg, device="cpu")
    with caplog.at_level("WARNING"):
        assert resume_from(cm, core)
    assert core.updates == 1 and len(core.replay) == 0
    assert "resuming with an empty replay memory" in caplog.text
    with pytest.raises(CheckpointError, match="keep_replays"):
        CheckpointManager(tmp_path, keep_replays=0)


@pytest.mark.parametrize("forge, match", [
    # sizes the arrays do not have: the memory was built to them first (2e8 frames: 5 GB) and failed after
    (lambda arrays, state: state.update(frame_capacity=200_000_000), r"declares .*200000000.*arrays hold"),
    (lambda arrays, state: state.update(frame_shape="ab"), r"declares .*\('a', 'b'\)"),
    # an array in a dtype numpy cannot read: safetensors' TypeError, a traceback (once ml_dtypes, which onnx
    # imports, has taught numpy bfloat16, the file reads, and its digest is not the checkpoint's)
    (lambda arrays, state: arrays.update(reward=torch.zeros(len(arrays["reward"]), dtype=torch.bfloat16)),
     "cannot be read .*bfloat16|belongs to another checkpoint"),
])
def test_a_replay_file_that_lies_about_its_arrays_is_refused_in_one_line_before_anything_is_built(
        tmp_path, forge, match):
    from shared.learning.checkpoints import FORMAT, load_replay, load_tensors_file, save_tensors_file

    agent, mem = setup(DQNConfig())
    fill(mem)
    saved = CheckpointManager(tmp_path).save(agent, replay=mem)
    replay_path = CheckpointManager(tmp_path).load(saved).replay_path
    arrays, meta = load_tensors_file(replay_path, FORMAT + "-replay", framework="numpy")
    tensors = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in arrays.items()}
    forge(tensors, meta["replay"])
    # the digest covers the tensors: forged metadata keeps it, and the bfloat16 array fails before it is compared
    save_tensors_file(replay_path, tensors, {k: v for k, v in meta.items() if k != "digest"})
    with pytest.raises(CheckpointError, match=match):
        load_replay(saved)


@pytest.mark.parametrize("saved", [None, "stored", "most", "abc", -5, True, 2.5, "fewer", "more", 10**400])
def test_a_checkpoint_s_transition_count_resumes_only_as_a_count_the_run_can_have(tmp_path, caplog, saved):
    """The learner's own count paces its replay ratio and the actors' credit; one that no run could
    have (hand-made, or forged past the tensors' digest; a huge one would hold the actors for good)
    takes the replay memory's size, with a warning instead of a crash or a stall."""
    from shared.learning.learner import MAX_TRACKED_ACTORS, LearnerCore, resume_from
    from shared.wire.messages import MAX_BATCH_STEPS

    agent, mem = setup(DQNConfig())
    fill(mem)
    step(agent, mem)
    cfg = RunConfig(sensor=TINY, model=MODEL, replay=ReplayConfig(capacity=64, prioritized=True))
    core = LearnerCore(cfg, device="cpu")
    stored, most = len(mem), core.transitions_needed + MAX_TRACKED_ACTORS * MAX_BATCH_STEPS
    count = {"stored": stored, "most": most, "fewer": stored - 1, "more": most + 1}.get(saved, saved)
    CheckpointManager(tmp_path).save(agent, replay=mem, extra=None if saved is None else {"transitions_received": count})
    with caplog.at_level("WARNING"):
        assert resume_from(CheckpointManager(tmp_path), core)
    assert len(core.replay) == stored
    kept = saved in ("stored", "most")
    assert core.received == (count if kept else stored)
    assert ("is not a count" in caplog.text) == (saved is not None and not kept)


def test_partial_write_leaves_the_previous_checkpoint_usable(tmp_path):
    agent, mem = setup(DQNConfig())
    fill(mem)
    cm = CheckpointManager(tmp_path, keep=3)
    step(agent, mem)
    good = cm.save(agent)
    # a writer killed mid-write leaves only a temporary file; latest is untouched
    step(agent, mem)
    full = save_checkpoint(tmp_path / "scratch.safetensors", agent).read_bytes()
    (tmp_path / ".ckpt-000000002.safetensors.tmp-999").write_bytes(full[: len(full) // 2])
    assert cm.latest() == good
    assert cm.load().update_count == 1
    # a truncated checkpoint under its final name gives a clear error ...
    partial = cm.path_for(2)
    partial.write_bytes(full[: len(full) // 3])
    with pytest.raises(CheckpointError, match="partial or corrupt"):
        load_checkpoint(partial)
    # ... and load_latest falls back past it when latest names it
    (tmp_path / "latest").write_text(partial.name + "\n")
    ck = cm.load_latest()
    assert ck is not None and ck.path == good and ck.update_count == 1
    assert len(cm.skipped) == 1 and "ckpt-000000002" in cm.skipped[0]
    with pytest.raises(CheckpointError):
        cm.load()


def test_flipped_bytes_are_detected_by_the_digest(tmp_path):
    agent, _ = setup(DQNConfig())
    path = save_checkpoint(tmp_path / "c.safetensors", agent)
    raw = bytearray(path.read_bytes())
    raw[-100] ^= 0xFF  # inside the tensor data, header intact
    path.write_bytes(bytes(raw))
    with pytest.raises(CheckpointError, match="digest"):
        load_checkpoint(path)
    path.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="partial or corrupt"):
        load_checkpoint(path)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.safetensors")


def test_checkpoint_of_another_architecture_or_optimiser_is_refused(tmp_path):
    agent, _ = setup(DQNConfig())
    ck = load_checkpoint(save_checkpoint(tmp_path / "c.safetensors", agent))
    other = DQNAgent(ModelConfig(fc1=64, fc2=16), TINY, DQNConfig(), device="cpu")
    with pytest.raises(CheckpointError, match="architecture"):
        ck.restore(other)
    adam = DQNAgent(MODEL, TINY, DQNConfig(optimizer="adam"), device="cpu")
    with pytest.raises(CheckpointError, match="optimiser"):
        ck.restore(adam)
    mem = ReplayMemory(ReplayConfig(capacity=64), (30, 40))
    with pytest.raises(CheckpointError, match="without its replay"):
        ck.restore(agent, mem)


class ForgedCheckpoints:
    """An agent's checkpoint after one update (``good``, its ``tensors`` and ``meta`` without the
    digest, which a forged file gets anew), and a fresh agent whose state no refusal may change."""

    def __init__(self, tmp_path, optimizer: str, lr: float) -> None:
        from shared.learning.checkpoints import load_tensors_file

        agent, self.mem = setup(DQNConfig(optimizer=optimizer, lr=lr))
        fill(self.mem)
        step(agent, self.mem)
        self.tmp_path = tmp_path
        self.good = save_checkpoint(tmp_path / "good.safetensors", agent)
        self.tensors, meta = load_tensors_file(self.good, "cogexplore-checkpoint")
        self.meta = {k: v for k, v in meta.items() if k != "digest"}
        self.fresh, _ = setup(DQNConfig(optimizer=optimizer, lr=1e-3), seed=1)
        self.before, self.before_meta = self.fresh.state_tensors()

    def refused(self, tensors, meta, match: str) -> None:
        """``tensors`` and ``meta`` saved as a checkpoint are refused (``match``), the fresh agent unchanged."""
        from shared.learning.checkpoints import save_tensors_file

        save_tensors_file(self.tmp_path / "forged.safetensors", tensors, meta)
        with pytest.raises(CheckpointError, match=match):
            load_checkpoint(self.tmp_path / "forged.safetensors").restore(self.fresh)
        after, after_meta = self.fresh.state_tensors()
        assert after_meta == self.before_meta and after.keys() == self.before.keys(), match
        assert all(torch.equal(after[k], v) for k, v in self.before.items()) and self.fresh.target_version == 0


@pytest.mark.parametrize("optimizer", ["adam", "sgd"])
def test_optimiser_state_of_another_dtype_or_shape_is_refused_before_the_agent_changes(tmp_path, optimizer):
    """Moments that are float16, integers, complex or of another shape, a step that is no scalar, a
    moment of no parameter (a damaged or hand-made file, its digest recomputed): torch would cast them
    silently, or corrupt the memory in its fused step. Refused, naming the tensor, the agent as it was."""
    f = ForgedCheckpoints(tmp_path, optimizer, 1e-3)
    tensors = f.tensors
    moment = "optim.0.exp_avg" if optimizer == "adam" else "optim.0.momentum_buffer"
    forgeries = [(moment, tensors[moment].to(dtype)) for dtype in (torch.float16, torch.int64, torch.complex64)]
    forgeries += [(moment, tensors[moment][:3].clone()), (moment.replace(".0.", ".99."), tensors[moment].clone())]
    if optimizer == "adam":
        forgeries.append(("optim.0.step", torch.ones(2)))
    for name, forged in forgeries:
        f.refused({**tensors, name: forged}, f.meta, re.escape(name))
    load_checkpoint(f.good).restore(f.fresh)
    assert f.fresh.update_count == 1 and torch.equal(f.fresh.state_tensors()[0][moment], tensors[moment])


@pytest.mark.parametrize("optimizer", ["adam", "sgd"])
def test_optimiser_hyperparameters_that_are_no_sane_value_are_refused_before_the_agent_changes(tmp_path, optimizer):
    """An lr that is a string, negative or NaN, betas that are no pair, a missing or unknown key, a flag
    not this agent's (a damaged or hand-made file): torch took them, and failed at the first update or
    trained on nonsense. Refused naming the group and key, the agent as it was; a sane checkpoint loads,
    and the resumed agent trains at its own config's lr (what the run's config.toml says), not the file's."""
    f = ForgedCheckpoints(tmp_path, optimizer, 5e-4)
    forgeries = [(0, "lr", "0.001"), (1, "lr", -1e-3), (0, "lr", float("nan")), (0, "weight_decay", float("inf")),
                 (1, "maximize", True), (0, "name", "conv"), (0, "lr", None), (1, "fused", 1)]
    forgeries += ([(0, "betas", [0.9]), (1, "betas", [0.9, 1.5]), (0, "eps", -1e-8), (0, "amsgrad", True)]
                  if optimizer == "adam" else [(0, "momentum", 1.5), (1, "betas", [0.9, 0.999])])
    for group, key, value in forgeries:
        forged = json.loads(json.dumps(f.meta))
        groups = forged["agent"]["optimizer"]["param_groups"]
        if value is None:
            del groups[group][key]
        else:
            groups[group][key] = value
        f.refused(f.tensors, forged, rf"optimiser group {group} \((fc|conv)\).*'?{key}")
    load_checkpoint(f.good).restore(f.fresh)
    assert f.fresh.lr == pytest.approx(1e-3)  # the config's (the file's was 5e-4)
    step(f.fresh, f.mem)


def test_weights_only_export_round_trip(tmp_path):
    agent, mem = setup(DQNConfig(lr=1e-3))
    fill(mem)
    step(agent, mem)
    path = export_weights(tmp_path / "deploy" / "w.safetensors", agent.online, agent.policy_version)
    net, meta = load_exported_weights(path)
    assert meta["policy_version"] == 1 and meta["sensor"]["width"] == 40
    assert not net.training
    depth = np.random.default_rng(0).random((30, 40)).astype(np.float32) * 4
    np.testing.assert_array_equal(agent.q_values(depth), net(torch.from_numpy(depth[None, None] / 4)
                                                             .contiguous(memory_format=torch.channels_last))
                                  .detach().numpy()[0])
    assert os.path.getsize(path) < 0.6 * os.path.getsize(save_checkpoint(tmp_path / "c.safetensors", agent))
    with pytest.raises(CheckpointError, match="cogexplore-weights"):
        load_exported_weights(tmp_path / "c.safetensors")


def test_init_from_starts_the_whole_network_from_a_weights_file_and_refuses_misfits(tmp_path, capsys):
    """train.init_from (fine-tuning): online and target start as the file's network; a network of
    another image size, a training checkpoint or a missing file is a clear error, also from the CLI."""
    from services.cli import main
    from shared.config import ConfigError, TrainConfig, load_preset
    from shared.learning.learner import LearnerCore

    base = load_preset("tiny").with_overrides({"replay.capacity": 500})
    source = LearnerCore(base.with_overrides({"train.seed": 7}), device="cpu").agent
    path = export_weights(tmp_path / "w.safetensors", source.online)
    core = LearnerCore(base.with_overrides({"train.init_from": str(path)}), device="cpu")
    fresh = LearnerCore(base, device="cpu")
    for name, tensor in source.online.state_dict().items():
        assert torch.equal(core.agent.online.state_dict()[name], tensor), name
        assert torch.equal(core.agent.target.state_dict()[name], tensor), name
        assert not torch.equal(fresh.agent.online.state_dict()[name], tensor) or "bias" in name, name

    wide = base.with_overrides({"sensor.width": 48, "sensor.height": 36})
    with pytest.raises(CheckpointError, match="40 x 30 px.*is not this run.s.*48 x 36 px"):
        LearnerCore(wide.with_overrides({"train.init_from": str(path)}), device="cpu")
    ckpt = save_checkpoint(tmp_path / "ckpt.safetensors", source)
    with pytest.raises(CheckpointError, match="model export"):
        LearnerCore(base.with_overrides({"train.init_from": str(ckpt)}), device="cpu")
    code = main(["train", "--preset", "tiny", "--runs-dir", str(tmp_path / "runs"),
                 "--run", "bad", "--updates", "1", "--quiet", "--set", f"train.init_from={tmp_path}/none.safetensors"])
    assert code == 2 and "no such file" in capsys.readouterr().err

    with pytest.raises(ConfigError, match="init_from"):
        TrainConfig(init_from="model.pt")
    # the shipped model into its own recipe, whose conv transfer then stands aside
    shipped = load_preset("fast-40x30").with_overrides({"replay.capacity": 500, "train.init_from": "pretrained"})
    assert shipped.train.init_conv_from == "pretrained:sl"
    net, _ = load_exported_weights(pretrained_path("pretrained"))
    first = net.members[0] if isinstance(net, QEnsemble) else net  # an ensemble starts a run from its first network
    core = LearnerCore(shipped, device="cpu")
    assert all(torch.equal(core.agent.online.state_dict()[n], t) for n, t in first.state_dict().items())


def test_an_ensemble_is_one_weights_file_that_plays_the_mean_and_refuses_a_forged_shape(tmp_path, capsys):
    """``model export A B --ensemble``: one file holding both networks that loads as a QEnsemble
    (the mean of their Q-values, each member's provenance kept), starts a fine-tuning run from
    its first network, and whose member list, when forged, is a clear error."""
    from services.cli import main
    from shared.config import load_preset
    from shared.learning.checkpoints import load_model, load_tensors_file, save_tensors_file
    from shared.learning.learner import LearnerCore

    base = load_preset("tiny").with_overrides({"replay.capacity": 500})
    agents = [LearnerCore(base.with_overrides({"train.seed": s}), device="cpu").agent for s in (1, 2)]
    paths = [export_weights(tmp_path / f"m{i}.safetensors", a.online, 100 * (i + 1)) for i, a in enumerate(agents)]
    out = tmp_path / "ens.safetensors"
    assert main(["model", "export", *map(str, paths), "--ensemble", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["ensemble"] == 2
    model = load_model(out)
    assert isinstance(model.net, QEnsemble) and len(model.net.members) == 2 and model.label == "ens@100"
    assert [e["source"] for e in model.ensemble_of] == list(map(str, paths))
    assert [e["weights_sha256"] for e in model.ensemble_of] == [load_model(p).weights_sha256 for p in paths]
    depth = np.random.default_rng(0).random((3, 30, 40)).astype(np.float32) * 4
    from shared.learning.model import InferenceRunner

    want = np.mean([a.q_values(depth) for a in agents], axis=0)
    np.testing.assert_allclose(InferenceRunner(model.net).q_values(depth), want, rtol=1e-5, atol=1e-6)
    # fine-tuning from an ensemble: a learner trains one network, the first
    core = LearnerCore(base.with_overrides({"train.init_from": str(out)}), device="cpu")
    for name, tensor in agents[0].online.state_dict().items():
        assert torch.equal(core.agent.online.state_dict()[name], tensor), name

    assert main(["model", "export", str(paths[0]), "--ensemble", "--out", str(tmp_path / "one.safetensors")]) == 2
    assert "at least two" in capsys.readouterr().err
    # A mean of ensembles averaged member i with member i of the others and kept the last one's
    # member digests, which no longer described the weights: refused in one line.
    assert main(["model", "export", str(out), str(out), "--out", str(tmp_path / "mean.safetensors")]) == 2
    assert "ensembles are not averaged" in capsys.readouterr().err
    assert not (tmp_path / "mean.safetensors").exists()
    tensors, meta = load_tensors_file(out, "cogexplore-weights")
    for forged in (meta["members"][:1], meta["members"] * 9, "two", [1, 2]):
        bad = tmp_path / "forged.safetensors"
        save_tensors_file(bad, tensors, {k: v for k, v in meta.items() if k != "digest"} | {"members": forged})
        with pytest.raises(CheckpointError, match="members must be a list|does not match"):
            load_model(bad)
    save_tensors_file(bad, tensors, {k: v for k, v in meta.items() if k != "digest"} | {"ensemble_of": "forged"})
    assert [e["source"] for e in load_model(bad).ensemble_of] == ["member 0", "member 1"]  # labels only


def test_export_members_takes_networks_out_of_an_ensemble(tmp_path, capsys):
    """``model export ENSEMBLE --members``: by label, by label without its update or by index, one
    pick is that network alone (the same weights), several a smaller ensemble in the order given;
    a pick that names no member, one named twice or a single network is a clear error."""
    from services.cli import main
    from shared.config import load_preset
    from shared.learning.checkpoints import load_model
    from shared.learning.learner import LearnerCore

    base = load_preset("tiny").with_overrides({"replay.capacity": 500})
    agents = [LearnerCore(base.with_overrides({"train.seed": s}), device="cpu").agent for s in (1, 2, 3)]
    paths = [export_weights(tmp_path / f"{name}.safetensors", a.online, 100 * (i + 1))
             for i, (name, a) in enumerate(zip(("A", "B", "C"), agents))]
    ens = tmp_path / "ens.safetensors"
    assert main(["model", "export", *map(str, paths), "--ensemble", "--out", str(ens)]) == 0
    capsys.readouterr()

    one = tmp_path / "b.safetensors"
    assert main(["model", "export", str(ens), "--members", "B", "--out", str(one)]) == 0
    assert json.loads(capsys.readouterr().out)["policy_version"] == 200
    b = load_model(one)
    assert not isinstance(b.net, QEnsemble) and b.weights_sha256 == load_model(paths[1]).weights_sha256

    two = tmp_path / "ca.safetensors"
    assert main(["model", "export", str(ens), "--members", "C@300, 0", "--out", str(two)]) == 0
    capsys.readouterr()
    ca = load_model(two)
    assert isinstance(ca.net, QEnsemble) and [e["label"] for e in ca.ensemble_of] == ["C@300", "A@100"]
    assert [e["weights_sha256"] for e in ca.ensemble_of] == [load_model(paths[i]).weights_sha256 for i in (2, 0)]
    depth = np.random.default_rng(0).random((2, 30, 40)).astype(np.float32) * 4
    from shared.learning.model import InferenceRunner

    want = np.mean([agents[i].q_values(depth) for i in (2, 0)], axis=0)
    np.testing.assert_allclose(InferenceRunner(ca.net).q_values(depth), want, rtol=1e-5, atol=1e-6)

    for members, message in (("D", "names no member.*0: A@100, 1: B@200, 2: C@300"), ("A,0", "twice"),
                             ("7", "names no member")):
        assert main(["model", "export", str(ens), "--members", members, "--out", str(tmp_path / "x.safetensors")]) == 2
        assert re.search(message, capsys.readouterr().err), members
    assert main(["model", "export", str(paths[0]), "--members", "A", "--out", str(tmp_path / "x.safetensors")]) == 2
    assert "one network, not an ensemble" in capsys.readouterr().err
    assert not (tmp_path / "x.safetensors").exists()


def test_an_export_keeps_its_runs_config_so_it_plays_in_that_runs_world(tmp_path, capsys):
    """``model export`` of a run's checkpoints (the mean `up` evaluates, a `model select` choice)
    keeps the run's config, so `evaluate` plays it in the run's world and robot as it plays the
    checkpoints; an export without one (the shipped models) has none; a forged one is refused."""
    from services.cli import main
    from shared.config import load_preset
    from shared.evaluation.setup import setup_evaluation
    from shared.learning.checkpoints import (CheckpointManager, load_model, load_tensors_file,
                                             save_tensors_file)
    from shared.learning.learner import LearnerCore

    cfg = load_preset("tiny").with_overrides({"replay.capacity": 500, "env.world": "corridor",
                                              "env.collision_distance_m": 0.5})
    manager = CheckpointManager(tmp_path / "checkpoints", keep=5)
    for seed, updates in enumerate((10, 20)):
        core = LearnerCore(cfg.with_overrides({"train.seed": seed}), device="cpu")
        core.agent.update_count = core.agent.policy_version = updates
        manager.save(core.agent, config=cfg.to_dict())
    out = tmp_path / "mean.safetensors"
    assert main(["model", "export", *map(str, manager.checkpoints()), "--out", str(out)]) == 0
    capsys.readouterr()
    mean = load_model(out)
    assert mean.run_config == load_model(manager.checkpoints()[-1]).run_config
    setup = setup_evaluation("greedy", model=mean, device="cpu")
    assert setup.world == "corridor" and setup.env_cfg.collision_distance_m == 0.5
    plain = export_weights(tmp_path / "plain.safetensors", mean.net, 20)
    assert load_model(plain).run_config is None
    assert setup_evaluation("greedy", model=load_model(plain), device="cpu").world == "paper-indoor"

    tensors, meta = load_tensors_file(out, "cogexplore-weights")
    bad = tmp_path / "forged.safetensors"
    for forged, message in (("corridor", "not a table of sections"),
                            ({**meta["run_config"], "env": {"collision_distance_m": -1}}, "run config is invalid")):
        save_tensors_file(bad, tensors, {k: v for k, v in meta.items() if k != "digest"} | {"run_config": forged})
        with pytest.raises(CheckpointError, match=message):
            load_model(bad)


def test_models_trained_for_different_robots_are_not_joined(tmp_path, capsys):
    """An ensemble plays in its first model's environment and a mean in its last's: a network trained
    for another robot (here a slower control period) would be scored on moves it never made. Other
    rewards are allowed (the card's ensembles with a trap charge)."""
    from services.cli import main
    from shared.config import load_preset
    from shared.evaluation.setup import setup_evaluation
    from shared.learning.checkpoints import CheckpointManager, load_model
    from shared.learning.learner import LearnerCore

    base = load_preset("tiny").with_overrides({"replay.capacity": 500})
    files = {}
    for name, overrides in (("base", {}), ("slow", {"env.control_period_s": 1.0}),
                            ("charged", {"env.reward_trap_penalty": 5.0})):
        cfg = base.with_overrides(overrides)
        manager = CheckpointManager(tmp_path / name, keep=5)
        manager.save(LearnerCore(cfg, device="cpu").agent, config=cfg.to_dict())
        files[name] = str(manager.checkpoints()[-1])
    for argv in (["--ensemble"], []):  # an ensemble, a mean
        assert main(["model", "export", files["base"], files["slow"], *argv, "--out", str(tmp_path / "x.safetensors")]) == 2
        err = capsys.readouterr().err
        assert "env.control_period_s = 1.0" in err and "must share the robot" in err, err
        assert not (tmp_path / "x.safetensors").exists()
    with pytest.raises(CheckpointError, match="env.control_period_s"):
        setup_evaluation("greedy", checkpoint=files["base"], ensemble=(files["slow"],), device="cpu")
    assert main(["model", "export", files["base"], files["charged"], "--ensemble",
                 "--out", str(tmp_path / "two.safetensors")]) == 0
    assert len(load_model(tmp_path / "two.safetensors").ensemble_of) == 2


def test_a_checkpoint_with_forged_metadata_is_skipped_not_a_crash(tmp_path):
    """The tensors' digest does not cover the metadata: a file whose metadata was damaged or forged
    (a list, a missing agent, a replay entry naming another file, a version that is no count) is a
    CheckpointError; a run resumes from the newest good checkpoint and the learner's pruning goes on."""
    import safetensors.torch

    from shared.config import load_preset
    from shared.learning.checkpoints import (CheckpointManager, load_checkpoint, load_model, load_tensors_file,
                                             save_tensors_file)
    from shared.learning.learner import LearnerCore

    cfg = load_preset("tiny").with_overrides({"replay.capacity": 500})
    core = LearnerCore(cfg, device="cpu")
    manager = CheckpointManager(tmp_path / "checkpoints", keep=5)
    core.agent.update_count = 10
    good = manager.save(core.agent, config=cfg.to_dict())
    tensors, meta = load_tensors_file(good, "cogexplore-checkpoint")
    meta = {k: v for k, v in meta.items() if k != "digest"}
    forged = manager.path_for(20)
    agent = meta["agent"]
    for changed in ({"agent": None}, {"agent": []}, {"agent": {**agent, "update_count": "20"}},
                    {"agent": {**agent, "policy_version": -1}}, {"replay": 5},
                    {"replay": {"file": "../../config.toml", "digest": "0" * 12}}, {"extra": [1]}):
        save_tensors_file(forged, tensors, meta | changed)
        with pytest.raises(CheckpointError):
            load_checkpoint(forged)
    for section in ("model", "sensor"):  # a network's config that is no table
        for forged_config in ("abc", 5, None, [1, 2]):
            save_tensors_file(forged, tensors, meta | {"agent": {**agent, section: forged_config}})
            with pytest.raises(CheckpointError, match=f"stored {section} config is invalid"):
                load_model(forged)
    for raw in ("[]", "[" * 100_000, '{"format": ' + "9" * 5000 + "}"):
        safetensors.torch.save_file(tensors, forged, metadata={"cogexplore": raw})
        with pytest.raises(CheckpointError):
            load_checkpoint(forged)
        with pytest.raises(CheckpointError):
            load_model(forged)
    copied = tmp_path / "best.safetensors"  # a checkpoint copied away keeps its replay entry: it loads
    copied.write_bytes(good.read_bytes())
    assert load_checkpoint(copied).replay_path is None or not load_checkpoint(copied).replay_path.exists()
    assert load_model(copied).policy_version == load_model(good).policy_version
    (manager.directory / "latest").write_text(forged.name + "\n")
    resumed = manager.load_latest()
    assert resumed is not None and resumed.path == good and any(forged.name in s for s in manager.skipped)
    core.agent.update_count = 30
    assert manager.save(core.agent, config=cfg.to_dict()).name == "ckpt-000000030.safetensors"  # pruning reads it too


def _in_a_child(code: str, tmp_path, memory_gib: int = 4) -> list:
    """The JSON lines ``code`` prints, run in a child Python whose address space is capped after its
    imports: a FIFO that safetensors waits on (in Rust: no signal stops it) or a read without end hangs
    or fills the child, not the test run."""
    import subprocess
    import sys
    prelude = ("import json, os, resource, sys\n"
               "from pathlib import Path\n"
               "from shared.learning import checkpoints as C\n"
               f"resource.setrlimit(resource.RLIMIT_AS, ({memory_gib} << 30, {memory_gib} << 30))\n"
               "def attempt(f):\n"
               "    try:\n"
               "        f(); return 'loaded'\n"
               "    except C.CheckpointError as exc:\n"
               "        return 'CheckpointError: ' + str(exc)\n"
               "    except BaseException as exc:\n"
               "        return type(exc).__name__ + ': ' + str(exc)\n")
    try:
        done = subprocess.run([sys.executable, "-c", prelude + code], capture_output=True, text=True, timeout=60,
                              cwd=os.getcwd(), env=dict(os.environ, PYTHONPATH=os.getcwd()))
    except subprocess.TimeoutExpired:
        pytest.fail("the child hung")
    assert done.returncode == 0, done.stderr[-2000:]
    return [json.loads(line) for line in done.stdout.splitlines()]


def test_a_fifo_or_a_device_where_a_file_should_be_is_refused_not_waited_on_nor_read_for_ever(tmp_path):
    from shared.learning.checkpoints import load_model

    agent, _ = setup(DQNConfig())
    cm = CheckpointManager(tmp_path / "run" / "checkpoints")
    agent.update_count = 1
    good = cm.save(agent)
    fifo = cm.path_for(2)
    os.mkfifo(fifo)  # a newer "checkpoint" that latest names
    (cm.directory / "latest").write_text(fifo.name + "\n")
    os.mkfifo(tmp_path / "latest-fifo")
    os.symlink("/dev/zero", tmp_path / "latest-zero")
    out = _in_a_child(f"""
cm = C.CheckpointManager(Path({str(cm.directory)!r}))
ckpt = cm.load_latest()
print(json.dumps([ckpt.path.name, cm.skipped]))
print(json.dumps(attempt(lambda: C.load_exported_weights({str(fifo)!r}))))
for pointer in ("latest-fifo", "latest-zero"):
    os.replace(Path({str(tmp_path)!r}) / pointer, cm.directory / "latest")
    ckpt = cm.load_latest()
    print(json.dumps([ckpt.path.name, cm.skipped]))
""", tmp_path)
    assert out[0][0] == good.name and "ckpt-000000002.safetensors is not a regular file" in out[0][1][0]
    assert out[1].startswith("CheckpointError: ") and "is not a regular file" in out[1]
    for name, skipped in out[2:]:
        assert name == good.name and skipped[0].startswith(f"{cm.directory / 'latest'} cannot be read")
    os.unlink(cm.directory / "latest")
    os.symlink("latest", cm.directory / "latest")  # a symlink loop
    assert load_model(cm.directory).path == good
    with pytest.raises(CheckpointError, match="neither a file nor a folder .a FIFO"):
        load_model(fifo)


def _forge_export(tmp_path, name, tensors=None, **meta_changes):
    """A weights export whose tensors or metadata are replaced, its digest recomputed (the digest
    only proves the bytes are the writer's, and a forger writes them)."""
    from shared.learning.checkpoints import load_tensors_file, save_tensors_file

    agent, _ = setup(DQNConfig())
    good = export_weights(tmp_path / "good.safetensors", agent.online)
    own, meta = load_tensors_file(good, "cogexplore-weights")
    meta = {k: v for k, v in {**meta, **meta_changes}.items() if k != "digest"}
    save_tensors_file(tmp_path / name, own if tensors is None else tensors(own), meta)
    return tmp_path / name


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.complex64, torch.uint8])
def test_weights_of_a_dtype_the_network_does_not_compute_in_are_refused(tmp_path, dtype):
    forged = _forge_export(tmp_path, "w.safetensors",
                           lambda t: {**t, "fc3.weight": (t["fc3.weight"] * 100).to(dtype)})
    with pytest.raises(CheckpointError, match=f"fc3.weight: dtype {dtype}, network wants floating-point"):
        load_exported_weights(forged)


def test_weights_in_float8_load_and_a_nan_among_them_is_refused_not_a_traceback(tmp_path):
    ok = _forge_export(tmp_path, "f8.safetensors", lambda t: {**t, "fc3.bias": t["fc3.bias"].to(torch.float8_e4m3fn)})
    net, _ = load_exported_weights(ok)
    assert net.fc3.bias.dtype == torch.float32

    def nan_in_float8(t):
        bias = t["fc3.bias"].clone()
        bias[0] = float("nan")
        return {**t, "fc3.bias": bias.to(torch.float8_e4m3fn)}
    with pytest.raises(CheckpointError, match="fc3.bias holds NaN"):
        load_exported_weights(_forge_export(tmp_path, "nan8.safetensors", nan_in_float8))


def test_only_a_file_of_another_kind_is_called_not_a_supervised_model(tmp_path):
    """``load_supervised`` called every refusal "not a supervised model (write one with `cogexplore
    pretrain`)", a supervised model with NaN weights or a corrupt one too: that prefix now stands only
    before a file of another format, and the others say what is wrong with the file they name."""
    from shared.learning.checkpoints import load_supervised, load_tensors_file, save_supervised, save_tensors_file
    from shared.learning.model import SupervisedNet

    good = save_supervised(tmp_path / "sl.safetensors", SupervisedNet(TINY))
    tensors, meta = load_tensors_file(good, "cogexplore-supervised")
    meta = {k: v for k, v in meta.items() if k != "digest"}
    nan = tmp_path / "nan.safetensors"
    save_tensors_file(nan, {**tensors, "fc.bias": torch.full_like(tensors["fc.bias"], float("nan"))}, meta)
    newer = tmp_path / "newer.safetensors"
    save_tensors_file(newer, tensors, {**meta, "version": 99})
    corrupt = tmp_path / "corrupt.safetensors"
    data = bytearray(good.read_bytes())
    data[-10] ^= 0xFF
    corrupt.write_bytes(bytes(data))
    refusals = {nan: "fc.bias holds NaN", newer: "format version 99", corrupt: "is corrupt",
                tmp_path / "none.safetensors": "does not exist"}
    for path, reason in refusals.items():
        with pytest.raises(CheckpointError) as refused:
            load_supervised(path)
        assert str(refused.value).startswith(f"{path}") and reason in str(refused.value)
    agent, _ = setup(DQNConfig())
    with pytest.raises(CheckpointError, match=r"^not a supervised model .*'cogexplore-checkpoint' file"):
        load_supervised(save_checkpoint(tmp_path / "ckpt.safetensors", agent))
    assert load_supervised(good)[1]["sensor"]["width"] == 40


def test_only_a_file_of_another_kind_gets_the_other_kinds_refusals_and_hints(tmp_path):
    """``load_model`` called a weights export with NaN weights "neither a checkpoint nor a weights
    export" (beside "is a 'cogexplore-weights' file, expected 'cogexplore-checkpoint'"), and
    ``train.init_from`` told to export a checkpoint that was a diverged weights file: each now says
    only what is wrong with the file, and keeps the other kind's words for a file of another kind."""
    from shared.learning.checkpoints import init_agent_weights, load_model, save_supervised
    from shared.learning.model import SupervisedNet

    def nan_bias(t):
        return {**t, "fc1.bias": torch.full_like(t["fc1.bias"], float("nan"))}
    nan = _forge_export(tmp_path, "nan.safetensors", nan_bias)
    agent, _ = setup(DQNConfig())
    for load, prefix in ((load_model, f"{nan}: "),
                         (lambda p: init_agent_weights(agent, p), f"train.init_from: {nan}: ")):
        with pytest.raises(CheckpointError) as refused:
            load(nan)
        assert str(refused.value) == prefix + "fc1.bias holds NaN or infinite values (diverged or damaged weights)"
    ckpt = save_checkpoint(tmp_path / "ckpt.safetensors", agent)
    with pytest.raises(CheckpointError, match=r"'cogexplore-checkpoint' file, expected 'cogexplore-weights' "
                                              r"\(a training checkpoint becomes a weights file with"):
        init_agent_weights(agent, ckpt)
    with pytest.raises(CheckpointError, match=r"is neither a checkpoint nor a weights export: .*expected "
                                              r"'cogexplore-checkpoint' \| .*expected 'cogexplore-weights'"):
        load_model(save_supervised(tmp_path / "sl.safetensors", SupervisedNet(TINY)))


def test_a_forged_config_claiming_networks_far_larger_than_the_file_is_refused_before_any_memory(tmp_path):
    """A few kB whose metadata claims 16 networks of 2 GiB each: refused from the file's tensors,
    before a byte of the 32 GiB is taken (the child may use 4 GiB)."""
    from shared.learning.model import MAX_FC1_WEIGHTS, MAX_ENSEMBLE_MEMBERS, QNetwork

    sensor = SensorConfig(width=640, height=480)
    flat = 64 * (480 // 8) * (640 // 8)
    big = ModelConfig(fc1=MAX_FC1_WEIGHTS // flat)
    with torch.device("meta"):
        fingerprint = architecture_fingerprint(QEnsemble([QNetwork(big, sensor)] * MAX_ENSEMBLE_MEMBERS))
    forged = _forge_export(tmp_path, "huge.safetensors", sensor=dataclasses.asdict(sensor),
                           model=dataclasses.asdict(big), members=[dataclasses.asdict(big)] * MAX_ENSEMBLE_MEMBERS,
                           fingerprint=fingerprint)
    single = _forge_export(tmp_path, "huge1.safetensors", sensor=dataclasses.asdict(sensor),
                           model=dataclasses.asdict(big))
    out = _in_a_child(f"""
print(json.dumps(attempt(lambda: C.load_exported_weights({str(forged)!r}))))
print(json.dumps(attempt(lambda: C.load_model({str(single)!r}))))
""", tmp_path)
    assert out[0].startswith("CheckpointError: ") and "weights do not fit QEnsemble" in out[0]
    assert out[1].startswith("CheckpointError: ")


def test_export_metadata_cannot_be_overridden_by_extra(tmp_path):
    """A caller's extra (a card, a selection) named like the file's own keys would make the export
    unloadable (another version) or another network."""
    agent, _ = setup(DQNConfig())
    path = export_weights(tmp_path / "w.safetensors", agent.online, 7,
                          extra={"version": "2.1", "format": "mine", "policy_version": 3, "note": "kept"})
    net, meta = load_exported_weights(path)
    assert meta["policy_version"] == 7 and meta["note"] == "kept"


def test_the_newest_save_keeps_its_replay_beside_higher_numbered_leftovers(tmp_path):
    """A run resumed from an older checkpoint (its newest one was damaged, or ``latest`` was not
    rewritten after it) saves below the leftover: that save, which ``latest`` names, keeps its replay."""
    agent, mem = setup(DQNConfig())
    fill(mem)
    cm = CheckpointManager(tmp_path, keep=3, keep_replays=1)
    agent.update_count = 30
    cm.save(agent, replay=mem)
    (tmp_path / "latest").write_text(cm.path_for(10).name + "\n")  # the pointer of the timeline resumed
    agent.update_count = 20
    newest = cm.save(agent, replay=mem)
    assert cm.latest() == newest and cm.load().replay_path.exists()


def test_pruning_leaves_a_live_writers_temporary_file_and_removes_a_dead_ones(tmp_path):
    """Another process writing into the folder (an export, a second manager) keeps its file being
    written; a crashed writer's is removed."""
    import subprocess
    import sys

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        writing = tmp_path / f".mean.safetensors.tmp-{live.pid}"
        crashed = tmp_path / f".ckpt-000000001.safetensors.tmp-{int(dead.stdout)}"
        writing.write_bytes(b"half")
        crashed.write_bytes(b"half")
        agent, _ = setup(DQNConfig())
        CheckpointManager(tmp_path).save(agent)
        assert writing.exists() and not crashed.exists()
    finally:
        live.kill()
        live.wait()


def test_a_weights_file_that_fills_the_disk_is_one_line_and_leaves_nothing(tmp_path) -> None:
    """safetensors reports a failed write as its own error: `model export` (and a learner's checkpoint)
    on a full disk ended in a traceback, not the CLI's one line for a file that cannot be written."""
    from service_processes import run_on_a_full_disk

    out = tmp_path / "R3.safetensors"
    done = run_on_a_full_disk("import sys; from services.cli import main; sys.exit(main(['model', 'export', "
                              f"'pretrained', '--members', 'R3', '--out', {str(out)!r}]))", 100_000)
    assert done.returncode == 2, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1, done.stderr
    assert f"{out} cannot be written" in done.stderr and "File too large" in done.stderr
    assert list(tmp_path.iterdir()) == []  # no file, no temporary
