"""``cogexplore report`` on a small but real run folder, and the probe scenes it uses."""

from __future__ import annotations

import base64
import dataclasses
import html
import json
import re
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
from PIL import Image

from services.cli import main
from services.tools.document import DocumentError, Heading, Paragraph, Table, html_page, markdown
from services.tools.report import (
    EvalPoint,
    build_report,
    eval_curve_points,
    rows_of_worlds_now,
    save_eval_curve_png,
)
from shared.config import SensorConfig, load_preset, to_toml
from shared.evaluation import PROTOCOLS
from shared.evaluation.eval_log import load_eval_log
from shared.evaluation.protocol import file_world_sha256
from shared.evaluation.probes import (
    PROBE_DIR,
    PROBE_SCENES,
    ProbeError,
    generate_probes,
    load_probe_image,
    load_probes,
)
from shared.evaluation.results import load_results

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SMALL = {"sensor.width": 64, "sensor.height": 48, "model.fc1": 32, "model.fc2": 16, "env.world": "box-room"}


def small_config():
    return load_preset("paper").with_overrides(SMALL)


QUICK = dict(episodes_per_start=1, max_steps=3, baselines=("reactive",), progress=False, protocols=("paper",))
"""A report of the reactive baseline alone, one 3-step episode per start, under the paper protocol."""


def bare_run(path: Path) -> Path:
    """A run folder at ``path`` with its config and nothing else (no checkpoint, no logs)."""
    path.mkdir(parents=True)
    (path / "config.toml").write_text(to_toml(small_config()))
    return path


def make_run(root: Path, policy_version: int = 1000) -> Path:
    """A run folder with one checkpoint of a fresh network, as the learner writes it."""
    from shared.learning.checkpoints import CheckpointManager
    from shared.learning.dqn import DQNAgent

    cfg = small_config()
    agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=0)
    agent.update_count = agent.policy_version = policy_version
    CheckpointManager(root / "checkpoints").save(agent, config=cfg.to_dict())
    return root


