"""``cogexplore bench env|learner|transport``; ``bench system`` lives with the launcher (services.up)."""
