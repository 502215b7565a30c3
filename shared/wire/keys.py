"""Every Zenoh key expression of cogexplore, namespaced by run name.

Nothing else in the project spells a key by hand: services build keys with :class:`RunKeys`
and read them back with :func:`parse_key`. The layout, for run ``<run>``::

    cogexplore/<run>/transitions/<actor>        TransitionBatch stream of one actor (put, BLOCK)
    cogexplore/<run>/weights                    WeightsMessage stream from the learner (put, BLOCK)
    cogexplore/<run>/weights/latest             queryable: the learner's newest WeightsMessage
    cogexplore/<run>/flow                       FlowControl from the learner (replay-ratio credit)
    cogexplore/<run>/config                     queryable: the learner's RunConfigMessage
    cogexplore/<run>/stats/episode/<actor>      EpisodeStats of one actor
    cogexplore/<run>/stats/learner/<learner>    LearnerStats
    cogexplore/<run>/stats/eval/<evaluator>     EvalResult
    cogexplore/<run>/alive/<role>/<id>          liveliness token of one process

Run names, process ids and roles are single key chunks: letters, digits, ``_``, ``-`` and
``.``, starting with a letter or digit, at most 64 characters. That excludes every character
with a meaning in Zenoh key expressions (``/ * $ # ?``) and whitespace, and keeps a run name
safe as the directory ``runs/<run>/``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from shared.errors import CogexploreError

ROOT = "cogexplore"
"""First chunk of every key."""

ROLES: tuple[str, ...] = ("actor", "learner", "evaluator", "router", "trainer")
"""Roles a process may announce with a liveliness token."""

STATS_KINDS: tuple[str, ...] = ("episode", "learner", "eval")
"""Kinds of statistics published under ``stats/``."""

MAX_NAME_LEN = 64
_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]*")
# Characters named in errors because they are the likely mistakes.
_SPECIAL = {"/": "slash", "*": "wildcard '*'", "$": "'$'", "#": "'#'", "?": "'?'"}


class KeyExprError(CogexploreError):
    """A run name, id, role or key expression is not valid; the message names the problem."""


def validate_name(name: object, what: str = "name") -> str:
    """Return ``name`` if it is a valid single key chunk, else raise :class:`KeyExprError`.

    ``what`` names the thing in the error ("run name", "actor id", ...).
    """
    if not isinstance(name, str):
        raise KeyExprError(f"{what} must be a string, got {type(name).__name__}")
    if not name:
        raise KeyExprError(f"{what} must not be empty")
    if len(name) > MAX_NAME_LEN:
        raise KeyExprError(f"{what} {name!r} is longer than {MAX_NAME_LEN} characters")
    for ch in name:
        if ch in _SPECIAL:
            raise KeyExprError(f"{what} {name!r} contains a {_SPECIAL[ch]}, which Zenoh key "
                               "expressions reserve")
        if ch.isspace():
            raise KeyExprError(f"{what} {name!r} contains whitespace")
    if not _NAME_RE.fullmatch(name):
        raise KeyExprError(f"{what} {name!r} is invalid: use letters, digits, '_', '-' and '.', "
                           "starting with a letter or digit")
    return name


def validate_role(role: object) -> str:
    """Return ``role`` if it is one of :data:`ROLES`."""
    if role not in ROLES:
        raise KeyExprError(f"role {role!r} is unknown; known roles: {list(ROLES)}")
    return role  # type: ignore[return-value]


def _validate_stats_kind(kind: object) -> str:
    if kind not in STATS_KINDS:
        raise KeyExprError(f"stats kind {kind!r} is unknown; known kinds: {list(STATS_KINDS)}")
    return kind  # type: ignore[return-value]


@dataclass(frozen=True)
class RunKeys:
    """Key expressions of one run. ``RunKeys("exp1").transitions("actor-0")`` and so on."""

    run: str

    def __post_init__(self) -> None:
        validate_name(self.run, "run name")

    @property
    def prefix(self) -> str:
        """``cogexplore/<run>``."""
        return f"{ROOT}/{self.run}"

    # -- transitions -------------------------------------------------------------------
    def transitions(self, actor_id: str) -> str:
        """Where actor ``actor_id`` publishes its TransitionBatch messages."""
        return f"{self.prefix}/transitions/{validate_name(actor_id, 'actor id')}"

    @property
    def all_transitions(self) -> str:
        """Subscribe here to receive every actor's transitions."""
        return f"{self.prefix}/transitions/*"

    # -- weights -----------------------------------------------------------------------
    @property
    def weights(self) -> str:
        """Where the learner publishes each new WeightsMessage."""
        return f"{self.prefix}/weights"

    @property
    def weights_latest(self) -> str:
        """The learner's queryable answering with its newest WeightsMessage."""
        return f"{self.prefix}/weights/latest"

    # -- configuration -----------------------------------------------------------------
    @property
    def config(self) -> str:
        """The learner's queryable answering with the run's configuration (RunConfigMessage)."""
        return f"{self.prefix}/config"

    # -- flow control ------------------------------------------------------------------
    @property
    def flow(self) -> str:
        """Where the learner says how many more transitions it wants (see FlowControl)."""
        return f"{self.prefix}/flow"

    # -- statistics --------------------------------------------------------------------
    def stats(self, kind: str, source_id: str) -> str:
        """Statistics of ``kind`` (one of :data:`STATS_KINDS`) from process ``source_id``."""
        return f"{self.prefix}/stats/{_validate_stats_kind(kind)}/{validate_name(source_id, 'source id')}"

    def episode_stats(self, actor_id: str) -> str:
        return self.stats("episode", actor_id)

    def learner_stats(self, learner_id: str) -> str:
        return self.stats("learner", learner_id)

    def eval_results(self, evaluator_id: str) -> str:
        return self.stats("eval", evaluator_id)

    def all_stats(self, kind: str | None = None) -> str:
        """Every statistics key of the run, or only those of ``kind``."""
        if kind is None:
            return f"{self.prefix}/stats/**"
        return f"{self.prefix}/stats/{_validate_stats_kind(kind)}/*"

    # -- liveliness --------------------------------------------------------------------
    def alive(self, role: str, process_id: str) -> str:
        """Liveliness token key of one process."""
        return f"{self.prefix}/alive/{validate_role(role)}/{validate_name(process_id, 'process id')}"

    def all_alive(self, role: str | None = None) -> str:
        """Liveliness key expression matching every process, or every process of ``role``."""
        if role is None:
            return f"{self.prefix}/alive/**"
        return f"{self.prefix}/alive/{validate_role(role)}/*"