def write_learner_csv(run: Path) -> None:
    (run / "stats").mkdir(parents=True, exist_ok=True)
    rows = ["update,loss,mean_q,epsilon"] + [f"{u},{5.0 * np.exp(-u / 300) + 0.1:.4f},{-u / 100},0.5"
                                             for u in range(0, 1000, 50)]
    (run / "stats" / "learner.csv").write_text("\n".join(rows) + "\n")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    run = make_run(tmp_path_factory.mktemp("runs") / "exp")
    (run / "config.toml").write_text(to_toml(small_config()))
    write_learner_csv(run)
    # Two rows as the evaluator service writes them, and a torn last line (a crash mid-write).
    rows = [{"policy_version": v, "max_steps": 200, "summary": {"mean_steps": m}} for v, m in ((0, 4.0), (1000, 9.5))]
    (run / "stats" / "eval.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"policy_ver')
    return run


def links(markdown: str) -> list[str]:
    return re.findall(r"\]\(([^)]+)\)", markdown)


def test_report_writes_every_figure_and_links_them(run_dir: Path, tmp_path: Path) -> None:
    user_png = tmp_path / "door.png"
    Image.fromarray(np.full((30, 40), 1500, np.uint16)).save(user_png)  # 1.5 m everywhere, another size
    report = build_report(run_dir, episodes_per_start=1, max_steps=5, probe_files=[user_png], device="cpu",
                          progress=False)
    out = run_dir / "report"
    assert report.markdown == out / "report.md"
    text = report.markdown.read_text()
    for name in ("heatmaps.png", "loss.png", "eval-curve.png", "heatmap-exp-1000.png", "heatmap-random.png",
                 "heatmap-reactive.png"):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC, name
    receptive = sorted((out / "receptive").glob("*.png"))
    assert len(receptive) == len(PROBE_SCENES) + 1  # the stored scenes and the user's image, one model
    # Every link in the Markdown points at a file that exists.
    for link in links(text):
        assert (out / link).is_file(), link
    assert len(set(links(text))) >= len(report.figures)
    # Table III with the three models, Table II with every scene.
    for model in ("exp@1000", "random", "reactive"):
        assert f"| {model} |" in text
    assert "| Count | exp@1000 |" in text and "Coverage (%)" in text
    # how much training the run had, from its learner log (this one has neither time nor transitions)
    assert "Training: 950 updates (`stats/learner.csv`)." in text
    for scene in [s.name for s in PROBE_SCENES] + ["user:door"]:
        assert f"| {scene} | exp@1000 |" in text
    assert "resized from 40x30 to 64x48" in text
    assert text.count("rendered from their stored poses for the 64x48 sensor") == 1
    # Table III under both test protocols, the robust one first, each saying what it is.
    assert list(report.results) == ["robust", "paper"]
    robust_at, paper_at = text.index("## Table III, robust protocol"), text.index("## Table III, paper protocol")
    assert robust_at < paper_at and text.count("| Count | exp@1000 |") == 2
    assert f"_{PROTOCOLS['robust'].describe()}._" in text and "| exp@1000 | robust |" in text
    # Every model's mean under both protocols beside the paper's own Table III figures.
    beside = text[text.index("## Beside the paper's Table III"):]
    assert re.search(r"\| exp@1000 \| this report \| \d+\.\d \| \d+\.\d \|  \|", beside)
    assert "| paper: DRL-40000 | Tai & Liu 2016, Table III |  |  | 92.6 |" in beside
    assert "| paper: SL |" in beside and "| reactive | this report |" in beside
    # Results were evaluated with the requested protocol and saved for next time.
    means, coverage, first_xy = {}, {}, {}
    for protocol, paths in report.results.items():
        assert list(paths) == ["exp@1000", "random", "reactive"]
        for model, path in paths.items():
            doc = json.loads(Path(path).read_text())
            assert doc["meta"]["episodes_per_start"] == 1 and doc["meta"]["max_steps"] == 5
            assert doc["meta"]["protocol"] == PROTOCOLS[protocol].to_dict()
            assert len(doc["episodes"]) == 4, model
            means[protocol, model] = doc["summary"]["overall"]["mean_steps"]
            coverage[protocol, model] = doc["summary"]["overall"]["mean_coverage_pct"]
            first_xy[protocol, model] = [e["trajectory_xy"][0] for e in doc["episodes"]]
    # Each protocol's tables show that protocol's results: its Table III's "All" column and its
    # column beside the paper's figures.
    sections = {"robust": text[robust_at:paper_at], "paper": text[paper_at:text.index("## Beside the paper's")]}
    for (protocol, model), mean in means.items():
        count_row = re.search(rf"^\| (?:Count)? *\| {re.escape(model)} \|.*\| \**([\d.]+)\** \|$",
                              sections[protocol], re.M)
        assert count_row and float(count_row.group(1)) == pytest.approx(mean, abs=0.05), (protocol, model)
        covered = sections[protocol][sections[protocol].index("| Coverage (%) |"):]
        coverage_row = re.search(rf"^\| (?:Coverage \(%\))? *\| {re.escape(model)} \|.*\| \**([\d.]+)\** \|$",
                                 covered, re.M)
        assert coverage_row and float(coverage_row.group(1)) == pytest.approx(coverage[protocol, model], abs=0.05)
    for model in ("exp@1000", "random", "reactive"):
        assert f"| {model} | this report | {means['robust', model]:.1f} | {means['paper', model]:.1f} |" in beside
    # the two protocols' tables are not one table twice (five steps from each start leave every mean equal
    # under both: their coverage is not), and the robust episodes began elsewhere, jittered
    assert any(coverage["robust", m] != pytest.approx(coverage["paper", m], abs=0.05)
               for m in ("exp@1000", "random", "reactive"))
    for model in ("exp@1000", "random", "reactive"):
        assert all(r != p for r, p in zip(first_xy["robust", model], first_xy["paper", model], strict=True)), model

    # A second report reuses every result instead of evaluating again.
    def stamps(r):
        return {(c, m): Path(p).stat().st_mtime_ns for c, paths in r.results.items() for m, p in paths.items()}

    first = stamps(report)
    again = build_report(run_dir, episodes_per_start=1, max_steps=5, device="cpu", progress=False)
    assert stamps(again) == first
    again_text = again.markdown.read_text()
    assert again_text.count("robust reused: ") == again_text.count("paper reused: ") == 3
    # Other episodes do not reuse them.
    longer = build_report(run_dir, out_dir=tmp_path / "longer", episodes_per_start=1, max_steps=6,
                          baselines=("reactive",), device="cpu", progress=False)
    assert "reused: " not in longer.markdown.read_text()
    # Nor do the random baseline's results from before its per-episode draws (other episodes).
    for paths in again.results.values():
        doc = json.loads(Path(paths["random"]).read_text())
        assert doc["meta"].pop("random_draws") == "per-episode"
        Path(paths["random"]).write_text(json.dumps(doc))
    third = build_report(run_dir, episodes_per_start=1, max_steps=5, device="cpu", progress=False)
    assert {k for k in first if stamps(third)[k] != first[k]} == {("robust", "random"), ("paper", "random")}


def test_report_reuses_the_final_evaluation_of_cogexplore_up(run_dir: Path, tmp_path: Path) -> None:
    # `cogexplore up` ends with `evaluate --checkpoint RUN --json RUN/stats/final-eval.json`, then `report RUN`.
    final = run_dir / "stats" / "final-eval.json"
    assert main(["evaluate", "--checkpoint", str(run_dir), "--episodes-per-start", "1", "--max-steps", "4",
                 "--json", str(final), "--device", "cpu", "--quiet"]) == 0
    report = build_report(run_dir, out_dir=tmp_path / "r", episodes_per_start=1, max_steps=4, baselines=(),
                          device="cpu", progress=False)
    assert report.results["robust"] == {"exp@1000": final}  # evaluate's protocol; the paper's is evaluated
    assert report.results["paper"]["exp@1000"].parent == tmp_path / "r" / "results"
    final.unlink()


def test_report_plays_the_model_it_is_given_for_the_run(tmp_path: Path) -> None:
    # `cogexplore up` gives the mean of the run's last checkpoints (`--model`), not its latest one.
    from shared.learning.checkpoints import CheckpointManager, load_model
    from shared.learning.dqn import DQNAgent

    run = make_run(tmp_path / "avg", policy_version=1000)
    cfg = small_config()
    agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=1)
    agent.update_count = agent.policy_version = 2000
    CheckpointManager(run / "checkpoints").save(agent, config=cfg.to_dict())
    mean = run / "avg-mean2.safetensors"
    assert main(["model", "export", *(str(run / "checkpoints" / f"ckpt-{u:09d}.safetensors") for u in (1000, 2000)),
                 "--out", str(mean)]) == 0
    report = build_report(run, model=mean, episodes_per_start=1, max_steps=3, baselines=(), device="cpu",
                          progress=False, protocols=("paper",))
    text = report.markdown.read_text()
    assert "| avg-mean2@2000 | greedy |" in text and "the mean of 2 checkpoints' weights, versions 1000, 2000" in text
    played = load_results(report.results["paper"]["avg-mean2@2000"])
    assert played.meta["weights_sha256"] == load_model(mean).weights_sha256 != load_model(run).weights_sha256


