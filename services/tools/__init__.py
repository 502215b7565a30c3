"""The offline tools: ``evaluate``, ``report``, ``model`` (summary, export, select), ``worlds``,
``experiment``, ``pretrain`` and ``train`` (the single-process trainer); their options in ``options``."""
