"""``cogexplore evaluate``: the test protocol on a checkpoint or a baseline policy.

    cogexplore evaluate --checkpoint runs/exp1 --json out.json --rrd out.rrd
    cogexplore evaluate --checkpoint pretrained --protocol paper      # exact starts, no noise
    cogexplore evaluate --checkpoint runs/exp1 --ensemble runs/exp2 runs/exp3   # a Q-value ensemble
    cogexplore evaluate --policy random --world paper-indoor --episodes-per-start 2 --json out.json
    cogexplore evaluate --checkpoint runs/exp1 --rerun-connect rerun+http://127.0.0.1:9876/proxy
    cogexplore evaluate --checkpoint runs/exp1 --rerun-serve     # then open the printed address

Greedy episodes (dropout off) at the TEST speed table from every start pose of the world,
``--episodes-per-start`` each, capped at ``--max-steps`` moving steps, under ``--protocol``
(default ``robust``: each start jittered by up to ±5 cm and ±3°, Kinect-like depth noise;
``paper``: the exact starts, no noise; ``--start-jitter-m``, ``--start-jitter-deg`` and
``--sensor-noise-m`` override the set: ``shared.evaluation.PROTOCOLS``); results per start and
overall (``shared.evaluation.results``) go to the JSON, the steps to an optional Rerun recording: a file
(``--rrd``), a running viewer (``--rerun-connect URL``, e.g. one started with ``rerun``; a
viewer that does not answer is warned about and skipped) or a gRPC server plus web viewer that
this command hosts (``--rerun-serve``; it prints the address to open and keeps serving after
the evaluation until Ctrl-C, or for ``--rerun-serve-seconds``; the ``--rrd`` file takes its name
when serving stops).

``--ensemble CKPT ...`` adds checkpoints whose Q-values the greedy policy averages with
``--checkpoint``'s (each fed the command the ensemble chose last): a Q-value ensemble of
independently trained models, played in ``--checkpoint``'s environment.

``--checkpoint`` accepts what ``shared.learning.checkpoints.load_model`` reads: a checkpoint file,
a checkpoint directory (its ``latest``, falling back to the newest that loads), a run folder (its
``checkpoints/``), a weights-only export or ``pretrained``. The network's model and sensor configs
come from the file; the environment's (robot radius, control period, collision distance) from the
run config stored in a checkpoint, else the preset (``shared.evaluation.setup``). The protocol
itself is ``shared.evaluation.protocol``; its recording ``services.viz.rerun``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

os.environ.setdefault("RERUN_ANALYTICS", "0")  # offline machines: never phone home

from services.options import apply_cpu_threads, protocol_from_args
from services.process import stop_event_on_signals
from services.viz.rerun import (
    evaluate_recorded,
    live_viewer_url,
    open_recorder,
    parse_viewer_url,
)
from shared.config import ConfigError, parse_world_list
from shared.evaluation import ProtocolConfig
from shared.evaluation.foresight import ForesightProbe, foresight_summary
from shared.evaluation.protocol import evaluate_policy, protocol_env_config
from shared.evaluation.results import (
    EvalResults,
    aggregate,
    save_results,
    slug,
    table_markdown,
)
from shared.evaluation.setup import EvalSetup, EvaluateError, setup_evaluation
from shared.learning.checkpoints import LoadedModel

log = logging.getLogger("cogexplore.evaluate")


def _check_live_options(args: argparse.Namespace) -> None:
    serve_seconds = getattr(args, "rerun_serve_seconds", None)
    if serve_seconds is not None and not args.rerun_serve:
        raise EvaluateError("--rerun-serve-seconds needs --rerun-serve")
    if serve_seconds is not None and not serve_seconds >= 0:
        raise EvaluateError(f"--rerun-serve-seconds must be >= 0, got {serve_seconds}")
    if args.rerun_serve and args.rerun_port == args.rerun_web_port:
        raise EvaluateError(f"--rerun-port and --rerun-web-port are both {args.rerun_port}")
    if args.rerun_connect:
        try:
            parse_viewer_url(args.rerun_connect)
        except ValueError as exc:
            raise EvaluateError(f"--rerun-connect: {exc}") from None


def _serve_until_stopped(seconds: float | None) -> None:
    """Keep the process (and with it the Rerun servers) up for ``seconds``, or until SIGINT/SIGTERM."""
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
    except ConfigError as exc:
        raise EvaluateError(f"--world: {exc}") from None
    if not worlds:
        raise EvaluateError("--world names no world")
    if len(worlds) > 1:
        given = [flag for flag, on in (("--rrd", args.rrd), ("--rerun-connect", args.rerun_connect),
                                       ("--rerun-serve", args.rerun_serve), ("--starts", args.starts)) if on]
        if given:
            raise EvaluateError(f"{', '.join(given)} take one world; --world names {len(worlds)}")
    return worlds


def _start_indices(starts: list[int] | None, world: str) -> list[int] | None:
    """--starts, numbered from 1 as the tables are, as the protocol's 0-based start indices."""
    if starts is None:
        return None
    from shared.sim.world import load_world

    n_starts = len(load_world(world).starts)
    bad = [s for s in starts if not 1 <= s <= n_starts]
    if bad:
        raise EvaluateError(f"--starts {' '.join(map(str, bad))}: world {world!r} has starts 1-{n_starts}")
    twice = sorted({s for s in starts if starts.count(s) > 1})
    if twice:  # the results would hold one (start, episode) twice and be refused after the whole run
        raise EvaluateError(f"--starts names start {' '.join(map(str, twice))} more than once")
    return [s - 1 for s in starts]


def _json_path(path: str, world: str, several: bool) -> Path:
    p = Path(path)
    return p.with_name(f"{p.stem}-{slug(world)}{p.suffix or '.json'}") if several else p


