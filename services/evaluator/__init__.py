"""The evaluator: the paper's test protocol, Rerun logging, figures and tables.

Modules (imported on demand; none pulls in the others):

- ``results``: per-episode results, aggregation, the results JSON schema, the Table III
  Markdown and ``run_protocol`` (every start x N greedy episodes).
- ``rerun_log``: ``EvalRecorder``, the Rerun entity layout, timelines and default blueprint.
- ``receptive``: receptive-field maps of pool3 (Fig. 7).
- ``figures``: trajectory heatmaps, loss curves and the Q-value table (Table II).
"""
