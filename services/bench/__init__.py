"""``cogexplore bench env|learner|transport|drive``; ``bench system`` lives with the launcher (services.up)."""

from __future__ import annotations

import json
import signal
from typing import Any


def print_json(result: Any, indent: bool) -> None:
    """A benchmark's figures on stdout, always JSON (what the commands' help promises): indented
    (``--json``) or on one line."""
    print(json.dumps(result, indent=2 if indent else None, default=float))


def _interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt


def interrupt_on_stop_signals() -> None:
    """SIGTERM, and SIGINT even where a background shell ignored it, end a benchmark as Ctrl-C does:
    through its clean-up, which stops the processes it started (SIGTERM's default left them running)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _interrupt)
