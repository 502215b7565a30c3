"""The learner's process shell: its weights sender and its statistics log across a restart."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from services.bus.session import ZenohSettings, free_tcp_port, open_router
from services.learner.service import LatestSender, run_learner
from services.runs import RunPaths
from shared.config import load_preset
from shared.learning.checkpoints import CheckpointManager, export_weights
from shared.learning.learner import LearnerCore
from shared.learning.stats import CsvLog, LearnerRow, read_csv_records
from tests.shared.learning.test_learner import diverge_at


class SlowLink:
    """A publisher whose puts take their time, as BLOCK congestion control does on a slow link."""

    def __init__(self, put_s: float):
        self.put_s = put_s
        self.putting = threading.Event()
        self.sent: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.putting.set()
        time.sleep(self.put_s)
        self.sent.append(payload)


def test_the_sender_publishes_the_final_weights_even_behind_a_slow_put():
    link = SlowLink(put_s=0.5)
    sender = LatestSender(link)
    sender.offer(b"update 100")
    assert link.putting.wait(5.0)
    sender.offer(b"older, never sent")
    sender.offer(b"final")  # offered while update 100's put is still under way
    sender.close()  # it dropped the final weights: actors and the evaluator never saw the last version
    assert link.sent == [b"update 100", b"final"]
    sender.close()  # a second close is harmless


def _row(update: int) -> LearnerRow:
    return LearnerRow(time_s=update / 10, update=update, policy_version=update, loss=0.1, mean_q=1.0,
                      updates_per_s=10.0, transitions=update + 50, transitions_per_s=10.0, replay_size=update,
                      rejected=0, actors_alive=1, mean_weight_lag=0.0, label_agreement=None, lr=1e-3,
                      safe_agreement=None, session=1)


def test_a_learner_restarted_without_a_checkpoint_does_not_log_its_updates_going_back(tmp_path: Path):
    paths = RunPaths(tmp_path / "run").make()
    with CsvLog(paths.stats, LearnerRow) as log:  # a learner killed at update 300, before its first checkpoint
        for update in (0, 100, 200, 300):
            log.write(_row(update))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    stop = threading.Event()
    with open_router([endpoint]):
        timer = threading.Timer(1.0, stop.set)
        timer.start()
        try:
            result = run_learner(load_preset("smoke"), "run", paths, ZenohSettings(mode="client", connect=(endpoint,)),
                                 stop, stats_every_s=0.2)
        finally:
            timer.cancel()
    assert result["updates"] == 0  # no checkpoint: it started over
    rows = list(read_csv_records(paths.stats / LearnerRow.FILE))
    # the rows after update 0 went: their updates come again (they were logged as 0, 100, 200, 300, 0, ...)
    assert len(rows) > 1 and {int(r["update"]) for r in rows} == {0}
    # each session's rows carry its own mark (the summary tells the sessions apart by it)
    assert rows[0]["session"] == "1" and len({r["session"] for r in rows[1:]}) == 1 and int(rows[1]["session"]) > 1


def _run_with_transitions(paths: RunPaths, cfg, count: int = 200) -> None:
    """A checkpoint at update 0 whose replay memory holds ``count`` transitions: updates are due at once,
    with no actor."""
    core = LearnerCore(cfg, device="cpu")
    for i in range(count):
        core.add_transition("s", np.full((30, 40), 1.0 + 0.1 * (i % 7), np.float32), i % 5, cfg.env.reward_move,
                            np.full((30, 40), 1.1, np.float32), False, False)
    CheckpointManager(paths.checkpoints).save(core.agent, replay=core.replay, config=cfg.to_dict(),
                                              extra=core.checkpoint_extra())


def _learn(cfg, paths: RunPaths) -> dict:
    """``run_learner`` until ``total_updates``, through a router of its own."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        return run_learner(cfg, "run", paths, ZenohSettings(mode="client", connect=(endpoint,)), threading.Event())


def test_the_last_update_s_checkpoint_is_written_once(tmp_path: Path, checkpoint_saves: list[int]):
    # At total_updates the loop's periodic checkpoint and then the final one wrote the same file twice.
    cfg = load_preset("smoke").with_overrides({"train.total_updates": 10, "train.checkpoint_every": 5})
    paths = RunPaths(tmp_path / "run").make()
    _run_with_transitions(paths, cfg)
    saved = checkpoint_saves
    saved.clear()  # the transitions' own checkpoint
    assert _learn(cfg, paths)["updates"] == 10
    assert saved == [5, 10]
    # an end off the period, and a resume that has nothing left to do, still write their final checkpoint
    assert _learn(cfg.with_overrides({"train.total_updates": 13}), paths)["updates"] == 13
    assert _learn(cfg.with_overrides({"train.total_updates": 13}), paths)["updates"] == 13
    assert saved == [5, 10, 13, 13]
    assert [p.name for p in CheckpointManager(paths.checkpoints).checkpoints()] == [
        f"ckpt-{u:09d}.safetensors" for u in (5, 10, 13)]  # keep_checkpoints: the newest 3


