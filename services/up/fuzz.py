"""``cogexplore bench fuzz``: malformed and hostile payloads on every key a run's services listen to.

A secured run (router, learner, one actor, evaluator; the launcher's own start-up) is fuzzed with
sessions of the roles allowed to put on each key, so that every payload reaches its receivers, who
must reject it, count it and carry on:

    key                         from      listened to by
    transitions/<id>            actor     the learner
    stats/episode/<id>          actor     this bench (a viewer, as the launcher's progress bar)
    weights, flow               learner   the actor and the evaluator (both: flow control is the learner's pulse)
    stats/learner/<id>          learner   this bench
    stats/eval/<id>             evaluator this bench
    weights/latest (queries)    actor     the learner's queryable (payloads it must ignore)

Every payload is invalid for its receivers by construction: random bytes, empty, truncated or
byte-flipped valid messages, another schema version or type, missing, unknown or mistyped fields,
arrays of the wrong dtype or shape, NaN, an unknown field of ``--max-bytes`` padding, zero-filled
payloads of ``--big-bytes`` (up to the size limit: memory), and values no run can
produce (rewards of 3.4e38, depth beyond the sensor, versions of 2^62, a learner epoch from the
future, another architecture's weights). So the rejects must add up: each receiver's count equals
what was sent to it. The services' memory (VmRSS) is read after a first fifth of the payloads,
when the allocators and queues have warmed (every kind of payload, and with ``--big-bytes`` the
big ones, have passed), and after each of four more rounds: a leak grows every round, warming
levels off. Fuzzing starts once every receiver has joined and each fuzzing publisher has seen its
receivers' subscriptions, and ends once the learner's and the actor's live statistics have counted
every payload sent to them, so a slow machine delays the counts instead of losing them. Prints JSON;
exits 1 when a service crashed while fuzzed (``crashes``) or at the stop (``failed_at_stop``: each said
in one line as ``up`` says it, ``Launcher.failed_at_stop``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import random
import re
import shutil
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable

import msgpack
import numpy as np

from shared.errors import CogexploreError

RUN_PREFIX = "bench-fuzz"
"""The start of a fuzzed run's folder name (``<prefix>-<time>-<pid>``)."""
PAYLOAD_KINDS: tuple[str, ...] = ("random", "empty", "truncated", "flipped", "schema", "type", "missing_field",
                                  "unknown_field", "field_type", "dtype", "shape", "nan", "padding", "physical")
_DONE = re.compile(r"(?:done|rejected weights): (\{.*\})\)?\s*$")


class FuzzError(CogexploreError, RuntimeError):
    """The fuzzed system could not be started or measured."""


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


