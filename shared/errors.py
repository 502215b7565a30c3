"""The one base of every error a user can cause: a bad setting, file, name, message or endpoint.

Every such error of cogexplore derives from :class:`CogexploreError` (and from ``ValueError``, as
they all did before there was a common base), so the command line catches it once and prints its
message in one line instead of a traceback; anything else is a bug and keeps its traceback.

:class:`PolicyError` lives here too, not beside the torch policy that raises it most
(``shared.learning.policy`` re-exports it): the torch-free ONNX runner (``cogexplore.onnx_runner``)
raises the same error for the same bad image or command without importing torch.
"""

from __future__ import annotations


class CogexploreError(ValueError):
    """Input that cannot be used (a setting, file, world, checkpoint, message, endpoint...); the
    message names what and why."""


class StopRequested(CogexploreError):
    """A stop (SIGTERM, Ctrl-C) that came while a command was still getting ready (waiting for its
    router): not a failure; the command line says so in one line and exits 0."""


class PolicyError(CogexploreError):
    """A policy that cannot be built or fed: bad schedule parameters or actor index, an unknown
    policy name, a missing network, a wrong-sized image."""
