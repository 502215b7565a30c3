"""``cogexplore evaluate``: the paper's test protocol on a checkpoint or a baseline policy.

    cogexplore evaluate --checkpoint runs/exp1 --json out.json --rrd out.rrd
    cogexplore evaluate --policy random --world paper-indoor --episodes-per-start 2 --json out.json
    cogexplore evaluate --checkpoint runs/exp1 --rerun-connect rerun+http://127.0.0.1:9876/proxy
    cogexplore evaluate --checkpoint runs/exp1 --rerun-serve     # then open the printed address

Greedy episodes (dropout off) at the TEST speed table from every start pose of the world,
``--episodes-per-start`` each, capped at ``--max-steps`` moving steps; results per start and
overall (``results.py``) go to the JSON, the steps to an optional Rerun recording: a file
(``--rrd``), a running viewer (``--rerun-connect URL``, e.g. one started with ``rerun``; a
viewer that does not answer is warned about and skipped) or a gRPC server plus web viewer that
this command hosts (``--rerun-serve``; it prints the address to open and keeps serving after
the evaluation until Ctrl-C, or for ``--rerun-serve-seconds``).

``--checkpoint`` accepts what ``shared.checkpoint`` writes: a checkpoint file, a checkpoint
directory (its ``latest``, falling back to the newest that loads), a run folder (its
``checkpoints/``), or a weights-only export. The network's model and sensor configs come from
the file; the environment's (robot radius, control period, collision distance) from the run
config stored in a checkpoint, else the preset. ``load_model`` and ``evaluate_policy`` are the
pieces the evaluator service and the report reuse.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import logging
import os
import sys
import threading
import time
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
from shared.config import (
    ConfigError,
    EnvConfig,
    RunConfig,
    SensorConfig,
    from_dict,
    load_preset,
    parse_override,
    parse_world_list,
)
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
    name: str | None = None
    """A fixed table name (the baselines: 'SL', 'RL'); None: derived from the path."""
    averaged_from: tuple[dict[str, Any], ...] = ()
    """For a mean of several checkpoints (:func:`average_models`): each source and its update."""

    @property
    def label(self) -> str:
        """A short name for tables: ``name``, else ``<run or file>@<policy_version>``."""
        if self.name is not None:
            return self.name
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
    directory that exists but holds no checkpoint yet. ``pretrained`` (or ``pretrained:drl``,
    ``pretrained:sl``) names a model shipped with the package."""
    from shared.checkpoint import CheckpointError, CheckpointManager, pretrained_path

    try:
        shipped = pretrained_path(source)
    except CheckpointError as exc:
        raise EvaluateError(str(exc)) from None
    if shipped is not None:
        return shipped
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


def average_models(models: Sequence[LoadedModel]) -> LoadedModel:
    """The element-wise mean of several loaded models' weights (one run's later checkpoints),
    labelled with the last one's file, update and run config; one model is returned as is."""
    from shared.model import ModelError, average_weights, load_tensors

    if len(models) == 1:
        return models[0]
    if not models:
        raise EvaluateError("nothing to average")
    last = models[-1]
    net = copy.deepcopy(last.net)
    try:
        load_tensors(net, average_weights([m.net for m in models]))
    except ModelError as exc:
        raise EvaluateError(f"cannot average these checkpoints: {exc}") from None
    return dataclasses.replace(last, net=net.eval(), weights_sha256=weights_sha256(net),
                               averaged_from=tuple({"source": str(m.path), "policy_version": m.policy_version}
                                                   for m in models))