@dataclass(frozen=True)
class ParsedKey:
    """A concrete key taken apart by :func:`parse_key`.

    ``channel`` is one of ``transitions``, ``weights``, ``weights_latest``, ``config``,
    ``stats``, ``alive``. ``kind`` is the stats kind or the liveliness role (None elsewhere); ``source``
    is the actor / process id (None for the weights keys).
    """

    run: str
    channel: str
    kind: str | None = None
    source: str | None = None


def parse_key(key: object) -> ParsedKey:
    """Take a concrete key (no wildcards) built by :class:`RunKeys` apart.

    Raises :class:`KeyExprError` for a key outside this layout, so a service can reject a
    sample published on a key it does not understand.
    """
    text = str(key)  # accepts zenoh.KeyExpr as well as str
    parts = text.split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise KeyExprError(f"key {text!r} does not start with '{ROOT}/<run>/'")
    run = validate_name(parts[1], "run name")
    rest = parts[2:]
    try:
        if rest[0] == "transitions" and len(rest) == 2:
            return ParsedKey(run, "transitions", None, validate_name(rest[1], "actor id"))
        if rest == ["weights"]:
            return ParsedKey(run, "weights")
        if rest == ["weights", "latest"]:
            return ParsedKey(run, "weights_latest")
        if rest == ["config"]:
            return ParsedKey(run, "config")
        if rest[0] == "stats" and len(rest) == 3:
            return ParsedKey(run, "stats", _validate_stats_kind(rest[1]),
                             validate_name(rest[2], "source id"))
        if rest[0] == "alive" and len(rest) == 3:
            return ParsedKey(run, "alive", validate_role(rest[1]),
                             validate_name(rest[2], "process id"))
    except KeyExprError as exc:
        raise KeyExprError(f"key {text!r}: {exc}") from None
    raise KeyExprError(f"key {text!r} is not a cogexplore key (expected transitions/<actor>, "
                       "weights, weights/latest, config, stats/<kind>/<id> or alive/<role>/<id>)")


ROBOT_CHUNK = "@robot"
"""Second chunk of every robot key: a verbatim chunk (``@...``) matches only itself, so no run's
wildcard (``cogexplore/*/...``) ever reaches a robot's keys, and no run name (which cannot start
with ``@``) collides with them."""


@dataclass(frozen=True)
class RobotKeys:
    """cogexplore's own keys beside a ROS 2 robot (``cogexplore drive`` and ``sim-robot``); the ROS 2
    topics themselves are spelled by ``shared.ros2.formats``::

        cogexplore/@robot/<robot>/diagnostics   DriveDiagnostics of the drive node, one per decision
        cogexplore/@robot/<robot>/status        SimRobotStatus of the simulated robot, one per control period
        cogexplore/@robot/<robot>/reset         any put: a new episode (drive forgets its previous
                                                command; sim-robot goes back to its start pose)
    """

    robot: str

    def __post_init__(self) -> None:
        validate_name(self.robot, "robot name")

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{ROBOT_CHUNK}/{self.robot}"

    @property
    def diagnostics(self) -> str:
        return f"{self.prefix}/diagnostics"

    @property
    def status(self) -> str:
        return f"{self.prefix}/status"

    @property
    def reset(self) -> str:
        return f"{self.prefix}/reset"
