"""Zenoh plumbing: session settings, opening sessions, reliable publishing, the router.

Nothing here opens a session at import time: Zenoh sessions hold threads and sockets that
do not survive ``fork``, so every process opens its own, after it has started, with
:func:`open_session` and closes it with ``with``::

    with open_session(ZenohSettings.from_env()) as session:
        publisher = declare_reliable_publisher(session, RunKeys(run).transitions(actor_id))
        publisher.put(batch.encode())

Data that must arrive (transitions, weights) goes out with ``CongestionControl.BLOCK``:
Zenoh's default for ``put`` is DROP, which silently loses samples when a queue is full.
All processes of a run meet at one router (``python -m services.router``); without a
config file, multicast scouting is off so that processes only ever talk to the endpoints
they are given.
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import itertools
import json
import logging
import os
import re
import secrets
import signal
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import zenoh

from services.bus import (
    DEFAULT_CONNECT,
    DEFAULT_ROUTER_LISTEN,
    DEFAULT_ROUTER_WAIT_S,
    ENV_CONFIG,
    ENV_CONNECT,
    ENV_LISTEN,
    ENV_MODE,
    ENV_ROUTER_WAIT,
    MODES,
)
from services.bus.security import (
    PASSWORD_KEY,
    PATH_KEYS,
    SECRET_PATH_KEYS,
    SecureFiles,
    SecurityError,
    check_private,
)
from services.runs import run_paths
from shared.config import parse_number
from shared.errors import CogexploreError, StopRequested
from shared.wire.messages import (
    MAX_MESSAGE_BYTES,
    OVERSIZE,
    Message,
    MessageError,
    RejectCounter,
    printable,
)

log = logging.getLogger(__name__)


# <protocol>/<address>, e.g. tcp/127.0.0.1:7447, udp/[::1]:7447, unixsock-stream/tmp/z.sock
_ENDPOINT_RE = re.compile(r"[a-z][a-z0-9\-]*/\S+")


class TransportConfigError(CogexploreError):
    """Zenoh settings are invalid (bad mode, endpoint or config file)."""


class TransportError(CogexploreError, RuntimeError):
    """A Zenoh session could not be opened or used; the message names the endpoints."""


def parse_endpoints(value: str | Sequence[str], what: str = "") -> tuple[str, ...]:
    """Endpoints from a comma-separated string or a sequence; raises TransportConfigError."""
    items = value.split(",") if isinstance(value, str) else list(value)
    out = []
    for item in items:
        if not isinstance(item, str):
            raise TransportConfigError(f"{what} endpoint {item!r} must be a string".lstrip())
        item = item.strip()
        if not item:
            continue
        if not _ENDPOINT_RE.fullmatch(item):
            raise TransportConfigError(f"{what} endpoint {item!r} is invalid: expected ".lstrip() +
                                       "<protocol>/<address>, e.g. tcp/127.0.0.1:7447")
        out.append(item)
    return tuple(out)


def endpoint_host_port(endpoint: str) -> tuple[str, str, str]:
    """(protocol, host, port) of a ``<protocol>/<host>:<port>[?metadata][#config]`` endpoint: an
    IPv6 host without its brackets; a part the endpoint lacks is empty."""
    protocol, _, address = re.split(r"[?#]", endpoint, maxsplit=1)[0].partition("/")
    host, _, port = address.rpartition(":")
    return protocol, host.strip("[]"), port


@dataclass(frozen=True)
class ZenohSettings:
    """How a process joins Zenoh.

    Fields left unset (None / empty) come from ``config_file`` when one is given, else from
    the defaults: client mode connecting to :data:`DEFAULT_CONNECT`.
    """

    mode: str | None = None
    """'peer', 'client' or 'router' (None: the config file's, else 'client')."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to, e.g. ('tcp/10.0.0.5:7447',)."""
    listen: tuple[str, ...] = ()
    """Endpoints to listen on (routers; peers that accept connections)."""
    config_file: str | None = None
    """A Zenoh JSON5 config file (TLS, credentials, ...); explicit fields override it."""
    router_wait_s: float = DEFAULT_ROUTER_WAIT_S
    """How long a service keeps retrying while no router answers (``open_service_session``): its
    router may still be starting; 0 fails at once."""
    second_session: bool = False
    """A process's second session (:meth:`second_link`): it listens nowhere and takes a Zenoh id of its
    own, whatever ``config_file`` says (the first's listeners hold their ports, and a router refuses a
    second session under an id it already has)."""

    def __post_init__(self) -> None:
        if self.mode is not None and self.mode not in MODES:
            raise TransportConfigError(f"Zenoh mode {self.mode!r} is invalid: use one of {list(MODES)}")
        object.__setattr__(self, "connect", parse_endpoints(self.connect, "connect"))
        object.__setattr__(self, "listen", parse_endpoints(self.listen, "listen"))
        if self.config_file is not None and not isinstance(self.config_file, (str, os.PathLike)):
            raise TransportConfigError(f"config_file must be a path, got {self.config_file!r}")
        if self.config_file is not None:
            object.__setattr__(self, "config_file", str(self.config_file))
        try:
            object.__setattr__(self, "router_wait_s", parse_number(
                self.router_wait_s, f"the router wait (--router-wait, {ENV_ROUTER_WAIT})", unit="of seconds"))
        except CogexploreError as exc:
            raise TransportConfigError(str(exc)) from None
        if self.config_file is not None:
            # now, in the thread that builds the settings: a missing, invalid or exposed file was a
            # traceback in the first background thread to open a session (an actor's run-config check)
            self._base_config()

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, *, overrides: Mapping[str, object] | None = None,
                 **defaults: object) -> "ZenohSettings":
        """Settings from ``COGEXPLORE_ZENOH_{MODE,CONNECT,LISTEN,CONFIG,ROUTER_WAIT_S}`` over ``defaults``,
        and ``overrides`` (a command line's options) over both.

        Endpoint lists are comma-separated. Empty variables count as unset.
        """
        env = os.environ if environ is None else environ
        values: dict[str, object] = dict(defaults)
        if env.get(ENV_MODE, "").strip():
            values["mode"] = env[ENV_MODE].strip()
        if env.get(ENV_CONNECT, "").strip():
            values["connect"] = parse_endpoints(env[ENV_CONNECT], ENV_CONNECT)
        if env.get(ENV_LISTEN, "").strip():
            values["listen"] = parse_endpoints(env[ENV_LISTEN], ENV_LISTEN)
        if env.get(ENV_CONFIG, "").strip():
            values["config_file"] = env[ENV_CONFIG].strip()
        if env.get(ENV_ROUTER_WAIT, "").strip():
            values["router_wait_s"] = env[ENV_ROUTER_WAIT].strip()
        values.update(overrides or {})
        return cls(**values)  # type: ignore[arg-type]

    @property
    def effective_mode(self) -> str:
        """The mode the session will run in (a config file's mode is read when set there)."""
        if self.mode is not None:
            return self.mode
        if self.config_file is not None:
            mode = _json_value(self._base_config(), "mode")
            if isinstance(mode, str) and mode in MODES:
                return mode
        return "client"

    @property
    def effective_connect(self) -> tuple[str, ...]:
        """Endpoints set here, else the default router for clients and peers without a file."""
        if self.connect or self.config_file is not None or self.effective_mode == "router":
            return self.connect
        return DEFAULT_CONNECT

    def _base_config(self) -> zenoh.Config:
        if self.config_file is None:
            config = zenoh.Config()
            # Only talk to the endpoints we are given: no surprise links to other runs' peers.
            config.insert_json5("scouting/multicast/enabled", "false")
            return config
        path = Path(self.config_file)
        if not path.is_file():
            name = str(self.config_file) or "''"  # Path("") reads ".", a folder
            said = "is not a file" if path.exists() and str(self.config_file) else "does not exist"
            raise TransportConfigError(f"Zenoh config file {name} {said}")
        try:
            config = zenoh.Config.from_file(str(path))
        except Exception as exc:  # zenoh raises its own ZError for parse errors
            raise TransportConfigError(f"Zenoh config file {path} is invalid: {_config_problem(exc)}") from None
        # Secrets (a password, the router's passwords, a private key) other users may read are refused, as
        # ssh refuses such a key; certificates are public.
        if isinstance(_json_value(config, PASSWORD_KEY), str):
            _check_secret(path)
        for key in PATH_KEYS:
            value = _json_value(config, key)
            if not (isinstance(value, str) and value):
                continue
            named = path.parent / value  # an absolute value stays as it is
            # Files it names relative to itself (services.bus.security writes them so, for a folder that
            # can be copied to another machine as it is); Zenoh would read them relative to the cwd.
            if not Path(value).is_absolute():
                if not named.is_file():
                    raise TransportConfigError(f"Zenoh config file {path}: {key} names {named}, which does not exist")
                config.insert_json5(key, json.dumps(str(named.resolve())))
            if key in SECRET_PATH_KEYS and named.is_file():
                _check_secret(named)
        return config

    def to_config(self) -> zenoh.Config:
        """A fresh ``zenoh.Config`` (a config is consumed by ``zenoh.open``)."""
        config = self._base_config()
        mode = self.effective_mode
        # A file that names no mode leaves Zenoh's own default, peer: a session that needs no router,
        # listens on every interface and scouts by multicast, while effective_mode says client.
        if self.mode is not None or self.config_file is None or _json_value(config, "mode") != mode:
            config.insert_json5("mode", json.dumps(mode))
        connect = self.effective_connect
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if self.listen:
            config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        elif self.second_session:
            config.insert_json5("listen/endpoints", "[]")
        if self.second_session:
            # 128 random bits with the top one set: Zenoh refuses an id written with a leading 0, which
            # token_hex gave one time in 16 (a session without retries failed to open)
            config.insert_json5("id", json.dumps(f"{secrets.randbits(128) | 1 << 127:032x}"))
        return config

    def second_link(self) -> "ZenohSettings | None":
        """Settings for a second session of this process, a link of its own to the same router (for BLOCK
        data that must not hold the rest up: :func:`declare_reliable_publisher`): a client's, listening
        nowhere. None for a peer or a router, whose second session would meet no one the first meets
        (peers that dial it) or take its ports: such a process keeps one session."""
        if self.effective_mode != "client":
            return None
        return dataclasses.replace(self, listen=(), second_session=True)

    def describe(self) -> str:
        """One line for logs and errors."""
        parts = [f"mode={self.mode or 'default'}"]
        if self.effective_connect:
            parts.append("connect=" + ",".join(self.effective_connect))
        if self.listen:
            parts.append("listen=" + ",".join(self.listen))
        if self.config_file:
            parts.append(f"config={self.config_file}")
        return " ".join(parts)


def _check_secret(path: Path) -> None:
    try:
        check_private(path)
    except SecurityError as exc:  # one kind of error for a bad config file, which callers catch
        raise TransportConfigError(str(exc)) from None


_PEST_WHERE_RE = re.compile(r"^\s*-->\s*(\d+):(\d+)")
_SERDE_WHERE_RE = re.compile(r"line:? (\d+),? column:? (\d+)")
_SERDE_MESSAGE_RE = re.compile(r'(?:msg: |message: |Error\()"((?:[^"\\]|\\.)*)"')
_SERDE_KINDS = ("invalid type", "invalid value", "invalid length", "unknown variant", "unknown field",
                "missing field", "duplicate field")


def _config_problem(exc: object) -> str:
    """What Zenoh says is wrong with a config file, in one line and without any of the file's text:
    its parser draws the line it stopped at, serde quotes the value it refused (the TOML parser the whole
    file) and the validator prints the whole config, a role's password among them, into a terminal and
    a log that other users may read. Said: where (line, column), serde's kind of error and what the
    schema expected, taken from where the parser or serde put them, never from the file's text."""
    text = str(exc)
    if text.startswith("Invalid configuration:"):  # the validator's: the whole config follows
        return "a value Zenoh refuses (a user without a password, a queue size out of range, ...)"
    lines = text.splitlines()
    pest_where = _PEST_WHERE_RE.match(lines[0]) if lines else None
    drawn = next((line.strip()[1:].strip() for line in lines if line.strip().startswith("= ")), None)
    said = _SERDE_MESSAGE_RE.search(text)
    where = None
    if pest_where and drawn is not None:  # the JSON5 grammar's: its place first, what it expected last
        where, what = pest_where, drawn
    elif said:
        message = said.group(1)  # serde's, up to its closing quote: what follows may quote the whole file
        where = _SERDE_WHERE_RE.search(text, said.end())  # after the message, which quotes the value
        path = re.match(r"[A-Za-z_][\w-]*(?:\.[A-Za-z_][\w-]*|\[\d+\])*: ", message)  # serde_yaml's key path
        if path:
            message = message[path.end():]
        # The refused value (or key) sits between serde's kind of error and its last ", expected ": neither
        # edge is taken from it, whatever quotes, backticks or words it holds. A message of another shape
        # (Zenoh's own checks, which quote the value first) says nothing but that it refused.
        kind = next((k for k in _SERDE_KINDS if message.startswith(k)), None)
        what = (path.group(0) if path else "") + (kind or "a value Zenoh refuses")
        if kind is not None:
            _, found, expected = message.rpartition(", expected ")
            what += " …" + (", expected " + expected.replace("\\n", " ").strip() if found else "")
    else:
        what = "it cannot be parsed"
    what = re.sub(r"\s+at \S+\.rs:\d+\.?\s*$", "", what)  # the Rust source line that raised
    if where:
        return f"line {where.group(1)}, column {where.group(2)}: {what}"
    return what


def _json_value(config: zenoh.Config, key: str) -> object:
    try:
        return json.loads(config.get_json(key))
    except Exception:
        return None


def open_session(settings: ZenohSettings | None = None, *, wait_s: float = 0.0,
                 give_up: Callable[[], str | None] | None = None) -> zenoh.Session:
    """Open a Zenoh session (``ZenohSettings.from_env()`` when ``settings`` is None).

    A client fails at once when no router answers; ``wait_s`` > 0 keeps retrying that long,
    for processes started alongside their router. ``give_up`` is asked after each failed try: a
    reason (e.g. the router process has exited) ends the wait at once with it. Use the result as a
    context manager.
    """
    settings = settings if settings is not None else ZenohSettings.from_env()
    deadline = time.monotonic() + max(0.0, wait_s)
    while True:
        try:
            return zenoh.open(settings.to_config())
        except zenoh.ZError as exc:
            remaining = deadline - time.monotonic()
            reason = give_up() if give_up is not None else None
            if remaining <= 0 or reason:
                # Zenoh's words for a router that did not take this session: "Unable to connect"
                refused = not reason and "Unable to connect" in str(exc)
                raise TransportError(f"cannot open a Zenoh session ({settings.describe()}): {reason or exc}"
                                     f"{_refused_hint(settings) if refused else ''}") from None
            time.sleep(min(0.2, remaining))


def _refused_hint(settings: ZenohSettings) -> str:
    """What to say when a session did not open although something takes connections at one of its
    endpoints: Zenoh's own error reads as if no router were there. A router of a secured run says
    nothing to a link whose password or certificate it refuses."""
    for endpoint in settings.effective_connect:
        where = _socket_address(endpoint)
        if where is None or not where[0]:
            continue
        try:
            socket.create_connection(where, timeout=1.0).close()
        except (OSError, UnicodeError, ValueError):  # a name IDNA cannot encode is no listener either
            continue
        return (f"; something takes connections at {where[0]}:{where[1]} but opened no session: the run's router "
                "refusing this process's password or certificate (a bundle of another run, made before `secure "
                "init --force`, or expired: export a fresh one), or tcp/ where it listens on tls/ (or the other way)")
    return ""


class StoppedWaiting(TransportError, StopRequested):
    """A stop (SIGTERM, Ctrl-C) came while a service waited for its router: it ends, as asked."""


class LinkWatch:
    """Counts the transports (links to other Zenoh nodes) of a session that open and close, and says
    so in the log.

    Zenoh closes a transport on which a BLOCK message could not be queued for ``wait_before_close``
    (5 s by default): a receiver stalled that long (a process stopped, or starved of CPU) loses
    what was in flight to it, and a client reconnects to its router within seconds. Without this
    watch such a loss is silent. The listener lives as long as the session (it is declared in the
    background); a session's own close is not reported.
    """

    def __init__(self, session: zenoh.Session, *, routine: bool = False) -> None:
        """``routine``: links come and go as a matter of course (a router's clients), logged as info;
        otherwise a lost link to a router is a warning."""
        self.opened = self.closed = 0
        self._routine = routine
        self._lock = threading.Lock()
        session.info.declare_transport_events_listener(self._on_event)

    def _on_event(self, event: zenoh.TransportEvent) -> None:
        remote = f"Zenoh {event.transport.whatami} {event.transport.zid}".lower()
        closed = event.kind == zenoh.SampleKind.DELETE
        with self._lock:
            if closed:
                self.closed += 1
            else:
                self.opened += 1
        if self._routine or event.transport.whatami != zenoh.WhatAmI.ROUTER:  # peers come and go
            log.info("%s %s", remote, "left" if closed else "joined")
        elif closed:
            log.warning("lost the link to %s (it stopped, the network dropped, or a receiver stalled past "
                        "Zenoh's wait_before_close): messages in flight on it are lost", remote)
        else:
            log.info("linked to %s", remote)


def open_service_session(settings: ZenohSettings, stop: threading.Event | None = None) -> zenoh.Session:
    """A service's session: :func:`open_session`, retrying ``settings.router_wait_s`` while no router
    answers (``--router-wait``); StoppedWaiting as soon as ``stop`` is set meanwhile (a service
    asked to stop waited out the whole wait, then failed). Its links lost and made again are logged
    (:class:`LinkWatch`)."""
    try:
        session = open_session(settings, wait_s=settings.router_wait_s,
                               give_up=None if stop is None else lambda: "stopped" if stop.is_set() else None)
    except TransportError:
        if stop is not None and stop.is_set():
            raise StoppedWaiting(f"stopped while waiting for the router ({settings.describe()})") from None
        raise
    LinkWatch(session)
    return session


# ---------------------------------------------------------------------------------------------
# Publishing, subscribing, querying
# ---------------------------------------------------------------------------------------------

def declare_reliable_publisher(session: zenoh.Session, key_expr: str, *,
                               priority: zenoh.Priority = zenoh.Priority.DATA) -> zenoh.Publisher:
    """A publisher that blocks rather than drops when queues are full (transitions, weights).

    A receiver that stops reading holds such a message, and with it everything else that comes after
    it on the sender's link to the router, DROP messages included, for up to Zenoh's wait_before_close
    (5 s): a process whose other messages must not wait that long (the learner's flow control behind
    its weights) publishes on a session of its own (:meth:`ZenohSettings.second_link`)."""
    return session.declare_publisher(key_expr, congestion_control=zenoh.CongestionControl.BLOCK,
                                     reliability=zenoh.Reliability.RELIABLE, priority=priority)


def put_reliable(session: zenoh.Session, key_expr: str, payload: bytes) -> None:
    """One ``put`` with BLOCK congestion control (for an occasional message)."""
    session.put(key_expr, payload, congestion_control=zenoh.CongestionControl.BLOCK)


def subscribe_messages(session: zenoh.Session, key_expr: str, cls: type[Message] | None,
                       on_message: Callable[[Message, str], None],
                       rejects: RejectCounter, max_bytes: int | None = None) -> zenoh.Subscriber:
    """Subscribe to ``key_expr``, decoding each sample as ``cls`` (any type when None).

    ``on_message(message, key)`` gets every valid message, on a Zenoh thread; invalid ones
    are counted in ``rejects`` (logged once per cause) and dropped. A payload longer than
    ``max_bytes`` (default: what ``cls`` allows) is refused before it is even copied out of Zenoh:
    a receiver that knows what it expects (weights of its own network, frames of its own sensor)
    passes that, so that 50 MB of garbage costs it nothing. An exception raised by ``on_message``
    is logged (the first with its traceback, then one line in a thousand: a message that keeps
    failing must not flood the log) and the subscription carries on.
    """
    limit = max_bytes if max_bytes is not None else (cls.MAX_BYTES if cls is not None else MAX_MESSAGE_BYTES)
    failures = itertools.count(1)

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        size = len(sample.payload)
        if size > limit:
            rejects.reject(MessageError(OVERSIZE, f"{size} bytes, more than the {limit} this receiver takes"), key)
            return
        message = rejects.decode(sample.payload.to_bytes(), cls, source=key)
        if message is None:
            return
        try:
            on_message(message, key)
        except Exception as exc:
            n = next(failures)
            if n == 1:
                log.exception("handler for %s failed on a message from %s", key_expr, printable(key))
            elif n % 1000 == 0:
                log.error("handler for %s failed %d times, last on a message from %s: %s", key_expr, n,
                          printable(key), printable(exc))

    return session.declare_subscriber(key_expr, on_sample)


def serve_latest(session: zenoh.Session, key_expr: str, latest: Callable[[], bytes | None], *,
                 drop: bool = False) -> zenoh.Queryable:
    """A queryable on ``key_expr`` answering with ``latest()`` (no reply while it is None).

    ``latest`` runs on a Zenoh thread for every query: return cached bytes, do not encode.
    Zenoh's replies block by default: a querier that stops reading holds them, and the replier's link
    to the router behind them, as a stopped subscriber holds a BLOCK publisher's
    (:func:`declare_reliable_publisher`). ``drop`` gives such a querier's reply up instead.
    """

    def on_query(query: zenoh.Query) -> None:
        try:
            payload = latest()
        except Exception:
            log.exception("latest() for %s failed", key_expr)
            return
        if payload is not None:
            query.reply(key_expr, payload, congestion_control=zenoh.CongestionControl.DROP if drop else None)

    return session.declare_queryable(key_expr, on_query)


def query_latest(session: zenoh.Session, key_expr: str, timeout_s: float = 2.0) -> bytes | None:
    """The payload of the first successful reply to a get on ``key_expr``, or None."""
    for reply in session.get(key_expr, timeout=timeout_s):
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        log.debug("error reply to %s: %s", key_expr, reply.err)
    return None


def query_replies(session: zenoh.Session, key_expr: str, max_bytes: int, timeout_s: float = 2.0,
                  oversize: Callable[[int], None] | None = None) -> Iterator[bytes]:
    """The payloads of every successful reply to a get on ``key_expr``, as they come, for a caller
    that must not take the first answer on trust (without the access control anyone may answer,
    first and as often as they like): the caller reads each and keeps what it can use. A payload
    over ``max_bytes`` is left in Zenoh (``oversize(size)`` is told)."""
    # every queryable, and no consolidation (by default Zenoh keeps one reply per key: the forger's, maybe)
    for reply in session.get(key_expr, timeout=timeout_s, target=zenoh.QueryTarget.ALL,
                             consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is None:
            log.debug("error reply to %s: %s", key_expr, reply.err)
        elif len(reply.ok.payload) > max_bytes:
            if oversize is not None:
                oversize(len(reply.ok.payload))
        else:
            yield reply.ok.payload.to_bytes()


# ---------------------------------------------------------------------------------------------
# Liveliness
# ---------------------------------------------------------------------------------------------

def declare_alive(session: zenoh.Session, key: str) -> zenoh.LivelinessToken:
    """Announce this process under ``key`` (e.g. ``RunKeys(run).alive("actor", id)``) until
    the token is undeclared or the session closes. Keep the returned token referenced:
    dropping it undeclares it."""
    return session.liveliness().declare_token(key)


class LivelinessWatch:
    """The set of live tokens matching a key expression, kept current by a liveliness
    subscriber (tokens alive before the watch started are included).

    ``on_change(key, alive)`` (optional) is called on a Zenoh thread for each change.
    """

    def __init__(self, session: zenoh.Session, key_expr: str,
                 on_change: Callable[[str, bool], None] | None = None) -> None:
        self.key_expr = key_expr
        self._alive: set[str] = set()
        self._changed = threading.Condition()
        self._on_change = on_change
        self._subscriber: zenoh.Subscriber | None = session.liveliness().declare_subscriber(
            key_expr, self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key, alive = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
        with self._changed:
            (self._alive.add if alive else self._alive.discard)(key)
            self._changed.notify_all()
        if self._on_change is not None:
            try:
                self._on_change(key, alive)
            except Exception:
                log.exception("liveliness handler for %s failed", self.key_expr)

    @property
    def alive(self) -> frozenset[str]:
        with self._changed:
            return frozenset(self._alive)

    def wait(self, predicate: Callable[[frozenset[str]], bool], timeout_s: float) -> bool:
        """Block until ``predicate(alive keys)`` holds; False on timeout."""
        with self._changed:
            return self._changed.wait_for(lambda: predicate(frozenset(self._alive)), timeout_s)

    def close(self) -> None:
        """Stop watching (idempotent; harmless after the session has closed)."""
        subscriber, self._subscriber = self._subscriber, None
        if subscriber is not None:
            try:
                subscriber.undeclare()
            except zenoh.ZError:
                pass  # the session is already closed, which undeclared it

    def __enter__(self) -> "LivelinessWatch":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------
# Router
# ---------------------------------------------------------------------------------------------

def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port nothing listens on right now (bind to port 0), for tests and benchmarks."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def _socket_address(endpoint: str) -> tuple[str, int] | None:
    """(host, port) of a ``tcp/`` or ``tls/`` endpoint a plain socket can reach (the host may be
    empty); None for another protocol, an ``#iface=`` endpoint or a port that is not a number."""
    protocol, host, port = endpoint_host_port(endpoint)
    if protocol not in ("tcp", "tls") or "#" in endpoint or not (port.isascii() and port.isdigit()):
        return None
    return host, int(port)


def port_taken(endpoint: str) -> str | None:
    """Why a router could not listen on ``endpoint`` (``tcp/`` or ``tls/`` HOST:PORT) because other
    sockets already hold its port at every address HOST resolves to (a Zenoh listener keeps the
    first address that binds); None when one is free, or when this cannot tell (an ``#iface=``
    endpoint, a name that does not resolve: the router then says what is wrong). A port in
    TIME_WAIT counts as free, as it does for a router."""
    if (where := _socket_address(endpoint)) is None:
        return None
    host, port = where
    try:
        addresses = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError, ValueError):
        return None
    reasons = []
    for family, kind, _, _, where in addresses:
        try:
            with socket.socket(family, kind) as probe:
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                probe.bind(where)
            return None
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE:
                return None
            reasons.append(exc.strerror)
    return f"port {port} of {host} is taken ({reasons[0]})" if reasons else None


def open_router(listen: Sequence[str] = DEFAULT_ROUTER_LISTEN, *,
                config_file: str | None = None) -> zenoh.Session:
    """Open a Zenoh session in router mode listening on ``listen`` (close it to stop)."""
    settings = ZenohSettings(mode="router", listen=tuple(listen), config_file=config_file)
    try:
        return zenoh.open(settings.to_config())
    except zenoh.ZError as exc:
        raise TransportError(f"cannot start a Zenoh router ({settings.describe()}): {exc}") from None


def run_router(listen: Sequence[str] = DEFAULT_ROUTER_LISTEN, *, config_file: str | None = None,
               stop: threading.Event | None = None,
               on_ready: Callable[[zenoh.Session], None] | None = None) -> int:
    """Run a Zenoh router in this process until SIGINT/SIGTERM (or ``stop`` is set).

    Signal handlers are installed only when called from the main thread, and restored on
    return. The session is always closed. Returns 0 (a process exit status).
    """
    stop = stop if stop is not None else threading.Event()
    previous: dict[int, object] = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, lambda *_: stop.set())
    try:
        with open_router(listen, config_file=config_file) as session:
            LinkWatch(session, routine=True)
            log.info("Zenoh router %s listening on %s", session.zid(), ", ".join(listen))
            if on_ready is not None:
                on_ready(session)
            while not stop.wait(0.2):  # a timed wait keeps the main thread responsive to signals
                pass
            log.info("Zenoh router stopping")
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)  # type: ignore[arg-type]
    return 0


