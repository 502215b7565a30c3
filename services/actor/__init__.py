"""The actor process (``service``): one environment, epsilon-greedy on the newest weights, transitions
out in batches (``batcher``); its options (``options``)."""
