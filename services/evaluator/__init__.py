"""The evaluator process: the test protocol on the newest weights of a run, every K updates
(``service``), and its options (``options``). The protocol itself is ``shared.evaluation``; its
recordings ``services.viz``; the offline ``evaluate`` and ``report`` commands ``services.tools``."""
