"""``cogexplore experiment paper``: the paper's comparison (Table III, Fig. 6) end to end.

    cogexplore experiment paper [--world paper-indoor] [--checkpoints 500,4000,7500,40000]
                                [--actors N] [--preset P] [--minutes-per-stage M]
                                [--out runs/experiment-paper]

Stages, in order, each recorded in ``<out>/state.json`` when it finishes, so that an interrupted
experiment picks up where it stopped (finished stages are skipped; a half-done training stage
resumes from its run's latest checkpoint):

1. ``sl``: the supervised model (``cogexplore pretrain``; or ``--sl-model`` to use one);
2. ``rl``: the RL baseline (the authors' RCAR 2016 Q-learning): a single-process DQN run with the
   conv layers copied from the SL model and frozen (``train.init_conv_from``, ``dqn.conv_lr_scale
   = 0``): only the fully connected layers learn;
3. ``drl-<u>`` for each checkpoint u: the DRL model through the distributed system, ``cogexplore
   up --updates u`` as a subprocess on ONE run (``<out>/runs/drl``) that each stage resumes, the
   conv layers initialised from the SL model; after each stage ``checkpoints/latest`` is exported
   to ``<out>/models/drl-<u>.safetensors``;
4. ``eval-<model>``: the full test protocol (``--episodes-per-start`` 10 episodes from every start,
   ``--max-steps`` 200, test speeds, ``--protocol`` default ``paper``: the exact starts without
   noise, as the paper's comparison; ``robust`` jitters them and adds sensor noise) for SL, RL,
   every DRL checkpoint, reactive and random;
5. ``eval-<model>@<world>`` for each of ``--unseen-worlds`` (default ``procedural:101-103``,
   worlds that neither the runs nor the SL data played): the same protocol there, the paper's
   generalisation question;
6. the report, rewritten every time: ``table.md`` (Count / Distance / Coverage per start),
   ``heatmaps.png`` (all models side by side), ``generalisation.md`` (mean steps per model and
   unseen world) with ``heatmaps-<world>.png``, ``learning_curve.png`` (DRL checkpoints against
   updates and minutes, beside the baselines and the paper's Table III), ``wallclock.md`` (how
   long each stage took) and ``report.md`` linking them. Unseen worlds can be added when resuming.

``--minutes-per-stage`` caps each training stage's wall time (the stage then ends early at the
update it reached, which the tables say). Every size is an option, so a tiny version runs in CI.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("RERUN_ANALYTICS", "0")  # offline machines: never phone home

from services.process import stop_signals_handled
from shared.config import (
    MAX_SEED,
    ConfigError,
    RunConfig,
    is_finite_number,
    is_whole,
    load_preset,
    parse_override,
    parse_world_list,
)
from shared.errors import CogexploreError
from shared.evaluation import (
    PAPER_BASELINE_STEPS,
    PAPER_DRL_STEPS,
    PROTOCOL_SENSOR_FIELDS,
    PROTOCOLS,
    ProtocolConfig,
)
from shared.files import atomic_write_text, save_png
from shared.jsontext import SMALL_JSON_BYTES, read_json_file

log = logging.getLogger("cogexplore.experiment")

STATE_FILE = "state.json"
STATE_FORMAT = "cogexplore-experiment"
STATE_VERSION = 1
DRL_RUN = "drl"
RL_RUN = "rl"
# Options that fix what the finished stages computed: a resumed experiment must not change them.
FIXED_OPTIONS = ("experiment", "world", "preset", "overrides", "sl_model", "sl_worlds", "sl_frames", "sl_epochs",
                 "rl_updates", "episodes_per_start", "max_steps", "seed", "protocol")


class ExperimentError(CogexploreError):
    """Options that do not fit together or do not fit the experiment already in ``--out``."""


def parse_checkpoints(text: str) -> list[int]:
    """'500,4000' -> [500, 4000]: positive, strictly increasing update counts."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise ExperimentError(f"--checkpoints {text!r}: give comma-separated update counts, e.g. 500,4000") from None
    if not values or any(v < 1 for v in values) or any(b <= a for a, b in itertools.pairwise(values)):
        raise ExperimentError(f"--checkpoints {text!r}: update counts must be >= 1 and strictly increasing")
    return values