def cli_overrides(args: argparse.Namespace) -> dict[str, object]:
    """The ``ZenohSettings`` fields a command line's Zenoh options set (those it has and were given)."""
    overrides: dict[str, object] = {}
    if getattr(args, "connect", None):
        overrides["connect"] = parse_endpoints(args.connect, "--connect")
    if getattr(args, "listen", None):
        overrides["listen"] = parse_endpoints(args.listen, "--listen")
    if getattr(args, "zenoh_mode", None):
        overrides["mode"] = args.zenoh_mode
    if getattr(args, "zenoh_config", None):
        overrides["config_file"] = args.zenoh_config
    if getattr(args, "router_wait", None) is not None:
        overrides["router_wait_s"] = args.router_wait
    return overrides


def zenoh_settings(args: argparse.Namespace, role: str | None = None) -> ZenohSettings:
    """Environment variables first, command-line options over them. With a config file from neither, a
    process of ``role`` takes its run's credentials where the run folder holds them
    (``<runs-dir>/<run>/secure/<role>.json5``: what ``up`` writes, or a ``secure export`` bundle put
    there on another machine)."""
    settings = ZenohSettings.from_env(overrides=cli_overrides(args))
    if settings.config_file is None and role is not None:
        found = SecureFiles(run_paths(args).secure).config(role)
        if found.is_file():
            log.info("Zenoh credentials of role %s: %s", role, found)
            # credentials name no router (SecureFiles writes none): without --connect the default
            # router, as without them, not a client that knows of no router to connect to
            settings = dataclasses.replace(settings, config_file=str(found),
                                           connect=settings.connect or settings.effective_connect)
    return settings