class PageParts(HTMLParser):
    """What a browser would show of a report page: headings, tables (rows of cell texts), images, links."""

    def __init__(self) -> None:
        super().__init__()
        self.headings: list[str] = []
        self.tables: list[list[list[str]]] = []
        self.images: list[tuple[str, str]] = []
        self.links: list[str] = []
        self._text: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag in ("h1", "h2", "h3") or tag in ("td", "th"):
            self._text = []
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag == "img":
            self.images.append((a["alt"], a["src"]))
        elif tag == "a":
            self.links.append(a["href"])

    def handle_data(self, data: str) -> None:
        if self._text is not None:
            self._text.append(data)

    def handle_endtag(self, tag: str) -> None:
        if tag in ("h1", "h2", "h3"):
            self.headings.append("".join(self._text))
        elif tag in ("td", "th"):
            self.tables[-1][-1].append("".join(self._text).strip())
        if tag in ("h1", "h2", "h3", "td", "th"):
            self._text = None


def markdown_tables(text: str) -> list[list[str]]:
    """The pipe tables of a Markdown text, each as its lines without the rule."""
    tables: list[list[str]] = []
    previous = ""
    for line in text.splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            if not previous.startswith("|"):
                tables.append([])
            tables[-1].append(line)
        previous = line
    return tables


def test_html_report_shows_every_section_table_and_image_of_the_markdown(run_dir: Path, tmp_path: Path) -> None:
    report = build_report(run_dir, out_dir=tmp_path / "r", episodes_per_start=1, max_steps=5, baselines=("reactive",),
                          device="cpu", progress=False)
    out = tmp_path / "r"
    assert report.html == out / "report.html"
    md, page = report.markdown.read_text(), PageParts()
    page.feed(report.html.read_text())
    page.close()
    # The same sections in the same order.
    assert page.headings == [line.lstrip("#").strip().replace("`", "") for line in md.splitlines()
                             if line.startswith("#")]
    assert {"Evaluations during training", "Notes"} <= set(page.headings)
    assert report.html.read_text().count("<li>") == sum(line.startswith("- ") for line in md.splitlines())
    # The same tables, row for row and cell for cell (the Markdown's images and links as their text).
    tables = markdown_tables(md)
    assert len(page.tables) == len(tables) >= 7
    for html_rows, md_rows in zip(page.tables, tables):
        assert len(html_rows) == len(md_rows)
        for cells, line in zip(html_rows, md_rows):
            md_cells = [re.sub(r"!\[[^\]]*\]\([^)]*\)", "", re.sub(r"(?<!!)\[([^\]]+)\]\([^)]*\)", r"\1", c))
                        .replace("**", "").replace("`", "").strip() for c in line.strip("|").split("|")]
            assert cells == md_cells
    curve = next(t for t in page.tables if t[0][0] == "Policy version")
    assert [row[0] for row in curve[1:]] == ["0", "1000"]  # the final evaluation stands in for version 1000
    assert curve[1][-1] == "during training" and curve[2][-1] == "final (Table III)"
    # Every image of the Markdown, inlined byte for byte (the figures are small); every link kept.
    md_images = re.findall(r"!\[([^\]]*)\]\(([^)]+)\)", md)
    assert len(md_images) == len(page.images) >= 8
    for (alt, src), (html_alt, data) in zip(md_images, page.images):
        assert html_alt == alt and data.startswith("data:image/png;base64,")
        assert base64.b64decode(data.split(",", 1)[1]) == (out / src).read_bytes()
    assert page.links == re.findall(r"(?<!!)\[[^\]]+\]\(([^)]+)\)", md)
    assert all((out / href).is_file() for href in page.links)
    assert report.html.stat().st_size < 5_000_000


def test_html_page_links_images_too_big_to_inline(tmp_path: Path) -> None:
    noise = np.random.default_rng(0).integers(0, 256, (1300, 1300, 3), dtype=np.uint8)
    Image.fromarray(noise).save(tmp_path / "big.png")  # about 5 MB: noise does not compress
    Image.fromarray(noise[:20, :20]).save(tmp_path / "small.png")
    doc = [Heading(1, "Figures <&>"), Paragraph("![big](big.png) and ![small](small.png)"),
           Table(("a", "b"), (False, True), (("`x|y`", "**2.0**"),))]
    for embed, srcs in ((None, ["big.png", "small.png"]), (False, ["big.png", "small.png"])):
        page = PageParts()
        page.feed(html_page(doc, "t", tmp_path, embed=embed))
        assert [src for _, src in page.images] == srcs
    page = PageParts()
    page.feed(html_page(doc[:1] + [Paragraph("![small](small.png)")], "t", tmp_path))
    assert page.headings == ["Figures <&>"] and page.images[0][1].startswith("data:image/png;base64,")
    assert markdown(doc) == "# Figures <&>\n\n![big](big.png) and ![small](small.png)\n\n| a | b |\n|---|---:|\n" \
                            "| `x\\|y` | **2.0** |\n"  # a cell's | escaped, as GFM reads it


def test_a_name_holding_a_script_link_stays_text_in_the_html(tmp_path: Path) -> None:
    # A probe file (its path is a scene's description) or a model file (its stem names heatmap links)
    # named "[open](javascript:...)" became a link that ran script when the opened report was clicked.
    doc = [Table(("Scene", "What it shows"), (False, False),
                 (("user:x", "user image p/[open](javascript:alert%28document.domain%29).png"),)),
           Paragraph("[m](JaVaScRiPt:alert%281%29) · [n](\x01javascript:x) · ![i](data:text/html,x) · "
                     "[ok](heatmap-x.png) · [web](https://example.org/a_b)"),
           Heading(2, "<script>alert(1)</script> & \"quotes\"")]
    page = PageParts()
    text = html_page(doc, "<b>t</b>", tmp_path)
    page.feed(text)
    assert page.links == ["heatmap-x.png", "https://example.org/a_b"] and page.images == []
    assert page.tables[0][1] == ["user:x", "user image p/[open](javascript:alert%28document.domain%29).png"]
    assert "<script>" not in text and "<b>t</b>" not in text
    assert page.headings == ['<script>alert(1)</script> & "quotes"']


