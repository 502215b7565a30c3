"""``cogexplore``: the one command-line entry to every service and tool.

The command tree below names, for each command, the light module that declares its options and the
module that runs it: building the parser imports only the options modules (argparse, the config
dataclasses, a few constants), so ``cogexplore --help`` and every ``cogexplore COMMAND --help``
start in a fraction of a second, and a command imports only what it runs. A user-facing error
(:class:`shared.errors.CogexploreError`: a bad setting, file, world, checkpoint, endpoint...) is
caught here, once, and printed as one line with exit status 2; so is an OSError (a path that is a
folder, no permission, a full disk) or a MemoryError (a setting that asks more than the machine has),
whose traceback goes to the log at debug level. A reader of stdout that goes away (``cogexplore bench
env | head -1``) ends the command quietly, as it ends ``yes | head -1``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from dataclasses import dataclass, field
from typing import Any

os.environ.setdefault("RERUN_ANALYTICS", "0")  # offline machines: no telemetry attempts


@dataclass(frozen=True)
class Command:
    """One command: its help line, ``module:function`` adding its options, ``module:function`` running it."""

    help: str
    options: str
    run: str


@dataclass(frozen=True)
class Group:
    """A command with actions (``cogexplore worlds list``)."""

    help: str
    metavar: str
    actions: dict[str, Command] = field(default_factory=dict)


TOOLS = "services.tools.options"
COMMANDS: dict[str, Command | Group] = {
    "up": Command("run router, learner, actors and evaluator locally (the embedded default)",
                  "services.up.options:add_up_arguments", "services.up.launcher:run_up_command"),
    "train": Command("train in one process (the paper's Algorithm 1; reference and baseline)",
                     f"{TOOLS}:add_train_arguments", "services.tools.train:run_train_command"),
    "router": Command("run a Zenoh router (default tcp/0.0.0.0:7447)",
                      "services.router.options:add_arguments", "services.router.service:run"),
    "learner": Command("run the learner service", "services.learner.options:add_learner_arguments",
                       "services.learner.service:run_learner_command"),
    "actor": Command("run one actor service (joins a run through its router)",
                     "services.actor.options:add_actor_arguments", "services.actor.service:run_actor_command"),
    "evaluator": Command("run the evaluator service (tests the newest weights every K updates)",
                         "services.evaluator.options:add_evaluator_arguments", "services.evaluator.service:run_evaluator"),
    "drive": Command("drive a ROS 2 robot with a trained policy over Zenoh (rmw_zenoh or zenoh-bridge-ros2dds): "
                     "depth image in, cmd_vel out, with a watchdog and a collision stop",
                     "services.drive.options:add_drive_arguments", "services.drive.service:run_drive_command"),
    "sim-robot": Command("the MuJoCo world as a ROS 2 robot over Zenoh (depth Image, Odometry, cmd_vel): a robot "
                         "to try `drive` on", "services.sim_robot.options:add_sim_robot_arguments",
                         "services.sim_robot.service:run_sim_robot_command"),
    "evaluate": Command("run the test protocol (robust, or the paper's) on a checkpoint or a baseline policy",
                        f"{TOOLS}:add_evaluate_arguments", "services.tools.evaluate:run_evaluate"),
    "report": Command("the paper's tables and figures (PNG, Markdown and HTML) for a run",
                      f"{TOOLS}:add_report_arguments", "services.tools.report:run_report"),
    "pretrain": Command("the supervised model (SL baseline, DRL conv init) from expert-labelled depth images",
                        f"{TOOLS}:add_pretrain_arguments", "services.tools.pretrain:run_pretrain_command"),
    "experiment": Command("the paper's SL / RL / DRL comparison end to end (resumable)",
                          f"{TOOLS}:add_experiment_arguments", "services.tools.experiment:run_experiment_command"),
    "worlds": Group("list and draw the worlds", "ACTION", {
        "list": Command("list built-in worlds (name, size, starts)", f"{TOOLS}:add_worlds_list_arguments",
                        "services.tools.worlds:run_list"),
        "show": Command("draw a top-down map with start poses and headings", f"{TOOLS}:add_worlds_show_arguments",
                        "services.tools.worlds:run_show"),
        "starts": Command("check that every start pose can survive: a beam search over command sequences on the "
                          "map (exact kinematics, the depth-collision rule) for the longest survival from each "
                          "start", f"{TOOLS}:add_worlds_starts_arguments", "services.tools.worlds:run_starts"),
        "demo": Command("plan demonstrations for training (train.demos): a beam search in the environment itself "
                        "from each --start for the smoothest command sequence that survives --horizon steps and "
                        "ends farthest away, recorded as images, commands and rewards (shared/learning/demos.py)",
                        f"{TOOLS}:add_worlds_demo_arguments", "services.tools.worlds:run_demo"),
    }),
    "model": Group("inspect, export and choose Q-networks", "ACTION", {
        "summary": Command("each layer's output shape and parameter count", f"{TOOLS}:add_model_summary_arguments",
                           "services.tools.model:run_summary"),
        "export": Command("write a checkpoint's online weights as a weights-only file (deployment, "
                          "`evaluate --checkpoint FILE`) and/or, with --onnx, an ONNX file that runs without "
                          "torch (`drive --onnx`); several checkpoints are averaged",
                          f"{TOOLS}:add_model_export_arguments", "services.tools.model:run_export"),
        "select": Command("choose the model to ship from a run: the mean of N consecutive checkpoints' weights "
                          "that reaches --gate-min on --gate-world and, among those, scores best on the --validate "
                          "worlds (writes the weights, <out>-windows.png and a resumable <out>-windows.jsonl)",
                          f"{TOOLS}:add_model_select_arguments", "services.tools.model:run_select"),
        "agreement": Command("how often models choose the map expert's command on the states a run's actors "
                             "visited (the labels kept in its replay memory: explore.expert_label_prob), and a "
                             "command with a way out where it marked them (explore.safe_label_prob); with the "
                             "majority command's and the actors' own agreement beside them",
                             f"{TOOLS}:add_model_agreement_arguments", "services.tools.model:run_agreement"),
    }),
    "secure": Group("close a run's bus to everyone but its own services (credentials, access control, TLS)",
                    "ACTION", {
        "init": Command("write a run's security folder: a user and password per role, the router's access control "
                        "list, each role's Zenoh config, and with --tls a CA and certificates",
                        "services.bus.options:add_secure_init_arguments", "services.bus.security:run_secure_init"),
        "export": Command("copy what one role needs to join from another machine (its config, and with TLS its "
                          "certificate and the run's CA): no other role's password, no CA key",
                          "services.bus.options:add_secure_export_arguments", "services.bus.security:run_secure_export"),
    }),
    "bench": Group("benchmarks: their figures as JSON (env, learner, transport, drive: on one line unless --json; "
                   "bench system without --json: a summary)",
                   "TARGET", {
        "env": Command("environment steps/s and depth-frame time on one core",
                       "services.bench.options:add_env_arguments", "services.bench.env:run_command"),
        "learner": Command("DQN update time, forward time and FLOP utilisation",
                           "services.bench.options:add_learner_arguments", "services.bench.learner:run_command"),
        "transport": Command("transitions/s through a loopback Zenoh router",
                             "services.bench.options:add_transport_arguments", "services.bench.transport:run_command"),
        "fuzz": Command("malformed and hostile payloads on every key a secured run's services listen to: crashes, "
                        "rejects by cause against what was sent, memory", "services.up.options:add_bench_fuzz_arguments",
                        "services.up.fuzz:run_command"),
        "drive": Command("image-to-command latency of `drive` through a loopback router (median, p99)",
                         "services.bench.options:add_drive_arguments", "services.bench.drive:run_command"),
        "system": Command("env steps/s, updates/s, weight lag and replay ratio of router + learner + N actors as "
                          "real processes", "services.up.options:add_bench_system_arguments",
                          "services.up.bench:run_command"),
    }),
}


def _function(target: str) -> Any:
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def _add(sub: Any, name: str, command: Command, path: str) -> None:
    p = sub.add_parser(name, help=command.help, description=command.help)
    _function(command.options)(p)
    # underscored names: no command option can have them (a --run option would overwrite a plain "run")
    p.set_defaults(_entry=command.run, _command=path)


def build_parser() -> argparse.ArgumentParser:
    """The whole command tree (imports only the options modules)."""
    from cogexplore.version import package_version

    parser = argparse.ArgumentParser(
        prog="cogexplore",
        description="Distributed deep RL for depth-only robot exploration (after Tai & Liu, 2016).",
    )
    parser.add_argument("--version", action="version", version=f"cogexplore {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, entry in COMMANDS.items():
        if isinstance(entry, Command):
            _add(sub, name, entry, name)
            continue
        group = sub.add_parser(name, help=entry.help, description=entry.help)
        actions = group.add_subparsers(dest=f"{name}_command", metavar=entry.metavar, required=True)
        for action, command in entry.actions.items():
            _add(actions, action, command, f"{name} {action}")
    return parser


SIGPIPE_STATUS = 128 + 13
"""The exit status of a command whose stdout reader went away, as a shell shows one killed by SIGPIPE."""


def error_line(command: str, error: BaseException | str) -> str:
    """``cogexplore COMMAND: error: MESSAGE`` in one line, even where a library's message has several
    (MuJoCo's compiler names the element below, Zenoh's parser draws the line it stopped at: its
    lines of bars and carets alone are left out)."""
    message = "; ".join(line.strip() for line in str(error).splitlines() if any(c.isalnum() for c in line))
    return f"cogexplore {command}: error: {message}"


def _stdout_reader_gone() -> bool:
    """Whether stdout is a pipe nobody reads any more (a write to it fails with EPIPE)."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
    except (AttributeError, OSError, ValueError):  # no real stdout (captured, closed)
        return False
    return any(events & select.POLLERR for _fd, events in poller.poll(0))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from shared.errors import CogexploreError, StopRequested

    try:
        status = int(_function(args._entry)(args) or 0)
        if sys.stdout is not None:  # None: started with stdout closed
            sys.stdout.flush()  # a reader that went away shows here, not as a message at interpreter exit
        return status
    except KeyboardInterrupt:
        return 130
    except StopRequested as exc:
        print(f"cogexplore {args._command}: {exc}", file=sys.stderr)
        return 0
    except CogexploreError as exc:
        print(error_line(args._command, exc), file=sys.stderr)
        return 2
    except (OSError, MemoryError) as exc:
        # a path that is a folder, no permission, a full disk; a config that asks for more memory than the
        # machine has (a replay.capacity of large images): the user's to fix, in one line
        if isinstance(exc, BrokenPipeError) and _stdout_reader_gone():
            # what is still buffered for stdout would fail again at exit: send it nowhere
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return SIGPIPE_STATUS
        import logging

        logging.getLogger("cogexplore").debug("%s failed", args._command, exc_info=True)
        print(error_line(args._command, f"out of memory: {exc}" if isinstance(exc, MemoryError) else exc),
              file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
