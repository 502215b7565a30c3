"""Benchmarks run by ``cogexplore bench``; each module has ``run(...) -> dict``."""