def test_a_pipe_in_a_model_name_stays_in_its_cell() -> None:
    # A run or file named a|b shifted every cell after it: start 1's value under "2", the true "All" dropped.
    from shared.evaluation.results import EpisodeResult, EvalResults, table_markdown

    episodes = tuple(EpisodeResult(start, 0, 10 * (start + 1), False, True, None, 1.0, 2.0, 3.0, 0.1)
                     for start in range(2))
    table = Table.from_markdown(table_markdown({"x|y@70": EvalResults(episodes), "z": EvalResults(episodes)}))
    assert table.header == ("Metric", "Model", "1", "2", "All")
    assert table.rows[0] == ("Count", "x|y@70", "**10.0**", "**20.0**", "**15.0**")
    assert Table.from_markdown(markdown([table]).strip()) == table  # written and read back alike
    with pytest.raises(DocumentError, match="a row of 4 cells in a table of 3 columns"):
        Table.from_markdown("| a | b | c |\n|---|---|---|\n| x | y | z | w |")


@pytest.fixture(scope="module")
def odd_names(tmp_path_factory) -> tuple[Path, object, list[str]]:
    """A report on three models of their own weights whose file names slug alike ("a b", "a-b") or hold
    Markdown's link syntax (and a "$\\x$", which matplotlib's titles read as mathtext and failed to draw
    after every evaluation had run), two user images of one stem, and a result to reuse from a file of an
    odd name."""
    from shared.learning.checkpoints import CheckpointManager
    from shared.learning.dqn import DQNAgent

    root = tmp_path_factory.mktemp("odd")
    run = make_run(root / "exp")
    files = []
    for i, stem in enumerate(("a b", "a-b", "x](y) [z]\\*_w_*$\\x$")):
        cfg = small_config()
        agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=10 + i)
        agent.update_count = agent.policy_version = 1000
        saved = CheckpointManager(root / f"c{i}").save(agent, config=cfg.to_dict())
        files.append(saved.rename(root / f"{stem}.safetensors"))
    probes = []
    for d, metres in (("p", 1.5), ("q", 0.5)):
        (root / d).mkdir()
        Image.fromarray(np.full((48, 64), int(metres * 1000), np.uint16)).save(root / d / "door.png")
        probes.append(root / d / "door.png")
    kw = dict(episodes_per_start=1, max_steps=3, baselines=(), device="cpu", progress=False, protocols=("paper",))
    first = build_report(run, compare=files[:1], out_dir=root / "first", **kw)
    (run / "stats").mkdir()  # found there by a later report: a file the user kept under a name of their own
    (run / "stats" / "my results (1).json").write_bytes(first.results["paper"]["exp@1000"].read_bytes())
    report = build_report(run, compare=files, probe_files=probes, **kw)
    return run / "report", report, ["exp@1000", "a b@1000", "a-b@1000", "x](y) [z]\\*_w_*$\\x$@1000"]


def test_models_whose_names_slug_alike_keep_their_own_files(odd_names) -> None:
    # "a b" and "a-b" both wrote results/a-b-1000-paper.json, heatmap-a-b-1000.png and receptive/a-b-1000-*.png:
    # the second overwrote the first, whose links then showed the other model's results and figures.
    out, report, names = odd_names
    paths = report.results["paper"]
    assert list(paths) == names and len(set(paths.values())) == len(names)
    for name, path in paths.items():
        assert load_results(path).meta["model"] == name or path.name == "my results (1).json"
    assert paths["a b@1000"].name == "a-b-1000-paper.json" and paths["a-b@1000"].name == "a-b-1000-2-paper.json"
    assert len(set(report.figures)) == len(report.figures)
    assert {p.name for p in out.glob("heatmap-*.png")} == {"heatmap-exp-1000.png", "heatmap-a-b-1000.png",
                                                            "heatmap-a-b-1000-2.png", "heatmap-x-y-z-_w_-x-1000.png"}
    # and two user images of one file stem are two scenes, each with its own row and figures
    text = report.markdown.read_text()
    assert "| user:door | exp@1000 |" in text and "| user:door (2) | exp@1000 |" in text
    assert len(list((out / "receptive").glob("*.png"))) == len(names) * (len(PROBE_SCENES) + 2)
    assert "| user:door | user image " + str(out.parent.parent / "p" / "door.png") in text
    assert "| user:door (2) | user image " + str(out.parent.parent / "q" / "door.png") in text


def test_markdown_syntax_in_a_name_stays_text(odd_names) -> None:
    # A model named "x](y" closed its heatmap link early: the link pointed at "y@1000](heatmap-..." and
    # both report files showed a broken link; "*_w_*" became emphasis; a reused results file named
    # "my results (1).json" was no link at all.
    out, report, names = odd_names
    text = report.markdown.read_text()
    # a link's or image's target, as CommonMark ends it (a code span's brackets are its text)
    targets = re.findall(r"(?<!\\)\]\(([^)\s]+)\)", re.sub(r"(`+).+?\1", "", text))
    assert len(targets) >= len(report.figures) + len(names)
    for target in targets:
        assert (out / unquote(target)).is_file(), target
    assert "[my results (1).json](../stats/my%20results%20%281%29.json)" in text
    page = PageParts()
    page.feed(report.html.read_text())
    assert all((out / unquote(href)).is_file() for href in page.links)
    models = next(t for t in page.tables if t[0][0] == "Model")
    assert [row[0] for row in models[1:]] == names
    assert [row[1] for row in next(t for t in page.tables if t[0][:2] == ["Metric", "Model"])[1:5]] == names
    # the name as written wherever a table shows it, and as the alt text of its receptive fields
    assert {c for t in page.tables for row in t for c in row if "x](y" in c and "safetensors" not in c} == {names[-1]}
    assert [alt for alt, _ in page.images if "x](y" in alt] == \
        [f"{s} {names[-1]}" for s in [p.name for p in PROBE_SCENES] + ["user:door", "user:door (2)"]]


def test_the_means_beside_the_papers_name_their_step_cap(odd_names) -> None:
    # The heading read "mean moving steps of 200" above means of a 3-step cap.
    text = odd_names[1].markdown.read_text()
    assert "## Beside the paper's Table III: mean moving steps of 3 here, of 200 in the paper\n" in text


