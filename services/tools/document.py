"""A report as a list of blocks, written out as Markdown and as one HTML page.

Blocks hold their text in the small Markdown subset the tools write (```code```, ``**bold**``,
``_emphasis_``, ``[text](href)``, ``![alt](src)``, and ``\\`` before a punctuation mark meant
literally); ``shared.evaluation.results.escape_text``, ``code_span`` and ``link_target`` put names
and paths in.
``markdown`` writes the blocks as they are, ``html`` translates them, so both files come from the
same content. Tables that other modules produce as Markdown come in through ``Table.from_markdown``.
"""

from __future__ import annotations

import base64
import html
import re
import string
from bisect import bisect_right
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, unquote

from shared.errors import CogexploreError
from shared.evaluation.results import markdown_cell, one_line

# A page with every image inlined stays below this (base64 adds a third); else images are linked.
EMBED_LIMIT_BYTES = 5_000_000

# A backslash before ASCII punctuation makes it literal (CommonMark): link texts may hold escaped brackets.
_ESCAPED = r"\\(?P<esc>[!-/:-@\[-`{-~])"
_PUNCTUATION = frozenset(string.punctuation)
_WORD = re.compile(r"\w")
_STYLE = """body{font-family:system-ui,sans-serif;max-width:72rem;margin:2rem auto;padding:0 1rem;line-height:1.45}
table{border-collapse:collapse;margin:0.8rem 0}th,td{border:1px solid #ccc;padding:0.25rem 0.6rem}
th{background:#f3f3f3}td.num{text-align:right;font-variant-numeric:tabular-nums}
img{max-width:100%}td img{max-width:22rem}code{background:#f3f3f3;padding:0 0.2rem}"""


class DocumentError(CogexploreError):
    """A table the document cannot read."""


@dataclass(frozen=True)
class Heading:
    level: int
    text: str


@dataclass(frozen=True)
class Paragraph:
    text: str


@dataclass(frozen=True)
class Bullets:
    items: tuple[str, ...]


@dataclass(frozen=True)
class Table:
    """A pipe table: header cells, ``right`` per column (numbers), rows of cells."""

    header: tuple[str, ...]
    right: tuple[bool, ...]
    rows: tuple[tuple[str, ...], ...]

    @classmethod
    def from_markdown(cls, text: str) -> Table:
        """The table a Markdown pipe table (header, rule, rows) holds; ``\\|`` in a cell is a ``|`` of
        its text (a model named ``a|b``), every other ``|`` a column border."""
        lines = [line.strip() for line in text.strip().splitlines()]
        if len(lines) < 2 or not all(line.startswith("|") and line.endswith("|") and not line.endswith("\\|")
                                     for line in lines):
            raise DocumentError(f"not a Markdown pipe table: {text[:80]!r}")
        header, rule, *rows = ([c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line[1:-1])]
                               for line in lines)
        if len(rule) != len(header) or not all(re.fullmatch(r":?-+:?", c) for c in rule):
            raise DocumentError(f"the table's second line is not a rule of {len(header)} columns: {lines[1]!r}")
        for line, row in zip(lines[2:], rows):
            if len(row) != len(header):  # a cell's unescaped | would shift every cell after it
                raise DocumentError(f"a row of {len(row)} cells in a table of {len(header)} columns: {line[:80]!r}")
        return cls(tuple(header), tuple(c.endswith(":") for c in rule), tuple(tuple(r) for r in rows))


Block = Heading | Paragraph | Bullets | Table


# -- Markdown ---------------------------------------------------------------------------------


def code_span(value: object) -> str:
    """``value`` as a code span, fenced by more backticks than any run of them it holds. A line break
    becomes a blank, as a code span shows it: in a heading or an item it ended the line, and the rest
    of the name, outside the span, was raw HTML in the Markdown file (a folder named ``x\\n<img ...>``)."""
    s = one_line(value)
    fence = "`" * (max((len(run) for run in re.findall("`+", s)), default=0) + 1)
    pad = " " if s.startswith("`") or s.endswith("`") else ""
    return f"{fence}{pad}{s}{pad}{fence}"


def link_target(path: str) -> str:
    """A relative path as a link's or image's target: blanks, brackets and the like percent-encoded,
    so a file named ``my results (1).json`` stays one link."""
    return quote(path, safe="/")


