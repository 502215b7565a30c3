"""Pictures of a run: Rerun recordings and live streams (``rerun``), PNG figures (``figures``).
No process owns them; the actor, the evaluator and the offline tools all draw through here. This
file holds only names that command-line options need without importing Rerun."""

ENV_RERUN_URL = "COGEXPLORE_RERUN_URL"
"""The Rerun viewer the actors and the evaluator stream to when ``--rerun-connect`` is not given."""
