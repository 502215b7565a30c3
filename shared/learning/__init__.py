"""Learning: ``model`` (the Q-network), ``replay``, ``dqn`` (the update), ``policy`` (epsilon-greedy),
``learner`` (LearnerCore: replay + agent + replay ratio), ``checkpoints`` (every model file),
``weights`` (network <-> WeightsMessage), ``stats`` (the CSV records) and ``demos`` (planner
demonstrations)."""
