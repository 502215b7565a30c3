"""The evaluator process: the test protocol on the newest weights, every K learner updates.

    cogexplore evaluator --run NAME --connect tcp/<router-host>:7447 [--every-updates 1000] [--full] [--once]
    python -m services.evaluator ...            (the same)

On start it follows the ``weights`` stream, announces itself (liveliness ``alive/evaluator/<id>``)
and asks the learner's queryable for its newest weights (``services.bus.follower.WeightFollower``,
as the actors do). Zenoh threads only park the newest message; the main loop takes it and
evaluates it when it is due: the first weights it sees, then whenever the policy version (the
learner's update count at publication) enters a new multiple of ``--every-updates``; weights whose
evaluation the run's ``eval.jsonl`` holds already (the same digest, protocol, episodes and seed: the
checkpoint a restarted learner resumed from and publishes first) are not evaluated twice. A message
for another architecture (fingerprint) or one that does not decode is counted by cause and dropped;
the service carries on.

Each evaluation (cheap by default: 1 episode per start, 200 steps; ``--full``: 10 per start), under
``--protocol`` (default ``robust``: jittered starts and sensor noise; ``paper``: exact starts)

- publishes an ``EvalResult`` on ``stats/eval/<id>``;
- appends one JSON line to ``runs/<run>/stats/eval.jsonl`` (summary, per start, rejects, the
  weights' digest; ``shared.evaluation.eval_log`` reads it);
- saves the results JSON to ``runs/<run>/stats/eval/eval-<version:06d>.json`` (the report
  reuses it when the run's checkpoint holds the same weights);
- writes a Rerun recording to ``runs/<run>/recordings/eval-<version:06d>.rrd`` (every
  ``--image-every``-th depth image, every step's pose, Q-values and command);
- where those names hold another evaluation of the version (another protocol, or other weights
  after a learner restart) or one under way (another evaluator's: the results file is created empty
  when an evaluation begins, claiming its name), names both ``eval-<version:06d>-<8 hex digits of the
  evaluation's digest>`` instead, and ``...-<digest>-<evaluator id>`` where another evaluator plays
  the same evaluation at that moment (``EvaluatorService.files_stem``), so that each row of
  ``eval.jsonl`` keeps its own files (the row names both: ``recording``, ``results``);
- with ``--rerun-connect URL`` (default: env ``COGEXPLORE_RERUN_URL``), also streams that
  recording live to the Rerun viewer there. The viewer is checked before each evaluation: one
  that does not answer is warned about once and skipped (the ``.rrd`` files go on), one that
  goes away mid-evaluation only costs a warning.

SIGINT/SIGTERM (or the ``stop`` event in tests) ends the loop within one environment step; the
session, and with it the liveliness token, is closed on the way out.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("RERUN_ANALYTICS", "0")  # offline machines: never phone home

import torch

from services.bus.follower import WeightFollower
from services.bus.run_config import join_run_config
from services.bus.session import (
    TransportError,
    ZenohSettings,
    declare_alive,
    open_service_session,
    put_reliable,
    zenoh_settings,
)
from services.evaluator.options import (
    CHEAP_EPISODES_PER_START,
    DEFAULT_EVERY_UPDATES,
    DEFAULT_IMAGE_EVERY,
    add_evaluator_arguments,
)
from services.options import protocol_from_args
from services.process import default_process_id, lower_priority, setup_logging, stop_event_on_signals
from services.runs import run_paths
from services.viz.rerun import ViewerLink, evaluate_recorded, remove_orphan_recordings
from shared.config import ConfigError, RunConfig, is_whole
from shared.errors import CogexploreError, StopRequested
from shared.evaluation import (
    DEFAULT_PROTOCOL,
    PAPER_EPISODES_PER_START,
    PAPER_MAX_STEPS,
    PROTOCOLS,
    TEST_SEED,
    ProtocolConfig,
)
from shared.evaluation.eval_log import EVAL_LOG, evaluation_digest, evaluation_key, load_eval_log
from shared.evaluation.policies import GreedyPolicy
from shared.evaluation.protocol import WORLD_META, EvaluationCancelled, file_world_sha256
from shared.evaluation.results import EvalResults, ResultsError, load_results, save_results
from shared.files import WRITE_FAILURES, append_line
from shared.learning.checkpoints import weights_sha256
from shared.learning.model import (
    QNetwork,
    architecture_fingerprint,
    named_shapes,
    resolve_device,
)
from shared.learning.policy import NonFiniteQValues
from shared.learning.stats import TensorBoardLog
from shared.sim.world import load_world
from shared.wire.keys import RunKeys, validate_name
from shared.wire.messages import MAX_EVAL_EPISODES, EvalResult, RejectCounter, WeightsMessage

EVALUATOR_NICENESS = 10
"""Scheduling niceness of a long-running evaluator (0 = as the learner; 19 = the lowest)."""
EVALUATION_META = "evaluation_sha256"
"""The results meta field holding :func:`evaluation_digest`: which evaluation a file holds."""
log = logging.getLogger("cogexplore.evaluator")


def result_stem(policy_version: int, digest: str | None = None) -> str:
    """``eval-<version:06d>``, with ``-<digest's first 8 hex digits>`` when given."""
    return f"eval-{policy_version:06d}" + (f"-{digest[:8]}" if digest else "")