def _markdown_block(block: Block) -> str:
    if isinstance(block, Heading):  # a heading and an item are a line each: a line break would end them
        return "#" * block.level + " " + one_line(block.text)
    if isinstance(block, Paragraph):
        return block.text
    if isinstance(block, Bullets):
        return "\n".join("- " + one_line(item) for item in block.items)
    rule = "|" + "".join("---:|" if r else "---|" for r in block.right)
    return "\n".join([_markdown_row(block.header), rule, *(_markdown_row(r) for r in block.rows)])


def _markdown_row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(markdown_cell(c) for c in cells) + " |"


def markdown(blocks: Sequence[Block]) -> str:
    """The blocks as a Markdown file's text."""
    return "\n\n".join(_markdown_block(b) for b in blocks) + "\n"


# -- HTML -------------------------------------------------------------------------------------


def _safe_target(target: str) -> bool:
    """Whether a link or image may point at ``target``: a relative path or a web address. Names and
    file names reach the text as they are; one holding ``[x](javascript:...)`` must not become a link
    that runs script when the page, opened in a browser, is clicked (browsers drop control characters
    and blanks around a scheme, so a target with any is refused too)."""
    if any(ord(ch) < 0x20 or ord(ch) == 0x7F for ch in target):
        return False
    scheme = re.match(r"([A-Za-z][A-Za-z0-9+.-]*):", target)
    return scheme is None or scheme[1].lower() in ("http", "https")


def _stops(text: str, closer: str) -> list[int]:
    """For each position, where a run of escaped punctuation and other characters than ``closer`` and
    ``\\`` starting there ends: at the first ``closer`` or lone backslash (``len(text)``: none)."""
    n = len(text)
    stop = [n] * (n + 2)
    for i in range(n - 1, -1, -1):
        if text[i] == "\\":
            stop[i] = stop[i + 2] if i + 1 < n and text[i + 1] in _PUNCTUATION else i
        else:
            stop[i] = i if text[i] == closer else stop[i + 1]
    return stop


def _first_from(text: str, pattern: str) -> list[int]:
    """For each position, the start of the first match of ``pattern`` there or after (``len(text)``: none)."""
    n = len(text)
    first, starts = [n] * (n + 1), [m.start() for m in re.finditer(pattern, text)]
    for i in range(n - 1, -1, -1):
        first[i] = starts.pop() if starts and starts[-1] == i else first[i + 1]
    return first


def _spans(text: str) -> Iterator[tuple[str, int, int, tuple[str, ...]]]:
    """The constructs of the Markdown subset in ``text``, left to right, as (kind, start, end, parts).

    Each start tries its one construct (the first character says which) in O(1) against ends found
    for every position beforehand: a regex's scan from each ``[`` to the end of the text made a line of
    40,000 of them take from 16 to 50 s."""
    n = len(text)
    brackets, underscores = _stops(text, "]"), _stops(text, "_")
    target_end = _first_from(text, r"[)\s]")  # a target is no blank and no ")"
    bold_end, line_end = _first_from(text, r"(?=\*\*)"), _first_from(text, "\n")
    runs = [(m.start(), m.end()) for m in re.finditer("`+", text)]
    run_end = [0] * n
    fences: dict[int, list[int]] = {}  # backtick runs by length: their starts
    for start, end in runs:
        run_end[start:end] = [end] * (end - start)
        fences.setdefault(end - start, []).append(start)

    def target(close: int) -> int | None:  # where "](target)" after a text ending at ``close`` ends
        if close + 1 < n and text[close] == "]" and text[close + 1] == "(":
            end = target_end[close + 2]
            if end > close + 2 and end < n and text[end] == ")":
                return end
        return None

    pos = 0
    while pos < n:
        c, span = text[pos], None
        if c == "\\" and pos + 1 < n and text[pos + 1] in _PUNCTUATION:
            span = ("esc", pos, pos + 2, (text[pos + 1],))
        elif c == "`":
            # a span ends at the first run of as many backticks (no more, no fewer) on its line
            end = run_end[pos]
            starts = fences.get(end - pos, [])
            k = bisect_right(starts, end)
            if k < len(starts) and starts[k] < line_end[end]:
                span = ("code", pos, starts[k] + end - pos, (text[end:starts[k]],))
        elif text.startswith("**", pos):
            close = bold_end[pos + 3] if pos + 3 <= n else n
            if close < n and line_end[pos] > close:
                span = ("bold", pos, close + 2, (text[pos + 2:close],))
        elif text.startswith("![", pos):
            close = brackets[pos + 2]
            end = target(close)
            if end is not None:
                span = ("image", pos, end + 1, (text[pos + 2:close], text[close + 2:end]))
        elif c == "[":
            close = brackets[pos + 1]
            end = target(close) if close > pos + 1 else None
            if end is not None:
                span = ("link", pos, end + 1, (text[pos + 1:close], text[close + 2:end]))
        elif c == "_" and not (pos and _WORD.match(text[pos - 1])):
            close = underscores[pos + 1]
            if pos + 1 < close < n and text[close] == "_" and not (close + 1 < n and _WORD.match(text[close + 1])):
                span = ("em", pos, close + 1, (text[pos + 1:close],))
        if span is None:
            pos += 1
        else:
            yield span
            pos = span[2]


