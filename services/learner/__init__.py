"""The learner process (``service``): transitions in, DQN updates at the replay ratio, weights out;
its options (``options``). The algorithm side is ``shared.learning.learner.LearnerCore``."""
