"""``cogexplore report RUN_DIR``: the paper's tables and figures for a run, as PNG + Markdown.

    cogexplore report runs/exp1 [--compare CKPT ...] [--out DIR] [--episodes-per-start N] [--world W]
                                [--probe depth.png ...]

Into ``RUN_DIR/report/`` (or ``--out``), linked from ``report.md``:

- Table III (Count / Distance per start, plus coverage) for the run's latest checkpoint, each
  ``--compare`` checkpoint and the ``random`` and ``reactive`` baselines, with collisions by
  cause and capped episodes per model. Results JSON already in the run (``report/results/``,
  the evaluator service's ``stats/eval/``, ``stats/``, the run folder) is reused when its
  weights and protocol match; everything else is evaluated (the full protocol, 10 episodes per
  start, by default) and saved to ``report/results/`` for next time;
- trajectory heatmaps per model and side by side (Fig. 6);
- the loss curve over learner updates (Fig. 5) from ``stats/learner.csv``, and the evaluator
  service's mean steps per policy version from ``stats/eval.jsonl``, when they exist;
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
from typing import Any, Mapping, Sequence

os.environ.setdefault("RERUN_ANALYTICS", "0")  # offline machines: never phone home

import numpy as np

from shared.errors import CogexploreError
from shared.evaluation import PAPER_EPISODES_PER_START, PAPER_MAX_STEPS
from shared.evaluation.protocol import evaluate_policy
from shared.evaluation.results import (
    EvalResults,
    ResultsError,
    aggregate,
    load_results,
    save_results,
    slug,
    table_markdown,
)
from shared.evaluation.setup import EvalSetup, setup_evaluation
from shared.learning.checkpoints import LoadedModel, load_model, resolve_checkpoint

log = logging.getLogger("cogexplore.report")

BASELINES: tuple[str, ...] = ("random", "reactive")
LEARNER_LOG = "learner.csv"
EVAL_LOG = "eval.jsonl"
# Meta fields that must agree for a stored result to stand for a new evaluation.
PROTOCOL_KEYS: tuple[str, ...] = ("policy", "world", "speed_table", "starts", "episodes_per_start", "max_steps",
                                  "seed", "sensor", "env")


class ReportError(CogexploreError):
    """A run folder, checkpoint or probe the report cannot use."""


@dataclass
class ReportModel:
    """One column group of the report: a model, how it was evaluated, and its results."""

    name: str
    setup: EvalSetup
    results: EvalResults | None = None
    reused_from: Path | None = None

    @property
    def model(self) -> LoadedModel | None:
        return self.setup.model


@dataclass
class Report:
    """What ``build_report`` produced: the Markdown file and every figure, plus notes."""

    markdown: Path
    figures: list[Path] = field(default_factory=list)
    results: dict[str, Path] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def _matches(meta: Mapping[str, Any], want: Mapping[str, Any]) -> bool:
    return all(meta.get(k) == want[k] for k in want)


def find_results(search_dirs: Sequence[Path], want: Mapping[str, Any]) -> tuple[EvalResults, Path] | None:
    """The first stored results JSON in ``search_dirs`` whose meta matches ``want`` (every key
    equal, after a JSON round trip so tuples compare as lists)."""
    want = json.loads(json.dumps(dict(want)))
    for d in search_dirs:
        if not d.is_dir():
            continue
        for path in sorted(d.glob("*.json")):
            try:
                results = load_results(path)
            except ResultsError:
                continue  # not a results file (configs, other JSON): not ours to judge
            if _matches(results.meta, want):
                return results, path
    return None


def _protocol_meta(setup: EvalSetup, world: str, episodes_per_start: int, max_steps: int, seed: int,
                   starts: list[int]) -> dict[str, Any]:
    from dataclasses import asdict

    from shared.evaluation.protocol import protocol_env_config

    env = protocol_env_config(setup.env_cfg, world, max_steps)
    want = {"policy": setup.policy, "world": world, "speed_table": "test", "starts": starts,
            "episodes_per_start": episodes_per_start, "max_steps": max_steps, "seed": seed,
            "sensor": asdict(setup.sensor_cfg),
            "env": {k: v for k, v in asdict(env).items() if k != "start_index"}}
    if setup.model is not None:
        want["weights_sha256"] = setup.model.weights_sha256
    return want


def _unique(name: str, taken: set[str]) -> str:
    out, k = name, 2
    while out in taken:
        out, k = f"{name} ({k})", k + 1
    taken.add(out)
    return out


# ---------------------------------------------------------------------------------------------
# Figures beyond services/viz/figures.py
# ---------------------------------------------------------------------------------------------


def load_eval_log(path: Path) -> list[dict[str, Any]]:
    """The evaluator service's ``eval.jsonl`` rows (bad lines skipped), sorted by version."""
    rows = []
    for line in path.read_text(errors="replace").splitlines():  # a damaged line is skipped like a bad one
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if (isinstance(row, dict) and isinstance(row.get("policy_version"), int)
                and isinstance(row.get("summary"), dict)):
            rows.append(row)
    return sorted(rows, key=lambda r: r["policy_version"])