def test_escaped_text_code_spans_and_targets_read_back_as_written(tmp_path: Path) -> None:
    from services.tools.document import code_span, inline_html, link_target
    from shared.evaluation.results import escape_text

    name = "x](y) [z] a\\b *c* _d_ `e` <i>&amp; ~~f~~ a|b"
    (tmp_path / "a b (1).png").write_bytes(b"png")
    doc = [Paragraph(f"[{escape_text(name)}]({link_target('a b (1).png')}) {code_span('p`q``r')}"),
           Table(("Model", "n"), (False, True), ((escape_text(name), "1"),))]
    page = PageParts()
    page.feed(html_page(doc, "t", tmp_path))
    assert page.links == ["a%20b%20%281%29.png"] and page.tables[0][1] == [name, "1"]
    assert inline_html(escape_text(name)) == html.escape(name)
    assert inline_html(code_span("p`q``r")) == "<code>p`q``r</code>"
    assert inline_html(f"run {code_span('`x')}") == "run <code>`x</code>"
    assert Table.from_markdown(markdown([doc[1]])) == doc[1]  # a | in a name stays in its cell


# -- the evaluation curve -------------------------------------------------------------------------


def test_eval_curve_ends_in_the_final_evaluation_at_its_version(tmp_path: Path) -> None:
    # A short `cogexplore up`: the evaluator saw version 0 only, the final evaluation the last checkpoint.
    run = make_run(tmp_path / "short", policy_version=1000)
    (run / "config.toml").write_text(to_toml(small_config()))
    (run / "stats").mkdir()
    world = small_config().env.world
    periodic = {"policy_version": 0, "protocol": "robust", "world": world, "episodes_per_start": 1,
                "max_steps": 200, "summary": {"mean_steps": 3.0}}
    (run / "stats" / "eval.jsonl").write_text(json.dumps(periodic) + "\n")
    final_json = run / "stats" / "final-eval.json"
    assert main(["evaluate", "--checkpoint", str(run), "--episodes-per-start", "1", "--max-steps", "4",
                 "--json", str(final_json), "--device", "cpu", "--quiet"]) == 0
    final = load_results(final_json)
    final_steps = final.summary["overall"]["mean_steps"]

    # The data: version 0 from the evaluator, then the final evaluation at the checkpoint's version.
    points, left_out = eval_curve_points(load_eval_log(run / "stats" / "eval.jsonl"),
                                         EvalPoint.final_of(final, world))
    assert left_out == 0
    assert points == [EvalPoint(0, 3.0, 1, 200, protocol="robust", world=world),
                      EvalPoint(1000, final_steps, 1, 4, final=True, protocol="robust", world=world,
                                protocol_config=PROTOCOLS["robust"])]
    # A periodic evaluation of the final version is not drawn a second time: the final one stands for it.
    again, left_out = eval_curve_points([periodic, {**periodic, "policy_version": 1000,
                                                    "summary": {"mean_steps": 7.0}}], EvalPoint.final_of(final, world))
    assert [(p.policy_version, p.final) for p in again] == [(0, False), (1000, True)] and left_out == 0
    # One line joins one task: rows in another world or protocol, and a final evaluation in another
    # world, are left out (counted, for the report's note), not joined to the evaluator's newest.
    elsewhere = [{**periodic, "policy_version": 500, "world": "procedural:5"},
                 {**periodic, "policy_version": 700, "protocol": "paper"}, periodic]
    only, left_out = eval_curve_points(elsewhere, EvalPoint.final_of(final, "procedural:5"))
    assert [(p.policy_version, p.world, p.final) for p in only] == [(0, world, False)] and left_out == 2
    # Results that do not say their version (a hand-edited file) give no final point.
    unversioned = dataclasses.replace(final, meta={k: v for k, v in final.meta.items() if k != "policy_version"})
    assert EvalPoint.final_of(unversioned, world) is None
    assert EvalPoint.final_of(dataclasses.replace(final, meta={**final.meta, "policy_version": None}), world) is None
    assert again[1].mean_steps == final_steps
    png = save_eval_curve_png(again, tmp_path / "curve.png")
    assert png.read_bytes()[:8] == PNG_MAGIC

    # The report reuses the final evaluation and draws both points, under the evaluator's protocol.
    report = build_report(run, episodes_per_start=1, max_steps=4, baselines=(), device="cpu", progress=False)
    assert report.results["robust"] == {"short@1000": final_json}
    assert report.eval_curve == points
    assert (run / "report" / "eval-curve.png").read_bytes()[:8] == PNG_MAGIC
    assert f"| 1000 | {final_steps:.1f} | robust | 1 | 4 | **final** (Table III) |" in report.markdown.read_text()
    # An evaluator from before the protocol was recorded ran the paper's: the curve ends in that one.
    (run / "stats" / "eval.jsonl").write_text(json.dumps({k: v for k, v in periodic.items() if k != "protocol"}) + "\n")
    older = build_report(run, episodes_per_start=1, max_steps=4, baselines=(), device="cpu", progress=False)
    paper = load_results(older.results["paper"]["short@1000"])
    assert older.eval_curve == [EvalPoint(0, 3.0, 1, 200, world=world), EvalPoint.final_of(paper, world)]
    assert older.eval_curve[1].protocol == "paper"


