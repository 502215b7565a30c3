"""Zenoh plumbing on loopback: a real router, real client sessions, no mocks."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from services.bench import transport as bench
from services.bus import DEFAULT_CONNECT
from services.bus.session import (
    LinkWatch,
    LivelinessWatch,
    TransportConfigError,
    TransportError,
    ZenohSettings,
    declare_alive,
    declare_reliable_publisher,
    free_tcp_port,
    open_router,
    open_service_session,
    open_session,
    port_taken,
    put_reliable,
    query_latest,
    serve_latest,
    subscribe_messages,
)
from services.router.options import READY_LINE
from services.router.service import main as router_main
from shared.wire.keys import RunKeys
from shared.wire.messages import (
    GARBAGE,
    RejectCounter,
    TransitionBatch,
    WeightsMessage,
    shape_fingerprint,
)

REPO = Path(__file__).resolve().parents[3]
KEYS = RunKeys("test-transport")


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        yield endpoint


def client(endpoint: str) -> zenoh.Session:
    return open_session(ZenohSettings(mode="client", connect=(endpoint,)))


def small_batch(episode: int) -> TransitionBatch:
    rng = np.random.default_rng(episode)
    frames = rng.integers(0, 4000, size=(3, 12, 16), dtype=np.uint16)
    return TransitionBatch(actor_id="a0", episode=episode, first_step=0, start_index=1, actor_epoch=0,
                           depth_mm=frames[:2], next_depth_mm=frames[2],
                           action=np.array([0, 4], np.uint8), reward=np.ones(2, np.float32),
                           policy_version=np.array([1, 1], np.int64),
                           pose=np.zeros((2, 3), np.float32), truncated=True)


def weights(version: int) -> WeightsMessage:
    tensors = {"w": np.full((4, 4), float(version), dtype=np.float32)}
    return WeightsMessage(policy_version=version,
                          architecture_fingerprint=shape_fingerprint({"w": (4, 4)}),
                          tensors=tensors)


def wait_until(predicate, timeout_s: float = 5.0) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def subscribed(session: zenoh.Session, key_expr: str):  # type: ignore[no-untyped-def]
    """A predicate: some subscriber on ``key_expr`` is known to ``session`` (a put from it now reaches it)."""
    probe = session.declare_publisher(key_expr)
    return lambda: probe.matching_status.matching


# --- settings ---------------------------------------------------------------------------------

def test_settings_from_env() -> None:
    env = {"COGEXPLORE_ZENOH_MODE": "peer",
           "COGEXPLORE_ZENOH_CONNECT": "tcp/10.0.0.5:7447, tcp/10.0.0.6:7447",
           "COGEXPLORE_ZENOH_LISTEN": "tcp/0.0.0.0:7448",
           "COGEXPLORE_ZENOH_CONFIG": ""}
    settings = ZenohSettings.from_env(env)
    assert settings == ZenohSettings(mode="peer", connect=("tcp/10.0.0.5:7447", "tcp/10.0.0.6:7447"),
                                     listen=("tcp/0.0.0.0:7448",))
    assert ZenohSettings.from_env({}) == ZenohSettings()
    assert ZenohSettings.from_env({}, mode="router").mode == "router"
    config = settings.to_config()
    assert json.loads(config.get_json("mode")) == "peer"
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/10.0.0.5:7447", "tcp/10.0.0.6:7447"]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    default = ZenohSettings().to_config()
    assert json.loads(default.get_json("mode")) == "client"
    assert json.loads(default.get_json("connect/endpoints")) == list(DEFAULT_CONNECT)


def test_bad_settings_are_refused() -> None:
    with pytest.raises(TransportConfigError, match="mode 'server'"):
        ZenohSettings(mode="server")
    with pytest.raises(TransportConfigError, match="'127.0.0.1:7447' is invalid"):
        ZenohSettings.from_env({"COGEXPLORE_ZENOH_CONNECT": "127.0.0.1:7447"})
    with pytest.raises(TransportConfigError, match="does not exist"):
        ZenohSettings(config_file="/nonexistent/zenoh.json5").to_config()
    # a folder, or an empty name (Path("") is the working folder), was said not to exist
    with pytest.raises(TransportConfigError, match="^Zenoh config file /tmp is not a file$"):
        ZenohSettings(config_file="/tmp").to_config()
    with pytest.raises(TransportConfigError, match="^Zenoh config file '' does not exist$"):
        ZenohSettings(config_file="").to_config()


def test_config_file_is_the_base_and_fields_override_it(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "peer", // a JSON5 comment\n  listen: { endpoints: ["tcp/127.0.0.1:0"] } }')
    from_file = ZenohSettings(config_file=str(path))
    assert from_file.effective_mode == "peer"
    assert json.loads(from_file.to_config().get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    overridden = ZenohSettings(config_file=str(path), mode="client", connect=("tcp/127.0.0.1:9",))
    assert json.loads(overridden.to_config().get_json("mode")) == "client"
    # a file that names no mode (TLS settings only, say) is a client, as effective_mode says: Zenoh's
    # default, peer, opened without a router and listened on every interface
    no_mode = tmp_path / "no-mode.json5"
    no_mode.write_text("{ transport: {} }")
    settings = ZenohSettings(config_file=str(no_mode), connect=(f"tcp/127.0.0.1:{free_tcp_port()}",))
    assert settings.effective_mode == "client" == json.loads(settings.to_config().get_json("mode"))
    with pytest.raises(TransportError, match="cannot open a Zenoh session"):
        open_session(settings)
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(TransportConfigError, match="invalid"):
        ZenohSettings(config_file=str(bad)).to_config()


def test_a_service_finds_its_runs_credentials_unless_told_others(tmp_path: Path, monkeypatch, caplog) -> None:
    import argparse

    from services.actor.options import add_actor_arguments
    from services.bus.security import init_secure
    from services.bus.session import zenoh_settings

    parser = argparse.ArgumentParser()
    add_actor_arguments(parser)
    monkeypatch.delenv("COGEXPLORE_ZENOH_CONFIG", raising=False)
    argv = ["--connect", "tcp/127.0.0.1:9", "--run", "r1", "--runs-dir", str(tmp_path)]
    assert zenoh_settings(parser.parse_args(argv), "actor").config_file is None  # no folder: none
    files = init_secure(tmp_path / "r1" / "secure", "r1")
    with caplog.at_level("INFO", logger="services.bus.session"):
        found = zenoh_settings(parser.parse_args(argv), "actor")
    assert found.config_file == str(files.config("actor")) and found.connect == ("tcp/127.0.0.1:9",)
    assert str(files.config("actor")) in caplog.text  # the log names the file
    assert zenoh_settings(parser.parse_args(argv), "evaluator").config_file == str(files.config("evaluator"))
    # without --connect, the run's credentials go to the default router as a run without them does (they
    # name no router: the client had none to connect to, "No peer specified and multicast scouting deactivated")
    bare = zenoh_settings(parser.parse_args(argv[2:]), "actor")
    assert bare.config_file == str(files.config("actor")) and bare.effective_connect == DEFAULT_CONNECT
    assert json.loads(bare.to_config().get_json("connect/endpoints")) == list(DEFAULT_CONNECT)
    assert zenoh_settings(parser.parse_args(argv)).config_file is None  # no role, no search
    other = tmp_path / "other.json5"
    other.write_text("{}")  # a file that is not there is refused where the settings are made
    assert zenoh_settings(parser.parse_args([*argv, "--zenoh-config", str(other)]), "actor").config_file == str(other)
    monkeypatch.setenv("COGEXPLORE_ZENOH_CONFIG", str(other))
    assert zenoh_settings(parser.parse_args(argv), "actor").config_file == str(other)


def test_an_option_on_the_command_line_wins_over_its_environment_variable(monkeypatch) -> None:
    import argparse

    from services.actor.options import add_actor_arguments
    from services.bus.options import add_ros2_arguments
    from services.bus.ros2 import ros2_settings
    from services.bus.session import zenoh_settings

    # what docker-compose.yml sets in every container; a user's `--connect` must still be obeyed
    monkeypatch.setenv("COGEXPLORE_ZENOH_CONNECT", "tcp/10.9.9.9:7447")
    monkeypatch.setenv("COGEXPLORE_ZENOH_MODE", "peer")
    monkeypatch.setenv("COGEXPLORE_ZENOH_ROUTER_WAIT_S", "5")
    monkeypatch.delenv("COGEXPLORE_ZENOH_CONFIG", raising=False)
    service, ros2 = argparse.ArgumentParser(), argparse.ArgumentParser()
    add_actor_arguments(service)
    add_ros2_arguments(ros2)
    for parser, settings_of in ((service, zenoh_settings), (ros2, ros2_settings)):
        from_env = settings_of(parser.parse_args([]))
        assert from_env.connect == ("tcp/10.9.9.9:7447",) and from_env.mode == "peer"
        assert from_env.router_wait_s == 5.0
        given = settings_of(parser.parse_args(["--connect", "tcp/192.168.1.10:7447", "--router-wait", "0.5"]))
        assert given.connect == ("tcp/192.168.1.10:7447",) and given.router_wait_s == 0.5
    assert zenoh_settings(service.parse_args(["--zenoh-mode", "client"])).mode == "client"
    monkeypatch.delenv("COGEXPLORE_ZENOH_MODE")
    assert ros2_settings(ros2.parse_args([])).mode == "client"  # the robot's router: a client by default


@pytest.mark.parametrize("value", ["nan", "-1", "inf", "soon"])
def test_a_router_wait_that_is_not_a_time_is_refused(value: str, monkeypatch, capsys) -> None:
    import argparse

    from services.options import add_service_arguments

    parser = argparse.ArgumentParser(prog="cogexplore actor")
    add_service_arguments(parser)
    with pytest.raises(SystemExit) as exit_info:
        parser.parse_args(["--router-wait", value])
    assert exit_info.value.code == 2 and "argument --router-wait: " in capsys.readouterr().err
    monkeypatch.setenv("COGEXPLORE_ZENOH_ROUTER_WAIT_S", value)  # a NaN would never stop waiting
    with pytest.raises(TransportConfigError, match="COGEXPLORE_ZENOH_ROUTER_WAIT_S"):
        ZenohSettings.from_env()


def test_a_service_waits_for_its_router_as_long_as_it_is_told() -> None:
    from services.bus.session import open_service_session

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    assert ZenohSettings().router_wait_s == 30.0  # started beside its router, a service gives it time
    started = time.monotonic()
    with pytest.raises(TransportError, match="cannot open a Zenoh session"):
        open_service_session(ZenohSettings(connect=(endpoint,), router_wait_s=1.0))
    assert 1.0 <= time.monotonic() - started < 15.0  # the 30 s default would not end here


def test_a_service_asked_to_stop_while_it_waits_for_its_router_stops_at_once() -> None:
    # SIGTERM set the stop event, but the wait went on for --router-wait (30 s), then failed.
    from services.bus.session import StoppedWaiting, open_service_session

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    stop = threading.Event()
    threading.Timer(0.5, stop.set).start()
    started = time.monotonic()
    with pytest.raises(StoppedWaiting, match="stopped while waiting for the router"):
        open_service_session(ZenohSettings(connect=(endpoint,), router_wait_s=60.0), stop)
    assert time.monotonic() - started < 10.0


def test_client_without_router_fails_clearly_and_can_wait_for_one() -> None:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    settings = ZenohSettings(mode="client", connect=(endpoint,))
    with pytest.raises(TransportError, match=endpoint.split("/")[1]):
        open_session(settings)
    # a router that appears while the client waits is found
    routers: list[zenoh.Session] = []
    starter = threading.Timer(0.3, lambda: routers.append(open_router([endpoint])))
    starter.start()
    try:
        with open_session(settings, wait_s=10.0) as session:
            assert not session.is_closed()
    finally:
        starter.join()
        for r in routers:
            r.close()


def test_a_second_session_always_opens_under_an_id_of_its_own() -> None:
    # A random id written with a leading 0 (token_hex: one time in 16) is not one Zenoh takes: the
    # learner's weights link failed to open, at once where it had no wait for its router.
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    second = ZenohSettings(mode="client", connect=(endpoint,)).second_link()
    ids = [json.loads(second.to_config().get_json("id")) for _ in range(200)]
    assert len(set(ids)) == 200 and all(len(i) == 32 and i[0] != "0" for i in ids)
    with open_router([endpoint]):
        for _ in range(3):
            with open_session(second) as session:
                assert not session.is_closed()
    # with no router there, the error is the absent router's, not a refusal's
    with pytest.raises(TransportError) as info:
        open_session(second)
    assert "takes connections" not in str(info.value)


def test_a_wait_for_a_router_ends_at_once_when_told_why() -> None:
    """``give_up``: `up` asks whether its router process has exited after each failed try."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    asked: list[float] = []

    def give_up() -> str | None:
        asked.append(time.monotonic())
        return "its router exited (1): Address already in use" if len(asked) >= 3 else None

    started = time.monotonic()
    with pytest.raises(TransportError, match=r"cannot open a Zenoh session .*: its router exited \(1\)"):
        open_session(ZenohSettings(mode="client", connect=(endpoint,)), wait_s=30.0, give_up=give_up)
    assert len(asked) == 3 and time.monotonic() - started < 15.0