def load_supervised_model(source: str | Path, device: str | torch.device = "cpu") -> LoadedModel:
    """Load a supervised model file (``cogexplore pretrain``) for the ``sl`` policy, labelled SL."""
    from shared.model import ModelError, architecture_fingerprint, resolve_device
    from shared.supervised import SupervisedError, load_supervised

    path = resolve_checkpoint("pretrained:sl" if str(source) == "pretrained" else source)
    if path is None or not path.is_file():
        raise EvaluateError(f"the sl policy needs --checkpoint <supervised model .safetensors> (written by "
                            f"`cogexplore pretrain`); {str(source)!r} is not a file")
    try:
        net, _meta = load_supervised(path, resolve_device(device))
    except (SupervisedError, ModelError) as exc:
        raise EvaluateError(str(exc)) from None
    return LoadedModel(net, path, "supervised", 0, architecture_fingerprint(net), weights_sha256(net), None,
                       name="SL")


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
                    stop: threading.Event | None = None, rerun_connect: str | None = None,
                    recorder: Any = None) -> EvalResults:
    """Run the protocol with ``policy_fn`` and return its results (optionally recorded).

    ``rrd``: write a Rerun recording there (every ``image_every``-th depth image, every
    step's pose, Q-values/scores, command and trajectory, and the summary at update
    ``policy_version``). ``rerun_connect``: also stream it live to the viewer at that URL
    (``rerun+http://host:9876/proxy``); one that does not answer is skipped with a warning.
    ``recorder``: an ``EvalRecorder`` the caller opened (see :func:`open_recorder`) and
    closes, instead of ``rrd``/``rerun_connect``. ``stop``: when set, the run ends within
    one step with :class:`EvaluationCancelled` (the partial recording is deleted).
    """
    from shared.env import ExploreEnv

    if recorder is not None and (rrd is not None or rerun_connect is not None):
        raise EvaluateError("pass a recorder or rrd/rerun_connect, not both")
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
        if hasattr(policy_fn, "reset"):
            fn.reset = policy_fn.reset  # type: ignore[attr-defined]

    owns_recorder = recorder is None
    if recorder is None:
        rerun_connect = live_viewer_url(rerun_connect, rrd is not None)
    if recorder is None and (rrd is not None or rerun_connect is not None):
        recorder = open_recorder(world_obj, sensor_cfg, cfg, rrd, connect_url=rerun_connect,
                                 image_every=image_every, recording_name=recording_name)
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
        if recorder is not None and owns_recorder:
            recorder.close()
            if not ok and recorder.path is not None:
                recorder.path.unlink(missing_ok=True)


def live_viewer_url(url: str | None, writes_file: bool = False) -> str | None:
    """``url`` when a Rerun viewer answers there, else None with a warning: Rerun's own client
    would stall 5 s on it and then drop everything. EvaluateError when ``url`` is malformed."""
    if url is None:
        return None
    from services.evaluator.rerun_log import parse_viewer_url, viewer_reachable

    try:
        parse_viewer_url(url)
    except ValueError as exc:
        raise EvaluateError(str(exc)) from None
    if viewer_reachable(url):
        return url
    log.warning("no Rerun viewer answers at %s: not streaming this evaluation%s", url,
                " (the .rrd file is written)" if writes_file else "")
    return None


