"""The test protocol from Python: :func:`evaluate` a :class:`~cogexplore.Policy` or your own
controller, and its :class:`Results`.

It is ``cogexplore evaluate``: the same setup (``shared.evaluation.setup``: the network's camera,
the environment of its run or of the paper preset, its world) and the same protocol
(``shared.evaluation.protocol``: greedy episodes at the test speeds from every start pose, each
stopped at a collision or the step cap), so the same settings give the same results.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cogexplore._policy_io import CameraPolicy, same_aspect
from cogexplore.policy import Policy
from shared.evaluation import (
    DEFAULT_PROTOCOL,
    PAPER_EPISODES_PER_START,
    PAPER_MAX_STEPS,
    ProtocolConfig,
    protocol_named,
)
from shared.evaluation.protocol import evaluate_policy
from shared.evaluation.results import EvalResults, save_results, table_markdown
from shared.evaluation.setup import setup_evaluation
from shared.learning.policy import PolicyError


class Results(EvalResults):
    """The episodes of one evaluation and what they were run with (``shared.evaluation.results``:
    ``episodes``, ``meta``, ``summary`` with ``overall`` and ``per_start`` figures, ``to_dict()``)."""

    @property
    def mean_steps(self) -> float:
        """Mean moving steps per episode over every episode (the paper's Table III "Count")."""
        return float(self.summary["overall"]["mean_steps"])

    @property
    def per_start_steps(self) -> dict[int, float]:
        """Mean moving steps per episode from each start pose, by start index."""
        return {s["start_index"]: float(s["mean_steps"]) for s in self.summary["per_start"]}

    def table(self) -> str:
        """Table III (count, distance, coverage per start) as Markdown."""
        return table_markdown({str(self.meta.get("model", "policy")): self})

    def save(self, path: str | Path) -> Path:
        """Write the results JSON (``cogexplore.eval-results/2``, what ``cogexplore evaluate --json``
        writes and ``cogexplore report`` reads)."""
        return save_results(self, path)


class _Controller:
    """A callable ``depth_m -> command`` (or ``(command, scores)``, as ``shared.evaluation.policies``
    return) as the protocol calls it; its ``reset()``, if any, runs at each episode's start."""

    def __init__(self, fn: Callable[[np.ndarray], Any]):
        self.fn = fn
        if callable(getattr(fn, "reset", None)):
            self.reset = fn.reset

    def __call__(self, depth_m: np.ndarray) -> tuple[Any, Any]:
        out = self.fn(depth_m)
        return (out[0], out[1]) if isinstance(out, tuple) and len(out) == 2 else (out, None)


def _name(fn: Any) -> str:
    return getattr(fn, "__qualname__", None) or type(fn).__name__


def evaluate(policy: Policy | Callable[[np.ndarray], Any], world: str | None = None, *,
             episodes_per_start: int = PAPER_EPISODES_PER_START, max_steps: int = PAPER_MAX_STEPS,
             starts: Sequence[int] | None = None, seed: int = 0, resolution: tuple[int, int] | None = None,
             progress: bool = False, protocol: str | ProtocolConfig = DEFAULT_PROTOCOL) -> Results:
    """Run the test protocol and return its :class:`Results`.

    ``policy``: a :class:`Policy` (:func:`cogexplore.load_policy`), or any callable taking a float32
    (H, W) depth image in metres (0 = no return) and returning a command index 0..4 (see
    ``cogexplore.COMMAND_NAMES``), with an optional ``reset()`` called at each episode's start.
    A Policy sees its network's camera and plays in its run's world; an ONNX policy
    (:func:`cogexplore.onnx_runner.load_onnx_policy`) sees its network's camera and plays the paper's
    task in ``paper-indoor``; a callable sees the paper's 160 x 120 camera and plays in
    ``paper-indoor``. ``world``: a world name (``paper-indoor``, ``procedural:101``, a world XML
    file...), None for that default. ``episodes_per_start`` (the
    paper's 10: ten different draws under ``robust``; under ``paper`` each repeats exactly, so 1
    gives the same mean) episodes from each of ``starts`` (start indices from 0, as in the results; the tables and
    ``cogexplore evaluate --starts`` number them from 1; None: every start pose), each at most
    ``max_steps`` moving steps. ``seed`` seeds the episodes. ``resolution`` ``(width, height)`` renders the camera
    at another size (same field of view; a Policy resizes the images back to its network's).
    ``progress`` shows a progress bar. ``protocol``: ``robust`` (the default of ``cogexplore
    evaluate`` too: each start jittered by up to ±5 cm and ±3°, Kinect-like depth noise), ``paper``
    (the exact starts, no noise) or a ``shared.evaluation.ProtocolConfig``.
    """
    policy_version = 0
    if isinstance(policy, Policy):
        setup = setup_evaluation(None, model=policy.model, world=world)
        meta = setup.meta()
        policy_version = setup.model.policy_version
    elif isinstance(policy, CameraPolicy):
        # An ONNX export (cogexplore.onnx_runner.OnnxPolicy): its network's camera and command period, as
        # a Policy of the same network would see them; the file carries no run, so the paper's task.
        setup = setup_evaluation("random", world=world)
        setup = dataclasses.replace(setup, sensor_cfg=policy.sensor.noise_free(), env_cfg=dataclasses.replace(
            setup.env_cfg, control_period_s=policy.control_period_s))
        info = getattr(policy, "info", None)
        policy_version = getattr(info, "policy_version", 0)
        meta = {"policy": "greedy", "model": policy.label, "policy_version": policy_version,
                "weights_sha256": getattr(info, "weights_sha256", None)}
    elif callable(policy):
        # The baselines' setup (no network): the paper preset's camera and environment.
        setup = setup_evaluation("random", world=world)
        meta = {"policy": "callable", "model": _name(policy)}
    else:
        raise PolicyError(f"policy must be a cogexplore.Policy or a callable depth_m -> command, "
                          f"got {type(policy).__name__}")
    if not isinstance(protocol, (str, ProtocolConfig)):
        raise PolicyError(f"protocol must be 'robust', 'paper' or a ProtocolConfig, got {type(protocol).__name__}")
    sensor = setup.sensor_cfg
    if resolution is not None:
        if not (isinstance(resolution, (tuple, list)) and len(resolution) == 2):
            raise PolicyError(f"resolution must be (width, height), got {resolution!r}")
        sensor = dataclasses.replace(sensor, width=resolution[0], height=resolution[1])
        if isinstance(policy, CameraPolicy) and not same_aspect(sensor.width, sensor.height, policy.sensor):
            # else refused at the first step, as an image to crop: these have the network's field of view
            raise PolicyError(f"resolution {sensor.width} x {sensor.height} is not the aspect ratio of the network's "
                              f"{policy.sensor.width} x {policy.sensor.height} camera, whose images it takes")
    results = evaluate_policy(_Controller(policy), world=setup.world, sensor_cfg=sensor, env_cfg=setup.env_cfg,
                              episodes_per_start=episodes_per_start, max_steps=max_steps, seed=seed, starts=starts,
                              policy_version=policy_version,
                              progress=progress, meta=meta,
                              protocol=protocol_named(protocol) if isinstance(protocol, str) else protocol)
    return Results(results.episodes, results.meta)