def test_eval_curve_keeps_two_custom_protocols_apart(tmp_path: Path) -> None:
    # Both are named "custom" in eval.jsonl: their points were drawn as one line, labelled alike.
    near, far = (PROTOCOLS["robust"].overridden(start_jitter_m=m) for m in (0.04, 0.5))

    def row(version: int, protocol: str, steps: float, config: dict | None = None) -> dict:
        return {"policy_version": version, "protocol": protocol, "world": "box-room", "episodes_per_start": 1,
                "max_steps": 200, "summary": {"mean_steps": steps}} | ({"protocol_config": config} if config else {})

    rows = [row(0, "custom", 3.0, near.to_dict()), row(1000, "custom", 50.0, far.to_dict()),
            row(2000, "custom", 4.0, near.to_dict())]
    points, left_out = eval_curve_points(rows)
    assert [p.policy_version for p in points] == [0, 2000] and left_out == 1
    final = EvalPoint(3000, 9.0, 1, 200, final=True, protocol="custom", world="box-room")
    assert eval_curve_points(rows, dataclasses.replace(final, protocol_config=far)) == (points, 1)
    points, _ = eval_curve_points(rows, dataclasses.replace(final, protocol_config=near))
    assert [p.policy_version for p in points] == [0, 2000, 3000]
    assert {p.protocol_label for p in points} == {near.describe()} and "±4 cm" in near.describe()
    png = save_eval_curve_png(points, tmp_path / "curve.png")
    assert png.read_bytes()[:8] == PNG_MAGIC
    # Rows from before the evaluator recorded the fields: a named protocol's name stands for its
    # fields, a custom one's for none that a row records.
    older = [row(0, "robust", 3.0), row(500, "custom", 7.0), row(1000, "robust", 4.0, PROTOCOLS["robust"].to_dict())]
    points, left_out = eval_curve_points(older)
    assert [(p.policy_version, p.protocol_label) for p in points] == [(0, "robust"), (1000, "robust")]
    assert left_out == 1
    points, left_out = eval_curve_points([*older, row(2000, "custom", 8.0, near.to_dict())])
    assert [p.policy_version for p in points] == [2000] and left_out == 3
    # Fields this version does not know (or under another name) are not a protocol: the row is drawn by its name.
    unknown = row(3000, "custom", 6.0, {**near.to_dict(), "future_field": 1})
    renamed = row(4000, "custom", 5.0, {**far.to_dict(), "name": "x"})
    points, _ = eval_curve_points([row(500, "custom", 7.0), unknown, renamed])
    assert [(p.policy_version, p.protocol_config) for p in points] == [(500, None), (3000, None), (4000, None)]


def test_the_eval_curve_draws_a_world_file_only_as_it_is_now(tmp_path: Path, caplog) -> None:
    # Keyed by the world's name, the curve drew the evaluator's rows of an MJCF file from before and
    # after the user edited it as one line: scores of two worlds under one name.
    from services.bus.session import ZenohSettings
    from services.evaluator.service import EvaluatorService
    from shared.learning.weights import to_message
    from tests.services.evaluator.test_evaluator_service import OVERRIDES, small_net
    from tests.shared.evaluation.test_eval_log import write_room

    run = bare_run(tmp_path / "run")
    world = write_room(tmp_path / "room.xml")
    net = small_net()

    def evaluate(version: int) -> None:
        EvaluatorService(load_preset("paper").with_overrides(OVERRIDES), "run", run, ZenohSettings(), "ev-1",
                         episodes_per_start=1, max_steps=3, record=False,
                         world=str(world)).evaluate(to_message(net, version), repeat=False)

    evaluate(0)
    evaluate(10)
    write_room(world, pillar_x=-0.6)  # the pillar moved into the robot's way
    evaluate(20)
    with caplog.at_level("WARNING", logger="cogexplore.report"):
        report = build_report(run, **{**QUICK, "world": str(world)})
    assert [p.policy_version for p in report.eval_curve] == [20]  # the file as it is now
    said = "2 evaluation(s) played on an MJCF world file as it was before an edit"
    assert said in caplog.text and said in report.markdown.read_text()
    # A built-in world's row from before rows recorded a digest stands (fixed by its name), as does a row
    # naming no world; a file's row without one cannot say which content it played.
    rows = [{"world": "box-room"}, {"world": str(world)}, {}, {"world": str(world), "world_sha256": "0" * 64},
            {"world": str(world), "world_sha256": file_world_sha256(str(world))}]
    assert rows_of_worlds_now(rows, file_world_sha256) == ([rows[0], rows[2], rows[4]], 2)
    # A file gone since holds none of the content its rows played: their curve is not drawn.
    world.unlink()
    assert build_report(run, **{**QUICK, "world": "box-room"}).eval_curve == []


def test_an_eval_log_row_the_evaluator_could_not_have_written_is_skipped(tmp_path: Path, caplog) -> None:
    good = {"policy_version": 1000, "protocol": "robust", "episodes_per_start": 1, "max_steps": 200,
            "summary": {"mean_steps": 42.5}}
    bad = [{**good, "summary": {}}, {**good, "summary": {"mean_steps": "abc"}}, {**good, "policy_version": -7},
           {**good, "episodes_per_start": "x"}, {**good, "max_steps": 0}, {**good, "protocol": 3},
           {**good, "policy_version": 10**400}, {**good, "summary": {"mean_steps": 10**400}}]
    lines = [json.dumps(good), *map(json.dumps, bad), json.dumps(good).replace("42.5", "NaN"),
             json.dumps(good).replace("42.5", "1e999"), "[" * 100_000, '{"policy_ver']
    path = tmp_path / "eval.jsonl"
    path.write_text("\n".join(lines) + "\n")
    with caplog.at_level("WARNING", logger="cogexplore.eval_log"):
        assert load_eval_log(path) == [good]
    assert "12 row(s) skipped" in caplog.text


def test_report_without_checkpoint_or_loss_log_says_so(tmp_path: Path) -> None:
    run = bare_run(tmp_path / "fresh")
    report = build_report(run, **QUICK)
    text = report.markdown.read_text()
    assert list(report.results) == ["paper"] and "## Table III, paper protocol" in text and "robust" not in text
    assert "no checkpoint yet" in text and "learner.csv does not exist" in text
    assert "No checkpoint to probe" in text
    assert "| reactive |" in text and (run / "report" / "heatmaps.png").is_file()


