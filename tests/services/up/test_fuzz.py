"""Ten thousand malformed and hostile payloads on every key a secured run listens to (``bench fuzz``)."""

from __future__ import annotations

import pytest

from services.up import fuzz


@pytest.mark.timeout(600)
def test_ten_thousand_payloads_crash_nothing_and_every_one_is_counted(tmp_path) -> None:
    result = fuzz.run(10_000, max_bytes=16 * 1024, runs_dir=tmp_path)
    assert result["payloads_sent"] == 10_000 and set(result["by_kind"]) == set(fuzz.PAYLOAD_KINDS)
    assert result["crashes"] == [] and all(code == 0 for code in result["exit_codes"].values()), result
    totals = {k: sum(v.values()) if isinstance(v, dict) else v for k, v in result["rejects"].items()}
    assert totals == result["expected_rejects"], result["rejects"]
    assert result["weights_query_answered_after"]
    before, after = result["rss_mb"]["after_first_round"], result["rss_mb"]["at_end"]
    assert all(after[name] - before[name] < 50 for name in before), result["rss_mb"]
