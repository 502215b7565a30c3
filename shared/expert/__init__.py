"""The privileged map expert (``expert``), the supervised data it labels (``dataset``) and the
supervised model trained on it (``supervised``)."""