def test_a_report_elsewhere_reuses_the_runs_own_report_results(tmp_path: Path) -> None:
    # With --out, the run's report/results/ (which the docs say is reused) was not searched: every
    # model was evaluated again, minutes of the full protocol for numbers already in the run.
    run = bare_run(tmp_path / "run")
    first = build_report(run, **QUICK)
    again = build_report(run, out_dir=tmp_path / "elsewhere", **QUICK)
    assert again.results == first.results == {"paper": {"reactive": run / "report" / "results" / "reactive-paper.json"}}
    assert "paper reused: [reactive-paper.json](../run/report/results/reactive-paper.json)" in again.markdown.read_text()
    assert not (tmp_path / "elsewhere" / "results").exists()


def test_a_world_spelt_with_leading_zeros_reuses_its_results(tmp_path: Path) -> None:
    # procedural:0301 is the world procedural:301, and its results say so: looked up by the name as
    # typed, they never matched, and every report played every model again.
    run = bare_run(tmp_path / "run")
    first = build_report(run, **{**QUICK, "world": "procedural:0301"})
    again = build_report(run, **{**QUICK, "world": "procedural:301"})
    assert again.results == first.results
    assert "paper reused" in again.markdown.read_text()
    assert load_results(first.results["paper"]["reactive"]).meta["env"]["world"] == "procedural:301"


def test_a_line_break_in_a_run_name_does_not_end_its_heading(tmp_path: Path) -> None:
    # The heading's code span broke at the line break: report.md's next line was the raw HTML
    # "<img src=x onerror=alert(1)>`", run by a Markdown viewer that shows HTML.
    run = bare_run(tmp_path / "x\n<img src=x onerror=alert(1)>")
    report = build_report(run, **QUICK)
    text = report.markdown.read_text()
    assert text.startswith("# Report: run `x <img src=x onerror=alert(1)>`\n")
    assert not [line for line in text.splitlines() if line.startswith("<")]
    page = PageParts()
    page.feed(report.html.read_text())
    assert page.headings[0] == "Report: run x <img src=x onerror=alert(1)>" and page.images[0][0] == "heatmaps"


def test_a_garbled_learner_log_is_a_note_not_a_crash(tmp_path: Path) -> None:
    run = bare_run(tmp_path / "garbled")
    (run / "stats").mkdir()
    (run / "stats" / "learner.csv").write_bytes(b"update,loss\n1,\x00\xff\xfe2\n")  # not text
    report = build_report(run, **QUICK)
    text = report.markdown.read_text()
    # What parses is read (update 1); the loss that does not is a note, not a crash.
    assert "Training: 1 updates" in text
    assert "The loss curve could not be drawn" in text and "non-numeric update or loss" in text
    assert "| reactive |" in text
    # A power loss's tail of NUL bytes (one csv field past the module's limit) after good rows: the
    # rows before it still make the training line and the curve (before, csv.Error ended the report).
    (run / "stats" / "learner.csv").write_bytes(b"update,loss\n1,2.0\n2,1.5\n" + b"\0" * 200_000)
    report = build_report(run, **QUICK)
    text = report.markdown.read_text()
    assert "Training: 2 updates" in text and "The loss curve could not be drawn" not in text
    assert (run / "report" / "loss.png").read_bytes()[:8] == PNG_MAGIC


def report(argv: list[str]) -> int:
    """``cogexplore report ARGV``: the exit status."""
    return main(["report", *argv])


def test_report_command_refuses_bad_input(run_dir: Path, tmp_path: Path, capsys) -> None:
    nan = tmp_path / "nan.npy"
    depth = np.ones((48, 64), np.float32)
    depth[3, 4] = np.nan
    np.save(nan, depth)
    assert report([str(run_dir), "--probe", str(nan), "--episodes-per-start", "1", "--max-steps", "2",
                   "--out", str(tmp_path / "r"), "--quiet", "--device", "cpu"]) == 2
    assert "NaN" in capsys.readouterr().err
    assert report([str(tmp_path / "no-such-run")]) == 2
    assert "does not exist" in capsys.readouterr().err
    # --protocol chooses Table III's protocols and their order.
    assert report([str(run_dir), "--protocol", "paper", "--episodes-per-start", "1", "--max-steps", "2",
                   "--out", str(tmp_path / "p"), "--quiet", "--device", "cpu"]) == 0
    text = (tmp_path / "p" / "report.md").read_text()
    assert "## Table III, paper protocol" in text and "Table III, robust" not in text


# -- probes -------------------------------------------------------------------------------------


