"""The run's configuration over a real loopback router: taken from the learner without --preset,
checked against it with one; and one default preset for ``up`` and the services."""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.actor.options import add_actor_arguments
from services.bus.run_config import RunConfigCheck, ask_run_config, config_rejects, fetch_run_config, join_run_config
from services.bus.session import (
    TransportError,
    ZenohSettings,
    free_tcp_port,
    open_router,
    open_session,
    query_replies,
    serve_latest,
)
from services.evaluator.options import add_evaluator_arguments
from services.learner.options import add_learner_arguments
from services.runs import RunPaths, resolve_config
from services.up.options import add_up_arguments
from shared.config import DEFAULT_PRESET, ConfigMismatchError, load_preset
from shared.wire.keys import RunKeys
from shared.wire.messages import RunConfigMessage

RUN = "cfg"
KEYS = RunKeys(RUN)


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        yield endpoint


@pytest.fixture
def learner(router: str) -> Iterator[None]:
    """A session answering the config query as the learner does (the smoke preset)."""
    payload = RunConfigMessage(learner_id="learner", config=load_preset("smoke")).encode()
    with open_session(ZenohSettings(connect=(router,))) as session:
        queryable = serve_latest(session, KEYS.config, lambda: payload)  # noqa: F841
        time.sleep(0.2)  # the queryable reaches the router
        yield


def wait_for_answers(session, count: int, timeout_s: float = 30.0) -> None:  # type: ignore[no-untyped-def]
    """Until a get on the config key has ``count`` answers (every queryable has reached the router)."""
    deadline = time.monotonic() + timeout_s
    while True:
        oversize: list[int] = []
        got = len(list(query_replies(session, KEYS.config, RunConfigMessage.MAX_BYTES, timeout_s=5.0,
                                     oversize=oversize.append))) + len(oversize)
        if got >= count:
            return
        assert time.monotonic() < deadline, f"{got} of {count} answers on {KEYS.config}"
        time.sleep(0.05)


