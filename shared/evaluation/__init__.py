"""The test protocols (the paper's Section V-A, and a robust one) and what they run: policies,
results, probe scenes.

``protocol`` runs episodes (``shared.rollout``) and returns ``results``; ``setup`` resolves a
checkpoint or baseline into a policy; ``policies`` are the learned policy and the baselines;
``probes`` are the Table II scenes. The protocols' numbers live here, importable without numpy
(the command line's options read them): the episode counts and :data:`PROTOCOLS`, the named test
conditions (:class:`ProtocolConfig`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from shared.config import ConfigError, SensorConfig, is_finite_number

PAPER_MAX_STEPS = 200
"""Moving steps per test episode at most (the paper's cap)."""
PAPER_EPISODES_PER_START = 10
"""Test episodes from each start pose (the paper's 12 x 10)."""
PAPER_BASELINE_STEPS = {"SL": 14.6, "RL": 20.9}
"""The paper's Table III, mean moving steps of 200 over its 12 starts (Gazebo, 160 x 120 depth):
its supervised and RL baselines."""
PAPER_DRL_STEPS = {500: 9.3, 4000: 21.6, 7500: 27.3, 40000: 92.6}
"""The same table's DRL model after each number of updates."""
DEFAULT_WORLD = "paper-indoor"
"""The world a model without a stored training world is evaluated in."""
POLICY_NAMES: tuple[str, ...] = ("greedy", "random", "reactive", "sl", "rl", "expert")
"""Names ``policies.make_policy`` and ``cogexplore evaluate --policy`` accept."""
BASELINE_POLICIES: tuple[str, ...] = ("random", "reactive", "expert")
"""Policies that need no checkpoint ("expert" reads the map, not the image: a ceiling, not a baseline
a depth policy must beat)."""


PROTOCOL_SENSOR_FIELDS: tuple[str, ...] = ("noise_std_m", "noise_quadratic_per_m", "dropout_prob")
"""The ``SensorConfig`` fields a protocol sets for its episodes (``ProtocolConfig.sensor_<field>``),
whatever the network was trained with: the test's sensor noise is the protocol's."""


@dataclass(frozen=True)
class ProtocolConfig:
    """The conditions of the test episodes: where each starts and what the sensor adds.

    Every episode starts from a world's named start pose, moved by a uniform draw within
    ``start_jitter_m`` in x and y and ``start_jitter_deg`` in heading (a draw whose robot would
    touch an obstacle, or whose first image is nearer than the collision distance plus a margin,
    is drawn again: ``shared.sim.env``), and sees depth with the noise of the ``sensor_*`` fields.
    The draws and the noise are seeded by (seed, start, episode) alone, so two policies meet the
    same ones and a run repeats exactly.

    The named sets (:data:`PROTOCOLS`):

    - ``paper``: the paper's protocol as this simulation can run it: the exact start poses and a
      noiseless sensor, so the ten episodes per start are one episode repeated.
    - ``robust``: what a real robot meets. Nobody places a robot to the millimetre or the
      degree: ±5 cm and ±3° is a careful hand placement (the paper's own protocol ran in Gazebo,
      whose runs are not bit-exact either). The depth noise is a Kinect's axial noise as
      Nguyen et al. (2012) fit it, sigma(z) = 1.2 mm + 1.9 mm/m² · (z − 0.4 m)²: 1.9 mm at 1 m,
      6 mm at 2 m, 14 mm at 3 m and 26 mm at 4 m (the camera's range), in line with Khoshelham
      and Elberink (2012: ~1.5 mm at 1 m growing quadratically to ~4 cm at 5 m). No random pixel
      dropout: a Kinect's missing returns sit on edges and dark or glancing surfaces, not at
      random, and the images already read 0 where nothing is in range.
    """

    name: str
    """``paper``, ``robust`` or ``custom`` (a named set with options overridden)."""
    start_jitter_m: float = 0.0
    """Half-width (m) of the uniform draw added to the start's x and to its y (0: the exact start)."""
    start_jitter_deg: float = 0.0
    """Half-width (degrees) of the uniform draw added to the start's heading."""
    sensor_noise_std_m: float = 0.0
    """``SensorConfig.noise_std_m`` of the test episodes: depth noise sigma (m) at every distance."""
    sensor_noise_quadratic_per_m: float = 0.0
    """``SensorConfig.noise_quadratic_per_m`` of the test episodes: the sigma's growth with distance."""
    sensor_dropout_prob: float = 0.0
    """``SensorConfig.dropout_prob`` of the test episodes: the chance a pixel reads 0."""

    def __post_init__(self) -> None:
        if not (isinstance(self.name, str) and self.name):
            raise ConfigError(f"protocol name must be a non-empty string, got {self.name!r}")
        for name, top in (("start_jitter_m", 2.0), ("start_jitter_deg", 180.0), ("sensor_noise_std_m", 1.0),
                          ("sensor_noise_quadratic_per_m", 1.0)):
            value = getattr(self, name)
            # is_finite_number: a results file's integer of hundreds of digits is refused, not an OverflowError
            if not (is_finite_number(value) and 0 <= value <= top):
                raise ConfigError(f"protocol {self.name!r}: {name} = {value!r} is invalid: a number in [0, {top:g}]")
        p = self.sensor_dropout_prob
        if not (is_finite_number(p) and 0 <= p < 1):
            raise ConfigError(f"protocol {self.name!r}: sensor_dropout_prob = {p!r} is invalid: a probability "
                              "in [0, 1)")

    @property
    def jittered(self) -> bool:
        """Whether episodes start off the named poses."""
        return self.start_jitter_m > 0 or self.start_jitter_deg > 0

    @property
    def exact(self) -> bool:
        """Whether every episode from a start is the same one: no jitter and a noiseless sensor."""
        return not self.jittered and not any(getattr(self, f"sensor_{f}") for f in PROTOCOL_SENSOR_FIELDS)

    def sensor(self, cfg: SensorConfig) -> SensorConfig:
        """``cfg`` with this protocol's noise (:data:`PROTOCOL_SENSOR_FIELDS`)."""
        return dataclasses.replace(cfg, **{f: getattr(self, f"sensor_{f}") for f in PROTOCOL_SENSOR_FIELDS})

    def overridden(self, *, start_jitter_m: float | None = None, start_jitter_deg: float | None = None,
                   sensor_noise_std_m: float | None = None) -> ProtocolConfig:
        """This set with the command line's overrides (None: keep). A constant
        ``sensor_noise_std_m`` replaces the distance-dependent noise. Named ``custom`` when
        anything changed."""
        changes: dict[str, float] = {}
        if start_jitter_m is not None:
            changes["start_jitter_m"] = start_jitter_m
        if start_jitter_deg is not None:
            changes["start_jitter_deg"] = start_jitter_deg
        if sensor_noise_std_m is not None:
            changes.update(sensor_noise_std_m=sensor_noise_std_m, sensor_noise_quadratic_per_m=0.0)
        out = dataclasses.replace(self, **changes)
        return out if out == self else dataclasses.replace(out, name="custom")

    def describe(self) -> str:
        """One line for reports: the name and what it sets."""
        if self.exact:
            return f"{self.name}: exact start poses, no sensor noise"
        parts = [f"starts ±{100 * self.start_jitter_m:g} cm, ±{self.start_jitter_deg:g}°"
                 if self.jittered else "exact start poses"]
        if self.sensor_noise_quadratic_per_m:
            parts.append(f"depth noise σ = {1000 * self.sensor_noise_std_m:g} mm + "
                         f"{1000 * self.sensor_noise_quadratic_per_m:g} mm/m² · (z − 0.4 m)²")
        elif self.sensor_noise_std_m:
            parts.append(f"depth noise σ = {1000 * self.sensor_noise_std_m:g} mm")
        else:
            parts.append("no depth noise")
        if self.sensor_dropout_prob:
            parts.append(f"{100 * self.sensor_dropout_prob:g} % pixel dropout")
        return f"{self.name}: " + ", ".join(parts)

    def to_dict(self) -> dict[str, Any]:
        """Every field, JSON-ready (the results' ``meta.protocol``)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ProtocolConfig:
        """The inverse of :meth:`to_dict`; ConfigError naming a missing or unknown field."""
        if not isinstance(d, Mapping):
            raise ConfigError(f"a protocol must be an object of its fields, got {type(d).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        if set(d) != names:
            raise ConfigError(f"protocol fields must be {sorted(names)}; missing {sorted(names - set(d))}, "
                              f"unknown {sorted(set(d) - names)}")
        return cls(**d)


PROTOCOLS: dict[str, ProtocolConfig] = {
    "paper": ProtocolConfig("paper"),
    "robust": ProtocolConfig("robust", start_jitter_m=0.05, start_jitter_deg=3.0, sensor_noise_std_m=0.0012,
                             sensor_noise_quadratic_per_m=0.0019),
}
"""The named test protocols (see :class:`ProtocolConfig`), by ``--protocol`` name."""
DEFAULT_PROTOCOL = "robust"
"""The protocol ``cogexplore evaluate``, ``model select`` and the evaluator service run unless told
otherwise: a figure a real robot can reproduce. ``experiment paper`` defaults to ``paper``, the
paper's comparison; ``report`` shows both."""
TEST_SEED = 0
"""Seed of the test episodes' start draws and sensor noise: the default of ``cogexplore evaluate``,
``report``, ``experiment``, the evaluator service and ``model select``'s ``--test`` worlds, so every
reported figure of a model is measured on the same draws."""
SELECTION_SEED = 1
"""Seed of the episodes ``cogexplore model select`` chooses a model on. Not :data:`TEST_SEED`: a
model is never chosen on the start draws and sensor noise its reported figures are measured on."""


def protocol_named(name: str) -> ProtocolConfig:
    """The named set; ConfigError naming the known ones."""
    try:
        return PROTOCOLS[name]
    except KeyError:
        raise ConfigError(f"unknown protocol {name!r}; known: {', '.join(PROTOCOLS)}") from None