def inline_html(text: str, image_src: Callable[[str], str] = lambda src: src) -> str:
    """``text`` (the Markdown subset) as HTML; ``image_src`` maps an image's path to its ``src``.
    Linear in the text's length, whatever it holds."""
    out, pos = [], 0
    for kind, start, end, parts in _spans(text):
        out.append(html.escape(text[pos:start]))
        pos = end
        if kind == "esc":
            out.append(html.escape(parts[0]))
        elif kind == "code":
            c = parts[0]  # CommonMark drops one blank each side (the padding of a span fenced by a backtick)
            c = c[1:-1] if len(c) > 2 and c[0] == c[-1] == " " else c
            out.append(f"<code>{html.escape(c)}</code>")
        elif kind in ("image", "link") and not _safe_target(parts[1]):
            out.append(html.escape(text[start:end]))  # shown as written, not followed
        elif kind == "bold":
            out.append(f"<strong>{inline_html(parts[0], image_src)}</strong>")
        elif kind == "image":
            out.append(f'<img src="{html.escape(image_src(parts[1]))}" alt="{html.escape(_unescape(parts[0]))}">')
        elif kind == "link":
            out.append(f'<a href="{html.escape(parts[1])}">{inline_html(parts[0], image_src)}</a>')
        else:
            out.append(f"<em>{inline_html(parts[0], image_src)}</em>")
    out.append(html.escape(text[pos:]))
    return "".join(out)


def _unescape(text: str) -> str:
    return re.sub(_ESCAPED, r"\g<esc>", text)


def images(blocks: Sequence[Block]) -> list[str]:
    """Every image path the blocks show, in order."""
    found: list[str] = []
    for text in (t for b in blocks for t in _texts(b)):
        inline_html(text, lambda src: found.append(src) or src)  # the images the page shows, as it reads them
    return found


def _texts(block: Block) -> list[str]:
    if isinstance(block, (Heading, Paragraph)):
        return [block.text]
    if isinstance(block, Bullets):
        return list(block.items)
    return [*block.header, *(c for r in block.rows for c in r)]


def _html_block(block: Block, src: Callable[[str], str]) -> str:
    if isinstance(block, Heading):
        return f"<h{block.level}>{inline_html(block.text, src)}</h{block.level}>"
    if isinstance(block, Paragraph):
        return f"<p>{inline_html(block.text, src)}</p>"
    if isinstance(block, Bullets):
        return "<ul>\n" + "\n".join(f"<li>{inline_html(i, src)}</li>" for i in block.items) + "\n</ul>"
    head = "".join(f"<th>{inline_html(c, src)}</th>" for c in block.header)
    body = "\n".join("<tr>" + "".join(f'<td class="num">{inline_html(c, src)}</td>' if right
                                      else f"<td>{inline_html(c, src)}</td>"
                                      for c, right in zip(row, block.right)) + "</tr>" for row in block.rows)
    return f"<table>\n<thead><tr>{head}</tr></thead>\n<tbody>\n{body}\n</tbody>\n</table>"


def html_page(blocks: Sequence[Block], title: str, base: Path, embed: bool | None = None) -> str:
    """The blocks as one HTML page. Image paths are relative to ``base``; they are inlined as
    data URIs when ``embed`` (default: when all of them together fit ``EMBED_LIMIT_BYTES``),
    else linked, so the page opens from its folder either way."""
    paths = {src: base / unquote(src) for src in images(blocks)}
    if embed is None:
        embed = sum(p.stat().st_size for p in paths.values() if p.is_file()) * 4 / 3 < EMBED_LIMIT_BYTES

    def src(path: str) -> str:
        file = paths.get(path)
        if not embed or file is None or not file.is_file() or file.suffix.lower() != ".png":
            return path
        return "data:image/png;base64," + base64.b64encode(file.read_bytes()).decode("ascii")

    body = "\n".join(_html_block(b, src) for b in blocks)
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>{html.escape(title)}</title>\n'
            f"<style>\n{_STYLE}\n</style>\n</head>\n<body>\n{body}\n</body>\n</html>\n")
