"""Ten thousand malformed and hostile payloads on every key a secured run listens to (``bench fuzz``)."""

from __future__ import annotations

import pytest

from services.up import fuzz


@pytest.mark.timeout(600)
def test_ten_thousand_payloads_crash_nothing_and_every_one_is_counted(tmp_path) -> None:
    # a 16 MB payload to every key each round: a receiver (or the router) that kept them would
    # grow by 32 MB or more over the last two rounds
    result = fuzz.run(10_000, max_bytes=16 * 1024, big_bytes=16_000_000, runs_dir=tmp_path)
    assert result["by_kind"].pop("big") == 30 and result["payloads_sent"] == 10_030 and set(result["by_kind"]) == set(fuzz.PAYLOAD_KINDS)
    assert result["crashes"] == [] and all(code == 0 for code in result["exit_codes"].values()), result
    assert result["failed_at_stop"] == [] and "/bench-fuzz-" in result["logs"]  # not bench-system's name
    totals = {k: sum(v.values()) if isinstance(v, dict) else v for k, v in result["rejects"].items()}
    assert totals == result["expected_rejects"], {k: result[k] for k in ("rejects", "drain_s", "reported_live", "logs")}
    # the learner and the actor also count them in the statistics they publish as the run goes on
    assert result["reported_live"] == {k: result["expected_rejects"][k] for k in result["reported_live"]}, result
    assert result["weights_query_answered_after"]
    rss = result["rss_mb"]
    rounds = [rss["after_first_round"]] + [rss[f"after_round_{i}"] for i in range(2, 6)]
    series = {name: [round(r[name]) for r in rounds] for name in rounds[0]}  # MB after each round
    for name, mb in series.items():
        # A receiver that kept what it refused would grow in every round (by 16 MB for the big
        # payloads); a loaded machine may grow a queue or an allocator arena in a round or two
        # (the learner once went 447, 456, 471 MB in rounds 3-5, then level when run again).
        assert not all(b - a >= 8 for a, b in zip(mb[1:], mb[2:])), f"{name} grows round after round: {series}"
        assert mb[4] - mb[2] < 40, f"{name} grew over the last two rounds: {series}"
        # the 50 MB is measured by `bench fuzz`; two loaded CI cores keep growing queues longer
        assert mb[4] - mb[0] < 75, f"{name} grew after the first round: {series}"