def test_a_port_another_socket_holds_is_named_before_a_router_tries_it() -> None:
    import socket

    with socket.socket() as listening, socket.socket() as bound:
        listening.bind(("127.0.0.1", 0))
        listening.listen()
        bound.bind(("127.0.0.1", 0))
        for sock in (listening, bound):
            port = sock.getsockname()[1]
            for endpoint in (f"tcp/127.0.0.1:{port}", f"tls/127.0.0.1:{port}", f"tcp/0.0.0.0:{port}"):
                assert f"port {port} of" in port_taken(endpoint) and "in use" in port_taken(endpoint), endpoint
            # a listener bound to one device may share the port: the router decides
            assert port_taken(f"tcp/127.0.0.1:{port}#iface=lo") is None
        port = listening.getsockname()[1]
    assert port_taken(f"tcp/127.0.0.1:{port}") is None  # closed: free again, TIME_WAIT or not
    for endpoint in (f"udp/127.0.0.1:{port}", "tcp/no-such-host.invalid:7447", "tcp/127.0.0.1:\u00b2"):
        assert port_taken(endpoint) is None, endpoint  # not for this check: the router says what is wrong


# --- data through a router ---------------------------------------------------------------------

def test_transition_batches_cross_the_router_with_block(router: str) -> None:
    received: list[tuple[TransitionBatch, str]] = []
    rejects = RejectCounter("transition batch")
    with client(router) as learner, client(router) as actor:
        subscribe_messages(learner, KEYS.all_transitions, TransitionBatch,
                           lambda msg, key: received.append((msg, key)), rejects)
        publisher = declare_reliable_publisher(actor, KEYS.transitions("a0"))
        assert publisher.congestion_control == zenoh.CongestionControl.BLOCK
        assert wait_until(lambda: publisher.matching_status.matching)
        sent = [small_batch(e) for e in range(20)]
        publisher.put(b"\xc1 not a message")  # rejected and counted; the stream carries on
        for batch in sent:
            publisher.put(batch.encode())
        assert wait_until(lambda: len(received) == len(sent))
    assert [msg.episode for msg, _ in received] == list(range(20))  # all, in order
    first, key = received[0]
    assert key == KEYS.transitions("a0")
    assert np.array_equal(first.depth_mm, sent[0].depth_mm) and first.truncated
    assert rejects.counts == {GARBAGE: 1}