@dataclass
class Options:
    """The resolved command line."""

    experiment: str
    out: Path
    world: str
    checkpoints: list[int]
    actors: int
    preset: str
    overrides: list[str]
    minutes_per_stage: float | None
    sl_model: str | None
    sl_worlds: list[str]
    sl_frames: int
    sl_epochs: int
    rl_updates: int
    unseen_worlds: list[str]
    episodes_per_start: int
    max_steps: int
    seed: int
    device: str | None
    quiet: bool
    protocol: ProtocolConfig = PROTOCOLS["paper"]
    rl_updates_given: bool = True
    """``--rl-updates`` was given; without it ``rl_updates`` is the last checkpoint's of the experiment
    as it began (a resumed one keeps its own, whatever checkpoints are added)."""

    def fixed(self) -> dict[str, Any]:
        return json.loads(json.dumps({k: getattr(self, k).to_dict() if k == "protocol" else getattr(self, k)
                                      for k in FIXED_OPTIONS}))


# ---------------------------------------------------------------------------------------------
# State
# ---------------------------------------------------------------------------------------------


def _stage_problem(name: str, stage: Any) -> str | None:
    """What is wrong with one finished stage of a state file (hand-edited, damaged), or None."""
    if not isinstance(stage, dict):
        return "is not an object"
    if not (is_finite_number(stage.get("seconds")) and stage["seconds"] >= 0):
        return "has no time in seconds"
    text = {"drl-": ("file",), "eval-": ("results",), "sl": ("model",), "rl": ("run",)}
    number = {"drl-": ("updates",), "eval-": ("mean_steps",)}
    kind = next((k for k in text if name == k or (k.endswith("-") and name.startswith(k))), None)
    if kind is None:
        return "is no stage of an experiment"
    if kind == "drl-" and not name[4:].isdigit():
        return "names no number of updates"
    if not all(isinstance(stage.get(key), str) for key in text[kind]):
        return f"lacks {' or '.join(text[kind])}"
    if not all(is_finite_number(stage.get(key)) for key in number.get(kind, ())):
        return f"lacks a number for {' or '.join(number[kind])}"
    if kind == "sl" and not (stage.get("accuracy") is None or is_finite_number(stage["accuracy"])):
        return "has an accuracy that is not a number"
    return None


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP to the experiment, raised where it runs: stages end as on Ctrl-C."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_terminated(signum: int, _frame: Any) -> None:
    raise Terminated(signum)


def _stop_child(proc: subprocess.Popen, signal_it: bool) -> None:
    """Let ``cogexplore up`` write its final checkpoint and exit (at most 180 s; SIGINT first when it
    did not get the signal that stops the experiment), then kill it."""
    if proc.poll() is not None:
        return
    if signal_it:
        proc.send_signal(signal.SIGINT)  # the launcher's orderly stop: final checkpoint first
    try:
        proc.wait(timeout=180)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def training_inputs(opts: Options) -> dict[str, str]:
    """The SHA-256 of each file the training stages read that its name does not fix: the MJCF world
    files they train in (``--world``, ``--sl-worlds``: their content) and a preset given as a TOML path
    (the config it gives: a comment may change). A built-in or procedural world and a preset named by
    its name are fixed by that name (as for evaluations)."""
    import hashlib

    from shared.evaluation.protocol import file_world_sha256

    digests = {f"world {w}": digest for w in dict.fromkeys((opts.world, *opts.sl_worlds))
               if (digest := file_world_sha256(w)) is not None}
    if Path(opts.preset).suffix:
        config = json.dumps(load_preset(opts.preset).to_dict(), sort_keys=True)
        digests[f"preset {opts.preset}"] = hashlib.sha256(config.encode()).hexdigest()
    return digests


