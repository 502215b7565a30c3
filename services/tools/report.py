"""``cogexplore report RUN_DIR``: the paper's tables and figures for a run, as PNG + Markdown + HTML.

    cogexplore report runs/exp1 [--model CKPT] [--compare CKPT ...] [--out DIR] [--episodes-per-start N]
                                [--world W] [--probe depth.png ...] [--protocol robust paper]

Into ``RUN_DIR/report/`` (or ``--out``), shown by ``report.html`` (for a browser, the figures
inlined while they stay small) and linked from ``report.md`` (the same sections, for terminals and GitHub):

- Table III (Count / Distance per start, plus coverage) for the run's latest checkpoint (or
  ``--model``: ``cogexplore up`` gives the mean of the run's last checkpoints' weights), each
  ``--compare`` checkpoint and the ``random`` and ``reactive`` baselines, once per test protocol
  (``--protocol``, default the robust one first, then the paper's: ``shared.evaluation.PROTOCOLS``),
  with collisions by cause and capped episodes per model and protocol. Results JSON already in the
  run (``report/results/``, the evaluator service's ``stats/eval/``, ``stats/``, the run folder) is
  reused when its weights, protocol and world (by content: an MJCF file edited since is played again)
  match; everything else is evaluated (the full protocol, 10 episodes per start, by default) and
  saved to ``report/results/`` for next time;
- trajectory heatmaps per model and side by side (Fig. 6), under the first protocol;
- the loss curve over learner updates (Fig. 5) from ``stats/learner.csv``, and the evaluator
  service's mean steps per policy version from ``stats/eval.jsonl``, when they exist, ending in
  the report's own evaluation of the run's checkpoint (the final one of ``cogexplore up``) at its
  version under the evaluator's protocol;
- the Q-values of the probe scenes (Table II: ``shared/evaluation/probe_scenes`` plus ``--probe`` images) and
  their receptive-field maps with the chosen command (Fig. 7), for every checkpoint model.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

os.environ.setdefault("RERUN_ANALYTICS", "0")  # offline machines: never phone home

import numpy as np

from services.tools.document import (
    Block,
    Bullets,
    Heading,
    Paragraph,
    Table,
    code_span,
    html_page,
    link_target,
    markdown,
)
from services.tools.options import REPORT_PROTOCOLS
from shared.config import is_whole
from shared.errors import CogexploreError
from shared.evaluation import (
    PAPER_BASELINE_STEPS,
    PAPER_DRL_STEPS,
    PAPER_EPISODES_PER_START,
    PAPER_MAX_STEPS,
    PROTOCOLS,
    TEST_SEED,
    ProtocolConfig,
    protocol_named,
)
from shared.evaluation.eval_log import EVAL_LOG, load_eval_log, row_protocol
from shared.evaluation.protocol import WORLD_META, evaluate_policy, file_world_sha256, played_as_now, world_sha256
from shared.evaluation.results import (
    EvalResults,
    ResultsError,
    aggregate,
    escape_text,
    load_results,
    save_results,
    slug,
    table_markdown,
)
from shared.evaluation.setup import EvalSetup, setup_evaluation
from shared.files import atomic_write_text, save_png
from shared.learning.checkpoints import LoadedModel, load_model, resolve_checkpoint
from shared.learning.stats import TrainingSummary, summarize_learner_log

log = logging.getLogger("cogexplore.report")

BASELINES: tuple[str, ...] = ("random", "reactive")
LEARNER_LOG = "learner.csv"
# Meta fields that must agree for a stored result to stand for a new evaluation.
PROTOCOL_KEYS: tuple[str, ...] = ("policy", "world", "speed_table", "starts", "episodes_per_start", "max_steps",
                                  "seed", "protocol", "sensor", "env")


class ReportError(CogexploreError):
    """A run folder, checkpoint or probe the report cannot use."""


@dataclass
class ReportModel:
    """One column group of the report: a model, how it was evaluated, and its results by protocol name."""

    name: str
    setup: EvalSetup
    stem: str
    """The name in its file names: its slug, unique in the report (``_unique_slug``)."""
    results: dict[str, EvalResults] = field(default_factory=dict)
    reused_from: dict[str, Path] = field(default_factory=dict)

    @property
    def model(self) -> LoadedModel | None:
        return self.setup.model


@dataclass
class Report:
    """What ``build_report`` produced: the Markdown and HTML files, every figure, the results files
    (``{protocol name: {model name: path}}``), notes and the evaluation curve's points."""

    markdown: Path
    html: Path
    figures: list[Path] = field(default_factory=list)
    results: dict[str, dict[str, Path]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    eval_curve: list[EvalPoint] = field(default_factory=list)


ResultsCache = dict[tuple[Path, int, int], "EvalResults | None"]
"""Results files read so far, by (path, size, mtime): a file written since is read anew."""


def _load_cached(path: Path, cache: ResultsCache) -> EvalResults | None:
    """``path``'s results, or None when it holds none (configs, other JSON: not ours to judge)."""
    try:
        stat = path.stat()
    except OSError:
        return None
    key = (path, stat.st_size, stat.st_mtime_ns)
    if key not in cache:
        try:
            cache[key] = load_results(path)
        except ResultsError:
            cache[key] = None
    return cache[key]


def find_results(search_dirs: Sequence[Path], want: Mapping[str, Any], optional: Sequence[str] = (),
                 cache: ResultsCache | None = None) -> tuple[EvalResults, Path] | None:
    """The first stored results JSON in ``search_dirs`` whose meta matches ``want`` (every key
    equal, after a JSON round trip so tuples compare as lists; a key in ``optional`` may also be
    missing, from a file written before results recorded it). ``cache`` keeps the files read
    across calls (a report looks for every model under every protocol in the same folders)."""
    want = json.loads(json.dumps(dict(want)))
    cache = {} if cache is None else cache
    for d in search_dirs:
        if not d.is_dir():
            continue
        for path in sorted(d.glob("*.json")):
            results = _load_cached(path, cache)
            if results is not None and all(results.meta.get(k) == v or (k in optional and k not in results.meta)
                                           for k, v in want.items()):
                return results, path
    return None


def _protocol_meta(setup: EvalSetup, world: str, world_digest: str, episodes_per_start: int, max_steps: int,
                   seed: int, starts: list[int], protocol: ProtocolConfig) -> dict[str, Any]:
    from dataclasses import asdict

    from shared.evaluation.protocol import protocol_env_config

    env = protocol_env_config(setup.env_cfg, world, max_steps)
    want = {"policy": setup.policy, "world": world, WORLD_META: world_digest, "speed_table": "test", "starts": starts,
            "episodes_per_start": episodes_per_start, "max_steps": max_steps, "seed": seed,
            "protocol": protocol.to_dict(), "sensor": asdict(protocol.sensor(setup.sensor_cfg)),
            "env": {k: v for k, v in asdict(env).items() if k != "start_index"}}
    if setup.model is not None:
        want["weights_sha256"] = setup.model.weights_sha256
    return want | setup.draws_meta()


def _unique(name: str, taken: set[str], form: str = "{} ({})", fold: Callable[[str], str] = str) -> str:
    """``name``, or ``form`` of it and 2, 3, ... when one already in ``taken`` (compared by ``fold``);
    adds it to ``taken``."""
    out, k = name, 2
    while fold(out) in taken:
        out, k = form.format(name, k), k + 1
    taken.add(fold(out))
    return out


def _unique_slug(name: str, taken: set[str]) -> str:
    """``slug(name)``, with ``-2``, ``-3``, ... when one already in ``taken`` is the same but for
    case: "a b" and "a-b" would otherwise write (and show) one another's files, and a case-blind
    file system holds "A" and "a" as one file. Adds it to ``taken``."""
    return _unique(slug(name), taken, "{}-{}", str.casefold)


# ---------------------------------------------------------------------------------------------
# Figures beyond services/viz/figures.py
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EvalPoint:
    """One point of the evaluation curve: a policy version (learner updates) and its mean moving steps."""

    policy_version: int
    mean_steps: float
    episodes_per_start: int | None
    max_steps: int | None
    final: bool = False
    protocol: str = "paper"
    """The test protocol's name (rows the evaluator wrote before it recorded one ran the paper's)."""
    world: str | None = None
    """The world evaluated in, as the evaluator was given it (None: a row that did not say)."""
    protocol_config: ProtocolConfig | None = None
    """The protocol's every field (None: a row from before the evaluator recorded them)."""

    @property
    def protocol_set(self) -> ProtocolConfig | str:
        """What the points of one curve share: the protocol's fields, a named protocol's for a row
        that gave only its name; the name alone for a ``custom`` one that did (its fields unknown)."""
        return self.protocol_config or PROTOCOLS.get(self.protocol) or self.protocol

    @property
    def protocol_label(self) -> str:
        """The protocol as the report names it: a named protocol by its name, any other set with
        what it sets (two ``custom`` ones must read apart)."""
        config = self.protocol_config
        return config.describe() if config is not None and config != PROTOCOLS.get(config.name) else self.protocol

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> EvalPoint:
        """A periodic evaluation, from a row of ``eval.jsonl``."""
        world = row.get("world")
        return cls(row["policy_version"], float(row["summary"]["mean_steps"]), row.get("episodes_per_start"),
                   row.get("max_steps"), protocol=str(row.get("protocol", "paper")),
                   world=world if isinstance(world, str) else None, protocol_config=row_protocol(row))

    @classmethod
    def final_of(cls, results: EvalResults, world: str) -> EvalPoint | None:
        """The final evaluation of a checkpoint in ``world``, at the version its weights were saved
        at; None when its results do not say which version (a hand-edited or older file)."""
        meta = results.meta
        version = meta.get("policy_version")
        if not (is_whole(version) and version >= 0):
            return None
        return cls(int(version), float(results.summary["overall"]["mean_steps"]),
                   meta.get("episodes_per_start"), meta.get("max_steps"), final=True,
                   protocol=results.protocol.name, world=world, protocol_config=results.protocol)


def eval_curve_points(rows: Sequence[Mapping[str, Any]], final: EvalPoint | None = None
                      ) -> tuple[list[EvalPoint], int]:
    """The evaluator's periodic evaluations in the world and protocol (:attr:`EvalPoint.protocol_set`)
    of its newest one, and the final one if it was measured in the same, by policy version; and how
    many rows were left out (other worlds or protocols: one line must not join two tasks). The final
    evaluation stands in for a periodic one of the same version (it is Table III's number), so no
    version is drawn twice."""
    if not rows:
        return [], 0
    every = [EvalPoint.from_row(r) for r in rows]
    task = (every[-1].world, every[-1].protocol_set)
    points = [p for p in every if (p.world, p.protocol_set) == task]
    left_out = len(every) - len(points)
    # A row from before the evaluator recorded its world ran the run's own, the report's default.
    if final is not None and final.protocol_set == task[1] and task[0] in (None, final.world):
        points = [p for p in points if p.policy_version != final.policy_version] + [final]
    return sorted(points, key=lambda p: p.policy_version), left_out


def rows_of_worlds_now(rows: Sequence[Mapping[str, Any]], digest_now: Callable[[str], str | None]
                       ) -> tuple[list[Mapping[str, Any]], int]:
    """The ``eval.jsonl`` rows played on their world as it is now, and how many were not. A row of an
    MJCF file world stands for it only when its :data:`WORLD_META` is ``digest_now(world)`` (a file edited
    since is another world under the same name; a row without the digest cannot say which it played);
    ``digest_now`` gives None for a built-in or procedural world, fixed by its name: all its rows stand.
    A row that does not name its world stands too (it ran the run's own: :func:`eval_curve_points`)."""
    kept = [r for r in rows if not isinstance(r.get("world"), str) or played_as_now(r, digest_now(r["world"]))]
    return kept, len(rows) - len(kept)


def save_eval_curve_png(points: Sequence[EvalPoint], out_path: Path, dpi: int = 110) -> Path:
    """Mean moving steps against policy version, the final evaluation marked."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    from shared.sim.maps import plain_text

    fig = Figure(figsize=(7.0, 3.6))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([p.policy_version for p in points], [p.mean_steps for p in points], marker="o", lw=1.5,
            label="mean moving steps")
    for p in points:
        if p.final:
            ax.plot([p.policy_version], [p.mean_steps], marker="*", ms=14, color="tab:red", ls="none",
                    label=f"final evaluation (version {p.policy_version})")
    for cap in sorted({p.max_steps for p in points if p.max_steps}):
        ax.axhline(cap, color="gray", lw=0.8, ls="--", label=f"step cap ({cap})")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("policy version (learner updates)")
    ax.set_ylabel("mean moving steps")
    protocols = sorted({p.protocol_label for p in points})
    worlds = sorted({p.world or "world not recorded" for p in points})
    ax.set_title(plain_text(f"Evaluations during training: {', '.join(worlds)}\nprotocol {'; '.join(protocols)}"),
                 fontsize="medium")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return save_png(fig, out_path, dpi)


# ---------------------------------------------------------------------------------------------
# The report
# ---------------------------------------------------------------------------------------------


def training_line(t: TrainingSummary) -> str:
    """One sentence on how much training the run had, from its learner log."""
    parts = [f"Training: {t.updates} updates"]
    if t.transitions is not None:
        parts.append(f" from {t.transitions} transitions")
    if t.learner_s:
        parts.append(f" in {t.learner_s / 60:.1f} min of learner time ({t.updates_per_s:.1f} updates/s)")
    if t.lr_first is not None and t.lr_last is not None:
        parts.append(f"; learning rate {t.lr_first:.3g}" + (f" falling to {t.lr_last:.3g}" if t.lr_last != t.lr_first
                                                             else ", constant"))
    return "".join(parts) + f" (`stats/{LEARNER_LOG}`)."


def build_report(run_dir: str | Path, *, model: str | Path | None = None, compare: Sequence[str | Path] = (),
                 out_dir: str | Path | None = None,
                 episodes_per_start: int = PAPER_EPISODES_PER_START, max_steps: int = PAPER_MAX_STEPS,
                 world: str | None = None, probe_files: Sequence[str | Path] = (), seed: int = TEST_SEED,
                 device: str = "cpu", progress: bool = True,
                 baselines: Sequence[str] = BASELINES,
                 protocols: Sequence[str | ProtocolConfig] = REPORT_PROTOCOLS) -> Report:
    """Evaluate (or reuse results for) every model under every protocol (names or configs, in
    Table III's order) and write the report; see the module docstring. ``model`` stands for the run
    in place of its latest checkpoint (``cogexplore up``: the mean of its last checkpoints)."""
    from services.tools.receptive import (
        ReceptiveFieldError,
        receptive_field,
        render_receptive_png,
    )
    from services.viz.figures import (
        FigureError,
        q_value_table_markdown,
        save_heatmap_png,
        save_heatmaps_side_by_side,
        save_loss_curve_png,
    )
    from shared.config import load_preset
    from shared.evaluation.probes import ProbeError, load_probe_image, load_probes
    from shared.sim.maps import free_area_m2, occupancy_grid
    from shared.sim.world import WorldError, canonical_world_name, load_world

    run = Path(run_dir)
    if not run.is_dir():
        raise ReportError(f"run folder {run} does not exist")
    conditions = [protocol_named(p) if isinstance(p, str) else p for p in protocols]
    if not conditions or len({c.name for c in conditions}) != len(conditions):
        raise ReportError(f"give one or more different protocols, got {[c.name for c in conditions]}")
    lead = conditions[0].name
    out = Path(out_dir) if out_dir is not None else run / "report"
    out.mkdir(parents=True, exist_ok=True)
    report = Report(markdown=out / "report.md", html=out / "report.html")
    notes = report.notes
    run_cfg = load_preset(run / "config.toml", complete=True) if (run / "config.toml").is_file() else None

    for f in probe_files:  # refuse a bad probe before spending minutes on evaluations
        try:
            load_probe_image(f)
        except ProbeError as exc:
            raise ReportError(f"--probe {f}: {exc}") from None

    # -- the models -------------------------------------------------------------------------
    taken: set[str] = set()
    stems: set[str] = set()
    models: list[ReportModel] = []
    loaded: list[LoadedModel] = []
    run_has_checkpoint = model is not None or resolve_checkpoint(run) is not None
    if not run_has_checkpoint:
        notes.append(f"The run has no checkpoint yet ({run / 'checkpoints'}): only the baselines are evaluated.")
    else:
        loaded.append(load_model(run if model is None else model, device))
    for c in compare:
        loaded.append(load_model(c, device))
    first_cfg = loaded[0].run_config if loaded else None
    # canonical (procedural:0301 is procedural:301): results record that name, and the search below matches it
    world_name = canonical_world_name(world or (run_cfg or first_cfg or load_preset("paper")).env.world)
    for m in loaded:
        setup = setup_evaluation("greedy", model=m, world=world_name, seed=seed)
        name = _unique(m.label, taken)
        models.append(ReportModel(name, setup, _unique_slug(name, stems)))
    for name in baselines:
        setup = _baseline_setup(name, run_cfg, loaded[0] if loaded else None, world_name, seed)
        name = _unique(name, taken)
        models.append(ReportModel(name, setup, _unique_slug(name, stems)))

    # -- results: reuse or evaluate ---------------------------------------------------------
    world_obj = load_world(world_name)
    starts = list(range(len(world_obj.starts)))
    results_dir = out / "results"
    # Ours first (this --out's, then the run's own report's), then the evaluator service's
    # (stats/eval/), then anything the user put in the run.
    search = list(dict.fromkeys([results_dir, run / "report" / "results", run / "stats" / "eval", run / "stats",
                                 run, run / "results"]))
    result_files: set[str] = set()
    # A built-in or procedural world is fixed by its name: results from before they recorded the world's
    # content stand for it. A file's content is not (the user edits it): those stand for nothing.
    undigested = () if world_obj.kind == "file" else (WORLD_META,)
    world_digest = world_sha256(world_obj)
    read: ResultsCache = {}
    for protocol in conditions:
        saved: dict[str, Path] = {}
        for m in models:
            want = _protocol_meta(m.setup, world_name, world_digest, episodes_per_start, max_steps, seed, starts,
                                  protocol)
            found = find_results(search, want, optional=undigested, cache=read)
            if found is not None:
                m.results[protocol.name], m.reused_from[protocol.name] = found
                if found[1].parent == results_dir:  # not to be overwritten by another model's results
                    result_files.add(found[1].stem.casefold())
                log.info("%s, %s protocol: reusing %s", m.name, protocol.name, found[1])
                continue
            log.info("%s, %s protocol: evaluating (%d starts x %d episodes, %d steps at most)", m.name,
                     protocol.name, len(starts), episodes_per_start, max_steps)
            m.results[protocol.name] = evaluate_policy(
                m.setup.policy_fn, world=world_name, sensor_cfg=m.setup.sensor_cfg, env_cfg=m.setup.env_cfg,
                episodes_per_start=episodes_per_start, max_steps=max_steps, seed=seed, progress=progress,
                meta={**m.setup.meta(), "model": m.name}, protocol=protocol)
            stem = _unique_slug(f"{m.stem}-{protocol.name}", result_files)
            saved[m.name] = save_results(m.results[protocol.name], results_dir / f"{stem}.json")
        report.results[protocol.name] = {m.name: m.reused_from.get(protocol.name) or saved[m.name] for m in models}

    # -- heatmaps ---------------------------------------------------------------------------
    grid = occupancy_grid(world_obj)
    heatmaps: dict[str, Path] = {}
    for m in models:
        try:
            heatmaps[m.name] = save_heatmap_png(world_obj, grid, m.results[lead], out / f"heatmap-{m.stem}.png",
                                                title=f"{m.name} on {world_name} ({lead} protocol)")
        except FigureError as exc:
            notes.append(f"No heatmap for {m.name}: {exc}")
    side_by_side = None
    if heatmaps:
        side_by_side = save_heatmaps_side_by_side(world_obj, grid, {m.name: m.results[lead] for m in models
                                                                    if m.name in heatmaps}, out / "heatmaps.png")
    report.figures += list(heatmaps.values()) + ([side_by_side] if side_by_side else [])

    # -- training curves --------------------------------------------------------------------
    loss_png = training = None
    learner_csv = run / "stats" / LEARNER_LOG
    if learner_csv.is_file():
        try:
            training = summarize_learner_log(learner_csv)
        except OSError as exc:
            notes.append(f"The training line could not be read from {learner_csv}: {exc}")
        try:
            loss_png = save_loss_curve_png(learner_csv, out / "loss.png", title=f"Training loss ({run.name})")
            report.figures.append(loss_png)
        except FigureError as exc:
            notes.append(f"The loss curve could not be drawn from {learner_csv}: {exc}")
    else:
        notes.append(f"No loss curve: {learner_csv} does not exist (the learner writes it during training).")
    eval_png = None
    eval_log = run / "stats" / EVAL_LOG
    rows = load_eval_log(eval_log) if eval_log.is_file() else []
    world_digests = {world_name: world_digest if world_obj.kind == "file" else None}

    def digest_now(name: str) -> str | None:
        if name not in world_digests:
            try:
                world_digests[name] = file_world_sha256(name)
            except WorldError:  # a file gone or broken since: it holds none of the content its rows played
                world_digests[name] = ""
        return world_digests[name]

    rows, edited = rows_of_worlds_now(rows, digest_now)
    if edited:
        note = (f"Evaluations during training: {edited} evaluation(s) played on an MJCF world file as it was "
                f"before an edit (or before evaluations recorded its content) are not drawn ({eval_log}).")
        log.warning("%s", note)
        notes.append(note)
    if rows:  # the evaluator ran during training: its curve, ending in this report's evaluation of the run
        evaluator_protocol = EvalPoint.from_row(rows[-1]).protocol
        run_results = models[0].results.get(evaluator_protocol) if run_has_checkpoint else None  # the run's
        final = EvalPoint.final_of(run_results, world_name) if run_results is not None else None
        report.eval_curve, left_out = eval_curve_points(rows, final)
        if left_out:
            notes.append(f"Evaluations during training: {left_out} evaluation(s) in another world or protocol "
                         f"than the evaluator's newest are not drawn ({eval_log}).")
        eval_png = save_eval_curve_png(report.eval_curve, out / "eval-curve.png")
        report.figures.append(eval_png)

    # -- probes: Table II and receptive fields ------------------------------------------------
    greedy = [m for m in models if m.model is not None]
    q_scenes: dict[str, dict[str, np.ndarray]] = {}
    scene_rows: list[tuple[str, str]] = []
    receptive: dict[tuple[str, str], Path] = {}
    probe_notes: list[str] = []
    receptive_files: set[str] = set()
    scene_names: set[str] = set()
    # One name per user image, however many share a file stem (a/door.png, b/door.png)
    user_scenes = [_unique(f"user:{Path(f).stem}", scene_names) for f in probe_files]
    if not greedy:
        notes.append("No Q-value table or receptive fields: there is no checkpoint to probe.")
    for m in greedy:
        net = m.model.net
        try:
            probes = load_probes(sensor_cfg=net.sensor_cfg)
        except ProbeError as exc:
            probes = []
            notes.append(f"Stored probe scenes unavailable: {exc}")
        scenes: list[tuple[str, np.ndarray, str]] = [(p.name, p.depth_m, p.meta.get("description", "")) for p in probes]
        for note in (n for p in probes for n in p.notes):
            if note not in probe_notes:
                probe_notes.append(note)
        for f, scene in zip(probe_files, user_scenes):
            try:
                depth, file_notes = load_probe_image(f, net.sensor_cfg)
            except ProbeError as exc:
                raise ReportError(f"--probe {f}: {exc}") from None
            scenes.append((scene, depth, f"user image {f}"))
            probe_notes += [n for n in file_notes if n not in probe_notes]
        for scene, depth, description in scenes:
            if (scene, description) not in scene_rows:
                scene_rows.append((scene, description))
            try:
                _, mask, q, action = receptive_field(net, depth)
            except ReceptiveFieldError as exc:
                from shared.learning.policy import EpsilonGreedyPolicy

                q = EpsilonGreedyPolicy(net).q_values(depth)  # a network that reads several images sees this one
                note = f"No receptive field for {m.name}: {exc}"
                if note not in notes:
                    notes.append(note)
            else:
                stem = _unique_slug(f"{m.stem}-{scene}", receptive_files)
                path = render_receptive_png(depth, mask, q, action, out / "receptive" / f"{stem}.png",
                                            title=f"{scene} / {m.name}")
                receptive[(scene, m.name)] = path
                report.figures.append(path)
            q_scenes.setdefault(scene, {})[m.name] = q

    # -- the document: one list of blocks, written as Markdown and as HTML ----------------------
    def rel(p: Path) -> str:
        return link_target(os.path.relpath(p, out).replace(os.sep, "/"))

    doc: list[Block] = [Heading(1, f"Report: run {code_span(run.name)}")]
    free = free_area_m2(grid)
    doc += [Heading(2, "Protocol"), Bullets((
        (f"World {code_span(world_name)} ({len(starts)} start poses, {free:.1f} m² free), TEST speed table, "
         f"greedy policies (dropout off)."),
        f"{episodes_per_start} episode(s) per start, at most {max_steps} moving steps each; seed {seed}.",
        *(f"Protocol {escape_text(c.describe())}." for c in conditions),
        *((("Jittered starts and sensor noise are drawn from (seed, start, episode) alone: every model meets "
            "the same."),) if not all(c.exact for c in conditions) else ()),
        ("Count = mean moving steps before a collision or the cap; Distance = mean straight-line distance "
         "from the start to the end pose (m); Coverage = mean % of the free area the camera saw.")))]
    model_rows = []
    for m in models:
        src = f"{code_span(m.model.path)} ({_versions(m.model)})" if m.model is not None else "baseline"
        links_ = []
        for c in conditions:
            res = report.results[c.name][m.name]
            how = "reused" if c.name in m.reused_from else "evaluated"
            links_.append(f"{escape_text(c.name)} {how}: [{escape_text(res.name)}]({rel(res)})")
        model_rows.append((escape_text(m.name), m.setup.policy, src, "; ".join(links_)))
    doc += [Heading(2, "Models"), Table(("Model", "Policy", "Source", "Results"), (False,) * 4, tuple(model_rows))]
    for c in conditions:
        doc += [Heading(2, f"Table III, {escape_text(c.name)} protocol: moving steps and distance per start point"),
                Paragraph(f"_{escape_text(c.describe())}._"),
                Table.from_markdown(table_markdown({m.name: m.results[c.name] for m in models}))]
    # Beside the paper's own figures (its protocol: exact starts, no noise; Gazebo, 160 x 120 depth)
    means = {(m.name, c.name): aggregate(m.results[c.name].episodes)["overall"]["mean_steps"]
             for m in models for c in conditions}
    paper_rows = [(escape_text(m.name), "this report", *(f"{means[m.name, c.name]:.1f}" for c in conditions), "")
                  for m in models]
    paper_rows += [(f"paper: {name}", "Tai & Liu 2016, Table III", *("" for _ in conditions), f"{v:.1f}")
                   for name, v in [*PAPER_BASELINE_STEPS.items(),
                                   *((f"DRL-{k}", v) for k, v in PAPER_DRL_STEPS.items())]]
    cap = (f"of {max_steps}" if max_steps == PAPER_MAX_STEPS
           else f"of {max_steps} here, of {PAPER_MAX_STEPS} in the paper")  # another cap: not one scale
    doc += [Heading(2, f"Beside the paper's Table III: mean moving steps {cap}"),
            Paragraph("The paper's figures come from its own protocol (exact starts, no sensor noise) in Gazebo; "
                      f"its best, DRL-40000, is {PAPER_DRL_STEPS[40000]}."),
            Table(("Model", "Source", *(f"{escape_text(c.name)} protocol" for c in conditions), "paper's figure"),
                  (False, False) + (True,) * (len(conditions) + 1), tuple(paper_rows))]
    outcome_rows = []
    for c in conditions:
        for m in models:
            o = aggregate(m.results[c.name].episodes)["overall"]
            outcome_rows.append((escape_text(m.name), escape_text(c.name), str(o["episodes"]),
                                 str(o["collisions"]["depth"]),
                                 str(o["collisions"]["contact"]), str(o["reached_cap"]),
                                 f"{o['mean_path_length_m']:.2f}"))
    doc += [Heading(3, "Outcomes"),
            Table(("Model", "Protocol", "Episodes", "Collisions (depth)", "Collisions (contact)", "Reached cap",
                   "Mean path (m)"), (False, False) + (True,) * 5, tuple(outcome_rows))]
    doc.append(Heading(2, f"Fig. 6: trajectory heatmaps ({lead} protocol)"))
    if side_by_side is not None:
        doc.append(Paragraph(f"![heatmaps]({rel(side_by_side)})"))
    if heatmaps:
        doc.append(Paragraph(" · ".join(f"[{escape_text(n)}]({rel(p)})" for n, p in heatmaps.items())))
    doc.append(Heading(2, "Fig. 5: training loss"))
    if training is not None:
        doc.append(Paragraph(training_line(training)))
    doc.append(Paragraph(f"![loss]({rel(loss_png)})" if loss_png else "_No loss curve: see the notes below._"))
    if eval_png is not None:
        doc += [Heading(3, "Evaluations during training"), Paragraph(f"![evaluations]({rel(eval_png)})"),
                Table(("Policy version", "Mean moving steps", "Protocol", "Episodes per start", "Step cap",
                       "Evaluation"), (True, True, False, True, True, False),
                      tuple((str(p.policy_version), f"{p.mean_steps:.1f}", escape_text(p.protocol_label),
                             str(p.episodes_per_start or "-"),
                             str(p.max_steps or "-"), "**final** (Table III)" if p.final else "during training")
                            for p in report.eval_curve))]
    doc.append(Heading(2, "Table II: Q-values of the probe scenes"))
    if q_scenes:
        doc += [Table.from_markdown(q_value_table_markdown(q_scenes)),
                Table(("Scene", "What it shows"), (False, False),
                      tuple((escape_text(s), escape_text(d)) for s, d in scene_rows)),
                Heading(2, "Fig. 7: receptive fields (top 10 % of pool3, purple) and the chosen command")]
        if receptive:
            names = [m.name for m in greedy]
            doc += [Table(("Scene", *map(escape_text, names)), (False,) * (len(names) + 1),
                          tuple((escape_text(scene), *(f"![{escape_text(f'{scene} {n}')}]({rel(receptive[(scene, n)])})"
                                          if (scene, n) in receptive else "-" for n in names))
                                for scene, _ in scene_rows))]
    else:
        doc.append(Paragraph("_No checkpoint to probe: see the notes below._"))
    all_notes = notes + probe_notes
    if all_notes:
        doc += [Heading(2, "Notes"), Bullets(tuple(map(escape_text, all_notes)))]
    # whole or not at all: a report written again on a full disk keeps the earlier one, not half of each
    atomic_write_text(report.markdown, markdown(doc))
    atomic_write_text(report.html, html_page(doc, f"Report: run {run.name}", out))
    return report


def _versions(model: LoadedModel) -> str:
    """'version N', or for a mean of checkpoints' weights which versions it averages."""
    versions = [s["policy_version"] for s in model.averaged_from]
    if len(versions) < 2:
        return f"version {model.policy_version}"
    return f"the mean of {len(versions)} checkpoints' weights, versions {', '.join(map(str, versions))}"


def _baseline_setup(name: str, run_cfg: Any, model: LoadedModel | None, world: str, seed: int) -> EvalSetup:
    """A baseline that sees the run's own sensor and robot: the run's config, else its
    checkpoint's, else the paper preset's (the map expert plans for that robot too, as the
    episodes play it)."""
    from shared.config import EnvConfig, load_preset
    from shared.evaluation.policies import make_policy

    if run_cfg is not None:
        sensor, env = run_cfg.sensor, run_cfg.env
    elif model is not None:
        sensor = model.net.sensor_cfg
        env = model.run_config.env if model.run_config is not None else EnvConfig()
    else:
        paper = load_preset("paper")
        sensor, env = paper.sensor, paper.env
    return EvalSetup(name, make_policy(name, sensor_cfg=sensor, seed=seed, env_cfg=env), sensor, env, world, None)


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------


def run_report(args: argparse.Namespace) -> int:
    """``cogexplore report``: returns a process exit status."""
    from services.options import apply_cpu_threads

    apply_cpu_threads(args.threads)
    report = build_report(args.run_dir, model=args.model, compare=args.compare, out_dir=args.out,
                          episodes_per_start=args.episodes_per_start, max_steps=args.max_steps,
                          world=args.world, probe_files=args.probe, seed=args.seed, device=args.device,
                          progress=not args.quiet, protocols=args.protocol)
    for note in report.notes:
        print(f"note: {note}")
    print(report.html)
    print(report.markdown)
    return 0