def test_get_on_the_weights_queryable_returns_the_latest(router: str) -> None:
    latest: dict[str, bytes] = {}
    with client(router) as learner, client(router) as actor:
        queryable = serve_latest(learner, KEYS.weights_latest, lambda: latest.get("w"))
        assert query_latest(actor, KEYS.weights_latest, timeout_s=1.0) is None  # nothing yet
        latest["w"] = weights(1).encode()
        latest["w"] = weights(2).encode()
        payload = query_latest(actor, KEYS.weights_latest, timeout_s=5.0)
        assert payload is not None
        got = WeightsMessage.decode(payload)
        assert got.policy_version == 2 and float(got.tensors["w"][0, 0]) == 2.0
        # the weights stream is a separate key: a put there reaches stream subscribers only
        stream: list[int] = []
        subscribe_messages(actor, KEYS.weights, WeightsMessage,
                           lambda msg, _key: stream.append(msg.policy_version), RejectCounter())
        assert wait_until(subscribed(learner, KEYS.weights), 30.0), "the subscription never reached the router"
        put_reliable(learner, KEYS.weights, weights(3).encode())
        assert wait_until(lambda: stream == [3])
        queryable.undeclare()


def test_liveliness_token_seen_and_its_loss_seen(router: str) -> None:
    changes: list[tuple[str, bool]] = []
    with client(router) as watcher_session:
        with LivelinessWatch(watcher_session, KEYS.all_alive("actor"),
                             lambda key, alive: changes.append((key, alive))) as watch:
            key = KEYS.alive("actor", "a0")
            actor = client(router)
            token = declare_alive(actor, key)  # noqa: F841 - a dropped token is undeclared
            assert watch.wait(lambda keys: key in keys, 5.0)
            actor.close()  # the token dies with its session
            assert watch.wait(lambda keys: key not in keys, 5.0)
    assert changes == [(key, True), (key, False)]