class Payloads:
    """Invalid payloads of every kind for one message type, from a valid example of it."""

    def __init__(self, valid: bytes, rng: random.Random, max_bytes: int, physical: Callable[[], bytes]):
        self.valid, self.rng, self.max_bytes, self.physical = valid, rng, max_bytes, physical
        self.body = msgpack.unpackb(valid, raw=False)

    def _pack(self, body: dict) -> bytes:
        return msgpack.packb(body, use_bin_type=True)

    def make(self, kind: str) -> bytes:
        r, body = self.rng, dict(self.body)
        if kind == "random":
            return r.randbytes(r.randint(1, min(self.max_bytes, 4096)))
        if kind == "empty":
            return b""
        if kind == "truncated":
            return self.valid[:r.randint(0, len(self.valid) - 1)]
        if kind == "flipped":  # the first bytes: the envelope no longer parses as one map
            data = bytearray(self.valid)
            data[0] ^= 0xFF
            return bytes(data)
        if kind == "schema":
            return self._pack({**body, "schema": 99})
        if kind == "type":
            return self._pack({**body, "type": "no_such_type"})
        if kind == "missing_field":
            field = r.choice([k for k in body if k not in ("schema", "type")])
            return self._pack({k: v for k, v in body.items() if k != field})
        if kind == "unknown_field":
            return self._pack({**body, "no_such_field": 1})
        if kind == "field_type":
            ints = [k for k, v in body.items() if isinstance(v, int) and not isinstance(v, bool) and k != "schema"]
            return self._pack({**body, r.choice(ints): "not a number"})
        if kind in ("dtype", "shape", "nan"):
            return self._pack(self._spoil_array(body, kind))
        if kind == "padding":
            return self._pack({**body, "padding": b"\0" * self.max_bytes})
        if kind == "physical":
            return self.physical()
        raise ValueError(kind)

    def _spoil_array(self, body: dict, kind: str) -> dict:
        """``body`` with one array (top level, or one of ``tensors``) of a wrong dtype, a wrong shape,
        or a NaN in it."""
        r = self.rng
        places = [(k, None) for k, v in body.items() if isinstance(v, dict) and {"dtype", "shape", "data"} <= set(v)]
        places += [("tensors", name) for name in (body.get("tensors") or {})]
        if kind == "nan":
            places = [p for p in places if self._get(body, p)["dtype"] in ("float32", "float16")]
        if not places:  # no such array: text where a map of numbers belongs (every such message has one)
            maps = [k for k, v in body.items() if isinstance(v, dict)]
            return {**body, r.choice(maps): "not a number"}
        place = r.choice(places)
        arr = dict(self._get(body, place))
        if kind == "dtype":
            arr["dtype"] = "complex128"
        elif kind == "shape":
            arr["shape"] = [int(arr["shape"][0]) + 1, *arr["shape"][1:]] if arr["shape"] else [7]
        else:
            dtype = np.float32 if arr["dtype"] == "float32" else np.float16
            values = np.frombuffer(arr["data"], dtype).copy()
            values[r.randrange(len(values))] = np.nan
            arr["data"] = values.tobytes()
        key, inner = place
        if inner is None:
            return {**body, key: arr}
        return {**body, key: {**body[key], inner: arr}}

    @staticmethod
    def _get(body: dict, place: tuple[str, str | None]) -> dict:
        key, inner = place
        return body[key] if inner is None else body[key][inner]


def _changed(message: Any, **fields: Any) -> bytes:
    """``message`` on the wire with ``fields`` replaced (values its constructor would refuse)."""
    return msgpack.packb({**msgpack.unpackb(message.encode(), raw=False), **fields}, use_bin_type=True)


def _valid_messages(cfg: Any) -> dict[str, tuple[bytes, Callable[[], bytes]]]:
    """A valid message of every type the services receive, and a maker of physically impossible ones."""
    from shared.learning.model import QNetwork
    from shared.learning.weights import to_message
    from shared.wire.messages import (
        EpisodeStats,
        EvalResult,
        FlowControl,
        LearnerStats,
        TransitionBatch,
        WeightsMessage,
        new_epoch,
    )

    h, w = cfg.sensor.height, cfg.sensor.width
    frames = np.full((2, h, w), 1000, np.uint16)

    def batch(actor: str, reward: float = 1.0, depth_mm: int = 1000, version: int = 0) -> bytes:
        f = np.full_like(frames, depth_mm)
        return TransitionBatch(actor_id=actor, episode=0, first_step=0, start_index=0, actor_epoch=1,
                               depth_mm=f[:1], next_depth_mm=f[1], action=np.array([2], np.uint8),
                               reward=np.array([reward], np.float32), policy_version=np.array([version], np.int64),
                               pose=np.zeros((1, 3), np.float32)).encode()

    rng = np.random.default_rng(0)
    net = QNetwork(cfg.model, cfg.sensor)
    weights = to_message(net, 1)
    transposable = [k for k, v in weights.tensors.items() if v.ndim == 2 and v.shape[0] != v.shape[1]][0]

    def impossible_weights() -> bytes:
        if rng.random() < 0.5:  # the run's fingerprint, a tensor the wrong way round
            tensors = dict(weights.tensors, **{transposable: np.ascontiguousarray(weights.tensors[transposable].T)})
            return WeightsMessage(policy_version=2, architecture_fingerprint=weights.architecture_fingerprint,
                                  tensors=tensors, learner_epoch=1).encode()
        future = new_epoch() + 365 * 24 * 3600 * 10**9  # a learner that starts next year
        return to_message(net, 3, learner_epoch=future).encode()

    flow = FlowControl(learner_id="learner", updates=0, transitions_received=0, transitions_wanted=1).encode()
    stats = dict(learner_id="learner", updates=0, policy_version=0, replay_size=0, transitions_received=0,
                 transitions_rejected=0, loss=None, mean_q=None, updates_per_s=0.0, transitions_per_s=0.0, uptime_s=0.0)
    episode = dict(actor_id="fuzz", episode=0, start_index=0, steps=1, episode_return=1.0, terminated=False,
                   truncated=True, collision_cause=None, path_length_m=0.1, distance_from_start_m=0.1, epsilon=0.5,
                   policy_version=0, duration_s=0.1)
    ev = dict(evaluator_id="fuzz", policy_version=0, world="box-room", speed_table="test", max_steps=5,
              start_index=(0,), steps=(1,), collided=(False,), path_length_m=(0.1,))
    return {
        "transitions": (batch("fuzz"), lambda: batch("fuzz", reward=3.4e38) if rng.random() < 0.5
                        else batch("fuzz", depth_mm=65000)),
        "weights": (weights.encode(), impossible_weights),
        "flow": (flow, lambda: FlowControl(learner_id="learner", updates=0, transitions_received=0,
                                           transitions_wanted=1, learner_epoch=2**62).encode()),
        "stats/learner": (LearnerStats(**stats).encode(), lambda: _changed(LearnerStats(**stats), uptime_s=-1.0)),
        "stats/episode": (EpisodeStats(**episode).encode(), lambda: _changed(EpisodeStats(**episode), epsilon=7.0)),
        "stats/eval": (EvalResult(**ev).encode(), lambda: _changed(EvalResult(**ev), steps=[99])),
    }