def recording_path(recordings: Path, policy_version: int, digest: str | None = None) -> Path:
    """``recordings/<result_stem>.rrd``."""
    return recordings / f"{result_stem(policy_version, digest)}.rrd"


class EvaluatorService:
    """Evaluates the newest weights of one run; ``run(stop)`` is the process's main loop."""

    def __init__(self, cfg: RunConfig, run: str, root: Path, settings: ZenohSettings, evaluator_id: str, *,
                 every_updates: int = DEFAULT_EVERY_UPDATES, episodes_per_start: int = CHEAP_EPISODES_PER_START,
                 max_steps: int = PAPER_MAX_STEPS, world: str | None = None, image_every: int = DEFAULT_IMAGE_EVERY,
                 record: bool = True, seed: int = TEST_SEED, device: str = "cpu", query_timeout_s: float = 2.0,
                 rerun_url: str | None = None, tensorboard: Path | None = None,
                 protocol: ProtocolConfig = PROTOCOLS[DEFAULT_PROTOCOL]):
        for name, value in (("every_updates", every_updates), ("episodes_per_start", episodes_per_start),
                            ("max_steps", max_steps), ("image_every", image_every)):
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ConfigError(f"{name} must be an integer >= 1, got {value!r}")
        if not (is_whole(seed) and seed >= 0):  # refused now, not by the protocol when the first weights come
            raise ConfigError(f"seed must be an integer >= 0, got {seed!r}")
        self.cfg = cfg
        self.run_name = validate_name(run, "run name")
        self.keys = RunKeys(run)
        self.root = Path(root)
        self.settings = settings
        self.evaluator_id = validate_name(evaluator_id, "evaluator id")
        self.every_updates = every_updates
        self.protocol = protocol
        self.episodes_per_start = episodes_per_start
        self.max_steps = max_steps
        self.world = world or cfg.env.world
        episodes = len(load_world(self.world).starts) * episodes_per_start  # a bad world fails at start-up
        if episodes > MAX_EVAL_EPISODES:  # its result message could not carry them, after the first run
            raise ConfigError(f"{episodes_per_start} episode(s) per start in {self.world} are {episodes} episodes; "
                              f"an evaluation result carries at most {MAX_EVAL_EPISODES}: lower "
                              "--episodes-per-start")
        self.image_every = image_every
        self.record = record
        # an evaluator killed mid-recording left its temporary, which no later recorder opens again
        if record and (removed := remove_orphan_recordings(self.root / "recordings")):
            log.info("removed %d recording(s) a killed evaluator left unfinished (%s)", len(removed),
                     self.root / "recordings")
        # A malformed URL fails here, at start-up; one that does not answer is checked per evaluation.
        self.viewer = ViewerLink(rerun_url, what="streaming evaluations") if rerun_url else None
        self.seed = seed
        self.query_timeout_s = query_timeout_s
        self.device = resolve_device(device)
        self.net = QNetwork(cfg.model, cfg.sensor).to(self.device).eval()
        self.fingerprint = architecture_fingerprint(self.net)
        self.policy = GreedyPolicy(self.net)
        self.rejects = RejectCounter("weights or flow message", log)
        self.weights = WeightFollower(self.fingerprint, self.rejects, shapes=named_shapes(self.net))
        """The newest weights the learner has published (parked by Zenoh threads, taken by the loop)."""
        self.last_version: tuple[int, int] | None = None
        """(learner epoch, update) of the weights evaluated last."""
        self.evaluations: list[dict[str, Any]] = []
        """The JSON rows written so far (newest last)."""
        log_path = self.root / "stats" / EVAL_LOG
        rows = load_eval_log(log_path) if log_path.is_file() else []
        self.evaluated: set[tuple[Any, ...]] = {k for k in map(evaluation_key, rows) if k is not None}
        """Evaluations this run holds already (:func:`evaluation_key` of its rows): a restarted learner
        publishes the weights of the checkpoint it resumed from, which played the same draws before."""
        self.board = TensorBoardLog(tensorboard)
        """Each evaluation's duration and summary as ``eval/<key>`` at its policy version (closed by ``run``)."""

    def due(self, message: WeightsMessage) -> bool:
        """The first weights of each learner process (a restarted learner's at once), then each that
        enters a new multiple of ``every_updates``; and weights numbered below the last evaluated
        (a learner's versions only rise: the last was a forged one, which must not hold off the rest)."""
        epoch, update = message.version
        if self.last_version is None or epoch != self.last_version[0]:
            return True
        last = self.last_version[1]
        return update < last or (update > last and update // self.every_updates > last // self.every_updates)

    # -- one evaluation -------------------------------------------------------------------------

    def files_stem(self, version: int, digest: str) -> str:
        """The name of an evaluation's results and recording: the version's plain one, else (another
        evaluation holds it, or one that does not say, or one under way: :meth:`_claim`) with the
        digest, else (another evaluator plays this same evaluation now) with this evaluator's id too."""
        for stem in (result_stem(version), result_stem(version, digest)):
            if self._claim(stem, digest):
                return stem
        return f"{result_stem(version, digest)}-{self.evaluator_id}"  # ids are unique among live evaluators

    def _files(self, stem: str) -> tuple[Path, Path]:
        """The results file and the recording an evaluation named ``stem`` writes."""
        return self.root / "stats" / "eval" / f"{stem}.json", self.root / "recordings" / f"{stem}.rrd"

    def _claim(self, stem: str, digest: str) -> bool:
        """Whether ``stem`` names this evaluation's files: its results hold this evaluation (played
        again), or neither file exists and this evaluator creates the results file first, empty until
        its results replace it. Claimed as the evaluation begins, not when its results are saved
        minutes later: two evaluators of one version took one name, and the last to finish replaced
        the other's files under the other's row."""
        results, recording = self._files(stem)
        if results.exists():
            try:
                return load_results(results).meta.get(EVALUATION_META) == digest
            except ResultsError:  # damaged, or another's claim: not known to be this evaluation's
                return False
        if recording.exists():
            return False  # a recording without results (its evaluator killed in between) is someone's too
        results.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.close(os.open(results, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:  # another evaluator claimed it since
            return False
        return True

    def evaluate(self, message: WeightsMessage, stop: threading.Event | None = None,
                 session: Any = None, repeat: bool = True) -> dict[str, Any] | None:
        """Load ``message`` and run the protocol; write, record and publish the result.
        Returns the JSON row, or None when the weights do not load (counted as a reject) or, without
        ``repeat``, when the run's ``eval.jsonl`` holds this evaluation already."""
        version = message.policy_version
        if not self.weights.load(self.net, message):
            return None
        self.last_version = message.version
        weights_digest = weights_sha256(self.net)
        evaluated_as = {"policy_version": version, "weights_sha256": weights_digest, "world": self.world,
                        "protocol": self.protocol.name, "protocol_config": self.protocol.to_dict(),
                        "episodes_per_start": self.episodes_per_start,
                        "max_steps": self.max_steps, "seed": self.seed}  # its row's, and its key
        world_digest = file_world_sha256(self.world)  # read now: the file may have been edited since start-up
        if world_digest is not None:
            evaluated_as[WORLD_META] = world_digest
        key = evaluation_key(evaluated_as)
        if not repeat and key in self.evaluated:
            log.info("policy version %d: these weights were evaluated already (%s), not again", version, EVAL_LOG)
            return None
        stats = self.root / "stats"
        digest = evaluation_digest(key)
        results_file, recording = self._files(self.files_stem(version, digest))
        rrd = recording if self.record else None
        log.info("evaluating policy version %d on %s (%s protocol, %d episode(s) per start, %d steps)", version,
                 self.world, self.protocol.name, self.episodes_per_start, self.max_steps)
        started = time.monotonic()
        meta = {"policy": "greedy", "model": f"{self.run_name}@{version}", "policy_version": version,
                "fingerprint": self.fingerprint, "weights_sha256": weights_digest,
                "evaluator_id": self.evaluator_id, EVALUATION_META: digest}
        live = self.viewer.url if self.viewer is not None and self.viewer.up() else None
        try:
            results = evaluate_recorded(self.policy, world=self.world, sensor_cfg=self.cfg.sensor,
                                        env_cfg=self.cfg.env, episodes_per_start=self.episodes_per_start,
                                        max_steps=self.max_steps, seed=self.seed, rrd=rrd,
                                        image_every=self.image_every, policy_version=version,
                                        recording_name=f"eval {self.run_name} v{version}", progress=False, meta=meta,
                                        stop=stop, rerun_connect=live, protocol=self.protocol)
            duration = time.monotonic() - started
            results_path = save_results(results, results_file)
        except BaseException:  # cancelled or failed: the name it claimed is free again
            with contextlib.suppress(OSError):
                if results_file.stat().st_size == 0:
                    results_file.unlink()
            raise
        summary = results.summary
        row = {"time_unix": time.time(), "evaluator_id": self.evaluator_id, **evaluated_as,
               "duration_s": round(duration, 3), "summary": summary["overall"], "per_start": summary["per_start"],
               "recording": results.meta.get("recording"),  # None: not recorded, or it could not be written
               "results": str(results_path),
               "streamed_to": live,
               "rejected_weights": self.rejects.counts}
        stats.mkdir(parents=True, exist_ok=True)
        append_line(stats / EVAL_LOG, json.dumps(row))  # a row a killed evaluator cut short costs only itself
        self.board.write(Path(EVAL_LOG).stem, {"duration_s": row["duration_s"], **row["summary"]}, version)
        self.evaluations.append(row)
        self.evaluated.add(key)
        if session is not None:
            put_reliable(session, self.keys.eval_results(self.evaluator_id),
                         self.result_message(results, duration).encode())
        o = summary["overall"]
        log.info("policy version %d: mean steps %.1f, distance %.2f m, coverage %.1f %%, collisions %s, "
                 "capped %d (%.1f s)", version, o["mean_steps"], o["mean_distance_m"], o["mean_coverage_pct"],
                 o["collisions"], o["reached_cap"], duration)
        return row

    def evaluate_in_service(self, message: WeightsMessage, stop: threading.Event | None = None,
                            session: Any = None) -> dict[str, Any] | None:
        """:meth:`evaluate` as the service runs it, for as long as the run trains: an evaluation whose
        files cannot be written (a full disk, a quota, a read-only folder: :data:`WRITE_FAILURES`) is said
        in one line and lost, and the next version's goes on (None); its results file stays whole or
        absent, never half written. Weights whose Q-values are not finite are said and skipped alike."""
        try:
            return self.evaluate(message, stop, session, repeat=False)
        except NonFiniteQValues as exc:  # weights that load but overflow: theirs alone, not the next version's
            log.error("policy version %d not evaluated: %s", message.policy_version, exc)
            return None
        except OSError as exc:
            if exc.errno not in WRITE_FAILURES:  # a world file gone, a bug: not for every version to meet again
                raise
            log.error("evaluation of policy version %d lost: %s; the evaluator goes on with the next version",
                      message.policy_version, exc)
            return None

    def result_message(self, results: EvalResults, duration_s: float) -> EvalResult:
        """The wire form of an evaluation (one entry per episode, the summary in ``extra``)."""
        eps = results.episodes
        o = results.summary["overall"]
        extra = {"mean_steps": o["mean_steps"], "mean_distance_m": o["mean_distance_m"],
                 "mean_path_length_m": o["mean_path_length_m"], "mean_coverage_m2": o["mean_coverage_m2"],
                 "mean_coverage_pct": o["mean_coverage_pct"], "reached_cap": o["reached_cap"],
                 "episodes_per_start": self.episodes_per_start, "duration_s": duration_s,
                 **{f"collisions_{cause}": n for cause, n in o["collisions"].items()}}
        return EvalResult(evaluator_id=self.evaluator_id, policy_version=int(results.meta["policy_version"]),
                          world=self.world, speed_table="test", max_steps=self.max_steps,
                          start_index=tuple(e.start_index for e in eps), steps=tuple(e.steps for e in eps),
                          collided=tuple(e.terminated for e in eps),
                          path_length_m=tuple(e.path_length_m for e in eps), extra=extra)

    # -- the loop -----------------------------------------------------------------------------

    def run(self, stop: threading.Event, once: bool = False, wait_weights_s: float = 60.0) -> int:
        """Evaluate until ``stop`` is set (or, with ``once``, the latest weights once). Returns
        a process exit status: 0, or 1 when ``once`` found no weights within ``wait_weights_s``."""
        # the board closed also when no session opens: its writer thread would outlive the service
        with contextlib.closing(self.board), open_service_session(self.settings, stop) as session, \
                self.weights.following(session, self.keys, self.query_timeout_s):
            # Announced once subscribed: whoever sees the token can publish weights to us.
            token = declare_alive(session, self.keys.alive("evaluator", self.evaluator_id))
            log.info("evaluator %s on run %r: every %d updates, %d episode(s) per start, world %s, protocol %s",
                     self.evaluator_id, self.run_name, self.every_updates, self.episodes_per_start, self.world,
                     self.protocol.describe())
            try:
                deadline = time.monotonic() + wait_weights_s
                while not stop.is_set():
                    message = self.weights.take(timeout_s=0.2)
                    if message is None:
                        if once and time.monotonic() > deadline:
                            log.error("no weights for run %r within %.0f s (is the learner running?)",
                                      self.run_name, wait_weights_s)
                            return 1
                        continue
                    if not once and not self.due(message):
                        continue
                    try:
                        row = self.evaluate(message, stop, session, repeat=once) if once \
                            else self.evaluate_in_service(message, stop, session)
                    except EvaluationCancelled:
                        log.info("evaluation of version %d cancelled", message.policy_version)
                        break
                    if once and row is not None:
                        return 0
                return 0
            finally:
                token.undeclare()
                log.info("evaluator %s stopping (rejected weights: %s)", self.evaluator_id,
                         json.dumps(self.rejects.counts))


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------


def run_evaluator(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """``cogexplore evaluator``: returns a process exit status (2: bad options, a configuration the run
    cannot use, or none from its learner; 1: no router or, with ``--once``, no weights). ``stop`` (tests)
    replaces the SIGINT/SIGTERM handlers."""
    try:
        evaluator_id = validate_name(args.id or default_process_id("evaluator"), "evaluator id")
        paths = run_paths(args)
        setup_logging(args.log_level, paths.logs / f"{evaluator_id}.log")
        settings = zenoh_settings(args, "evaluator")
        if not args.once:
            # A watcher, not a worker: where it shares cores with the learner (`up` on one machine), it
            # takes the time the learner leaves, and its evaluations come a little later instead.
            # Before the first session, so that its Zenoh threads, and torch's, take it too.
            lower_priority(EVALUATOR_NICENESS)
        cfg, check = join_run_config(args, paths, settings, "this evaluator")
        # Like the actors, 'auto' means CPU here: the GPU, if any, belongs to the learner.
        device = cfg.train.device if cfg.train.device != "auto" else "cpu"
        episodes = args.episodes_per_start or (PAPER_EPISODES_PER_START if args.full else CHEAP_EPISODES_PER_START)
        service = EvaluatorService(cfg, args.run, paths.root, settings, evaluator_id,
                                   every_updates=args.every_updates, episodes_per_start=episodes,
                                   max_steps=args.max_steps, world=args.world, image_every=args.image_every,
                                   record=not args.no_record, seed=args.seed, device=device,
                                   query_timeout_s=args.query_timeout, rerun_url=args.rerun_connect,
                                   tensorboard=paths.tensorboard_folder(evaluator_id) if args.tensorboard else None,
                                   protocol=protocol_from_args(args))
    except CogexploreError as exc:  # config, world, run name, device: the message says which
        print(f"cogexplore evaluator: error: {exc}", file=sys.stderr)
        return 2
    # One image at a time gains nothing from intra-op threads, and threads that spin-wait on a shared
    # core take it from the learner (py-spy on a 2-core `up`: inference was 63% of its time).
    torch.set_num_threads(1)
    stop = stop if stop is not None else stop_event_on_signals()
    log.info("evaluator %s for run %r via %s", evaluator_id, args.run, settings.describe())
    if check is not None:
        check.start(settings, stop)  # a preset the run's weights do not fit stops the evaluator
    try:
        status = service.run(stop, once=args.once, wait_weights_s=args.wait_weights)
    except StopRequested as exc:  # asked to stop before its router answered: as asked, not a failure
        log.info("%s", exc)
        return 0
    except TransportError as exc:
        log.error("%s", exc)
        return 1
    except CogexploreError as exc:  # an evaluation the protocol cannot run here (a start with no clear draw)
        print(f"cogexplore evaluator: error: {exc}", file=sys.stderr)
        return 2
    finally:
        refused = check.finish() if check is not None else None
    if refused is not None:
        print(f"cogexplore evaluator: error: {refused}", file=sys.stderr)
        return 2
    return status


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.evaluator", description=__doc__.split("\n\n")[0])
    add_evaluator_arguments(parser)
    return run_evaluator(parser.parse_args(argv))