def open_recorder(world: Any, sensor_cfg: SensorConfig, env_cfg: EnvConfig, rrd: str | Path | None = None, *,
                  connect_url: str | None = None, serve: bool = False, serve_port: int = 9876,
                  web_port: int = 9090, image_every: int = 1, recording_name: str | None = None) -> Any:
    """An ``EvalRecorder`` for the protocol in ``world`` (a World or its name): a file, a live
    viewer, a hosted gRPC server + web viewer (``serve``), or several; EvaluateError for bad
    options (a malformed URL, a port in use)."""
    from services.evaluator.rerun_log import EvalRecorder
    from shared.maps import occupancy_grid

    world_obj = load_world(world) if isinstance(world, str) else world
    try:
        return EvalRecorder(rrd, world_obj, occupancy_grid(world_obj), sensor_cfg, connect_url=connect_url,
                            serve=serve, serve_port=serve_port, serve_web=serve, web_port=web_port,
                            image_every=image_every, recording_name=recording_name,
                            robot_radius_m=env_cfg.robot_radius_m)
    except ValueError as exc:
        raise EvaluateError(str(exc)) from None


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``cogexplore evaluate``."""
    parser.add_argument("--checkpoint", metavar="CKPT",
                        help="checkpoint file or directory, run folder, weights export, or `pretrained` "
                             "(the shipped DRL model; with --policy sl the shipped supervised model)")
    parser.add_argument("--policy", choices=POLICY_NAMES, default=None,
                        help="greedy (the checkpoint's; default with --checkpoint), random or reactive "
                             "(baselines, no checkpoint needed), sl (--checkpoint: a supervised model from "
                             "`cogexplore pretrain`) or rl (--checkpoint: a frozen-conv Q-learning run; "
                             "greedy, labelled RL)")
    parser.add_argument("--world", default=None,
                        help="built-in world, procedural:<seed> or an MJCF file (default: the checkpoint's "
                             f"training world, else {DEFAULT_WORLD}); several, comma-separated or as seed "
                             "ranges (procedural:101-110), are evaluated one after the other and averaged")
    parser.add_argument("--episodes-per-start", type=int, default=PAPER_EPISODES_PER_START,
                        help=f"episodes from each start pose (default {PAPER_EPISODES_PER_START})")
    parser.add_argument("--max-steps", type=int, default=PAPER_MAX_STEPS,
                        help=f"moving steps per episode at most (default {PAPER_MAX_STEPS})")
    parser.add_argument("--starts", type=int, nargs="+", default=None, metavar="I",
                        help="only these start indices (0-based; default: all)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes and the random policy")
    parser.add_argument("--json", dest="json_out", metavar="PATH",
                        help="write the results JSON here (several worlds: one file each, PATH-<world>.json)")
    parser.add_argument("--rrd", metavar="PATH", help="write a Rerun recording here")
    parser.add_argument("--image-every", type=int, default=1, metavar="N",
                        help="record every N-th depth image only (default 1)")
    live = parser.add_argument_group("Rerun live", "watch the evaluation while it runs (with or without --rrd)")
    live.add_argument("--rerun-connect", metavar="URL",
                      help="stream to a running Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy (start one "
                           "with `rerun`); a viewer that does not answer is skipped with a warning")
    live.add_argument("--rerun-serve", action="store_true",
                      help="host a Rerun gRPC server and web viewer, print the address to open, and keep serving "
                           "after the evaluation until Ctrl-C")
    live.add_argument("--rerun-port", type=int, default=9876, metavar="PORT",
                      help="gRPC port of --rerun-serve (default 9876)")
    live.add_argument("--rerun-web-port", type=int, default=9090, metavar="PORT",
                      help="web viewer port of --rerun-serve (default 9090)")
    live.add_argument("--rerun-serve-seconds", type=float, default=None, metavar="S",
                      help="with --rerun-serve: stop serving S seconds after the evaluation (scripts, tests)")
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
    if policy in ("greedy", "sl", "rl") and checkpoint is None and model is None:
        raise EvaluateError(f"the {policy} policy needs --checkpoint (baselines without one: --policy "
                            + " or ".join(BASELINE_POLICIES) + ")")
    if model is None and checkpoint is not None:
        model = load_supervised_model(checkpoint, device) if policy == "sl" else load_model(checkpoint, device)
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
    cfg = base.with_overrides(parsed) if parsed else base
    if model is not None and (cfg.sensor.width, cfg.sensor.height) != (model.net.sensor_cfg.width,
                                                                        model.net.sensor_cfg.height):
        raise EvaluateError(f"the network takes {model.net.sensor_cfg.width}x{model.net.sensor_cfg.height} "
                            "images; the sensor size cannot be overridden")
    fn = make_policy(policy, net=model.net if model is not None else None, sensor_cfg=cfg.sensor, seed=seed)
    world_name = world or (model.run_config.env.world if model is not None and model.run_config is not None
                           else DEFAULT_WORLD)
    return EvalSetup(policy, fn, cfg.sensor, cfg.env, world_name,
                     model if policy in ("greedy", "sl", "rl") else None)


def _check_live_options(args: argparse.Namespace) -> None:
    serve_seconds = getattr(args, "rerun_serve_seconds", None)
    if serve_seconds is not None and not args.rerun_serve:
        raise EvaluateError("--rerun-serve-seconds needs --rerun-serve")
    if serve_seconds is not None and not serve_seconds >= 0:
        raise EvaluateError(f"--rerun-serve-seconds must be >= 0, got {serve_seconds}")
    if args.rerun_serve and args.rerun_port == args.rerun_web_port:
        raise EvaluateError(f"--rerun-port and --rerun-web-port are both {args.rerun_port}")
    if args.rerun_connect:
        from services.evaluator.rerun_log import parse_viewer_url

        try:
            parse_viewer_url(args.rerun_connect)
        except ValueError as exc:
            raise EvaluateError(f"--rerun-connect: {exc}") from None


def _serve_until_stopped(seconds: float | None) -> None:
    """Keep the process (and with it the Rerun servers) up for ``seconds``, or until SIGINT/SIGTERM."""
    from services.common import stop_event_on_signals

    stop = stop_event_on_signals()  # installed now: Ctrl-C during the evaluation still interrupts it
    deadline = None if seconds is None else time.monotonic() + seconds
    while not stop.is_set():
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            break
        stop.wait(1.0 if left is None else min(left, 1.0))


def _worlds_of(args: argparse.Namespace) -> list[str | None]:
    """--world as a list (None: the checkpoint's own world); several worlds take no recording."""
    if args.world is None:
        return [None]
    try:
        worlds = list(parse_world_list(args.world))
    except ValueError as exc:
        raise EvaluateError(f"--world: {exc}") from None
    if not worlds:
        raise EvaluateError("--world names no world")
    if len(worlds) > 1:
        given = [flag for flag, on in (("--rrd", args.rrd), ("--rerun-connect", args.rerun_connect),
                                       ("--rerun-serve", args.rerun_serve), ("--starts", args.starts)) if on]
        if given:
            raise EvaluateError(f"{', '.join(given)} take one world; --world names {len(worlds)}")
    return worlds


def _json_path(path: str, world: str, several: bool) -> Path:
    from services.evaluator.report import slug

    p = Path(path)
    return p.with_name(f"{p.stem}-{slug(world)}{p.suffix or '.json'}") if several else p


def run_evaluate(args: argparse.Namespace) -> int:
    """``cogexplore evaluate``: returns a process exit status."""
    recorder = None  # only with --rerun-serve, which takes one world
    done: list[tuple[EvalSetup, EvalResults]] = []
    try:
        _check_live_options(args)
        model = None
        for world in _worlds_of(args):
            setup, results, recorder = _evaluate_one(args, world, model)
            done.append((setup, results))
            model = setup.model  # loaded once for every world
    except ValueError as exc:  # every error of bad input here is one (checkpoint, world, config, policy)
        print(f"cogexplore evaluate: error: {exc}", file=sys.stderr)
        return 2
    several = len(done) > 1
    for setup, results in done:
        json_path = _json_path(args.json_out, setup.world, several) if args.json_out else None
        if json_path is not None:
            save_results(results, json_path)
        summary = aggregate(results.episodes)["overall"]
        if several:
            print(f"## {setup.world}")
        print(table_markdown({setup.meta()["model"]: results}), end="")
        print(json.dumps({"model": setup.meta()["model"], "world": setup.world, **{k: summary[k] for k in (
            "episodes", "mean_steps", "mean_distance_m", "mean_path_length_m", "mean_coverage_pct",
            "collisions", "reached_cap")}}, default=float))
        if json_path is not None:
            print(f"results: {json_path}")
    if several:
        per_world = {setup.world: float(results.summary["overall"]["mean_steps"]) for setup, results in done}
        print(json.dumps({"model": done[0][0].meta()["model"], "worlds": len(per_world),
                          "mean_steps_over_worlds": sum(per_world.values()) / len(per_world),
                          "per_world_mean_steps": per_world}))
    if args.rrd:
        print(f"recording: {args.rrd}")
    if recorder is not None:
        try:
            recorder.rec.flush(timeout_sec=30.0)  # everything on disk and in the server while we serve
        except RuntimeError as exc:  # a --rerun-connect viewer that went away
            log.warning("Rerun live stream failed: %s", exc)
        seconds = args.rerun_serve_seconds
        print(f"rerun: serving at {recorder.web_url} " + (f"for {seconds:g} s" if seconds is not None
                                                          else "until Ctrl-C"), flush=True)
        try:
            _serve_until_stopped(seconds)
        finally:
            recorder.close()
    return 0


def _evaluate_one(args: argparse.Namespace, world: str | None, model: LoadedModel | None
                  ) -> tuple[EvalSetup, EvalResults, Any]:
    """One world of ``cogexplore evaluate``: (setup, results, the live-served recorder or None)."""
    setup = setup_evaluation(args.policy, None if model is not None else args.checkpoint, world=world,
                             preset=args.preset, overrides=args.overrides, seed=args.seed, device=args.device,
                             model=model)
    log.info("evaluating %s on %s", setup.meta()["model"], setup.world)
    recording_name = f"evaluate {setup.meta()['model']} on {setup.world}"
    recorder = None
    if args.rerun_serve:
        # Opened here, not in evaluate_policy: the server must outlive the evaluation.
        recorder = open_recorder(setup.world, setup.sensor_cfg,
                                 protocol_env_config(setup.env_cfg, setup.world, args.max_steps), args.rrd,
                                 connect_url=live_viewer_url(args.rerun_connect, args.rrd is not None),
                                 serve=True, serve_port=args.rerun_port,
                                 web_port=args.rerun_web_port, image_every=args.image_every,
                                 recording_name=recording_name)
        print(f"rerun: open {recorder.web_url} in a browser, or run `rerun --connect {recorder.viewer_url}` "
              "(from another machine, put this machine's name in place of localhost/127.0.0.1)", flush=True)
    try:
        results = evaluate_policy(
            setup.policy_fn, world=setup.world, sensor_cfg=setup.sensor_cfg, env_cfg=setup.env_cfg,
            episodes_per_start=args.episodes_per_start, max_steps=args.max_steps, seed=args.seed,
            starts=args.starts, rrd=None if recorder is not None else args.rrd,
            rerun_connect=None if recorder is not None else args.rerun_connect, recorder=recorder,
            image_every=args.image_every, policy_version=setup.model.policy_version if setup.model else 0,
            recording_name=recording_name, progress=not args.quiet, meta=setup.meta())
    except BaseException:
        if recorder is not None:
            recorder.close()
            if recorder.path is not None:
                recorder.path.unlink(missing_ok=True)
        raise
    return setup, results, recorder


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="cogexplore evaluate", description=__doc__.split("\n\n")[0])
    add_evaluate_arguments(parser)
    return run_evaluate(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
