"""The report's Markdown-to-HTML renderer (``services.tools.document``) on hostile input."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from services.tools.document import Paragraph, Table, html_page, inline_html


@pytest.mark.parametrize("text", ["[" * 20_000, "![" * 10_000, "[x](" * 20_000,
                                  "".join("`" * k + " " for k in range(1, 200))],
                         ids=["brackets", "images", "open-targets", "backtick-runs"])
def test_rendering_takes_linear_time_whatever_the_text(text: str, tmp_path: Path) -> None:
    # Each "[" (or "![", or fence) scanned to the end of the text for its closing: 40,000 of them in
    # a name or cell took from 16 to 50 s, and a report must never hang on what a user named a file.
    start = time.perf_counter()
    page = html_page([Paragraph(text), Table(("a",), (False,), ((text,),))], "t", tmp_path)
    assert time.perf_counter() - start < 2.0
    assert inline_html(text) in page
