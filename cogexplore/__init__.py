"""cogexplore from Python: the shipped depth-only exploration policy, or your own, on any depth
image and in the paper's test protocol.

    import cogexplore

    policy = cogexplore.load_policy("pretrained")       # the shipped DRL model (or a checkpoint, weights file, run dir)
    command = policy.act(depth_m)                       # an (H, W) image in metres, any resolution -> 0..4
    linear_mps, angular_rps = policy.twist(command)     # what to send the robot, for policy.control_period_s
    results = cogexplore.evaluate(policy, world="paper-indoor", episodes_per_start=1)
    print(results.mean_steps, results.per_start_steps)

``evaluate`` also takes any callable ``depth_m -> command`` (with an optional ``reset()``), so your
own controller runs the same protocol. ``load_onnx_policy("F.onnx")`` gives the same policy without
torch (an export of ``cogexplore model export --onnx``; onnxruntime and numpy only). Importing this
package is cheap: torch and MuJoCo load on the first use of ``load_policy``, ``Policy``, ``evaluate``
or ``Results``. Every error a caller can cause is a :class:`CogexploreError` (a ``ValueError``) with a
one-line message.
"""

from __future__ import annotations

from typing import Any

from cogexplore.version import __version__
from shared.errors import CogexploreError

_LAZY = {"load_policy": "cogexplore.policy", "Policy": "cogexplore.policy", "Command": "cogexplore._policy_io",
         "COMMAND_NAMES": "cogexplore._policy_io", "evaluate": "cogexplore.evaluation",
         "Results": "cogexplore.evaluation", "load_onnx_policy": "cogexplore.onnx_runner",
         "OnnxPolicy": "cogexplore.onnx_runner"}

__all__ = ["__version__", "CogexploreError", *_LAZY]


def __getattr__(name: str) -> Any:
    # PEP 562: the heavy modules load when one of their names is first asked for.
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'cogexplore' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