def test_liveliness_history_reports_tokens_declared_before_the_watch(router: str) -> None:
    with client(router) as learner, client(router) as actor:
        token = declare_alive(learner, KEYS.alive("learner", "l0"))
        time.sleep(0.1)
        with LivelinessWatch(actor, KEYS.all_alive("learner")) as watch:
            assert watch.wait(lambda keys: KEYS.alive("learner", "l0") in keys, 5.0)
            token.undeclare()
            assert watch.wait(lambda keys: not keys, 5.0)


def test_a_receiver_stalled_past_wait_before_close_loses_its_link_says_so_and_comes_back(tmp_path: Path,
                                                                                          caplog) -> None:
    # Zenoh closes a link on which a BLOCK message waited past wait_before_close (5 s by default,
    # 0.3 s here): what was in flight is lost. The stalled service's session says so, and reconnects.
    config = tmp_path / "router.json5"
    config.write_text(json.dumps({"transport": {"link": {"tx": {"queue": {"congestion_control": {
        "block": {"wait_before_close": 300_000}}}}}}}))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    settings = ZenohSettings(mode="client", connect=(endpoint,))
    received: list[int] = []

    def stall_on_the_first(sample: zenoh.Sample) -> None:
        received.append(len(sample.payload))
        if len(received) == 1:
            time.sleep(1.5)  # holds Zenoh's receiving thread: the router's queue to this session fills

    caplog.set_level("INFO", logger="services.bus.session")
    with open_router([endpoint], config_file=str(config)) as router:
        links = LinkWatch(router, routine=True)
        with open_service_session(settings) as receiver, open_session(settings) as sender:
            receiver.declare_subscriber(KEYS.weights, stall_on_the_first)
            publisher = declare_reliable_publisher(sender, KEYS.weights)
            assert wait_until(lambda: publisher.matching_status.matching, 30.0)
            sent, started = 0, time.monotonic()
            # until the buffers between them are full (tens of MB on loopback) and the router gives up
            while links.closed == 0 and time.monotonic() - started < 1.2:
                publisher.put(b"x" * 200_000)
                sent += 1
            assert wait_until(lambda: "linked to zenoh router" in caplog.text, 30.0), caplog.text
            assert [r.levelname for r in caplog.records if "lost the link to zenoh router" in r.message] == ["WARNING"]
            assert links.closed >= 1 and len(received) < sent  # the router's side: that client left
            assert wait_until(lambda: publisher.matching_status.matching, 30.0)
            before = len(received)
            publisher.put(b"back")
            assert wait_until(lambda: len(received) == before + 1 and received[-1] == 4, 10.0)


