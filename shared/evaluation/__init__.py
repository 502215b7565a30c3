"""The paper's test protocol (Section V-A) and what it runs: policies, results, probe scenes.

``protocol`` runs episodes (``shared.rollout``) and returns ``results``; ``setup`` resolves a
checkpoint or baseline into a policy; ``policies`` are the learned policy and the baselines;
``probes`` are the Table II scenes. The protocol's numbers live here, importable without numpy
(the command line's options read them).
"""

PAPER_MAX_STEPS = 200
"""Moving steps per test episode at most (the paper's cap)."""
PAPER_EPISODES_PER_START = 10
"""Test episodes from each start pose (the paper's 12 x 10)."""
DEFAULT_WORLD = "paper-indoor"
"""The world a model without a stored training world is evaluated in."""
POLICY_NAMES: tuple[str, ...] = ("greedy", "random", "reactive", "sl", "rl")
"""Names ``policies.make_policy`` and ``cogexplore evaluate --policy`` accept."""
BASELINE_POLICIES: tuple[str, ...] = ("random", "reactive")
"""Policies that need no checkpoint."""