def run(payloads: int = 10_000, *, max_bytes: int = 64 * 1024, big_bytes: int = 0, seed: int = 0,
        preset: str = "smoke", runs_dir: str | Path | None = None, echo: Callable[[str], None] | None = None
        ) -> dict[str, Any]:
    """Fuzz a fresh secured run with ``payloads`` payloads (round-robin over the keys, kinds drawn in
    turn); ``big_bytes`` > 0 also sends one payload that large to every key per round (memory)."""
    from services.bus.session import (
        ZenohSettings,
        open_session,
        query_latest,
        subscribe_messages,
    )
    from services.runs import resolve_config, save_config
    from services.up.bench import _launcher_args
    from services.up.launcher import Launcher
    from shared.wire.keys import RunKeys
    from shared.wire.messages import EpisodeStats, EvalResult, LearnerStats, RejectCounter

    if payloads < 1 or max_bytes < 16 or big_bytes < 0:
        raise FuzzError("payloads must be >= 1, max_bytes >= 16 and big_bytes >= 0")
    echo = echo or (lambda _msg: None)
    temporary = runs_dir is None
    root = Path(tempfile.mkdtemp(prefix="cogexplore-fuzz-")) if temporary else Path(runs_dir)
    args = _launcher_args(1, preset, ["train.total_updates=1000000", "train.checkpoint_every=1000000"], root, None,
                           prefix=RUN_PREFIX)
    args.no_evaluator = False
    args.eval_every = 1_000_000
    try:
        launcher = Launcher(args)  # a preset refused here has left an empty folder
    except BaseException:
        if temporary:
            shutil.rmtree(root, ignore_errors=True)  # nothing ran: nothing to keep
        raise
    unnamed_failure = False
    sent: Counter = Counter()
    sent_kinds: Counter = Counter()
    stats_rejects = RejectCounter("fuzzed stats")
    started = time.monotonic()
    try:
        launcher.config = resolve_config(args, launcher.paths)
        save_config(launcher.config, launcher.paths)
        keys = RunKeys(launcher.run)
        valid = _valid_messages(launcher.config)
        rng = random.Random(seed)
        makers = {name: Payloads(msg, rng, max_bytes, impossible) for name, (msg, impossible) in valid.items()}
        targets = [("actor", "transitions", keys.transitions("fuzz")),
                   ("actor", "stats/episode", keys.episode_stats("fuzz")),
                   ("learner", "weights", keys.weights), ("learner", "flow", keys.flow),
                   ("learner", "stats/learner", keys.learner_stats("fuzz")),
                   ("evaluator", "stats/eval", keys.eval_results("fuzz")), ("actor", "query", keys.weights_latest)]
        launcher.start()
        with open_session(launcher.settings("viewer"), wait_s=60) as viewer, contextlib.ExitStack() as closing:
            # what the services report while the run goes on: the start waits until every receiver
            # has joined (an evaluator still loading would miss the first payloads), the end until the
            # learner and the actor have counted every payload sent to them (a loaded machine drains late)
            seen: dict[str, Any] = {"updates": 0, "learner_rejects": 0, "actor_rejects": None, "evaluated": False}

            def on_stats(message: Any, _key: str) -> None:
                if isinstance(message, LearnerStats):
                    seen["updates"] = max(seen["updates"], message.updates)
                    seen["learner_rejects"] = max(seen["learner_rejects"], sum(message.rejects.values()))
                elif isinstance(message, EpisodeStats):
                    seen["actor_rejects"] = max(seen["actor_rejects"] or 0, int(message.extra.get(EpisodeStats.REJECTED, 0)))
                elif isinstance(message, EvalResult):
                    seen["evaluated"] = True

            subs = [subscribe_messages(viewer, keys.all_stats(), None, on_stats, stats_rejects,
                                       max_bytes=EvalResult.MAX_BYTES)]  # the largest statistics message
            deadline = time.monotonic() + 300
            while not (seen["updates"] and seen["actor_rejects"] is not None and seen["evaluated"]):
                if time.monotonic() > deadline or any(c.process.poll() is not None for c in launcher.children):
                    raise FuzzError(f"the run did not start (logs in {launcher.paths.logs}; seen: {seen}; "
                                    f"stats rejected: {stats_rejects.counts})")
                time.sleep(0.5)
            # closed (their publishers with them) however the fuzzing ends, before the viewer's session
            sessions = {role: closing.enter_context(open_session(
                ZenohSettings(mode="client", connect=(launcher.endpoint,),
                              config_file=str(launcher.secure.config(role))), wait_s=30))
                        for role in ("actor", "learner", "evaluator")}
            import zenoh

            # a put on a fresh session before it has heard of the receivers' subscriptions goes nowhere
            publishers = {key: sessions[role].declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                          for role, name, key in targets if name != "query"}
            deadline = time.monotonic() + 30
            while not all(p.matching_status.matching for p in publishers.values()):
                if time.monotonic() > deadline:
                    raise FuzzError("the fuzzing sessions never saw the receivers' subscriptions: "
                                    f"{[k for k, p in publishers.items() if not p.matching_status.matching]}")
                time.sleep(0.1)

            def send(k: int) -> None:
                role, name, key = targets[k % len(targets)]
                kind = PAYLOAD_KINDS[(k // len(targets)) % len(PAYLOAD_KINDS)]
                maker = makers["transitions" if name == "query" else name]
                payload = maker.make(kind)
                if name == "query":  # what a query carries is the learner's to ignore
                    sessions[role].get(key, payload=payload, timeout=2.0)
                else:
                    publishers[key].put(payload)
                sent[name] += 1
                sent_kinds[kind] += 1

            # a first fifth warms the allocators and the router's queues (every kind, and the big
            # payloads, once); a 2-core machine under load keeps growing them for a few thousand
            # payloads, so memory is compared after that fifth and after the four rounds that follow
            warm = min(payloads, max(len(targets) * len(PAYLOAD_KINDS) * 2, payloads // 5))
            edges = [0, warm] + [warm + (payloads - warm) * k // 4 for k in range(1, 5)]
            rounds = [range(a, b) for a, b in zip(edges, edges[1:])]
            rss: dict[str, dict[str, float | None]] = {}
            for i, part in enumerate(rounds):
                for k in part:
                    send(k)
                if big_bytes:
                    for role, name, key in targets[:-1]:
                        publishers[key].put(b"\x00" * big_bytes)
                        sent[name] += 1
                        sent_kinds["big"] += 1
                time.sleep(2.0)  # the receivers drain
                rss["after_first_round" if i == 0 else f"after_round_{i + 1}"] = {
                    c.name: _rss_mb(c.process.pid) for c in launcher.children}
                echo(f"round {i + 1}: {sum(sent.values())} payloads sent")
            drain_started = time.monotonic()
            while (seen["learner_rejects"] < sent["transitions"] or (seen["actor_rejects"] or 0) < sent["weights"] + sent["flow"]) \
                    and time.monotonic() - drain_started < 120:
                time.sleep(0.2)
            time.sleep(1.0)  # the evaluator takes the same weights stream as the actor
            drain_s = time.monotonic() - drain_started
            answered = query_latest(sessions["actor"], keys.weights_latest, timeout_s=5.0) is not None
            for sub in subs:
                sub.undeclare()
        alive = {c.name: c.process.poll() is None for c in launcher.children}
    except BaseException as exc:
        # a FuzzError names the logs, which stay; Ctrl-C or another error (out of memory) names no folder
        unnamed_failure = not isinstance(exc, FuzzError)
        raise
    finally:
        try:
            launcher.stop_services()
        finally:
            launcher.close()  # the run is let go however it ended (a traceback kept would hold it)
            if temporary and unnamed_failure:
                shutil.rmtree(root, ignore_errors=True)
    for c in launcher.children:
        c.said = not alive[c.name]  # a crash while fuzzing is said in "crashes"
    # one that crashed at the stop (the learner's final checkpoint, the actor's last counts) is said as up says it
    failed_at_stop = launcher.failed_at_stop()
    counted = {c.name: _final_counts(c.logfile) for c in launcher.children if c.role != "router"}
    result = {
        "payloads_sent": sum(sent.values()), "by_key": dict(sent), "by_kind": dict(sent_kinds),
        "crashes": [n for n, ok in alive.items() if not ok],
        "failed_at_stop": failed_at_stop,
        "exit_codes": {c.name: c.process.returncode for c in launcher.children},
        "rejects": {
            "learner (transitions)": counted.get("learner", {}).get("rejects", {}),
            "actor-0 (weights + flow)": counted.get("actor-0", {}).get("rejected_weights"),
            "evaluator (weights + flow)": counted.get("evaluator", {}),
            "viewer (stats)": stats_rejects.counts,
        },
        "expected_rejects": {"learner (transitions)": sent["transitions"],
                             "actor-0 (weights + flow)": sent["weights"] + sent["flow"],
                             "evaluator (weights + flow)": sent["weights"] + sent["flow"],
                             "viewer (stats)": sent["stats/learner"] + sent["stats/episode"] + sent["stats/eval"]},
        "weights_query_answered_after": answered,
        "drain_s": round(drain_s, 1),
        "reported_live": {"learner (transitions)": seen["learner_rejects"], "actor-0 (weights + flow)": seen["actor_rejects"]},
        "rss_mb": {**rss, "at_end": rss[f"after_round_{len(rounds)}"] if len(rounds) > 1 else rss["after_first_round"]},
        "seconds": round(time.monotonic() - started, 1), "logs": str(launcher.paths.logs),
    }
    if temporary and not result["crashes"] and not failed_at_stop:
        shutil.rmtree(root, ignore_errors=True)
    return result


def _final_counts(logfile: Path) -> dict[str, Any]:
    """A service's last 'done: {...}' (or evaluator 'rejected weights: {...}') JSON line."""
    found: dict[str, Any] = {}
    try:
        for line in logfile.read_text(errors="replace").splitlines():
            m = _DONE.search(line)
            if m:
                try:
                    found = json.loads(m.group(1))
                except json.JSONDecodeError:
                    pass
    except OSError:
        pass
    return found


def run_command(args: argparse.Namespace) -> int:
    """``cogexplore bench fuzz``."""
    import sys

    from services.bench import interrupt_on_stop_signals

    interrupt_on_stop_signals()  # SIGTERM ends the fuzzing through its clean-up, as Ctrl-C does
    result = run(args.payloads, max_bytes=args.max_bytes, big_bytes=args.big_bytes, seed=args.seed,
                 preset=args.preset, runs_dir=args.runs_dir,
                 echo=lambda msg: print(msg, file=sys.stderr, flush=True))
    print(json.dumps(result, indent=2, default=float))
    return 0 if not result["crashes"] and not result["failed_at_stop"] else 1