def run_evaluate(args: argparse.Namespace) -> int:
    """``cogexplore evaluate``: returns a process exit status."""
    apply_cpu_threads(args.threads)
    recorder = None  # only with --rerun-serve, which takes one world
    done: list[tuple[EvalSetup, EvalResults, ForesightProbe | None, Path | None]] = []
    _check_live_options(args)
    try:
        protocol = protocol_from_args(args)
    except ConfigError as exc:
        raise EvaluateError(f"--protocol: {exc}") from None
    model, ensemble = None, args.ensemble
    worlds = _worlds_of(args)
    several = len(worlds) > 1
    if args.json_out:  # refused now, not once the runs are done and their results cannot be written
        written: dict[Path, str] = {}
        for world in worlds:
            path = _json_path(args.json_out, world or "", several)
            if path.is_dir():
                raise EvaluateError(f"--json: {path} is a folder; give the results file's name")
            other = written.setdefault(path, world)  # 'w/a.xml' and 'w-a.xml' slug alike
            if other != world:
                raise EvaluateError(f"--json: worlds {other!r} and {world!r} would both write {path}")
    if several:  # a world that does not load is refused before hours go into the ones before it
        from shared.sim.world import load_world

        for world in worlds:
            load_world(world)
    for world in worlds:
        setup, results, recorder, probe = _evaluate_one(args, world, model, ensemble, protocol)
        json_path = _json_path(args.json_out, setup.world, several) if args.json_out else None
        if json_path is not None:  # saved at once: an interrupted run keeps the worlds it finished
            save_results(results, json_path)
        done.append((setup, results, probe, json_path))
        model, ensemble = setup.model, ()  # loaded (and joined into one ensemble) once for every world
    print(f"protocol {protocol.describe()}")
    for setup, results, probe, json_path in done:
        summary = aggregate(results.episodes)["overall"]
        if several:
            print(f"## {setup.world}")
        print(table_markdown({setup.meta()["model"]: results}), end="")
        print(json.dumps({"model": setup.meta()["model"], "world": setup.world, "protocol": protocol.name,
                          **{k: summary[k] for k in (
            "episodes", "mean_steps", "mean_distance_m", "mean_path_length_m", "mean_coverage_pct",
            "collisions", "reached_cap")}}, default=float))
        if probe is not None:
            print(json.dumps({"world": setup.world, "foresight": probe.summary([e.terminated for e in results.episodes])}))
        if json_path is not None:
            print(f"results: {json_path}")
    if several:
        per_world = {setup.world: float(results.summary["overall"]["mean_steps"]) for setup, results, _, _ in done}
        print(json.dumps({"model": done[0][0].meta()["model"], "protocol": protocol.name, "worlds": len(per_world),
                          "mean_steps_over_worlds": sum(per_world.values()) / len(per_world),
                          "per_world_mean_steps": per_world}))
        probes = [(probe, results) for _, results, probe, _ in done if probe is not None]
        if probes:
            pooled = foresight_summary([e for p, _ in probes for e in p.episodes],
                                       [e.terminated for _, r in probes for e in r.episodes], probes[0][0].horizon)
            print(json.dumps({"worlds": len(probes), "foresight": pooled}))
    if args.rrd:
        # Served, the file takes its name when serving stops, as every recording takes it once closed:
        # its sink stays open while the server runs, and Rerun writes a file's footer only as it closes.
        if recorder is not None:
            print(f"recording: {args.rrd} (written when serving stops)")
        elif done[0][1].meta.get("recording"):  # named by the results only once whole
            print(f"recording: {args.rrd}")
        else:
            print(f"recording: {args.rrd} not written (the error above says why)")
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


def _evaluate_one(args: argparse.Namespace, world: str | None, model: LoadedModel | None,
                  ensemble: Sequence[str | LoadedModel], protocol: ProtocolConfig,
                  ) -> tuple[EvalSetup, EvalResults, Any, ForesightProbe | None]:
    """One world of ``cogexplore evaluate``: (setup, results, the live-served recorder or None, the
    --foresight probe or None)."""
    setup = setup_evaluation(args.policy, None if model is not None else args.checkpoint, world=world,
                             preset=args.preset, overrides=args.overrides, seed=args.seed, device=args.device,
                             model=model, ensemble=ensemble)
    log.info("evaluating %s on %s", setup.meta()["model"], setup.world)
    starts = _start_indices(args.starts, setup.world)  # before a recording is opened for nothing
    recording_name = f"evaluate {setup.meta()['model']} on {setup.world}"  # the protocol: a property
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
    probe = ForesightProbe(setup.policy_fn, setup.sensor_cfg, setup.env_cfg) if args.foresight else None
    policy_fn = setup.policy_fn if probe is None else probe
    run = {"episodes_per_start": args.episodes_per_start, "max_steps": args.max_steps, "seed": args.seed,
           "starts": starts,
           "policy_version": setup.model.policy_version if setup.model else 0,
           "progress": not args.quiet, "meta": setup.meta(), "protocol": protocol}
    try:
        if recorder is not None:
            results = evaluate_policy(policy_fn, world=setup.world, sensor_cfg=setup.sensor_cfg,
                                      env_cfg=setup.env_cfg, recorder=recorder, **run)
        else:
            results = evaluate_recorded(policy_fn, world=setup.world, sensor_cfg=setup.sensor_cfg,
                                        env_cfg=setup.env_cfg, rrd=args.rrd, rerun_connect=args.rerun_connect,
                                        image_every=args.image_every, recording_name=recording_name, **run)
    except BaseException:
        if recorder is not None:
            recorder.close(keep=False)
        raise
    return setup, results, recorder, probe
