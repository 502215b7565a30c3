"""``cogexplore bench env|learner|transport|drive``; ``bench system`` lives with the launcher (services.up)."""

from __future__ import annotations

import json
from typing import Any


def print_json(result: Any, indent: bool) -> None:
    """A benchmark's figures on stdout, always JSON (what the commands' help promises): indented
    (``--json``) or on one line."""
    print(json.dumps(result, indent=2 if indent else None, default=float))