def test_an_update_skipped_for_a_non_finite_loss_is_not_checkpointed_again(tmp_path: Path, monkeypatch,
                                                                           checkpoint_saves: list[int]):
    # A skipped update (LearnerCore.train_step None: some sampled rows gave a non-finite loss) left the
    # count where it was, and the loop wrote the checkpoint of the update before it once more. The
    # replay's checks at load and ingest keep the poisoned rows that cause one out of a run (the trainer's
    # test poisons its memory directly), so the step after update 5 is made to skip as the core skips: no
    # update applied, None returned.
    cfg = load_preset("smoke").with_overrides({"train.total_updates": 12, "train.checkpoint_every": 1})
    paths = RunPaths(tmp_path / "run").make()
    _run_with_transitions(paths, cfg)
    real_step, calls = LearnerCore.train_step, []

    def skips_once(core):
        calls.append(core.updates)
        return None if len(calls) == 6 else real_step(core)

    monkeypatch.setattr(LearnerCore, "train_step", skips_once)
    checkpoint_saves.clear()
    assert _learn(cfg, paths)["updates"] == 12 and calls[5:7] == [5, 5]  # the skip, then update 6
    assert checkpoint_saves == list(range(1, 13))


def test_a_new_run_s_transfer_file_is_read_once_and_its_config_saved(tmp_path: Path, monkeypatch):
    # `cogexplore learner` on a new run read its train.init_from file twice: once to refuse a bad one
    # before saving the config, then again in the learner.
    import shared.learning.learner as learner_module
    from services.cli import main

    source = export_weights(tmp_path / "w.safetensors", LearnerCore(load_preset("smoke"), device="cpu").agent.online)
    reads: list[str] = []
    read = learner_module.init_agent_weights

    def counted(agent, path):
        reads.append(str(path))
        return read(agent, path)

    monkeypatch.setattr(learner_module, "init_agent_weights", counted)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        assert main(["learner", "--run", "new", "--runs-dir", str(tmp_path), "--preset", "smoke", "--connect", endpoint,
                     "--set", f"train.init_from={source}", "--set", "train.total_updates=0"]) == 0
    assert reads == [str(source)]
    saved = load_preset(tmp_path / "new" / "config.toml")
    assert saved.train.init_from == str(source) and saved.train.total_updates == 0


def test_a_resumed_learner_does_not_read_its_transfer_file_again(tmp_path: Path):
    # Its checkpoint replaces the transferred weights, yet the learner read train.init_from at every
    # start: a file moved or deleted since stopped the run.
    trained = load_preset("smoke").with_overrides({"train.total_updates": 3})
    paths = RunPaths(tmp_path / "run").make()
    _run_with_transitions(paths, trained)  # its checkpoint, from the transfer when the file was there
    assert _learn(trained.with_overrides({"train.init_from": str(tmp_path / "gone.safetensors")}), paths)["updates"] == 3


@pytest.mark.parametrize("weights_every, diverged_at", [(100, 4), (1, 3)], ids=["at-a-checkpoint", "at-a-publish"])
def test_diverged_weights_stop_the_learner_in_one_line_and_its_good_checkpoint_stays(
        tmp_path: Path, monkeypatch, capsys, weights_every: int, diverged_at: int):
    # Weights gone NaN at a checkpoint's update were saved like any other, and with one checkpoint kept the
    # run's good one pruned: nothing of it loaded. At a publish, the weights message refused them, and the
    # learner stopped on a MessageError that did not say the network had diverged.
    from services.cli import main

    cfg = load_preset("smoke")
    paths = RunPaths(tmp_path / "run").make()
    _run_with_transitions(paths, cfg)
    diverge_at(monkeypatch, diverged_at)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        code = main(["learner", "--run", "run", "--runs-dir", str(tmp_path), "--preset", "smoke", "--connect", endpoint,
                     "--weights-every", str(weights_every), "--set", "train.total_updates=10",
                     "--set", "train.checkpoint_every=2", "--set", "train.keep_checkpoints=1"])
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if "diverged" in line]
    good = paths.checkpoints / "ckpt-000000002.safetensors"
    assert code == 2 and "Traceback" not in err and said == [
        f"cogexplore learner: error: update {diverged_at}: weight online.advantage.bias holds NaN or infinite values, "
        "the network has diverged (the learning rate is probably too high); stopped without saving its weights: "
        f"the run resumes from its last good checkpoint {good} (update 2); its next start resumes at "
        f"dqn.lr={load_preset('smoke').dqn.lr / 2:g} (diverged.json)"], err
    checkpoints = CheckpointManager(paths.checkpoints)
    assert checkpoints.checkpoints() == [good] and checkpoints.load_latest().update_count == 2


