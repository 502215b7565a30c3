"""The learner's process shell: its weights sender and its statistics log across a restart."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from services.bus.session import ZenohSettings, free_tcp_port, open_router
from services.learner.service import LatestSender, run_learner
from services.runs import RunPaths
from shared.config import load_preset
from shared.learning.stats import CsvLog, LearnerRow, read_csv_records


class SlowLink:
    """A publisher whose puts take their time, as BLOCK congestion control does on a slow link."""

    def __init__(self, put_s: float):
        self.put_s = put_s
        self.putting = threading.Event()
        self.sent: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.putting.set()
        time.sleep(self.put_s)
        self.sent.append(payload)


def test_the_sender_publishes_the_final_weights_even_behind_a_slow_put():
    link = SlowLink(put_s=0.5)
    sender = LatestSender(link)
    sender.offer(b"update 100")
    assert link.putting.wait(5.0)
    sender.offer(b"older, never sent")
    sender.offer(b"final")  # offered while update 100's put is still under way
    sender.close()  # it dropped the final weights: actors and the evaluator never saw the last version
    assert link.sent == [b"update 100", b"final"]
    sender.close()  # a second close is harmless


def _row(update: int) -> LearnerRow:
    return LearnerRow(time_s=update / 10, update=update, policy_version=update, loss=0.1, mean_q=1.0,
                      updates_per_s=10.0, transitions=update + 50, transitions_per_s=10.0, replay_size=update,
                      rejected=0, actors_alive=1, mean_weight_lag=0.0, label_agreement=None, lr=1e-3,
                      safe_agreement=None)


def test_a_learner_restarted_without_a_checkpoint_does_not_log_its_updates_going_back(tmp_path: Path):
    paths = RunPaths(tmp_path / "run").make()
    with CsvLog(paths.stats, LearnerRow) as log:  # a learner killed at update 300, before its first checkpoint
        for update in (0, 100, 200, 300):
            log.write(_row(update))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    stop = threading.Event()
    with open_router([endpoint]):
        timer = threading.Timer(1.0, stop.set)
        timer.start()
        try:
            result = run_learner(load_preset("smoke"), "run", paths, ZenohSettings(mode="client", connect=(endpoint,)),
                                 stop, stats_every_s=0.2)
        finally:
            timer.cancel()
    assert result["updates"] == 0  # no checkpoint: it started over
    updates = [int(r["update"]) for r in read_csv_records(paths.stats / LearnerRow.FILE)]
    # the rows after update 0 went: their updates come again (they were logged as 0, 100, 200, 300, 0, ...)
    assert updates and set(updates) == {0}
