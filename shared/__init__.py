"""The pure layer of cogexplore: everything but processes, Zenoh and Rerun (see README, Layout)."""