class ExperimentState:
    """``state.json``: the options that fix the results, and every finished stage."""

    def __init__(self, path: Path, options: Options):
        self.path = path
        self.data: dict[str, Any] = {"format": STATE_FORMAT, "version": STATE_VERSION,
                                     "options": options.fixed(), "stages": {}}
        if path.is_file():
            try:
                old = read_json_file(path, "state file", ExperimentError, max_bytes=SMALL_JSON_BYTES)
            except ExperimentError as exc:
                raise ExperimentError(f"{exc}: move it away to start afresh") from None
            if not (isinstance(old, dict) and old.get("format") == STATE_FORMAT and old.get("version") == STATE_VERSION
                    and isinstance(old.get("options"), dict) and isinstance(old.get("stages"), dict)
                    and isinstance(old.get("partial_seconds", {}), dict)
                    and all(is_finite_number(v) for v in old.get("partial_seconds", {}).values())
                    and isinstance(old.get("training_inputs", {}), dict)
                    and all(isinstance(v, str) for v in old.get("training_inputs", {}).values())):
                raise ExperimentError(f"{path} is not a {STATE_FORMAT} v{STATE_VERSION} state file: move it away "
                                      "to start afresh")
            for name, stage in old["stages"].items():
                problem = _stage_problem(name, stage)
                if problem:
                    raise ExperimentError(f"{path}: stage {name!r} {problem}: move it away to start afresh")
            # State files from before the protocol was an option were evaluated under the paper's.
            old["options"].setdefault("protocol", PROTOCOLS["paper"].to_dict())
            # Without --rl-updates the RL baseline trains as long as the last checkpoint of the
            # experiment as it began: adding a checkpoint when resuming must not change it.
            began = old["options"].get("rl_updates")
            if not options.rl_updates_given and is_whole(began) and began >= 1:
                options.rl_updates = self.data["options"]["rl_updates"] = began
            differ = sorted(k for k in FIXED_OPTIONS if old["options"].get(k) != self.data["options"][k])
            if differ:
                was = {k: old["options"].get(k) for k in differ}
                raise ExperimentError(f"{path.parent} holds an experiment made with other options ({was}); "
                                      "use another --out, or the same options to resume it")
            self.data = old

    def done(self, stage: str) -> dict[str, Any] | None:
        return self.data["stages"].get(stage)

    def finish(self, stage: str, seconds: float, **info: Any) -> dict[str, Any]:
        entry = {"seconds": round(seconds, 3), "finished_unix": time.time(), **info}
        self.data["stages"][stage] = json.loads(json.dumps(entry))
        self.data.get("partial_seconds", {}).pop(stage, None)
        self.save()
        return entry

    def partial(self, stage: str) -> float:
        """Seconds spent on ``stage`` in attempts that were interrupted."""
        return float(self.data.get("partial_seconds", {}).get(stage, 0.0))

    def add_partial(self, stage: str, seconds: float) -> None:
        partial = self.data.setdefault("partial_seconds", {})
        partial[stage] = round(self.partial(stage) + seconds, 3)
        self.save()

    def forget(self, stages: list[str]) -> None:
        """Drop finished stages (to be run again)."""
        for stage in stages:
            self.data["stages"].pop(stage, None)
        self.save()

    def save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path, json.dumps(self.data, indent=2) + "\n")


# ---------------------------------------------------------------------------------------------
# The stages
# ---------------------------------------------------------------------------------------------