def parse(add, argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add(parser)
    return parser.parse_args(argv)


def actor_args(router: str, tmp_path: Path, *extra: str) -> argparse.Namespace:
    return parse(add_actor_arguments, ["--connect", router, "--run", RUN, "--runs-dir", str(tmp_path), *extra])


def test_without_a_preset_an_actor_takes_the_learners_with_its_set_over_it(router: str, learner: None,
                                                                           tmp_path: Path) -> None:
    settings = ZenohSettings(connect=(router,))
    args = actor_args(router, tmp_path, "--set", "env.world=procedural:7", "--set", "explore.eps_end=0.2")
    cfg, check = join_run_config(args, RunPaths(tmp_path / RUN), settings, "this actor")
    assert check is None
    assert cfg == load_preset("smoke").with_overrides({"env.world": "procedural:7", "explore.eps_end": 0.2})
    # a --set the run's data depends on is refused at once, naming what to drop
    args = actor_args(router, tmp_path, "--set", "sensor.width=64")
    with pytest.raises(ConfigMismatchError, match=r"^this actor's sensor.width=64 differs from the run's 40 "
                                                  r"\(learner 'learner' of run 'cfg'\); .*drop its --set"):
        join_run_config(args, RunPaths(tmp_path / RUN), settings, "this actor")


def test_without_a_learner_the_wait_is_bounded(router: str) -> None:
    started = time.monotonic()
    with pytest.raises(TransportError, match="no learner of run 'cfg' answered cogexplore/cfg/config within 1 s"):
        fetch_run_config(ZenohSettings(connect=(router,)), KEYS, wait_s=1.0)
    assert time.monotonic() - started < 5.0


def test_a_named_preset_is_checked_once_a_learner_answers(router: str, tmp_path: Path, caplog) -> None:
    settings = ZenohSettings(connect=(router,))
    cfg, check = join_run_config(actor_args(router, tmp_path, "--preset", "paper"), RunPaths(tmp_path / RUN), settings,
                                 "this actor")
    assert cfg == load_preset("paper") and check is not None
    stop = threading.Event()
    check.start(settings, stop)
    assert not stop.wait(1.0)  # no learner yet: the process goes on
    payload = RunConfigMessage(learner_id="learner", config=load_preset("smoke")).encode()
    with open_session(settings) as session:
        queryable = serve_latest(session, KEYS.config, lambda: payload)  # noqa: F841
        assert stop.wait(10.0), "a learner of another configuration stops the process"
    error = check.finish()
    assert isinstance(error, ConfigMismatchError)
    assert str(error).startswith("this actor's sensor.width=160 differs from the run's 40 (learner 'learner' of "
                                 "run 'cfg'; also differ: sensor.height, model.fc1")
    # the same preset as the learner's passes, and the process is not stopped
    same = RunConfigCheck(KEYS, load_preset("smoke").with_overrides({"env.world": "corridor"}), "this actor")
    stop = threading.Event()
    with open_session(settings) as session, caplog.at_level(logging.INFO, logger="cogexplore.config"):
        queryable = serve_latest(session, KEYS.config, lambda: payload)  # noqa: F841
        same.start(settings, stop)
        deadline = time.monotonic() + 60  # the check has had the learner's answer and found it the same
        while "the configuration matches the run's (learner 'learner' of run 'cfg')" not in caplog.text:
            assert time.monotonic() < deadline and not stop.is_set(), caplog.text
            time.sleep(0.05)
        assert same.finish() is None and not stop.is_set()


def test_finishing_a_check_that_waits_for_its_router_ends_the_wait() -> None:
    # finish() waited 5 s and left the check retrying zenoh.open for the rest of --router-wait, into
    # the interpreter's exit
    settings = ZenohSettings(connect=(f"tcp/127.0.0.1:{free_tcp_port()}",), router_wait_s=60.0)
    check = RunConfigCheck(KEYS, load_preset("smoke"), "this actor")
    stop = threading.Event()
    check.start(settings, stop)
    time.sleep(0.5)  # it is waiting for the router
    started = time.monotonic()
    assert check.finish() is None
    assert time.monotonic() - started < 3.0 and check._thread is not None and not check._thread.is_alive()
    assert not stop.is_set()


def test_an_answer_beside_the_learners_neither_stops_a_process_nor_is_taken_on_trust(router: str) -> None:
    # The first reply was taken: garbage from anyone stopped every new actor ("a configuration this
    # build cannot read"), and a readable config from anyone was taken when it came first.
    from shared.config import ConfigError

    settings = ZenohSettings(connect=(router,))
    real = RunConfigMessage(learner_id="learner", config=load_preset("smoke")).encode()
    forged = RunConfigMessage(learner_id="learner", config=load_preset("smoke").with_overrides(
        {"explore.eps_end": 1.0})).encode()
    with open_session(settings) as learner, open_session(settings) as outsider, open_session(settings) as actor:
        queryables = [serve_latest(learner, KEYS.config, lambda: real)]
        # twenty unreadable answers (the first sixteen replies were all that was read) and an oversized one
        for reply in [b"\x00garbage"] * 20 + [bytes(RunConfigMessage.MAX_BYTES + 1)]:
            queryables.append(serve_latest(outsider, KEYS.config, lambda reply=reply: reply))
        wait_for_answers(actor, len(queryables))  # the queryables reach the router
        for _ in range(3):
            assert ask_run_config(actor, KEYS).run_config == load_preset("smoke")
        queryables.append(serve_latest(outsider, KEYS.config, lambda: forged))
        wait_for_answers(actor, len(queryables))
        with pytest.raises(ConfigError, match="several answers on cogexplore/cfg/config that differ"):
            ask_run_config(actor, KEYS)
        for queryable in queryables:
            queryable.undeclare()


def test_answers_from_anyone_log_one_line_per_cause_however_often_they_come(router: str, caplog) -> None:
    # Each oversized answer logged a warning, every retry of the wait (and an unreadable one beside the
    # learner's, every ask): anyone on the router could flood the service's log.
    settings = ZenohSettings(connect=(router,))
    real = RunConfigMessage(learner_id="learner", config=load_preset("smoke")).encode()
    with open_session(settings) as outsider, open_session(settings) as actor, \
            caplog.at_level(logging.WARNING, logger="cogexplore.config"):
        queryables = [serve_latest(outsider, KEYS.config, lambda: bytes(RunConfigMessage.MAX_BYTES + 1))
                      for _ in range(3)]
        wait_for_answers(actor, len(queryables))
        with pytest.raises(TransportError, match="no learner of run 'cfg' answered"):
            fetch_run_config(settings, KEYS, wait_s=1.5)  # several retries, each with three oversized answers
        assert [r.getMessage() for r in caplog.records] == [
            "rejected config answer from cogexplore/cfg/config: oversize: a 65537-byte answer, more than a "
            "configuration takes (later 'oversize' rejects are counted, not logged)"]
        caplog.clear()
        queryables += [serve_latest(outsider, KEYS.config, lambda: real)]
        queryables += [serve_latest(outsider, KEYS.config, lambda: b"\x00garbage") for _ in range(2)]
        wait_for_answers(actor, len(queryables))
        rejects = config_rejects()
        for _ in range(3):
            assert ask_run_config(actor, KEYS, rejects=rejects).run_config == load_preset("smoke")
        assert rejects.counts == {"oversize": 9, "garbage": 6}
        assert len(caplog.records) == 2  # the first of each cause
        for queryable in queryables:
            queryable.undeclare()


def test_one_default_preset_for_up_and_the_services(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("COGEXPLORE_PRESET", "")  # what docker-compose.yml sets by default: unset
    fresh = RunPaths(tmp_path / "fresh")
    for add in (add_up_arguments, add_learner_arguments):
        args = parse(add, [])
        assert args.preset is None and resolve_config(args, fresh) == load_preset(DEFAULT_PRESET)
    for add in (add_actor_arguments, add_evaluator_arguments):  # theirs is the learner's
        assert parse(add, []).preset is None
    monkeypatch.setenv("COGEXPLORE_PRESET", "paper")
    assert parse(add_actor_arguments, []).preset == "paper"


def test_an_actors_device_is_its_own_not_its_learners(router: str, tmp_path: Path, monkeypatch) -> None:
    """`up --device cuda` saves the learner's device in the run's config, and the learner announces it:
    an actor (here, or on a machine without a GPU) still acts where it is told, else on the CPU."""
    from shared.config import to_toml

    monkeypatch.delenv("COGEXPLORE_DEVICE", raising=False)
    settings = ZenohSettings(connect=(router,))
    on_gpu = load_preset("smoke").with_overrides({"train.device": "cuda"})
    payload = RunConfigMessage(learner_id="learner", config=on_gpu).encode()
    run_file = tmp_path / "config.toml"
    run_file.write_text(to_toml(on_gpu))
    with open_session(settings) as session:
        queryable = serve_latest(session, KEYS.config, lambda: payload)  # noqa: F841
        time.sleep(0.2)
        for extra, device in (((), "auto"), (("--device", "cpu"), "cpu"), (("--set", "train.device=cpu"), "cpu"),
                              (("--preset", str(run_file)), "auto"), (("--preset", str(run_file), "--device", "cpu"), "cpu")):
            cfg, _ = join_run_config(actor_args(router, tmp_path, *extra), RunPaths(tmp_path / RUN), settings, "this actor")
            assert cfg.train.device == device, extra
            assert cfg.with_overrides({"train.device": "cuda"}) == on_gpu  # the rest is the run's
