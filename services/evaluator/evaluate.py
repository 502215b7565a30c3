"""``cogexplore evaluate``: the paper's test protocol on a checkpoint or a baseline policy.

    cogexplore evaluate --checkpoint runs/exp1 --json out.json --rrd out.rrd
    cogexplore evaluate --policy random --world paper-indoor --episodes-per-start 2 --json out.json

Greedy episodes (dropout off) at the TEST speed table from every start pose of the world,
``--episodes-per-start`` each, capped at ``--max-steps`` moving steps; results per start and
overall (``results.py``) go to the JSON, the steps to an optional Rerun recording.

``--checkpoint`` accepts what ``shared.checkpoint`` writes: a checkpoint file, a checkpoint
directory (its ``latest``, falling back to the newest that loads), a run folder (its
``checkpoints/``), or a weights-only export. The network's model and sensor configs come from
the file; the environment's (robot radius, control period, collision distance) from the run
config stored in a checkpoint, else the preset. ``load_model`` and ``evaluate_policy`` are the
pieces the evaluator service and the report reuse.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import os
import sys
import threading
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

os.environ.setdefault("RERUN_ANALYTICS", "0")  # offline machines: never phone home

import torch

from services.evaluator.policies import BASELINE_POLICIES, POLICY_NAMES, PolicyFn, make_policy
from services.evaluator.results import (
    PAPER_EPISODES_PER_START,
    PAPER_MAX_STEPS,
    EvalResults,
    aggregate,
    run_protocol,
    save_results,
    table_markdown,
)
from shared.config import ConfigError, EnvConfig, RunConfig, SensorConfig, from_dict, load_preset, parse_override
from shared.world import load_world

log = logging.getLogger("cogexplore.evaluate")

DEFAULT_WORLD = "paper-indoor"


class EvaluateError(ValueError):
    """A checkpoint that cannot be found or used, or options that do not fit together."""


class EvaluationCancelled(RuntimeError):
    """The ``stop`` event was set while an evaluation ran."""


# ---------------------------------------------------------------------------------------------
# Checkpoints and weights
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LoadedModel:
    """A network ready for greedy evaluation, and where it came from."""

    net: Any
    """The QNetwork (eval mode, on the requested device)."""
    path: Path
    """The file actually loaded (a run folder resolves to its latest checkpoint)."""
    kind: str
    """'checkpoint' or 'weights' (a weights-only export)."""
    policy_version: int
    fingerprint: str
    weights_sha256: str
    """Digest of the online weights: tells one checkpoint from another whatever its path."""
    run_config: RunConfig | None
    """The run config stored in a checkpoint (None for weights-only exports)."""

    @property
    def label(self) -> str:
        """A short name for tables: ``<run or file>@<policy_version>``."""
        stem = self.path.parent.parent.name if self.path.parent.name == "checkpoints" else self.path.stem
        return f"{stem}@{self.policy_version}"

    def meta(self) -> dict[str, Any]:
        return {"checkpoint": str(self.path), "checkpoint_kind": self.kind, "policy_version": self.policy_version,
                "fingerprint": self.fingerprint, "weights_sha256": self.weights_sha256}


def weights_sha256(net: torch.nn.Module) -> str:
    """SHA-256 (16 hex digits) over the network's parameter names and bytes (NCHW order)."""
    from shared.model import weights_to_tensors

    h = hashlib.sha256()
    for name, t in sorted(weights_to_tensors(net).items()):
        h.update(name.encode())
        h.update(t.to(torch.float32).contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def resolve_checkpoint(source: str | Path) -> Path | None:
    """The file a checkpoint argument names: a file as is; a directory through its
    ``latest`` pointer; a run folder through ``<run>/checkpoints``. None for a checkpoint
    directory that exists but holds no checkpoint yet."""
    from shared.checkpoint import CheckpointManager

    p = Path(source)
    if p.is_file():
        return p
    if not p.is_dir():
        raise EvaluateError(f"checkpoint {str(source)!r} does not exist (give a checkpoint file, a checkpoint "
                            "directory, a run folder or a weights export)")
    directory = p / "checkpoints" if (p / "checkpoints").is_dir() else p
    manager = CheckpointManager(directory)
    if manager.latest() is None and not manager.checkpoints():
        return None
    return manager.latest() or manager.checkpoints()[-1]


def load_model(source: str | Path, device: str | torch.device = "cpu") -> LoadedModel:
    """Load a checkpoint file/dir, run folder or weights export into a QNetwork (eval mode).

    A directory's ``latest`` checkpoint is used, or the newest older one that loads when it is
    corrupt (each skipped file is logged)."""
    from shared.checkpoint import CheckpointError, CheckpointManager, load_checkpoint, load_exported_weights
    from shared.model import ModelError, QNetwork, architecture_fingerprint, load_tensors, resolve_device

    try:
        dev = resolve_device(device)
    except ModelError as exc:
        raise EvaluateError(str(exc)) from None
    path = resolve_checkpoint(source)
    if path is None:
        raise EvaluateError(f"{source} holds no checkpoint yet")
    p = Path(source)
    errors: list[str] = []
    ckpt = None
    if p.is_dir():
        manager = CheckpointManager(path.parent)
        ckpt = manager.load_latest()
        for skipped in manager.skipped:
            log.warning("skipped checkpoint: %s", skipped)
        if ckpt is None:
            raise EvaluateError(f"no loadable checkpoint in {path.parent}: " + "; ".join(manager.skipped))
    else:
        try:
            ckpt = load_checkpoint(path)
        except CheckpointError as exc:
            errors.append(str(exc))
    if ckpt is not None:
        meta = ckpt.agent_meta
        run_config = None
        if ckpt.config:
            try:
                run_config = from_dict(ckpt.config)
            except ConfigError as exc:
                raise EvaluateError(f"{ckpt.path}: its stored run config is invalid: {exc}") from None
        try:
            model_cfg = run_config.model if "model" not in meta else _cfg(meta["model"], "model")
            sensor_cfg = run_config.sensor if "sensor" not in meta else _cfg(meta["sensor"], "sensor")
        except AttributeError:
            raise EvaluateError(f"{ckpt.path} stores neither the model/sensor config nor a run config") from None
        net = QNetwork(model_cfg, sensor_cfg)
        online = {k[len("online."):]: v for k, v in ckpt.tensors.items() if k.startswith("online.")}
        try:
            load_tensors(net, online)
        except ModelError as exc:
            raise EvaluateError(f"{ckpt.path}: the online weights do not fit the stored config: {exc}") from None
        net = net.to(dev).eval()
        return LoadedModel(net, ckpt.path, "checkpoint", ckpt.policy_version, architecture_fingerprint(net),
                           weights_sha256(net), run_config)
    try:
        net, meta = load_exported_weights(path, dev)
    except CheckpointError as exc:
        errors.append(str(exc))
        raise EvaluateError(f"{path} is neither a checkpoint nor a weights export: " + " | ".join(errors)) from None
    return LoadedModel(net, path, "weights", int(meta.get("policy_version", 0)), architecture_fingerprint(net),
                       weights_sha256(net), None)


def _cfg(data: Mapping[str, Any], section: str) -> Any:
    try:
        return getattr(from_dict({section: dict(data)}), section)
    except ConfigError as exc:
        raise EvaluateError(f"stored {section} config is invalid: {exc}") from None


# ---------------------------------------------------------------------------------------------
# One evaluation
# ---------------------------------------------------------------------------------------------


def protocol_env_config(base: EnvConfig | None, world: str, max_steps: int) -> EnvConfig:
    """The protocol's environment: ``base``'s robot and task, the given world, the TEST speed
    table, every start (none fixed) and a step cap no shorter than the protocol's."""
    return dataclasses.replace(base or EnvConfig(), world=world, speed_table="test",
                               max_episode_steps=max_steps, start_index=None)


def evaluate_policy(policy_fn: PolicyFn, *, world: str, sensor_cfg: SensorConfig, env_cfg: EnvConfig | None = None,
                    episodes_per_start: int = PAPER_EPISODES_PER_START, max_steps: int = PAPER_MAX_STEPS,
                    seed: int = 0, starts: Sequence[int] | None = None, rrd: str | Path | None = None,
                    image_every: int = 1, policy_version: int = 0, recording_name: str | None = None,
                    progress: bool = True, meta: Mapping[str, Any] | None = None,
                    stop: threading.Event | None = None) -> EvalResults:
    """Run the protocol with ``policy_fn`` and return its results (optionally recorded).

    ``rrd``: write a Rerun recording there (every ``image_every``-th depth image, every
    step's pose, Q-values/scores, command and trajectory, and the summary at update
    ``policy_version``). ``stop``: when set, the run ends within one step with
    :class:`EvaluationCancelled` (the partial recording is deleted).
    """
    from shared.env import ExploreEnv

    cfg = protocol_env_config(env_cfg, world, max_steps)
    world_obj = load_world(world)  # fail early, with the world's own error, before any env is built

    def make_env() -> ExploreEnv:
        return ExploreEnv(cfg, sensor_cfg, world=world_obj)

    fn = policy_fn
    if stop is not None:
        def fn(depth_m: Any) -> Any:
            if stop.is_set():
                raise EvaluationCancelled("evaluation cancelled")
            return policy_fn(depth_m)

    recorder = None
    if rrd is not None:
        from services.evaluator.rerun_log import EvalRecorder
        from shared.maps import occupancy_grid

        recorder = EvalRecorder(rrd, world_obj, occupancy_grid(world_obj), sensor_cfg, image_every=image_every,
                                recording_name=recording_name, robot_radius_m=cfg.robot_radius_m)
    full_meta = {"sensor": asdict(sensor_cfg), "env": {k: v for k, v in asdict(cfg).items() if k != "start_index"}}
    full_meta.update(meta or {})
    ok = False
    try:
        results = run_protocol(fn, make_env, starts=starts, episodes_per_start=episodes_per_start,
                               max_steps=max_steps, seed=seed, recorder=recorder, progress=progress,
                               meta=full_meta)
        if recorder is not None:
            recorder.log_evaluation(policy_version, results.summary)
        ok = True
        return results
    finally:
        if recorder is not None:
            recorder.close()
            if not ok and recorder.path is not None:
                recorder.path.unlink(missing_ok=True)


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``cogexplore evaluate``."""
    parser.add_argument("--checkpoint", metavar="CKPT",
                        help="checkpoint file or directory, run folder, or weights export (greedy policy)")
    parser.add_argument("--policy", choices=POLICY_NAMES, default=None,
                        help="greedy (the checkpoint's; default with --checkpoint), random or reactive "
                             "(baselines, no checkpoint needed)")
    parser.add_argument("--world", default=None,
                        help="built-in world, procedural:<seed> or an MJCF file (default: the checkpoint's "
                             f"training world, else {DEFAULT_WORLD})")
    parser.add_argument("--episodes-per-start", type=int, default=PAPER_EPISODES_PER_START,
                        help=f"episodes from each start pose (default {PAPER_EPISODES_PER_START})")
    parser.add_argument("--max-steps", type=int, default=PAPER_MAX_STEPS,
                        help=f"moving steps per episode at most (default {PAPER_MAX_STEPS})")
    parser.add_argument("--starts", type=int, nargs="+", default=None, metavar="I",
                        help="only these start indices (0-based; default: all)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes and the random policy")
    parser.add_argument("--json", dest="json_out", metavar="PATH", help="write the results JSON here")
    parser.add_argument("--rrd", metavar="PATH", help="write a Rerun recording here")
    parser.add_argument("--image-every", type=int, default=1, metavar="N",
                        help="record every N-th depth image only (default 1)")
    parser.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda, cuda:N (default auto)")
    parser.add_argument("--preset", default=None,
                        help="config preset for a baseline's sensor and env (default: the checkpoint's config, "
                             "else paper)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        help="override a sensor./env. field, e.g. --set sensor.noise_std_m=0.02 (repeatable)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


@dataclass(frozen=True)
class EvalSetup:
    """What an evaluation runs with, resolved from the options."""

    policy: str
    policy_fn: PolicyFn
    sensor_cfg: SensorConfig
    env_cfg: EnvConfig
    world: str
    model: LoadedModel | None

    def meta(self) -> dict[str, Any]:
        out: dict[str, Any] = {"policy": self.policy,
                               "model": self.model.label if self.model is not None else self.policy}
        if self.model is not None:
            out.update(self.model.meta())
        return out


def setup_evaluation(policy: str | None, checkpoint: str | Path | None = None, *, world: str | None = None,
                     preset: str | None = None, overrides: Sequence[str] = (), seed: int = 0,
                     device: str = "auto", model: LoadedModel | None = None) -> EvalSetup:
    """Resolve policy, network, sensor, env and world (shared by ``evaluate`` and ``report``)."""
    policy = policy or ("greedy" if (checkpoint is not None or model is not None) else None)
    if policy is None:
        raise EvaluateError("give --checkpoint (greedy policy) or --policy random|reactive")
    if policy not in POLICY_NAMES:
        raise EvaluateError(f"unknown policy {policy!r}; known: {list(POLICY_NAMES)}")
    if policy == "greedy" and checkpoint is None and model is None:
        raise EvaluateError("the greedy policy needs --checkpoint (baselines: --policy "
                            + " or ".join(BASELINE_POLICIES) + ")")
    if model is None and checkpoint is not None:
        model = load_model(checkpoint, device)
    if preset is not None:
        base = load_preset(preset)
    elif model is not None and model.run_config is not None:
        base = model.run_config
    else:
        base = load_preset("paper")
    if model is not None:
        base = dataclasses.replace(base, sensor=model.net.sensor_cfg, model=model.net.model_cfg)
    parsed = dict(parse_override(o) for o in overrides)
    bad = sorted(k for k in parsed if not k.startswith(("sensor.", "env.")))
    if bad:
        raise EvaluateError(f"evaluate only takes sensor.* and env.* overrides, got {bad}")
    cfg = base.with_overrides(parsed) if parsed else base
    if model is not None and (cfg.sensor.width, cfg.sensor.height) != (model.net.sensor_cfg.width,
                                                                        model.net.sensor_cfg.height):
        raise EvaluateError(f"the network takes {model.net.sensor_cfg.width}x{model.net.sensor_cfg.height} "
                            "images; the sensor size cannot be overridden")
    fn = make_policy(policy, net=model.net if model is not None else None, sensor_cfg=cfg.sensor, seed=seed)
    world_name = world or (model.run_config.env.world if model is not None and model.run_config is not None
                           else DEFAULT_WORLD)
    return EvalSetup(policy, fn, cfg.sensor, cfg.env, world_name, model if policy == "greedy" else None)


def run_evaluate(args: argparse.Namespace) -> int:
    """``cogexplore evaluate``: returns a process exit status."""
    try:
        setup = setup_evaluation(args.policy, args.checkpoint, world=args.world, preset=args.preset,
                                 overrides=args.overrides, seed=args.seed, device=args.device)
        log.info("evaluating %s on %s", setup.meta()["model"], setup.world)
        results = evaluate_policy(
            setup.policy_fn, world=setup.world, sensor_cfg=setup.sensor_cfg, env_cfg=setup.env_cfg,
            episodes_per_start=args.episodes_per_start, max_steps=args.max_steps, seed=args.seed,
            starts=args.starts, rrd=args.rrd, image_every=args.image_every,
            policy_version=setup.model.policy_version if setup.model else 0,
            recording_name=f"evaluate {setup.meta()['model']} on {setup.world}", progress=not args.quiet,
            meta=setup.meta())
    except ValueError as exc:  # every error of bad input here is one (checkpoint, world, config, policy)
        print(f"cogexplore evaluate: error: {exc}", file=sys.stderr)
        return 2
    if args.json_out:
        save_results(results, args.json_out)
    summary = aggregate(results.episodes)["overall"]
    print(table_markdown({setup.meta()["model"]: results}), end="")
    print(json.dumps({"model": setup.meta()["model"], "world": setup.world, **{k: summary[k] for k in (
        "episodes", "mean_steps", "mean_distance_m", "mean_path_length_m", "mean_coverage_pct",
        "collisions", "reached_cap")}}, default=float))
    for what, path in (("results", args.json_out), ("recording", args.rrd)):
        if path:
            print(f"{what}: {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="cogexplore evaluate", description=__doc__.split("\n\n")[0])
    add_evaluate_arguments(parser)
    return run_evaluate(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