def save_eval_curve_png(rows: Sequence[Mapping[str, Any]], out_path: Path, dpi: int = 110) -> Path:
    """Mean moving steps (and capped episodes) of the evaluator's runs against policy version."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    versions = [r["policy_version"] for r in rows]
    fig = Figure(figsize=(7.0, 3.6))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(versions, [r["summary"]["mean_steps"] for r in rows], marker="o", lw=1.5, label="mean moving steps")
    cap = [r.get("max_steps") for r in rows]
    if cap and cap[0]:
        ax.axhline(cap[0], color="gray", lw=0.8, ls="--", label=f"step cap ({cap[0]})")
    ax.set_xlabel("policy version (learner updates)")
    ax.set_ylabel("mean moving steps")
    ax.set_title("Evaluations during training")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=dpi)
    return out_path


# ---------------------------------------------------------------------------------------------
# The report
# ---------------------------------------------------------------------------------------------


def build_report(run_dir: str | Path, *, compare: Sequence[str | Path] = (), out_dir: str | Path | None = None,
                 episodes_per_start: int = PAPER_EPISODES_PER_START, max_steps: int = PAPER_MAX_STEPS,
                 world: str | None = None, probe_files: Sequence[str | Path] = (), seed: int = 0,
                 device: str = "cpu", progress: bool = True,
                 baselines: Sequence[str] = BASELINES) -> Report:
    """Evaluate (or reuse results for) every model and write the report; see the module docstring."""
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
    from shared.sim.world import load_world

    run = Path(run_dir)
    if not run.is_dir():
        raise ReportError(f"run folder {run} does not exist")
    out = Path(out_dir) if out_dir is not None else run / "report"
    out.mkdir(parents=True, exist_ok=True)
    report = Report(markdown=out / "report.md")
    notes = report.notes
    run_cfg = load_preset(str(run / "config.toml")) if (run / "config.toml").is_file() else None

    for f in probe_files:  # refuse a bad probe before spending minutes on evaluations
        try:
            load_probe_image(f)
        except ProbeError as exc:
            raise ReportError(f"--probe {f}: {exc}") from None

    # -- the models -------------------------------------------------------------------------
    taken: set[str] = set()
    models: list[ReportModel] = []
    loaded: list[LoadedModel] = []
    if resolve_checkpoint(run) is None:
        notes.append(f"The run has no checkpoint yet ({run / 'checkpoints'}): only the baselines are evaluated.")
    else:
        loaded.append(load_model(run, device))
    for c in compare:
        loaded.append(load_model(c, device))
    first_cfg = loaded[0].run_config if loaded else None
    world_name = world or (run_cfg or first_cfg or load_preset("paper")).env.world
    for m in loaded:
        setup = setup_evaluation("greedy", model=m, world=world_name, seed=seed)
        models.append(ReportModel(_unique(m.label, taken), setup))
    for name in baselines:
        setup = _baseline_setup(name, run_cfg, loaded[0] if loaded else None, world_name, seed)
        models.append(ReportModel(_unique(name, taken), setup))

    # -- results: reuse or evaluate ---------------------------------------------------------
    world_obj = load_world(world_name)
    starts = list(range(len(world_obj.starts)))
    results_dir = out / "results"
    # Ours first, then the evaluator service's (stats/eval/), then anything the user put in the run.
    search = [results_dir, run / "stats" / "eval", run / "stats", run, run / "results"]
    for m in models:
        want = _protocol_meta(m.setup, world_name, episodes_per_start, max_steps, seed, starts)
        found = find_results(search, want)
        if found is not None:
            m.results, m.reused_from = found
            log.info("%s: reusing %s", m.name, m.reused_from)
            continue
        log.info("%s: evaluating (%d starts x %d episodes, %d steps at most)", m.name, len(starts),
                 episodes_per_start, max_steps)
        m.results = evaluate_policy(m.setup.policy_fn, world=world_name, sensor_cfg=m.setup.sensor_cfg,
                                    env_cfg=m.setup.env_cfg, episodes_per_start=episodes_per_start,
                                    max_steps=max_steps, seed=seed, progress=progress,
                                    meta={**m.setup.meta(), "model": m.name})
        path = save_results(m.results, results_dir / f"{slug(m.name)}.json")
        report.results[m.name] = path
    for m in models:
        if m.reused_from is not None:
            report.results[m.name] = m.reused_from

    # -- heatmaps ---------------------------------------------------------------------------
    grid = occupancy_grid(world_obj)
    heatmaps: dict[str, Path] = {}
    for m in models:
        assert m.results is not None
        try:
            heatmaps[m.name] = save_heatmap_png(world_obj, grid, m.results, out / f"heatmap-{slug(m.name)}.png",
                                                title=f"{m.name} on {world_name}")
        except FigureError as exc:
            notes.append(f"No heatmap for {m.name}: {exc}")
    side_by_side = None
    if heatmaps:
        side_by_side = save_heatmaps_side_by_side(world_obj, grid, {n: next(m.results for m in models if m.name == n)
                                                                    for n in heatmaps}, out / "heatmaps.png")
    report.figures += list(heatmaps.values()) + ([side_by_side] if side_by_side else [])

    # -- training curves --------------------------------------------------------------------
    loss_png = None
    learner_csv = run / "stats" / LEARNER_LOG
    if learner_csv.is_file():
        try:
            loss_png = save_loss_curve_png(learner_csv, out / "loss.png", title=f"Training loss ({run.name})")
            report.figures.append(loss_png)
        except FigureError as exc:
            notes.append(f"The loss curve could not be drawn from {learner_csv}: {exc}")
    else:
        notes.append(f"No loss curve: {learner_csv} does not exist (the learner writes it during training).")
    eval_png = None
    eval_log = run / "stats" / EVAL_LOG
    if eval_log.is_file():
        rows = load_eval_log(eval_log)
        if rows:
            eval_png = save_eval_curve_png(rows, out / "eval-curve.png")
            report.figures.append(eval_png)

    # -- probes: Table II and receptive fields ------------------------------------------------
    greedy = [m for m in models if m.model is not None]
    q_scenes: dict[str, dict[str, np.ndarray]] = {}
    scene_rows: list[tuple[str, str]] = []
    receptive: dict[tuple[str, str], Path] = {}
    probe_notes: list[str] = []
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
        for f in probe_files:
            try:
                depth, file_notes = load_probe_image(f, net.sensor_cfg)
            except ProbeError as exc:
                raise ReportError(f"--probe {f}: {exc}") from None
            scenes.append((f"user:{Path(f).stem}", depth, f"user image {f}"))
            probe_notes += [n for n in file_notes if n not in probe_notes]
        for scene, depth, description in scenes:
            if (scene, description) not in scene_rows:
                scene_rows.append((scene, description))
            try:
                _, mask, q, action = receptive_field(net, depth)
            except ReceptiveFieldError as exc:
                from shared.learning.model import InferenceRunner

                q = InferenceRunner(net).q_values(depth)
                note = f"No receptive field for {m.name}: {exc}"
                if note not in notes:
                    notes.append(note)
            else:
                path = render_receptive_png(depth, mask, q, action,
                                            out / "receptive" / f"{slug(m.name)}-{slug(scene)}.png",
                                            title=f"{scene} / {m.name}")
                receptive[(scene, m.name)] = path
                report.figures.append(path)
            q_scenes.setdefault(scene, {})[m.name] = q

    # -- the Markdown -------------------------------------------------------------------------
    def rel(p: Path) -> str:
        return os.path.relpath(p, out).replace(os.sep, "/")

    lines = [f"# Report: run `{run.name}`", ""]
    free = free_area_m2(grid)
    lines += ["## Protocol", "",
              f"- World `{world_name}` ({len(starts)} start poses, {free:.1f} m² free), TEST speed table, "
              f"greedy policies (dropout off).",
              f"- {episodes_per_start} episode(s) per start, at most {max_steps} moving steps each; seed {seed}.",
              "- Count = mean moving steps before a collision or the cap; Distance = mean straight-line distance "
              "from the start to the end pose (m); Coverage = mean % of the free area the camera saw.", ""]
    lines += ["## Models", "", "| Model | Policy | Source | Results |", "|---|---|---|---|"]
    for m in models:
        src = f"`{m.model.path}` (version {m.model.policy_version})" if m.model is not None else "baseline"
        res = report.results.get(m.name)
        how = "reused" if m.reused_from is not None else "evaluated"
        lines.append(f"| {m.name} | {m.setup.policy} | {src} | {how}: [{res.name}]({rel(res)}) |")
    lines += ["", "## Table III: moving steps and distance per start point", ""]
    lines.append(table_markdown({m.name: m.results for m in models}))
    lines += ["| Model | Episodes | Collisions (depth) | Collisions (contact) | Reached cap | Mean path (m) |",
              "|---|---:|---:|---:|---:|---:|"]
    for m in models:
        o = aggregate(m.results.episodes)["overall"]
        lines.append(f"| {m.name} | {o['episodes']} | {o['collisions']['depth']} | {o['collisions']['contact']} | "
                     f"{o['reached_cap']} | {o['mean_path_length_m']:.2f} |")
    lines += ["", "## Fig. 6: trajectory heatmaps", ""]
    if side_by_side is not None:
        lines += [f"![heatmaps]({rel(side_by_side)})", ""]
    lines += [" · ".join(f"[{n}]({rel(p)})" for n, p in heatmaps.items()), ""]
    lines += ["## Fig. 5: training loss", ""]
    lines += [f"![loss]({rel(loss_png)})" if loss_png else "_No loss curve: see the notes below._", ""]
    if eval_png is not None:
        lines += ["### Evaluations during training", "", f"![evaluations]({rel(eval_png)})", ""]
    lines += ["## Table II: Q-values of the probe scenes", ""]
    if q_scenes:
        lines.append(q_value_table_markdown(q_scenes))
        lines += ["| Scene | What it shows |", "|---|---|"]
        lines += [f"| {s} | {d} |" for s, d in scene_rows]
        lines.append("")
        lines += ["## Fig. 7: receptive fields (top 10 % of pool3, purple) and the chosen command", ""]
        if receptive:
            names = [m.name for m in greedy]
            lines += ["| Scene | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
            for scene, _ in scene_rows:
                cells = [f"![{scene} {n}]({rel(receptive[(scene, n)])})" if (scene, n) in receptive else "-"
                         for n in names]
                lines.append(f"| {scene} | " + " | ".join(cells) + " |")
            lines.append("")
    else:
        lines += ["_No checkpoint to probe: see the notes below._", ""]
    all_notes = notes + probe_notes
    if all_notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in all_notes] + [""]
    report.markdown.write_text("\n".join(lines))
    return report


def _baseline_setup(name: str, run_cfg: Any, model: LoadedModel | None, world: str, seed: int) -> EvalSetup:
    """A baseline that sees the run's own sensor and robot: the run's config, else its
    checkpoint's, else the paper preset's."""
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
    return EvalSetup(name, make_policy(name, sensor_cfg=sensor, seed=seed), sensor, env, world, None)


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------


def run_report(args: argparse.Namespace) -> int:
    """``cogexplore report``: returns a process exit status."""
    report = build_report(args.run_dir, compare=args.compare, out_dir=args.out,
                          episodes_per_start=args.episodes_per_start, max_steps=args.max_steps,
                          world=args.world, probe_files=args.probe, seed=args.seed, device=args.device,
                          progress=not args.quiet)
    for note in report.notes:
        print(f"note: {note}")
    print(report.markdown)
    return 0
