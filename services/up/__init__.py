"""``cogexplore up`` (``launcher``: router, learner, actors and evaluator as local processes) and
``cogexplore bench system`` (``bench``), with their options (``options``)."""