def test_a_learner_that_listens_trains_and_sends_its_weights(tmp_path: Path):
    # The weights' own session (a link of their own to the router) took the learner's settings whole: a
    # learner given --listen (or a config file with listen endpoints) bound its ports twice, "Address
    # already in use", and one whose file names its Zenoh id was refused by the router the second time;
    # neither started. The second session now listens nowhere under an id of its own; a peer keeps one.
    import json

    from services.bus.session import open_session
    from shared.wire.keys import RunKeys

    cfg = load_preset("smoke").with_overrides({"train.total_updates": 3})
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    listening_file = tmp_path / "learner.json5"
    # a file that also names the session's Zenoh id: the router refused a second session under it
    listening_file.write_text(json.dumps({"mode": "client", "id": "abcdef12",
                                          "listen": {"endpoints": [f"tcp/127.0.0.1:{free_tcp_port()}"]}}))
    learners = {"--listen": ZenohSettings(mode="client", connect=(endpoint,), listen=(f"tcp/127.0.0.1:{free_tcp_port()}",),
                                          router_wait_s=0),
                "a config file that listens": ZenohSettings(connect=(endpoint,), config_file=str(listening_file),
                                                            router_wait_s=0),
                "a peer": ZenohSettings(mode="peer", connect=(endpoint,), listen=(f"tcp/127.0.0.1:{free_tcp_port()}",),
                                        router_wait_s=0)}
    assert learners["a peer"].second_link() is None
    for name, settings in learners.items():
        paths = RunPaths(tmp_path / name.replace(" ", "-")).make()
        _run_with_transitions(paths, cfg)
        with open_router([endpoint]), open_session(ZenohSettings(mode="client", connect=(endpoint,))) as watcher:
            seen: list[int] = []
            sub = watcher.declare_subscriber(RunKeys("run").weights, lambda sample: seen.append(len(sample.payload)))  # noqa: F841
            time.sleep(0.3)  # the subscription reaches the router before the learner's first weights
            assert run_learner(cfg, "run", paths, settings, threading.Event())["updates"] == 3, name
            deadline = time.monotonic() + 5
            while not seen and time.monotonic() < deadline:
                time.sleep(0.05)
        assert seen, f"{name}: no weights reached the router's subscribers"


def test_a_learner_resumed_with_a_new_rate_saves_it_as_the_runs_config(tmp_path: Path):
    # A learner kept the run's saved config.toml whatever it was started with: resumed with --set dqn.lr (after a
    # divergence, say) it trained at the new rate, and a later start without --set went back to the old one.
    from services.cli import main

    paths = RunPaths(tmp_path / "run").make()
    _run_with_transitions(paths, load_preset("smoke"))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    base = ["learner", "--run", "run", "--runs-dir", str(tmp_path), "--connect", endpoint]
    with open_router([endpoint]):
        assert main([*base, "--preset", "smoke", "--set", "train.total_updates=2"]) == 0
        assert main([*base, "--set", "dqn.lr=1e-6", "--set", "train.total_updates=4"]) == 0
        saved = load_preset(paths.config, complete=True)
        assert saved.dqn.lr == 1e-6 and saved.train.total_updates == 4
        assert main([*base, "--set", "train.total_updates=6"]) == 0  # no --set dqn.lr: the run's own
    assert load_preset(paths.config, complete=True).dqn.lr == 1e-6
    assert CheckpointManager(paths.checkpoints).load_latest().update_count == 6


def test_a_learner_that_diverged_resumes_at_half_the_rate_and_ends_the_streak_past_it(tmp_path: Path, monkeypatch,
                                                                                      capsys):
    # The learner service's start and checkpoints take part in the run's divergence record as the trainer's do:
    # compose restarts a diverged learner with its preset (COGEXPLORE_PRESET) at once.
    from services.cli import main

    paths = RunPaths(tmp_path / "run").make()
    _run_with_transitions(paths, load_preset("smoke"))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    base = ["learner", "--run", "run", "--runs-dir", str(tmp_path), "--preset", "smoke", "--connect", endpoint,
            "--set", "train.checkpoint_every=2", "--set", "train.total_updates=6"]
    rate = load_preset("smoke").dqn.lr
    with open_router([endpoint]):
        with monkeypatch.context() as patch:
            diverge_at(patch, 3)
            assert main(base) == 2
        assert f"its next start resumes at dqn.lr={rate / 2:g} (diverged.json)" in capsys.readouterr().err
        assert main(base) == 0
    err = capsys.readouterr().err
    assert f"at half that rate, dqn.lr={rate / 2:g} (divergence 1 in a row" in err
    assert load_preset(paths.config, complete=True).dqn.lr == rate / 2
    assert not (paths.root / "diverged.json").exists()  # checkpoints at 4 and 6: past update 3
    assert CheckpointManager(paths.checkpoints).load_latest().update_count == 6