# --- the router process ---------------------------------------------------------------------

def test_router_help_exits_cleanly(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        router_main(["--help"])
    assert info.value.code == 0
    assert "--listen" in capsys.readouterr().out


def test_router_process_serves_clients_and_stops_on_sigterm() -> None:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    env = dict(os.environ, PYTHONPATH=str(REPO), RERUN_ANALYTICS="0")
    proc = subprocess.Popen([sys.executable, "-m", "services.router", "--listen", endpoint,
                             "--log-level", "WARNING"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        assert READY_LINE in line, proc.stderr.read() if proc.poll() is not None else line  # type: ignore[union-attr]
        got: list[bytes] = []
        with client(endpoint) as a, client(endpoint) as b:
            a.declare_subscriber(KEYS.weights, lambda s: got.append(s.payload.to_bytes()))
            assert wait_until(subscribed(b, KEYS.weights), 30.0), "the subscription never reached the router"
            put_reliable(b, KEYS.weights, b"ping")
            assert wait_until(lambda: got == [b"ping"])
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()  # type: ignore[union-attr]
        proc.stderr.close()  # type: ignore[union-attr]


def test_router_refuses_a_bad_endpoint(capsys: pytest.CaptureFixture[str]) -> None:
    assert router_main(["--listen", "7447"]) == 2
    assert "invalid" in capsys.readouterr().err


# --- benchmark smoke test -------------------------------------------------------------------

def test_transport_benchmark_runs_and_loses_nothing() -> None:
    result = bench.run(seconds=0.3, batch_steps=4, height=24, width=32, processes=False)
    assert result["bytes_per_transition"] > 24 * 32 * 2
    assert result["codec"]["transitions_per_s"] > 0
    loop = result["loopback"]
    assert loop["batches_sent"] > 0 and loop["lost"] == 0 and loop["rejected"] == 0
    assert loop["links_closed"] == 0 and 0 <= loop["max_gap_s"] < 5 and 0 < loop["max_put_s"] < 5
    assert loop["transitions_per_s"] > 0


@pytest.mark.parametrize("service", ["learner", "evaluator"])
def test_a_service_stopped_before_its_router_answers_ends_at_once_and_cleanly(tmp_path: Path, service: str) -> None:
    # It waited out --router-wait (30 s), then exited 2 "cannot open a Zenoh session" (the
    # evaluator: 1, with an error).
    from service_processes import cogexplore, wait_for

    log = tmp_path / f"{service}.log"
    proc = cogexplore([service, "--run", "r", "--runs-dir", str(tmp_path), "--preset", "smoke", "--connect",
                       f"tcp/127.0.0.1:{free_tcp_port()}", "--zenoh-mode", "client", "--router-wait", "120"], log)
    try:
        wait_for(lambda: b"via mode=client" in log.read_bytes(), 60, f"the {service} waiting for its router", [log])
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=15) == 0
        assert "stopped while waiting for the router" in log.read_text() and "error" not in log.read_text().lower()
    finally:
        if proc.poll() is None:
            proc.kill()
