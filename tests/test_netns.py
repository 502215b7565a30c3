"""Actors on other machines: the router and learner in one Linux network namespace, an actor
in another, joined only by a veth pair (10.200.<x>.0/30). The actor reaches the router over
the veth address, its transitions reach the learner, and it acts with the learner's weights.

Needs root and iproute2's ``ip netns``; otherwise skipped with the reason. Every namespace,
link and process it makes is removed in ``finally``, also on failure.

This file is also the monitor that runs inside the learner's namespace:
``python tests/test_netns.py monitor --endpoint E --run R --actor A --timeout-s T``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PORT = 7447  # free by construction: the router's namespace is new


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run(["ip", *args], check=False, capture_output=True, text=True, timeout=30)
    if check and result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)} failed ({result.returncode}): {result.stderr.strip()}")
    return result


def _skip_reason() -> str | None:
    if not sys.platform.startswith("linux"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    if shutil.which("ip") is None:
        return "iproute2 ('ip') is not installed"
    probe = subprocess.run(["ip", "netns", "list"], check=False, capture_output=True, text=True)
    if probe.returncode != 0:
        return f"'ip netns' is not available: {probe.stderr.strip()}"
    return None


@contextlib.contextmanager
def veth_namespaces(tag: str, subnet: int) -> Iterator[tuple[str, str, str, str]]:
    """Two new namespaces joined by a veth pair: yields (ns1, ns2, addr1, addr2).

    The /30 holds exactly the two ends, so no other address can be a target.
    """
    ns1, ns2 = f"cgx{tag}a", f"cgx{tag}b"
    veth1, veth2 = f"cgx{tag}v1", f"cgx{tag}v2"  # interface names: at most 15 characters
    addr1, addr2 = f"10.200.{subnet}.1", f"10.200.{subnet}.2"
    made: list[str] = []
    try:
        for ns in (ns1, ns2):
            result = _ip("netns", "add", ns, check=False)
            if result.returncode != 0:
                pytest.skip(f"cannot create a network namespace: {result.stderr.strip()}")
            made.append(ns)
        _ip("link", "add", veth1, "type", "veth", "peer", "name", veth2)
        _ip("link", "set", veth1, "netns", ns1)
        _ip("link", "set", veth2, "netns", ns2)
        for ns, dev, addr in ((ns1, veth1, addr1), (ns2, veth2, addr2)):
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "addr", "add", f"{addr}/30", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
        yield ns1, ns2, addr1, addr2
    finally:
        _ip("link", "del", veth1, check=False)  # only if it never moved (deleting a netns removes it)
        for ns in made:
            _ip("netns", "del", ns, check=False)


def _spawn(ns: str, argv: list[str], log: Path) -> subprocess.Popen:
    # `ip netns exec` execs the command, so the Popen pid is the Python process itself.
    env = dict(os.environ, RERUN_ANALYTICS="0", PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    with open(log, "wb") as fh:
        return subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, *argv], cwd=REPO, env=env,
                                stdout=fh, stderr=subprocess.STDOUT)


def _stop(procs: dict[str, subprocess.Popen]) -> None:
    for p in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs.values():
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@pytest.mark.timeout(300)
def test_actor_in_another_namespace_over_veth(tmp_path: Path) -> None:
    reason = _skip_reason()
    if reason is not None:
        print(f"test_netns skipped: {reason}")
        pytest.skip(reason)
    pid = os.getpid()
    run, actor = f"netns{pid}", "actor-ns2"
    with veth_namespaces(str(pid % 10_000_000), pid % 250 + 1) as (ns1, ns2, addr1, _addr2):
        # The actor's namespace has loopback and the veth end and nothing else, and its route
        # to the router leaves by the veth.
        listing = _ip("-n", ns2, "-o", "link", "show").stdout.splitlines()
        links = {line.split(":")[1].strip().split("@")[0] for line in listing}
        veth2 = f"cgx{pid % 10_000_000}v2"
        assert links == {"lo", veth2}, links
        assert f"dev {veth2}" in _ip("-n", ns2, "route", "get", addr1).stdout

        endpoint = f"tcp/{addr1}:{PORT}"
        common = ["--run", run, "--runs-dir", str(tmp_path), "--connect", endpoint, "--zenoh-mode", "client",
                  "--preset", "smoke", "--set", "train.total_updates=100000",
                  "--set", "train.checkpoint_every=100000",
                  # Actors rarely wait on flow control at this ratio: weights reach them sooner.
                  "--set", "train.replay_ratio=0.25"]
        cli = ["-m", "services.cli"]
        procs: dict[str, subprocess.Popen] = {}
        try:
            procs["router"] = _spawn(ns1, [*cli, "router", "--listen", endpoint], tmp_path / "router.log")
            procs["learner"] = _spawn(ns1, [*cli, "learner", *common, "--weights-every", "5"],
                                      tmp_path / "learner.log")
            procs["actor"] = _spawn(ns2, [*cli, "actor", *common, "--actor-id", actor], tmp_path / "actor.log")
            monitor = subprocess.run(
                ["ip", "netns", "exec", ns1, sys.executable, str(Path(__file__).resolve()), "monitor",
                 "--endpoint", endpoint, "--run", run, "--actor", actor, "--timeout-s", "180"],
                check=False, cwd=REPO, env=dict(os.environ, RERUN_ANALYTICS="0"), capture_output=True, text=True,
                timeout=240)
            assert monitor.returncode == 0, f"monitor failed:\n{monitor.stdout}\n{monitor.stderr[-3000:]}"
            seen = json.loads(monitor.stdout.strip().splitlines()[-1])
            assert seen["received"] > 0, seen  # the learner's replay got the actor's transitions
            assert seen["max_policy_version"] > 0, seen  # chosen with weights that came over the veth
            assert all(p.poll() is None for p in procs.values()), "every process is still running"
            procs["learner"].send_signal(signal.SIGTERM)
            assert procs["learner"].wait(60) == 0
            # The learner's own record agrees (the run folder is shared, only the network is not).
            rows = (tmp_path / run / "stats" / "learner.csv").read_text().splitlines()
            header, last = rows[0].split(","), rows[-1].split(",")
            assert int(last[header.index("transitions")]) > 0
        finally:
            _stop(procs)
            for log in sorted(tmp_path.glob("*.log")):
                sys.stdout.write(f"--- {log.name}\n{log.read_text()[-2000:]}\n")


# -- the monitor, run inside the learner's namespace ---------------------------------------------

def monitor(endpoint: str, run: str, actor: str, timeout_s: float) -> int:
    """Watch until the learner reports transitions from ``actor`` and the actor's transitions
    carry a weights version > 0; print one JSON line of what was seen. Exit 0 when both."""
    from services.bus.session import ZenohSettings, open_session, subscribe_messages
    from shared.wire.keys import RunKeys
    from shared.wire.messages import LearnerStats, RejectCounter, TransitionBatch

    keys = RunKeys(run)
    lock = threading.Lock()
    seen = {"received": 0.0, "max_policy_version": 0, "batches": 0, "updates": 0}

    def on_stats(stats: LearnerStats, _key: str) -> None:
        with lock:
            seen["received"] = stats.extra.get(f"received.{actor}", 0.0)
            seen["updates"] = stats.updates

    def on_batch(batch: TransitionBatch, _key: str) -> None:
        if batch.actor_id == actor:
            with lock:
                seen["batches"] += 1
                seen["max_policy_version"] = max(seen["max_policy_version"], int(batch.policy_version.max()))

    rejects = RejectCounter("monitor")
    ok = False
    with open_session(ZenohSettings(mode="client", connect=(endpoint,)), wait_s=60.0) as session:
        subs = [subscribe_messages(session, keys.all_stats("learner"), LearnerStats, on_stats, rejects),
                subscribe_messages(session, keys.all_transitions, TransitionBatch, on_batch, rejects)]
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with lock:
                if seen["received"] > 0 and seen["max_policy_version"] > 0:
                    ok = True
                    break
            time.sleep(0.2)
        for sub in subs:
            sub.undeclare()
    with lock:
        print(json.dumps(seen), flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    parser = argparse.ArgumentParser(description="netns test monitor")
    parser.add_argument("command", choices=["monitor"])
    parser.add_argument("--endpoint", required=True)
    parser.add_argument("--run", required=True)
    parser.add_argument("--actor", required=True)
    parser.add_argument("--timeout-s", type=float, default=180.0)
    a = parser.parse_args()
    sys.exit(monitor(a.endpoint, a.run, a.actor, a.timeout_s))
