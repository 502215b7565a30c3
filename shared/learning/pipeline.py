"""TD targets one update ahead, on a second thread: the learner service's use of a second CPU core.

A CPU update spends a third of its time in the two gradient-free forward passes that make its TD
targets (theta^- on the next frames, and theta for Double DQN's argmax), the rest in the training
forward, backward and optimiser step. Splitting one update across two cores inside each operator
(torch's intra-op threads) falls apart as soon as other processes (the actors, the evaluator) share
those cores: every operator waits for its slowest thread. This pipeline splits it by stage instead:
while update k trains on the calling thread, a worker thread already computes the targets of
update k + 1, each on one thread, so a stage that loses its core for a moment slows only itself.

The price, stated: update k + 1's targets come from theta as it was *before* update k (one update
older than in :meth:`DQNAgent.update`), a delay of the kind distributed DQN learners accept
(Ape-X, R2D2); theta^- is the same target network, except when update k syncs it: update k + 1
still uses the one before (one update in every ``dqn.target_sync_every``). The worker reads its
own copies of theta and theta^-, refreshed from the agent while it is idle, so no optimiser step
ever writes under a forward pass. Every random draw (mirror flips, pixel shifts, dropout) stays on the calling
thread, so a pipelined run repeats exactly whatever the threads' timing. The single-process trainer does not
pipeline: there the environment already fills the second core between updates.
"""

from __future__ import annotations

import copy
from concurrent.futures import Future, ThreadPoolExecutor

import torch

from shared.learning.dqn import DQNAgent, PreparedBatch
from shared.learning.model import QNetwork
from shared.learning.replay import Batch


def _frozen_copy(net: QNetwork) -> QNetwork:
    twin = copy.deepcopy(net).eval()
    for p in twin.parameters():
        p.requires_grad_(False)
    return twin


class TargetPipeline:
    """Prepares (tensors, mirroring, TD targets) the next batch on a worker thread.

    ``submit(batch)`` starts the next batch (the worker must be idle: call it after ``take``);
    ``take()`` waits for it and returns ``(batch, prepared)``. ``close()`` stops the worker.
    """

    def __init__(self, agent: DQNAgent):
        self.agent = agent
        self._online = _frozen_copy(agent.online)
        self._target = _frozen_copy(agent.target)
        self._target_version = agent.target_version
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="td-targets")
        self._pending: tuple[Batch, Future[PreparedBatch]] | None = None

    @property
    def pending(self) -> bool:
        return self._pending is not None

    @torch.no_grad()
    def _refresh(self) -> None:
        # the worker is idle: its copies take the agent's current theta, and theta^- when it was
        # written since (every target_sync_every updates; copying it each update took 0.34 ms, 1.8%
        # of a `make run` update)
        pairs = [(self._online, self.agent.online)]
        if self._target_version != self.agent.target_version:
            pairs.append((self._target, self.agent.target))
            self._target_version = self.agent.target_version
        for mine, theirs in pairs:
            torch._foreach_copy_(list(mine.parameters()), list(theirs.parameters()))

    def submit(self, batch: Batch) -> None:
        if self._pending is not None:
            raise RuntimeError("TargetPipeline.submit: the previous batch was not taken")
        self._refresh()
        augmentation = self.agent.draw_augmentation(batch)
        self._pending = batch, self._worker.submit(self.agent.prepare, batch, augmentation, self._online,
                                                   self._target)

    def take(self) -> tuple[Batch, PreparedBatch]:
        if self._pending is None:
            raise RuntimeError("TargetPipeline.take: nothing was submitted")
        (batch, future), self._pending = self._pending, None
        return batch, future.result()

    def close(self) -> None:
        """Wait for the batch in flight (if any) and stop the worker; the batch is dropped."""
        self._pending = None
        self._worker.shutdown(wait=True)