def test_stored_probes_equal_the_regenerated_ones(tmp_path: Path) -> None:
    # If this fails after a change to paper-indoor: python -m shared.evaluation.probes
    generate_probes(tmp_path)
    stored = sorted(p.name for p in PROBE_DIR.iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == stored
    assert len(stored) == 2 * len(PROBE_SCENES)
    for scene in PROBE_SCENES:
        fresh, kept = np.load(tmp_path / f"{scene.name}.npy"), np.load(PROBE_DIR / f"{scene.name}.npy")
        assert kept.dtype == np.float32 and kept.shape == (120, 160)
        np.testing.assert_allclose(kept, fresh, atol=1e-5, err_msg=scene.name)
        assert json.loads((PROBE_DIR / f"{scene.name}.json").read_text()) == \
            json.loads((tmp_path / f"{scene.name}.json").read_text())
        # A probe is a scene the robot can be in: nothing in view nearer than the collision threshold.
        assert kept[kept > 0].min() > 0.55


def test_probes_load_for_any_sensor() -> None:
    paper = load_probes()
    assert [p.name for p in paper] == sorted(s.name for s in PROBE_SCENES)
    assert all(p.depth_m.shape == (120, 160) and not p.notes for p in paper)
    small = load_probes(sensor_cfg=SensorConfig(width=64, height=48))
    assert all(p.depth_m.shape == (48, 64) and p.notes for p in small)


def test_user_probe_images(tmp_path: Path) -> None:
    sensor = SensorConfig(width=64, height=48)
    mm = np.arange(48 * 64, dtype=np.uint16).reshape(48, 64) % 4000
    png = tmp_path / "mm.png"
    Image.fromarray(mm).save(png)
    depth, notes = load_probe_image(png, sensor)
    assert depth.dtype == np.float32 and notes == []
    np.testing.assert_allclose(depth, mm / 1000.0, atol=1e-6)

    big = tmp_path / "big.npy"
    np.save(big, np.full((96, 128), 2.0))
    depth, notes = load_probe_image(big, sensor)
    assert depth.shape == (48, 64) and "resized from 128x96 to 64x48" in notes[0]
    with pytest.raises(ProbeError, match="128x96 image, the sensor is 64x48"):
        load_probe_image(big, sensor, resize=False)

    far = tmp_path / "far.npy"
    np.save(far, np.full((48, 64), 9.0))
    depth, notes = load_probe_image(far, sensor)
    assert (depth == 0).all() and "beyond the sensor" in notes[0]

    rgb = tmp_path / "rgb.png"
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(rgb)
    for path, message in ((rgb, "colour image"), (tmp_path / "none.png", "does not exist")):
        with pytest.raises(ProbeError, match=message):
            load_probe_image(path, sensor)
    neg = tmp_path / "neg.npy"
    np.save(neg, -np.ones((48, 64)))
    with pytest.raises(ProbeError, match="negative"):
        load_probe_image(neg, sensor)
    txt = tmp_path / "depth.txt"
    txt.write_text("1 2 3")
    with pytest.raises(ProbeError, match="unknown probe format"):
        load_probe_image(txt, sensor)


def _drop_world_digest(path: Path) -> None:
    """``path`` as results were written before they recorded the world's content."""
    doc = json.loads(path.read_text())
    del doc["meta"]["world_sha256"]
    path.write_text(json.dumps(doc))


def test_results_stand_for_a_world_file_only_as_it_was_played(tmp_path: Path) -> None:
    # Matched by the world's name, the results of an MJCF file stood for it after the user edited it.
    run = bare_run(tmp_path / "run")
    from tests.shared.evaluation.test_eval_log import write_room

    world = write_room(tmp_path / "my_world.xml")
    kw = dict(world=str(world), episodes_per_start=1, max_steps=40, baselines=("reactive",), progress=False,
              protocols=("paper",))
    saved = build_report(run, **kw).results["paper"]["reactive"]
    played = load_results(saved).meta["world_sha256"]

    def reused() -> bool:
        return "paper reused" in build_report(run, **kw).markdown.read_text()

    assert reused()  # the same file: its results stand
    write_room(world, pillar_x=0.0)  # the pillar moved into the robot's way
    assert not reused() and load_results(saved).meta["world_sha256"] != played
    _drop_world_digest(saved)  # a file's results from before: they cannot say which content they played
    assert not reused()


def test_a_built_in_worlds_results_from_before_the_world_digest_are_reused(tmp_path: Path) -> None:
    run = bare_run(tmp_path / "run")
    _drop_world_digest(build_report(run, **QUICK).results["paper"]["reactive"])
    assert "paper reused" in build_report(run, **QUICK).markdown.read_text()  # box-room: fixed by its name


def test_find_results_reads_each_file_once_per_cache(tmp_path: Path) -> None:
    # A report looks for every model under every protocol: each lookup read and checked every results
    # JSON in the run again. With a cache a file is read once, and again only once it is written anew.
    import os

    from services.tools.report import find_results
    from shared.evaluation.results import EpisodeResult, EvalResults, save_results

    def save(model: str) -> Path:
        episode = EpisodeResult(0, 0, 3, False, True, None, 0.5, 0.6, 1.0, 0.1)
        return save_results(EvalResults((episode,), {"model": model, "protocol": PROTOCOLS["paper"].to_dict()}),
                            tmp_path / "m.json")

    stat = save("a").stat()
    cache: dict = {}
    assert find_results([tmp_path], {"model": "a"}, cache=cache)[0].meta["model"] == "a"
    save("b")  # the same size: only its time tells it is another file now
    os.utime(tmp_path / "m.json", ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert find_results([tmp_path], {"model": "a"}, cache=cache) is not None  # not read again
    os.utime(tmp_path / "m.json", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    assert find_results([tmp_path], {"model": "a"}, cache=cache) is None
    assert find_results([tmp_path], {"model": "b"}, cache=cache)[1] == tmp_path / "m.json"


def test_the_expert_baseline_drives_the_runs_robot(tmp_path: Path) -> None:
    # The map expert planned for the default robot (0.5 s control period) while the episodes played
    # the run's (0.3 s): its row scored a controller of another robot.
    from shared.evaluation.policies import make_policy
    from shared.evaluation.protocol import evaluate_policy

    run = tmp_path / "run"
    run.mkdir()
    cfg = small_config().with_overrides({"env.control_period_s": 0.3})
    (run / "config.toml").write_text(to_toml(cfg))
    quick = {**QUICK, "baselines": ("expert",), "max_steps": 10}
    played = load_results(build_report(run, **quick).results["paper"]["expert"])
    assert played.meta["env"]["control_period_s"] == 0.3

    def trajectories(env_cfg) -> list:
        expert = make_policy("expert", sensor_cfg=cfg.sensor, env_cfg=env_cfg)
        results = evaluate_policy(expert, world="box-room", sensor_cfg=cfg.sensor, env_cfg=cfg.env,
                                  episodes_per_start=1, max_steps=10, seed=played.meta["seed"],
                                  progress=False, protocol=PROTOCOLS["paper"])
        return [e.trajectory_xy for e in results.episodes]

    assert trajectories(None) != trajectories(cfg.env)  # the default robot's expert drives otherwise here
    assert [e.trajectory_xy for e in played.episodes] == trajectories(cfg.env)