class Experiment:
    def __init__(self, opts: Options, echo: Callable[[str], None] | None = None):
        self.o = opts
        self.out = opts.out.resolve()
        self.echo = echo or (lambda msg: print(f"[experiment] {msg}", file=sys.stderr, flush=True))
        self.state = ExperimentState(self.out / STATE_FILE, opts)
        self.cfg = self._config()
        self._check_unseen()
        self.ran: list[str] = []
        self.skipped: list[str] = []

    # -- config -------------------------------------------------------------------------------
    def _config(self) -> RunConfig:
        cfg = load_preset(self.o.preset)
        parsed = dict(parse_override(x) for x in self.o.overrides)
        parsed["env.world"] = self.o.world
        return cfg.with_overrides(parsed)

    def _check_unseen(self) -> None:
        from shared.sim.world import canonical_world_name

        trained = {self.o.world, *parse_world_list(self.cfg.env.extra_worlds)}
        if not self.o.sl_model:
            trained.update(self.o.sl_worlds)
        trained = {canonical_world_name(w) for w in trained}  # procedural:07 is the world procedural:7
        seen = [w for w in self.o.unseen_worlds if canonical_world_name(w) in trained]
        if seen:
            raise ExperimentError(f"--unseen-worlds {', '.join(seen)}: the runs or the SL data play "
                                  + ("it" if len(seen) == 1 else "them") + "; choose worlds never trained on")

    def _eval_overrides(self) -> list[str]:
        """The sensor and env overrides, less the sensor noise and the env fields the protocol sets:
        training's noise, world, speeds and episode cap are training's, the test's the protocol's."""
        from shared.evaluation.protocol import PROTOCOL_ENV_FIELDS

        # what setup_evaluation refuses (it would be refused after the training)
        owned = (*(f"sensor.{f}" for f in PROTOCOL_SENSOR_FIELDS), *(f"env.{f}" for f in PROTOCOL_ENV_FIELDS))
        return [x for x in self.o.overrides if x.strip().startswith(("sensor.", "env."))
                and parse_override(x)[0] not in owned]

    def stored(self, path: Path) -> str:
        """How a path goes into the state: relative to the experiment folder when inside it, so a
        moved or copied experiment reads its own files (not the original's)."""
        path = Path(path).resolve()
        return str(path.relative_to(self.out)) if path.is_relative_to(self.out) else str(path)

    def path(self, stored: str) -> Path:
        """A path from the state (relative ones are the experiment folder's)."""
        return self.out / stored if not Path(stored).is_absolute() else Path(stored)

    @property
    def sl_path(self) -> Path:
        if self.o.sl_model:
            return Path(self.o.sl_model).resolve()
        return self.out / "sl" / "sl.safetensors"

    @property
    def runs_dir(self) -> Path:
        return self.out / "runs"

    def _stage(self, name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        done = self.state.done(name)
        if done is not None:
            self.skipped.append(name)
            self.echo(f"{name}: done before ({done['seconds']:.1f} s), skipped")
            return done
        self.echo(f"{name}: starting")
        t0 = time.monotonic()
        try:
            info = fn()
        except BaseException:  # interrupted (or failed): its time counts when the stage is resumed
            self.state.add_partial(name, time.monotonic() - t0)
            raise
        entry = self.state.finish(name, self.state.partial(name) + time.monotonic() - t0, **info)
        self.ran.append(name)
        self.echo(f"{name}: finished in {entry['seconds']:.1f} s")
        return entry

    # -- SL -----------------------------------------------------------------------------------
    def _pretrain(self) -> dict[str, Any]:
        from services.tools.pretrain import run_pretraining

        if self.o.sl_model:
            from shared.learning.checkpoints import load_supervised

            _net, meta = load_supervised(self.sl_path)  # fail now, not after hours of training
            card = meta.get("card")
            accuracy = card.get("accuracy") if isinstance(card, dict) else None  # the file's word: checked
            return {"model": self.stored(self.sl_path), "given": True,
                    "accuracy": float(accuracy) if is_finite_number(accuracy) else None}
        result = run_pretraining(self.cfg, out=self.sl_path, worlds=self.o.sl_worlds, frames=self.o.sl_frames,
                                 epochs=self.o.sl_epochs, seed=self.o.seed, progress=not self.o.quiet,
                                 device=self.o.device or "auto")
        card = result.card
        return {"model": self.stored(self.sl_path), "given": False, "accuracy": card["accuracy"],
                "balanced_accuracy": card["balanced_accuracy"], "frames": card["data"]["frames"],
                "label_counts": card["data"]["label_counts"], "data_seconds": result.seconds["data"],
                "train_seconds": result.seconds["train"]}

    # -- RL -----------------------------------------------------------------------------------
    def _train_rl(self) -> dict[str, Any]:
        from services.runs import RunPaths
        from services.tools.train import train_single_process

        cfg = self.cfg.with_overrides({"train.init_conv_from": str(self.sl_path), "dqn.conv_lr_scale": 0.0,
                                       "train.total_updates": self.o.rl_updates,
                                       **({"train.device": self.o.device} if self.o.device else {})})
        paths = RunPaths(self.runs_dir / RL_RUN)
        summary = train_single_process(cfg, paths, progress=not self.o.quiet,
                                       max_minutes=self.o.minutes_per_stage)
        return {"run": self.stored(paths.root), "updates": int(summary["updates"]), "env_steps": int(summary["env_steps"]),
                "stopped_early": int(summary["updates"]) < self.o.rl_updates}

    # -- DRL ----------------------------------------------------------------------------------
    def _up_command(self, updates: int) -> list[str]:
        argv = [sys.executable, "-m", "services.cli", "up", "--run", DRL_RUN, "--runs-dir", str(self.runs_dir),
                "--preset", self.o.preset, "--actors", str(self.o.actors), "--updates", str(updates),
                "--no-evaluator", "--no-report"]
        for x in [*self.o.overrides, f"env.world={self.o.world}", f"train.init_conv_from={self.sl_path}"]:
            argv += ["--set", x]
        if self.o.device:
            argv += ["--device", self.o.device]
        if self.o.quiet:
            argv.append("--quiet")
        return argv

    def _train_drl(self, updates: int) -> dict[str, Any]:
        from shared.learning.checkpoints import (
            export_weights,
            load_checkpoint,
            load_model,
        )

        argv = self._up_command(updates)
        self.echo(" ".join(argv[2:]))
        env = dict(os.environ, RERUN_ANALYTICS="0", PYTHONUNBUFFERED="1")
        repo = Path(__file__).resolve().parents[2]
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(repo), env.get("PYTHONPATH", "")]))
        proc = subprocess.Popen(argv, env=env, stdin=subprocess.DEVNULL)
        limit = self.o.minutes_per_stage * 60 if self.o.minutes_per_stage else None
        timed_out = False
        try:
            proc.wait(timeout=limit)
        except subprocess.TimeoutExpired:
            timed_out = True
            self.echo(f"drl-{updates}: {self.o.minutes_per_stage} minutes are up: stopping the run")
            _stop_child(proc, signal_it=True)
        except BaseException as exc:
            # Ctrl-C reached the child too (one process group): let it write its checkpoint. A SIGTERM
            # (kill, timeout, systemd) reached only this process: the child is told, or it trains on alone.
            _stop_child(proc, signal_it=not isinstance(exc, KeyboardInterrupt) or isinstance(exc, Terminated))
            raise
        if proc.returncode != 0 and not timed_out:
            raise ExperimentError(f"`cogexplore up` for {updates} updates failed (exit {proc.returncode}); "
                                  f"see {self.runs_dir / DRL_RUN / 'logs'}")
        run = self.runs_dir / DRL_RUN
        try:
            model = load_model(run, "cpu")
        except ValueError as exc:
            raise ExperimentError(f"the DRL run left no usable checkpoint ({exc}); see {run / 'logs'}") from None
        reached = load_checkpoint(model.path).update_count
        if reached < 1:
            raise ExperimentError(f"the DRL run stopped before its first update; see {run / 'logs'}")
        path = self.out / "models" / f"drl-{updates}.safetensors"
        export_weights(path, model.net, model.policy_version, run_config=model.run_config)
        return {"file": self.stored(path), "checkpoint": self.stored(model.path), "updates": reached,
                "policy_version": model.policy_version, "stopped_early": reached < updates}

    # -- evaluation ---------------------------------------------------------------------------
    def models(self) -> list[tuple[str, str, str | None]]:
        """(table label, policy, checkpoint) of every model to evaluate, in table order."""
        rows: list[tuple[str, str, str | None]] = [("SL", "sl", str(self.sl_path)),
                                                   ("RL", "rl", str(self.runs_dir / RL_RUN))]
        for u in self.o.checkpoints:
            info = self.state.done(f"drl-{u}")
            # A stage that stopped where the one before it did (its minutes were up before another
            # checkpoint) holds the same model: one row, not two of one label sharing an evaluation.
            if info is not None and all(r[0] != f"DRL-{info['updates']}" for r in rows):
                rows.append((f"DRL-{info['updates']}", "greedy", str(self.path(info["file"]))))
        rows += [("reactive", "reactive", None), ("random", "random", None)]
        return rows

    def _evaluate(self, label: str, policy: str, checkpoint: str | None, world: str) -> dict[str, Any]:
        """The protocol for one model on ``world``."""
        from shared.evaluation.protocol import evaluate_policy
        from shared.evaluation.results import save_results, slug
        from shared.evaluation.setup import setup_evaluation

        setup = setup_evaluation(policy, checkpoint, world=world, preset=self.o.preset,
                                 overrides=self._eval_overrides(), seed=self.o.seed, device="cpu")
        results = evaluate_policy(setup.policy_fn, world=world, sensor_cfg=setup.sensor_cfg,
                                  env_cfg=setup.env_cfg, episodes_per_start=self.o.episodes_per_start,
                                  max_steps=self.o.max_steps, seed=self.o.seed, progress=not self.o.quiet,
                                  meta={**setup.meta(), "model": label}, protocol=self.o.protocol)
        folder = self.out / "eval" if world == self.o.world else self.out / "eval" / slug(world)
        path = folder / f"{slug(label)}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        save_results(results, path)
        overall = results.summary["overall"]
        return {"label": label, "world": world, "results": self.stored(path), "mean_steps": overall["mean_steps"],
                "mean_distance_m": overall["mean_distance_m"]}

    # -- report -------------------------------------------------------------------------------
    def eval_stage(self, label: str, world: str | None = None) -> str:
        """The stage name of one model's evaluation on ``world`` (default: the training world)."""
        return f"eval-{label}" if world in (None, self.o.world) else f"eval-{label}@{world}"

    def _results_on(self, world: str | None = None) -> dict[str, Any]:
        """{model label: EvalResults} of every model evaluated on ``world``, in table order."""
        from shared.evaluation.results import load_results

        results = {}
        for label, _policy, _ckpt in self.models():
            info = self.state.done(self.eval_stage(label, world))
            if info is not None:
                results[label] = load_results(self.path(info["results"]))
        return results

    def check_training_inputs(self) -> None:
        """ExperimentError when a file the finished training stages read (:func:`training_inputs`) has
        changed since: the models would stand for a world or recipe they were not trained on, and the
        stages still to run would train on the new one. Evaluations are redone after an edit; training
        is hours, so the user chooses. Recorded before the first stage (and by a state from before
        this record, as the files are now)."""
        now = training_inputs(self.o)
        trained = [name for name in self.state.data["stages"] if name in ("sl", "rl") or name.startswith("drl-")]
        recorded = self.state.data.get("training_inputs")
        if trained and recorded is not None:
            changed = sorted(k for k in now.keys() | recorded.keys() if now.get(k) != recorded.get(k))
            if changed:
                raise ExperimentError(f"{', '.join(changed)} changed since stage(s) {', '.join(trained)} trained on "
                                      "it: put the file back as it was to resume, or start the experiment over "
                                      "in another --out")
        if recorded != now:
            self.state.data["training_inputs"] = now
            self.state.save()

    def forget_evaluations_of_edited_worlds(self) -> None:
        """Forget every finished evaluation on an MJCF file world that was played on other content than the
        file's now (edited since, or results from before they recorded it): its score would share a table
        with the edited file's under one name. A built-in or procedural world is fixed by its name."""
        from shared.evaluation.protocol import file_world_sha256, played_as_now
        from shared.evaluation.results import load_results

        for world in (self.o.world, *self.o.unseen_worlds):
            now = file_world_sha256(world)
            if now is None:
                continue
            stale = [name for name in (self.eval_stage(label, world) for label, _policy, _ckpt in self.models())
                     if (info := self.state.done(name)) is not None
                     and not played_as_now(load_results(self.path(info["results"])).meta, now)]
            if stale:
                self.echo(f"{len(stale)} evaluation(s) on {world} played the file as it was before an edit "
                          "(or do not record its content): evaluated again")
                self.state.forget(stale)

    def _heatmaps(self, world: str, results: dict[str, Any], name: str) -> Path:
        from services.viz.figures import save_heatmaps_side_by_side
        from shared.sim.maps import occupancy_grid
        from shared.sim.world import load_world

        w = load_world(world)
        return save_heatmaps_side_by_side(w, occupancy_grid(w), results, self.out / name,
                                          ncols=min(4, len(results)))

    def write_report(self) -> Path:
        from shared.evaluation.results import table_markdown

        results = self._results_on()
        table = table_markdown(results)
        atomic_write_text(self.out / "table.md", table)  # a rewrite cut short keeps the last report whole
        heatmaps = self._heatmaps(self.o.world, results, "heatmaps.png")
        wall = self.wallclock_markdown()
        atomic_write_text(self.out / "wallclock.md", wall)
        unseen = self.write_generalisation()
        curve = self.save_learning_curve()
        sl = self.state.done("sl") or {}
        lines = [f"# Experiment `{self.o.experiment}`: SL, RL, DRL and baselines on `{self.o.world}`", "",
                 f"Preset `{self.o.preset}`" + (f", overrides `{' '.join(self.o.overrides)}`" if self.o.overrides
                                                else "")
                 + f"; protocol {self.o.protocol.describe()}; {self.o.episodes_per_start} episode(s) from each "
                   f"start, at most {self.o.max_steps} steps, test speeds, seed {self.o.seed}.", ""]
        if is_finite_number(sl.get("accuracy")):
            lines += [f"SL model `{sl['model']}`: test accuracy {sl['accuracy']:.3f}"
                      + (f" (balanced {sl['balanced_accuracy']:.3f}, {sl['frames']} frames)"
                         if "balanced_accuracy" in sl else "") + ".", ""]
        lines += [f"## Count / Distance / Coverage per start (Table III, {self.o.protocol.name} protocol)", "", table,
                  "## Trajectory heatmaps (Fig. 6)", "", f"![heatmaps]({heatmaps.name})", ""]
        if curve is not None:
            lines += ["## Learning curve", "", "Mean moving steps of each DRL checkpoint against updates and "
                      "training wall time, the baselines as lines, the paper's Table III as grey marks.", "",
                      f"![learning curve]({curve.name})", "",
                      "The paper (Table III, its own world): " + ", ".join(
                          [f"{k} {v}" for k, v in PAPER_BASELINE_STEPS.items()]
                          + [f"DRL-{k} {v}" for k, v in PAPER_DRL_STEPS.items()]) + ".", ""]
        if unseen:
            lines += ["## Generalisation: worlds never trained on", "",
                      "Mean moving steps per episode, same protocol; no run and no SL data played these worlds.",
                      "", unseen]
        lines += ["## Wall clock", "", wall]
        early = [n for n, info in self.state.data["stages"].items() if info.get("stopped_early")]
        if early:
            lines += ["", "Stopped early by --minutes-per-stage: " + ", ".join(
                f"{n} (at {self.state.data['stages'][n]['updates']} updates)" for n in early) + "."]
        path = self.out / "report.md"
        atomic_write_text(path, "\n".join(lines) + "\n")
        return path

    def write_generalisation(self) -> str:
        """``generalisation.md`` (mean steps per model and unseen world, and their mean) and one
        ``heatmaps-<world>.png`` per unseen world; returns the Markdown ('' without unseen worlds)."""
        from shared.evaluation.results import slug

        worlds = self.o.unseen_worlds
        if not worlds:
            return ""
        steps: dict[str, dict[str, float]] = {}
        figures = []
        for world in worlds:
            results = self._results_on(world)
            for label in results:
                steps.setdefault(label, {})[world] = float(self.state.done(self.eval_stage(label, world))["mean_steps"])
            if results:
                figures.append(self._heatmaps(world, results, f"heatmaps-{slug(world)}.png"))
        cols = [*worlds, "Mean"]
        rows = {label: [per.get(w) for w in worlds] + [sum(per.values()) / len(per)
                                                         if len(per) == len(worlds) else None]
                for label, per in steps.items()}
        best = [max((r[i] for r in rows.values() if r[i] is not None), default=None) for i in range(len(cols))]
        lines = ["| Model | " + " | ".join(f"`{c}`" if c != "Mean" else c for c in cols) + " |",
                 "|---|" + "---:|" * len(cols)]
        for label, values in rows.items():
            cells = ["-" if v is None else (f"**{v:.1f}**" if v == best[i] else f"{v:.1f}")
                     for i, v in enumerate(values)]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        text = "\n".join(lines) + "\n" + "".join(f"\n![{f.stem}]({f.name})\n" for f in figures)
        atomic_write_text(self.out / "generalisation.md", text)
        return text

    def save_learning_curve(self) -> Path | None:
        """``learning_curve.png``: every evaluated DRL checkpoint's mean steps (training world, and
        the unseen worlds' mean) against updates and cumulative training minutes, with the
        baselines and the paper's figures; None before any DRL checkpoint is evaluated."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        from shared.evaluation import PAPER_MAX_STEPS

        points = []  # (updates, cumulative minutes, steps on the training world, unseen mean or None)
        minutes = 0.0
        for u in self.o.checkpoints:
            stage = self.state.done(f"drl-{u}")
            if stage is None:
                break
            minutes += stage["seconds"] / 60
            label = f"DRL-{stage['updates']}"
            ev = self.state.done(self.eval_stage(label))
            if ev is None:
                continue
            if points and points[-1][0] == stage["updates"]:
                continue  # no further update: the same model, drawn once
            unseen = [self.state.done(self.eval_stage(label, w)) for w in self.o.unseen_worlds]
            points.append((stage["updates"], minutes, ev["mean_steps"],
                           sum(x["mean_steps"] for x in unseen) / len(unseen)
                           if unseen and all(unseen) else None))
        if not points:
            return None
        fig = Figure(figsize=(11.0, 4.0))
        FigureCanvasAgg(fig)
        axes = fig.subplots(1, 2, sharey=True)
        for ax, col, xlabel in ((axes[0], 0, "DRL updates"), (axes[1], 1, "DRL training wall time (min)")):
            xs = [p[col] for p in points]
            ax.plot(xs, [p[2] for p in points], "o-", color="C0", lw=1.8, label=f"DRL on {self.o.world}")
            if all(p[3] is not None for p in points):
                ax.plot(xs, [p[3] for p in points], "s--", color="C1", lw=1.4, label="DRL, unseen worlds' mean")
            for i, name in enumerate(("SL", "RL", "reactive", "random")):
                ev = self.state.done(self.eval_stage(name))
                if ev is not None:
                    ax.axhline(ev["mean_steps"], color=f"C{i + 2}", lw=1, ls=":", label=name)
            if col == 0 and self.o.max_steps == PAPER_MAX_STEPS:  # the paper's figures are of 200 steps
                ax.plot(list(PAPER_DRL_STEPS), list(PAPER_DRL_STEPS.values()), "x", color="gray", ms=8,
                        mew=2, label="paper's DRL (Table III)")
            if col == 0:
                ax.set_xscale("log")
            ax.axhline(self.o.max_steps, color="gray", lw=0.8, ls="--")
            ax.set_xlabel(xlabel)
            ax.grid(alpha=0.3)
        axes[0].set_ylabel(f"mean moving steps (of {self.o.max_steps})")
        axes[0].legend(fontsize=8, loc="upper left")
        fig.suptitle(f"Experiment {self.o.experiment}: DRL learning curve on {self.o.world}")
        fig.tight_layout()
        return save_png(fig, self.out / "learning_curve.png", dpi=110)

    def wallclock_markdown(self) -> str:
        lines = ["| Stage | Seconds | Updates | Cumulative DRL seconds |", "|---|---:|---:|---:|"]
        drl_total = 0.0
        for name, info in self.state.data["stages"].items():
            cumulative = ""
            if name.startswith("drl-"):
                drl_total += info["seconds"]
                cumulative = f"{drl_total:.1f}"
            lines.append(f"| {name} | {info['seconds']:.1f} | {info.get('updates', '')} | {cumulative} |")
        return "\n".join(lines) + "\n"

    # -- all of it ----------------------------------------------------------------------------
    def run(self) -> Path:
        # a state is saved before any stage starts: runs without one are another experiment's, whose
        # training stages would resume them (trained in another world, on another preset) as this one's
        leftovers = [str(p) for p in (self.runs_dir / RL_RUN, self.runs_dir / DRL_RUN)
                     if not self.state.path.is_file() and (p.exists() or p.is_symlink())]
        if leftovers:
            raise ExperimentError(f"{self.out} holds the runs of an experiment without its {STATE_FILE} "
                                  f"({', '.join(leftovers)}): use another --out, or move them away")
        self.out.mkdir(parents=True, exist_ok=True)
        self.state.save()
        self.check_training_inputs()
        done_drl = [int(n.split("-", 1)[1]) for n in self.state.data["stages"] if n.startswith("drl-")]
        if done_drl and min(self.o.checkpoints) < max(done_drl) and any(
                self.state.done(f"drl-{u}") is None for u in self.o.checkpoints if u < max(done_drl)):
            raise ExperimentError(f"the DRL run is already past {max(done_drl)} updates: checkpoints below it "
                                  "that were not taken then cannot be added now")
        self._stage("sl", self._pretrain)
        self._stage("rl", self._train_rl)
        for u in self.o.checkpoints:
            self._stage(f"drl-{u}", lambda u=u: self._train_drl(u))
        self.forget_evaluations_of_edited_worlds()
        for world in (self.o.world, *self.o.unseen_worlds):
            for label, policy, checkpoint in self.models():
                self._stage(self.eval_stage(label, world),
                            lambda a=(label, policy, checkpoint, world): self._evaluate(*a))
        path = self.write_report()
        self.echo(f"report: {path}")
        return path


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------


def options_from_args(args: argparse.Namespace) -> Options:
    from services.options import protocol_from_args
    from services.tools.pretrain import parse_worlds
    from shared.expert.supervised import MAX_EPOCHS

    checkpoints = parse_checkpoints(args.checkpoints)
    for name in ("actors", "sl_frames", "sl_epochs", "episodes_per_start", "max_steps"):
        if getattr(args, name) < 1:
            raise ExperimentError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.sl_epochs > MAX_EPOCHS:  # the pretrain stage's bound, as the seed's below
        raise ExperimentError(f"--sl-epochs must be <= {MAX_EPOCHS}, got {args.sl_epochs}")
    if not 0 <= args.seed <= MAX_SEED:  # the pretrain stage's bound, known before any stage runs
        raise ExperimentError(f"--seed must be in [0, {MAX_SEED}] (2**53 - 1), got {args.seed}")
    if args.rl_updates is not None and args.rl_updates < 1:
        raise ExperimentError(f"--rl-updates must be >= 1, got {args.rl_updates}")
    if args.minutes_per_stage is not None and not args.minutes_per_stage > 0:
        raise ExperimentError(f"--minutes-per-stage must be > 0, got {args.minutes_per_stage}")
    try:
        protocol = protocol_from_args(args)
    except ConfigError as exc:
        raise ExperimentError(f"--protocol: {exc}") from None
    return Options(experiment=args.experiment, out=Path(args.out), world=args.world, checkpoints=checkpoints,
                   actors=args.actors, preset=args.preset, overrides=list(args.overrides),
                   minutes_per_stage=args.minutes_per_stage,
                   sl_model=str(Path(args.sl_model).resolve()) if args.sl_model else None,
                   sl_worlds=parse_worlds(args.sl_worlds), sl_frames=args.sl_frames, sl_epochs=args.sl_epochs,
                   rl_updates=args.rl_updates or checkpoints[-1],
                   unseen_worlds=list(parse_world_list(args.unseen_worlds)), episodes_per_start=args.episodes_per_start,
                   max_steps=args.max_steps, seed=args.seed, device=args.device, quiet=args.quiet,
                   protocol=protocol, rl_updates_given=args.rl_updates is not None)


def run_experiment_command(args: argparse.Namespace) -> int:
    """``cogexplore experiment``: returns a process exit status."""
    from shared.sim.world import load_world

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    opts = options_from_args(args)
    for world in (opts.world, *opts.unseen_worlds):
        load_world(world)  # an unknown world fails now, not after the pretraining
    experiment = Experiment(opts)
    try:
        # Ctrl-C stays KeyboardInterrupt: it reached the children too
        with stop_signals_handled(_raise_terminated, keep_interrupt=True):
            report = experiment.run()
    except KeyboardInterrupt as exc:
        print("cogexplore experiment: interrupted; run the same command again to resume", file=sys.stderr)
        return 128 + exc.signum if isinstance(exc, Terminated) else 130  # as a shell reports the signal
    print((experiment.out / "table.md").read_text(), end="")
    print(f"ran: {', '.join(experiment.ran) or 'nothing'}; skipped (done before): "
          f"{', '.join(experiment.skipped) or 'nothing'}")
    print(f"report: {report}")
    return 0
