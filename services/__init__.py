"""The processes and the tools that need I/O (see README, Layout): rooms (``actor``, ``learner``,
``evaluator``, ``router``, ``up``, ``tools``, ``bench``) that import no other room, and the homes they
share (``bus``, ``viz``, ``options``, ``runs``, ``process``)."""
