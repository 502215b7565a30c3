"""What an evaluation runs with: a checkpoint or a baseline resolved into a policy, a sensor, an
env and a world (``cogexplore evaluate``, ``report``, ``experiment``, ``model select``)."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.config import EnvConfig, SensorConfig, load_preset, parse_override
from shared.errors import CogexploreError
from shared.evaluation import (
    BASELINE_POLICIES,
    DEFAULT_WORLD,
    POLICY_NAMES,
    PROTOCOL_SENSOR_FIELDS,
    TEST_SEED,
)
from shared.evaluation.policies import RandomPolicy, make_policy
from shared.evaluation.protocol import PROTOCOL_ENV_FIELDS, PolicyFn
from shared.learning.checkpoints import LoadedModel, ensemble_models, load_model, load_supervised_model

log = logging.getLogger("cogexplore.evaluate")


class EvaluateError(CogexploreError):
    """A checkpoint that cannot be found or used, or options that do not fit together."""


@dataclass(frozen=True)
class EvalSetup:
    """What an evaluation runs with, resolved from the options."""

    policy: str
    policy_fn: PolicyFn
    sensor_cfg: SensorConfig
    env_cfg: EnvConfig
    world: str
    model: LoadedModel | None
    """The network played (a Q-value ensemble when ``setup_evaluation`` was given ``ensemble``); None
    for a baseline."""

    def meta(self) -> dict[str, Any]:
        out: dict[str, Any] = {"policy": self.policy,
                               "model": self.model.label if self.model is not None else self.policy}
        if self.model is not None:
            out.update(self.model.meta())
        return out | self.draws_meta()

    def draws_meta(self) -> dict[str, Any]:
        """What stored results must also match to be this policy's episodes: the random baseline's
        draws (per episode now; a file of the earlier draws holds other episodes)."""
        return {"random_draws": RandomPolicy.DRAWS} if self.policy == "random" else {}


def setup_evaluation(policy: str | None, checkpoint: str | Path | None = None, *, world: str | None = None,
                     preset: str | None = None, overrides: Sequence[str] = (), seed: int = TEST_SEED,
                     device: str = "auto", model: LoadedModel | None = None,
                     ensemble: Sequence[str | Path | LoadedModel] = ()) -> EvalSetup:
    """Resolve policy, network, sensor, env and world (shared by ``evaluate`` and ``report``).
    ``ensemble``: further checkpoints (or loaded models) whose Q-values the greedy policy averages
    with the checkpoint's (``EvalSetup.model`` is then their ensemble); the environment stays the
    checkpoint's."""
    policy = policy or ("greedy" if (checkpoint is not None or model is not None) else None)
    if policy is None:
        raise EvaluateError("give --checkpoint (greedy policy) or --policy random|reactive")
    if policy not in POLICY_NAMES:
        raise EvaluateError(f"unknown policy {policy!r}; known: {list(POLICY_NAMES)}")
    if policy in ("greedy", "sl", "rl") and checkpoint is None and model is None:
        raise EvaluateError(f"the {policy} policy needs --checkpoint (baselines without one: --policy "
                            + " or ".join(BASELINE_POLICIES) + ")")
    if model is None and checkpoint is not None:
        model = load_supervised_model(checkpoint, device) if policy == "sl" else load_model(checkpoint, device)
    if ensemble and policy != "greedy":
        raise EvaluateError(f"an ensemble plays the greedy policy, not {policy}")
    members = tuple(m if isinstance(m, LoadedModel) else load_model(m, device) for m in ensemble)
    if members and model is not None:  # the episodes run in the checkpoint's environment: one robot
        model = ensemble_models([model, *members])
    if model is not None and (policy == "sl") != (model.kind == "supervised"):
        raise EvaluateError(f"{model.path} is a {model.kind} file: the sl policy takes a supervised model "
                            "(`cogexplore pretrain`), the other policies a Q-network checkpoint")
    if policy == "rl" and model is not None:
        if model.name is None:
            model = dataclasses.replace(model, name="RL")
        dqn = model.run_config.dqn if model.run_config is not None else None
        if dqn is not None and dqn.conv_lr_scale != 0:
            log.warning("%s was trained with dqn.conv_lr_scale = %g: not the RL baseline's frozen conv layers",
                        model.path, dqn.conv_lr_scale)
    if preset is not None:
        base = load_preset(preset)
    elif model is not None and model.run_config is not None:
        base = model.run_config
    else:
        base = load_preset("paper")
    if model is not None:
        base = dataclasses.replace(base, sensor=model.net.sensor_cfg,
                                   model=getattr(model.net, "model_cfg", base.model))
    parsed = dict(parse_override(o) for o in overrides)
    bad = sorted(k for k in parsed if not k.startswith(("sensor.", "env.")))
    if bad:
        raise EvaluateError(f"evaluate only takes sensor.* and env.* overrides, got {bad}")
    owned = sorted(k for k in parsed if k in {f"sensor.{f}" for f in PROTOCOL_SENSOR_FIELDS})
    if owned:
        raise EvaluateError(f"{', '.join(owned)}: the test protocol sets the sensor's noise; use --protocol or "
                            "--sensor-noise-m")
    # The protocol's own env fields (protocol_env_config): an override would silently do nothing
    # (--set env.world=corridor played the checkpoint's world; training's jitter never reached a test).
    protocol_owned = sorted(k for k in parsed if k.startswith("env.") and k[4:] in PROTOCOL_ENV_FIELDS)
    if protocol_owned:
        raise EvaluateError("; ".join(f"{k}: {PROTOCOL_ENV_FIELDS[k[4:]]}" for k in protocol_owned))
    cfg = base.with_overrides(parsed) if parsed else base
    if model is not None and (cfg.sensor.width, cfg.sensor.height) != (model.net.sensor_cfg.width,
                                                                        model.net.sensor_cfg.height):
        raise EvaluateError(f"the network takes {model.net.sensor_cfg.width}x{model.net.sensor_cfg.height} "
                            "images; the sensor size cannot be overridden")
    # the camera itself: a run's training noise (robust-40x30's) is no part of it, the protocol adds its own
    sensor = cfg.sensor.noise_free()
    fn = make_policy(policy, net=model.net if model is not None else None, sensor_cfg=sensor, seed=seed,
                     env_cfg=cfg.env)
    world_name = world or (model.run_config.env.world if model is not None and model.run_config is not None
                           else DEFAULT_WORLD)
    return EvalSetup(policy, fn, sensor, cfg.env, world_name, model if policy in ("greedy", "sl", "rl") else None)
