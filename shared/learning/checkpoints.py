"""Every model file of cogexplore, written and read in one place: training checkpoints,
weights-only exports, supervised models, the shipped models, and loading any of them for play.

**Training checkpoints** of a DQNAgent (and optionally its replay memory).

A checkpoint directory holds::

    ckpt-000001000.safetensors          online + target weights, optimiser tensors, torch RNG;
                                        JSON metadata (counters, optimiser hyperparameters,
                                        configs, caller extras, a SHA-256 of all tensor bytes)
    ckpt-000001000.replay-<digest>.safetensors
                                        optional: the replay memory's arrays + its JSON state
                                        (named by content, so re-saving the same update never
                                        pairs a checkpoint with another save's replay)
    latest                              the name of the newest complete checkpoint

Every file is written to a temporary name, fsynced, renamed into place and the directory
fsynced, replay before checkpoint before ``latest``, so a crash at any point leaves ``latest``
naming a complete checkpoint; the last ``keep`` checkpoints stay on disk, and the replay memory
with the newest ``keep_replays`` of them only (a replay is the bulk of a checkpoint's bytes and
only a resume reads it; an older checkpoint resumes with an empty replay). An agent whose weights or
optimiser state have diverged (NaN, infinite) is refused before any file is written, so its save never
prunes the run's good checkpoints (:class:`NonFiniteWeights`). Loading verifies the
format and the digest: a truncated or corrupt file raises :class:`CheckpointError` and
``CheckpointManager.load_latest`` falls back to the newest older checkpoint that loads.

**Weights-only exports**: ``export_weights`` writes the online net, its architecture and policy
version for deployment; ``load_exported_weights`` rebuilds it. ``pretrained[:drl|:sl]`` names the
models shipped in ``shared/pretrained/``; ``init_agent_weights`` starts a run from one (fine-tuning).

**Supervised models** (``cogexplore pretrain``, format ``cogexplore-supervised``):
``save_supervised`` / ``load_supervised``, and ``init_agent_conv``, the paper's transfer of their
conv layers into a DQN agent.

**Loading for play**: ``load_model`` takes whatever a user names (a checkpoint file or directory,
a run folder, a weights export, ``pretrained``) and returns a :class:`LoadedModel` (network in eval
mode, where it came from, its run config); ``average_models`` averages several networks' weights,
``ensemble_models`` makes a Q-value ensemble of them (one file with ``export_weights``).

Weights are safetensors and metadata JSON: nothing is ever unpickled.
"""

from __future__ import annotations

import copy
import dataclasses
import errno
import hashlib
import json
import logging
import os
import re
import stat
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import safetensors.numpy
import safetensors.torch
import torch
from safetensors import SafetensorError

from shared.files import TMP_MARK, atomic_write_text, read_regular_file, write_atomically
from shared.config import (
    ROBOT_FIELDS,
    ConfigError,
    ModelConfig,
    ReplayConfig,
    RunConfig,
    SensorConfig,
    config_differences,
    from_dict,
    is_whole,
)
from shared.errors import CogexploreError
from shared.jsontext import parse_json
from shared.learning.dqn import DQNAgent, DQNError
from shared.learning.model import (
    MAX_ENSEMBLE_MEMBERS,
    ModelError,
    QEnsemble,
    QNetwork,
    SupervisedNet,
    architecture_fingerprint,
    average_weights,
    check_weights_fit,
    copy_conv_weights,
    load_tensors,
    resolve_device,
    weights_to_tensors,
)
from shared.learning.replay import ReplayError, ReplayMemory

log = logging.getLogger("cogexplore.checkpoints")

FORMAT = "cogexplore-checkpoint"
WEIGHTS_FORMAT = "cogexplore-weights"
VERSION = 1
LATEST = "latest"
LATEST_MAX_BYTES = 4096
"""The most ``latest`` may hold: a checkpoint's file name, never more than a line."""
_META_KEY = "cogexplore"
_NAME_RE = re.compile(r"^ckpt-(\d{9})\.safetensors$")
_REPLAY_RE = re.compile(r"^ckpt-(\d{9})\.replay-[0-9a-f]{12}\.safetensors$")


class CheckpointError(CogexploreError):
    """A checkpoint or weights file is missing, partial, corrupt or does not fit."""


class NonFiniteWeights(CheckpointError):
    """An agent whose weights or optimiser state hold NaN or infinite values (diverged): never written
    as a checkpoint, since no loader takes it and saving it would prune the run's good ones."""


class WrongFileFormat(CheckpointError):
    """A readable safetensors file that is not of the format asked for (another cogexplore format,
    no cogexplore metadata, or metadata that is no table): not a damaged file of that format."""


def _digest(arrays: Mapping[str, Any]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = arrays[name]
        if isinstance(a, torch.Tensor):
            a = a.detach().to("cpu").contiguous().reshape(-1).view(torch.uint8).numpy()
        else:
            a = np.ascontiguousarray(a).reshape(-1).view(np.uint8)
        h.update(name.encode())
        h.update(str(a.size).encode())
        h.update(memoryview(a))
    return h.hexdigest()


def save_tensors_file(path: Path, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    """Atomically write tensors + JSON metadata (with a digest of the tensors) as safetensors. A write
    that fails (a full disk, a quota) is an OSError, as any other file's: safetensors reports it as
    its own error, which the CLI and the services would take for a bug (a traceback)."""
    meta = dict(meta, digest=_digest(tensors))
    _write_safetensors(path, lambda tmp: safetensors.torch.save_file(tensors, tmp,
                                                                     metadata={_META_KEY: json.dumps(meta)}))


def _write_safetensors(path: Path, save: Callable[[Path], None]) -> None:
    """``save(tmp)``, a safetensors writer, via :func:`write_atomically`: its failure (a full disk, a
    quota) an OSError naming ``path``, not safetensors' own error, which the CLI and the services would
    take for a bug (a traceback)."""
    def write(tmp: Path) -> None:
        try:
            save(tmp)
        except SafetensorError as exc:
            code = re.search(r"os error (\d+)", str(exc))
            # named by write_atomically: "<path> cannot be written: <safetensors' message>"
            raise OSError(int(code.group(1)) if code else errno.EIO, str(exc)) from None

    write_atomically(path, write)


def _require_regular_file(path: Path) -> None:
    """CheckpointError unless ``path`` is a regular file: safetensors would wait for ever for a FIFO's
    writer, in Rust where no signal stops it, and read ``/dev/zero`` without end."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise CheckpointError(f"{path} does not exist") from None
    except OSError as exc:  # a symlink loop, no permission
        raise CheckpointError(f"{path} cannot be read: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise CheckpointError(f"{path} is not a regular file (a folder, a FIFO, a device?)")


def _read_meta(path: Path, fmt: str) -> dict[str, Any]:
    _require_regular_file(path)
    try:
        with safetensors.safe_open(str(path), framework="numpy") as f:
            raw = (f.metadata() or {}).get(_META_KEY)
    except FileNotFoundError:
        raise CheckpointError(f"{path} does not exist") from None
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path} is not a readable safetensors file (partial or corrupt?): "
                              f"{exc}") from None
    if raw is None:
        raise WrongFileFormat(f"{path} has no cogexplore metadata: not a {fmt} file")
    meta = parse_json(raw, f"{path}: its metadata", WrongFileFormat)
    if not isinstance(meta, dict):
        raise WrongFileFormat(f"{path}: its metadata is not a table")
    if meta.get("format") != fmt:
        raise WrongFileFormat(f"{path} is a {meta.get('format')!r} file, expected {fmt!r}")
    if meta.get("version") != VERSION:
        raise CheckpointError(f"{path} has format version {meta.get('version')}, this code reads {VERSION}")
    return meta


def load_tensors_file(path: Path, fmt: str, framework: str = "pt") -> tuple[dict[str, Any], dict[str, Any]]:
    """Read a file written by save_tensors_file: check its format tag ``fmt`` and digest;
    raises CheckpointError if it is partial, corrupt or of another format."""
    meta = _read_meta(path, fmt)
    try:
        if framework == "pt":
            tensors: dict[str, Any] = safetensors.torch.load_file(str(path))
        else:
            tensors = safetensors.numpy.load_file(str(path))
    except (SafetensorError, OSError, ValueError, RuntimeError, TypeError) as exc:  # TypeError: a dtype numpy lacks
        raise CheckpointError(f"{path} cannot be read (partial or corrupt?): {exc}") from None
    if _digest(tensors) != meta.get("digest"):
        raise CheckpointError(f"{path} is corrupt: its tensor data does not match the stored digest")
    if framework == "pt":
        # the digest only proves the bytes are the writer's: a network with NaN or infinite weights gives
        # NaN Q-values, whose argmax an evaluation or a robot would play as a command
        bad = non_finite_tensor(tensors)
        if bad is not None:
            raise CheckpointError(f"{path}: {bad} holds NaN or infinite values (diverged or damaged weights)")
    return tensors, meta


def non_finite_tensor(tensors: Mapping[str, torch.Tensor]) -> str | None:
    """The name of the first floating-point tensor with a NaN or an infinity; None when all are finite
    (read on the tensors' own device)."""
    for name, t in tensors.items():
        if not t.is_floating_point():
            continue
        if t.dtype not in (torch.float16, torch.bfloat16, torch.float32, torch.float64):
            t = t.float()  # float8 has no isfinite; its NaN stays NaN in float32
        if not bool(torch.isfinite(t).all()):
            return name
    return None


# --------------------------------------------------------------------------- checkpoints
@dataclass
class Checkpoint:
    """A loaded, verified checkpoint (not yet applied to an agent)."""

    path: Path
    tensors: dict[str, torch.Tensor]
    agent_meta: dict[str, Any]
    config: dict[str, Any] | None
    extra: dict[str, Any]
    replay_path: Path | None = None
    replay_digest: str | None = None

    @property
    def update_count(self) -> int:
        return int(self.agent_meta["update_count"])

    @property
    def policy_version(self) -> int:
        return int(self.agent_meta["policy_version"])

    def restore(self, agent: DQNAgent, replay: ReplayMemory | None = None) -> None:
        """Load the agent's state (and the replay memory, when given and saved) exactly."""
        try:
            agent.load_state_tensors(self.tensors, self.agent_meta)
        except (DQNError, ModelError, KeyError, ValueError, TypeError, AttributeError, IndexError) as exc:
            # whatever a forged agent state raises: a CheckpointError, which a resume skips or reports
            raise CheckpointError(f"{self.path} does not fit this agent: {exc!r}") from None
        if replay is not None:
            self.restore_replay(replay)

    def check_replay_fits(self, replay: ReplayMemory) -> None:
        """CheckpointError when the replay memory kept with this checkpoint would not load into
        ``replay``; read from the file's header, not its arrays. Nothing to check without one."""
        if self.replay_path is None or not self.replay_path.exists():
            return
        mismatch = replay.state_mismatch(_read_meta(self.replay_path, FORMAT + "-replay").get("replay"))
        if mismatch is not None:
            raise CheckpointError(f"{self.replay_path} does not fit this replay memory: {mismatch}")

    def restore_replay(self, replay: ReplayMemory) -> None:
        """Load the replay memory saved with this checkpoint into ``replay``."""
        if self.replay_path is None:
            raise CheckpointError(f"{self.path} was saved without its replay memory")
        if not self.replay_path.exists():
            raise CheckpointError(f"{self.path}'s replay memory was not kept ({self.replay_path.name}: only "
                                  "the newest checkpoints keep theirs)")
        arrays, meta = load_tensors_file(self.replay_path, FORMAT + "-replay", framework="numpy")
        if meta.get("digest") != self.replay_digest:
            raise CheckpointError(f"{self.replay_path} belongs to another checkpoint")
        try:
            replay.load_state_dict(arrays, meta["replay"])
        except (ReplayError, KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{self.replay_path} does not fit this replay memory: {exc}") from None


def save_checkpoint(path: Path | str, agent: DQNAgent, *, replay: ReplayMemory | None = None,
                    config: Mapping[str, Any] | None = None,
                    extra: Mapping[str, Any] | None = None) -> Path:
    """Write one checkpoint file (and ``<stem>.replay-<digest>.safetensors`` with ``replay``).

    ``config`` is the run's config dict (RunConfig.to_dict()); ``extra`` any JSON-able state of
    the caller (environment steps, episode counts, other RNG states). NonFiniteWeights, with nothing
    written, when a weight or optimiser tensor of the agent is NaN or infinite.
    """
    path = Path(path)
    tensors, agent_meta = agent.state_tensors()
    bad = non_finite_tensor(tensors)
    if bad is not None:  # before any file, the replay's included: a loader would refuse the checkpoint
        raise NonFiniteWeights(f"{path}: not written: {bad} holds NaN or infinite values at update "
                               f"{agent.update_count} (diverged weights)")
    path.parent.mkdir(parents=True, exist_ok=True)
    replay_info = None
    if replay is not None:
        arrays, rmeta = replay.state_dict()
        rdigest = _digest(arrays)
        rpath = path.with_name(_replay_name(path, rdigest))
        new_replay = not rpath.exists()
        _write_safetensors(rpath, lambda tmp: safetensors.numpy.save_file(
            {k: np.ascontiguousarray(v) for k, v in arrays.items()}, tmp,
            metadata={_META_KEY: json.dumps({"format": FORMAT + "-replay", "version": VERSION,
                                             "replay": rmeta, "digest": rdigest})}))
        replay_info = {"file": rpath.name, "digest": rdigest}
    meta = {"format": FORMAT, "version": VERSION, "created_unix": time.time(), "agent": agent_meta,
            "config": dict(config) if config is not None else None,
            "extra": dict(extra) if extra is not None else {}, "replay": replay_info}
    try:
        json.dumps(meta)
    except TypeError as exc:
        raise CheckpointError(f"checkpoint config/extra must be JSON-serialisable: {exc}") from None
    try:
        save_tensors_file(path, tensors, meta)
    except BaseException:
        if replay_info is not None and new_replay:  # no checkpoint names it: on a full disk, space the retry needs
            rpath.unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: Path | str) -> Checkpoint:
    """Read and verify one checkpoint file; raises CheckpointError if partial or corrupt."""
    path = Path(path)
    tensors, meta = load_tensors_file(path, FORMAT)
    agent, config, extra = meta.get("agent"), meta.get("config"), meta.get("extra") or {}
    if not (isinstance(agent, dict) and all(is_whole(agent.get(k)) and agent[k] >= 0
                                            for k in ("update_count", "policy_version"))):
        raise CheckpointError(f"{path}: its agent state is not a table with whole update_count and policy_version")
    if not (config is None or isinstance(config, dict)) or not isinstance(extra, dict):
        raise CheckpointError(f"{path}: its config and extra must be tables")
    rinfo = _replay_info(path, meta)
    return Checkpoint(path=path, tensors=tensors, agent_meta=agent, config=config, extra=extra,
                      replay_path=path.with_name(rinfo["file"]) if rinfo else None,
                      replay_digest=rinfo["digest"] if rinfo else None)


def _writer_alive(tmp_name: str) -> bool:
    """Whether the process that names a temporary file (``.<name>.tmp-<pid>``) still runs: its file is
    being written (this process's, or another's, e.g. an export into this folder), not left by a crash."""
    pid = tmp_name.rpartition(TMP_MARK)[2]
    if not (pid.isascii() and pid.isdigit() and 0 < int(pid) < 2**22):
        return False
    try:
        os.kill(int(pid), 0)
    except PermissionError:  # another user's process
        return True
    except OSError:
        return False
    return True


def _replay_suffix(digest: str) -> str:
    return f".replay-{digest[:12]}.safetensors"


def _replay_name(checkpoint: Path, digest: str) -> str:
    """The name of a checkpoint's replay memory file, beside it."""
    return checkpoint.name.replace(".safetensors", _replay_suffix(digest))


def _replay_info(path: Path, meta: Mapping[str, Any]) -> dict[str, str] | None:
    """A checkpoint's note of its replay memory file (None: saved without one), checked: a forged
    one may name no other file than a replay memory beside it."""
    rinfo = meta.get("replay")
    if rinfo is None:
        return None
    name, digest = (rinfo.get("file"), rinfo.get("digest")) if isinstance(rinfo, dict) else (None, None)
    # a bare name beside the checkpoint, its digest's: a copied or renamed checkpoint keeps its old one
    if not (isinstance(digest, str) and isinstance(name, str) and "/" not in name and "\\" not in name
            and not name.startswith(".") and name.endswith(_replay_suffix(digest))):
        raise CheckpointError(f"{path}: its replay entry does not name a replay memory file and digest")
    return rinfo


@dataclass
class CheckpointManager:
    """Numbered checkpoints in one directory with a ``latest`` pointer; keeps the last ``keep``,
    the replay memory with the last ``keep_replays`` of them."""

    directory: Path
    keep: int = 3
    keep_replays: int = 2
    skipped: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.directory = Path(self.directory)
        for name in ("keep", "keep_replays"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise CheckpointError(f"{name} must be an integer >= 1, got {value!r}")

    def path_for(self, update_count: int) -> Path:
        return self.directory / f"ckpt-{update_count:09d}.safetensors"

    def checkpoints(self) -> list[Path]:
        """Checkpoint files present, oldest first."""
        if not self.directory.is_dir():
            return []
        return sorted(p for p in self.directory.iterdir() if _NAME_RE.match(p.name))

    def latest(self) -> Path | None:
        """The checkpoint ``latest`` names (None if there is none)."""
        pointer = self.directory / LATEST
        if not pointer.exists():
            return None
        try:  # a FIFO would wait for ever, /dev/zero or a big file would fill the memory
            name = read_regular_file(pointer, LATEST_MAX_BYTES).decode().strip()
        except (OSError, UnicodeDecodeError) as exc:  # a folder, no permission, bytes that are no name
            raise CheckpointError(f"{pointer} cannot be read: {exc}") from None
        if not _NAME_RE.match(name):
            raise CheckpointError(f"{pointer} names {name!r}, which is not a checkpoint file")
        return self.directory / name

    def save(self, agent: DQNAgent, *, replay: ReplayMemory | None = None,
             config: Mapping[str, Any] | None = None, extra: Mapping[str, Any] | None = None) -> Path:
        """Save at the agent's update count, point ``latest`` at it, prune older ones. An agent whose
        state is not finite (diverged) is refused (NonFiniteWeights) before anything is written or
        pruned: ``latest`` and every checkpoint stay as they were."""
        self.directory.mkdir(parents=True, exist_ok=True)
        path = save_checkpoint(self.path_for(agent.update_count), agent, replay=replay,
                               config=config, extra=extra)
        atomic_write_text(self.directory / LATEST, path.name + "\n")
        self._prune(path)
        return path

    def _prune(self, newest: Path) -> None:
        ckpts = [p for p in self.checkpoints() if p != newest]
        for old in ckpts[: max(0, len(ckpts) - (self.keep - 1))]:
            old.unlink(missing_ok=True)
        live_replays = set()
        # the new checkpoint's first: `latest` names it even when an older timeline left higher-numbered
        # files (a resume that fell back past a damaged one), which must not take its replay's place
        others = [p for p in self.checkpoints() if p != newest]
        for p in [newest, *others[max(0, len(others) - (self.keep_replays - 1)):]]:
            try:
                rinfo = _replay_info(p, _read_meta(p, FORMAT))
            except CheckpointError:
                continue  # unreadable: its replay is useless too
            if rinfo:
                live_replays.add(rinfo["file"])
        for p in self.directory.iterdir():
            # orphans: replays of pruned, re-saved or older checkpoints, temporaries of crashed writers
            orphan_replay = _REPLAY_RE.match(p.name) and p.name not in live_replays
            stale_tmp = p.name.startswith(".") and TMP_MARK in p.name and not _writer_alive(p.name)
            if orphan_replay or stale_tmp:
                p.unlink(missing_ok=True)

    def load(self, path: Path | str | None = None) -> Checkpoint:
        """Load ``path``, or the one ``latest`` names; errors if it is partial or corrupt."""
        target = Path(path) if path is not None else self.latest()
        if target is None:
            raise CheckpointError(f"no checkpoint in {self.directory}")
        return load_checkpoint(target)

    def load_latest(self) -> Checkpoint | None:
        """The newest checkpoint that loads, starting from ``latest``; None if there is none.

        Files that fail (and why) are listed in ``self.skipped``.
        """
        self.skipped = []
        candidates = list(reversed(self.checkpoints()))
        try:
            first = self.latest()
        except CheckpointError as exc:
            self.skipped.append(str(exc))
            first = None
        if first is not None:
            candidates = [first] + [p for p in candidates if p != first and p.name < first.name]
        for path in candidates:
            try:
                return load_checkpoint(path)
            except CheckpointError as exc:
                self.skipped.append(str(exc))
        return None


# --------------------------------------------------------------------------- weights-only export
def export_weights(path: Path | str, net: QNetwork | QEnsemble, policy_version: int = 0, *, half: bool = False,
                   run_config: RunConfig | None = None, extra: Mapping[str, Any] | None = None) -> Path:
    """Write the network's weights, architecture and policy version (for deployment).

    A :class:`QEnsemble` is written as one file: every member's weights (``members.<i>.``) and, in
    ``members``, every member's model config. ``half`` stores float16 (half the bytes; loading
    casts back to float32, and the greedy action is what matters, not the last bits of a Q-value).
    ``run_config``, the config of the run the weights come from, is kept so that the export is
    evaluated in that run's world and robot as its checkpoints are (without it: the paper preset's).
    ``extra`` is JSON-able metadata kept beside the weights (e.g. a model card)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # extra first: a key of its own named like one of the file's would make it unloadable
    meta = {**dict(extra or {}), "format": WEIGHTS_FORMAT, "version": VERSION, "policy_version": int(policy_version),
            "fingerprint": architecture_fingerprint(net),
            "model": asdict(net.model_cfg), "sensor": asdict(net.sensor_cfg)}
    if run_config is not None:
        meta["run_config"] = run_config.to_dict()
    if isinstance(net, QEnsemble):
        meta["members"] = [asdict(m.model_cfg) for m in net.members]
    save_tensors_file(path, export_tensors(net, path, half=half), meta)
    return path


def export_tensors(net: QNetwork | QEnsemble, path: Path | str, *, half: bool = False) -> dict[str, torch.Tensor]:
    """The tensors :func:`export_weights` writes to ``path``; CheckpointError for weights no loader
    takes (float16 overflows past 65504), so a caller writing other files too can ask first."""
    tensors = weights_to_tensors(net)
    if half:
        tensors = {n: t.half() if t.is_floating_point() else t for n, t in tensors.items()}
    bad = non_finite_tensor(tensors)
    if bad is not None:
        in_half = half and non_finite_tensor(weights_to_tensors(net)) is None
        raise CheckpointError(f"{path}: not written: weight {bad} is not finite"
                              + (" in float16 (drop --half)" if in_half else " (diverged weights?)"))
    return tensors


def load_exported_weights(path: Path | str, device: str | torch.device = "cpu",
                          ) -> tuple[QNetwork | QEnsemble, dict[str, Any]]:
    """Rebuild the network of an ``export_weights`` file (eval mode: a QNetwork, or a QEnsemble
    for an ensemble's file) and return it with its metadata."""
    path = Path(path)
    tensors, meta = load_tensors_file(path, WEIGHTS_FORMAT)
    members = meta.get("members")

    def build() -> QNetwork | QEnsemble:
        sensor = SensorConfig(**meta["sensor"])
        if members is None:
            return QNetwork(ModelConfig(**meta["model"]), sensor)
        if not (isinstance(members, list) and 2 <= len(members) <= MAX_ENSEMBLE_MEMBERS
                and all(isinstance(m, dict) for m in members)):
            raise CheckpointError(f"{path}: an ensemble's members must be a list of 2 to {MAX_ENSEMBLE_MEMBERS} "
                                  "model configs")
        return QEnsemble([QNetwork(ModelConfig(**m), sensor) for m in members])

    try:
        probe = _on_meta_device(build)
    except (ConfigError, ModelError, TypeError, KeyError) as exc:
        raise CheckpointError(f"{path}: architecture metadata is invalid: {exc}") from None
    if architecture_fingerprint(probe) != meta.get("fingerprint"):
        raise CheckpointError(f"{path}: fingerprint {meta.get('fingerprint')} does not match its own "
                              "architecture (written by another version?)")
    try:
        check_weights_fit(probe, tensors)
    except ModelError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    net = build()
    load_tensors(net, tensors)
    return net.to(device).eval(), meta


def _on_meta_device(build: Callable[[], Any]) -> Any:
    """``build()``'s network on the meta device: its shapes, at no memory. A file's config is checked
    against its tensors there first (:func:`check_weights_fit`), so that a forged config claiming far
    more weights than the file holds (16 members of 2 GiB) is refused before anything is allocated:
    a network then never costs more memory than its file."""
    with torch.device("meta"):
        return build()


# --------------------------------------------------------------------------- shipped models
PRETRAINED_DIR = Path(__file__).resolve().parents[1] / "pretrained"
"""Models shipped with the package (see ``shared/pretrained/MODEL_CARD.md``)."""
PRETRAINED_FILES = {"drl": "drl.safetensors", "sl": "sl.safetensors"}
"""``pretrained`` (= ``pretrained:drl``) and ``pretrained:sl`` name these files."""


def pretrained_path(name: str | Path) -> Path | None:
    """The shipped file a ``pretrained[:drl|:sl]`` argument names; None for any other argument.

    Raises CheckpointError for an unknown ``pretrained:<kind>`` or a missing shipped file."""
    text = str(name)
    if text != "pretrained" and not text.startswith("pretrained:"):
        return None
    kind = text.partition(":")[2] or "drl"
    if kind not in PRETRAINED_FILES:
        raise CheckpointError(f"unknown shipped model {text!r}; choose pretrained, "
                              + ", ".join(f"pretrained:{k}" for k in PRETRAINED_FILES))
    path = PRETRAINED_DIR / PRETRAINED_FILES[kind]
    if not path.is_file():
        raise CheckpointError(f"the shipped model {path} is missing (a broken install?)")
    return path


def init_agent_weights(agent: DQNAgent, source: str | Path) -> dict[str, Any]:
    """Fine-tuning (``train.init_from``): the agent's online and target networks from a weights
    export or ``pretrained`` (the shipped DRL model); from an ensemble's file, its first member (a
    learner trains one network, and the first is the one the ensemble was built around). Raises
    CheckpointError when the file's network or image is not the agent's. Returns the file's metadata."""
    path = pretrained_path(source) or Path(source)
    if not path.is_file():
        raise CheckpointError(f"train.init_from = {str(source)!r}: no such file")
    try:
        net, meta = load_exported_weights(path)
    except WrongFileFormat as exc:
        raise CheckpointError(f"train.init_from: {exc} (a training checkpoint becomes a weights file with "
                              "`cogexplore model export CKPT --out FILE`)") from None
    except CheckpointError as exc:  # a weights file, damaged or diverged: the hint would mislead
        raise CheckpointError(f"train.init_from: {exc}") from None
    if isinstance(net, QEnsemble):
        log.info("train.init_from = %s: an ensemble of %d networks; starting from its first", source,
                 len(net.members))
        net = net.members[0]
    theirs, ours = net.sensor_cfg, agent.sensor_cfg
    if architecture_fingerprint(net) != agent.fingerprint or (theirs.width, theirs.height, theirs.max_range_m) != (
            ours.width, ours.height, ours.max_range_m):
        raise CheckpointError(f"train.init_from = {str(source)!r}: its network ({asdict(net.model_cfg)}, "
                              f"{theirs.width} x {theirs.height} px, {theirs.max_range_m} m) is not this run's "
                              f"({asdict(agent.model_cfg)}, {ours.width} x {ours.height} px, {ours.max_range_m} m)")
    with torch.no_grad():
        agent.online.load_state_dict(net.state_dict())
    agent.sync_target()
    return meta


# --------------------------------------------------------------------------- supervised model files
MODEL_FORMAT = "cogexplore-supervised"


def card_path(model_path: str | Path) -> Path:
    """Where the JSON model card of a model file lives: ``<stem>.card.json`` next to it."""
    p = Path(model_path)
    return p.with_name(p.name.removesuffix(".safetensors") + ".card.json")


def supervised_model_path(path: str | Path) -> Path:
    """``path`` as a supervised model's file; CheckpointError unless it ends in .safetensors."""
    path = Path(path)
    if path.suffix != ".safetensors":
        raise CheckpointError(f"a supervised model file must end in .safetensors, got {path}")
    return path


def save_supervised(path: str | Path, net: SupervisedNet, card: Mapping[str, Any] | None = None) -> Path:
    """Write the model as safetensors (weights, sensor config, fingerprint, card in the metadata,
    atomically, with a digest) and its card as ``<stem>.card.json``."""
    path = supervised_model_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": MODEL_FORMAT, "version": VERSION, "fingerprint": architecture_fingerprint(net),
            "sensor": asdict(net.sensor_cfg), "depth_encoding": net.trunk.depth_encoding,
            "card": json.loads(json.dumps(dict(card or {})))}
    # The card file is a copy of the metadata's, for people: gone before the model changes, a process
    # killed between the two writes leaves the new model without one, not beside the old model's.
    card_path(path).unlink(missing_ok=True)
    save_tensors_file(path, weights_to_tensors(net), meta)
    atomic_write_text(card_path(path), json.dumps(meta["card"], indent=2) + "\n")
    return path


def load_supervised(path: str | Path, device: str | torch.device = "cpu") -> tuple[SupervisedNet, dict[str, Any]]:
    """Rebuild the SupervisedNet of a :func:`save_supervised` file (eval mode) and its metadata."""
    path = Path(path)
    try:
        tensors, meta = load_tensors_file(path, MODEL_FORMAT)
    except WrongFileFormat as exc:
        # only here: a missing, damaged or diverged supervised model says so by itself
        raise CheckpointError(f"not a supervised model (write one with `cogexplore pretrain`): {exc}") from None

    def build() -> SupervisedNet:
        return SupervisedNet(SensorConfig(**meta["sensor"]), meta.get("depth_encoding", "metric"))

    try:
        probe = _on_meta_device(build)
    except (ConfigError, ModelError, TypeError, KeyError) as exc:
        raise CheckpointError(f"{path}: sensor or depth-encoding metadata is invalid: {exc}") from None
    if architecture_fingerprint(probe) != meta.get("fingerprint"):
        raise CheckpointError(f"{path}: fingerprint {meta.get('fingerprint')} does not match its architecture")
    try:
        check_weights_fit(probe, tensors)
    except ModelError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    net = build()
    load_tensors(net, tensors)
    return net.to(resolve_device(device)).eval(), meta


def copy_conv_from_supervised(dst: torch.nn.Module, path: str | Path) -> dict[str, Any]:
    """Copy the conv layers of the supervised model file into ``dst`` (a QNetwork); nothing else
    changes. The conv weights do not depend on the image size, so any sensor size fits."""
    src, meta = load_supervised(path)
    device = next(dst.parameters()).device
    try:
        copy_conv_weights(src.to(device), dst)
    except ModelError as exc:
        raise CheckpointError(f"{path}: cannot copy its conv layers: {exc}") from None
    return meta


def init_agent_conv(agent: DQNAgent, path: str | Path) -> dict[str, Any]:
    """The paper's transfer: the agent's online conv layers from the supervised model, and the
    target network synchronised to the online one. ``pretrained:sl`` names the shipped supervised
    model. Returns the model file's metadata."""
    try:
        path = pretrained_path(path) or path
    except CheckpointError as exc:
        raise CheckpointError(f"train.init_conv_from: {exc}") from None
    if not Path(path).is_file():
        raise CheckpointError(f"train.init_conv_from = {str(path)!r}: no such file (write one with "
                              "`cogexplore pretrain --out PATH`)")
    meta = copy_conv_from_supervised(agent.online, path)
    agent.sync_target()
    return meta


# --------------------------------------------------------------------------- loading any model
@dataclass(frozen=True)
class LoadedModel:
    """A network ready for greedy evaluation, and where it came from."""

    net: Any
    """The QNetwork, or QEnsemble for an ensemble (eval mode, on the requested device)."""
    path: Path
    """The file actually loaded (a run folder resolves to its latest checkpoint)."""
    kind: str
    """'checkpoint', 'weights' (a weights-only export) or 'supervised' (a ``cogexplore pretrain`` model)."""
    policy_version: int
    fingerprint: str
    weights_sha256: str
    """Digest of the online weights: tells one checkpoint from another whatever its path."""
    run_config: RunConfig | None
    """The run config stored in a checkpoint (None for weights-only exports)."""
    name: str | None = None
    """A fixed table name (the baselines: 'SL', 'RL'); None: derived from the path."""
    averaged_from: tuple[dict[str, Any], ...] = ()
    """For a mean of several checkpoints (:func:`average_models`): each source and its update."""
    ensemble_of: tuple[dict[str, Any], ...] = ()
    """For a Q-value ensemble (:func:`ensemble_models`, or an ensemble's weights file): each member's
    source, policy version and weights digest, in the order of ``net.members``."""

    @property
    def label(self) -> str:
        """A short name for tables: ``name``, else ``<run or file>@<policy_version>``."""
        if self.name is not None:
            return self.name
        stem = self.path.parent.parent.name if self.path.parent.name == "checkpoints" else self.path.stem
        return f"{stem}@{self.policy_version}"

    def meta(self) -> dict[str, Any]:
        out = {"checkpoint": str(self.path), "checkpoint_kind": self.kind, "policy_version": self.policy_version,
               "fingerprint": self.fingerprint, "weights_sha256": self.weights_sha256}
        if self.ensemble_of:
            out["ensemble"] = [dict(m) for m in self.ensemble_of]
        return out

    def member_entries(self) -> tuple[dict[str, Any], ...]:
        """What an ensemble records of this model: one entry per network it holds."""
        if self.ensemble_of:
            return self.ensemble_of
        entry: dict[str, Any] = {"source": str(self.path), "label": self.label,
                                 "policy_version": self.policy_version, "weights_sha256": self.weights_sha256}
        if self.averaged_from:
            entry["averaged_from"] = list(self.averaged_from)
        return (entry,)


def weights_sha256(net: torch.nn.Module) -> str:
    """SHA-256 (16 hex digits) over the network's parameter names and bytes (NCHW order)."""
    h = hashlib.sha256()
    for name, t in sorted(weights_to_tensors(net).items()):
        h.update(name.encode())
        h.update(t.to(torch.float32).contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def resolve_checkpoint(source: str | Path) -> Path | None:
    """The file a checkpoint argument names: a file as is; a directory through its
    ``latest`` pointer; a run folder through ``<run>/checkpoints``. None for a checkpoint
    directory that exists but holds no checkpoint yet. ``pretrained`` (or ``pretrained:drl``,
    ``pretrained:sl``) names a model shipped with the package."""
    shipped = pretrained_path(source)
    if shipped is not None:
        return shipped
    p = Path(source)
    if p.is_file():
        return p
    if not p.is_dir():
        if os.path.lexists(p):  # is_file and is_dir say False for these too
            raise CheckpointError(f"checkpoint {str(source)!r} is neither a file nor a folder (a FIFO, a device, "
                                  "a dangling or looping symlink?)")
        raise CheckpointError(f"checkpoint {str(source)!r} does not exist (give a checkpoint file, a checkpoint "
                              "directory, a run folder or a weights export)")
    directory = p / "checkpoints" if (p / "checkpoints").is_dir() else p
    manager = CheckpointManager(directory)
    try:
        latest = manager.latest()
    except CheckpointError:
        latest = None  # a damaged pointer: load_model falls back to the newest checkpoint that loads
    if latest is None and not manager.checkpoints():
        return None
    return latest or manager.checkpoints()[-1]


def load_model(source: str | Path, device: str | torch.device = "cpu") -> LoadedModel:
    """Load a checkpoint file/dir, run folder or weights export into a QNetwork (eval mode).

    A directory's ``latest`` checkpoint is used, or the newest older one that loads when it is
    corrupt (each skipped file is logged)."""
    try:
        dev = resolve_device(device)
    except ModelError as exc:
        raise CheckpointError(str(exc)) from None
    if str(source).lower().endswith(".onnx") and Path(source).is_file():  # else refused as corrupt safetensors
        raise CheckpointError(f"{source} is an ONNX export: it runs without torch, through "
                              "cogexplore.load_onnx_policy or `cogexplore drive --onnx`; here give the weights "
                              "it was exported from")
    path = resolve_checkpoint(source)
    if path is None:
        raise CheckpointError(f"{source} holds no checkpoint yet")
    p = Path(source)
    errors: list[str] = []
    ckpt = None
    if p.is_dir():
        manager = CheckpointManager(path.parent)
        ckpt = manager.load_latest()
        for skipped in manager.skipped:
            log.warning("skipped checkpoint: %s", skipped)
        if ckpt is None:
            raise CheckpointError(f"no loadable checkpoint in {path.parent}: " + "; ".join(manager.skipped))
    else:
        try:
            ckpt = load_checkpoint(path)
        except WrongFileFormat as exc:  # a weights export, maybe; a damaged checkpoint is said as one
            errors.append(str(exc))
    if ckpt is not None:
        meta = ckpt.agent_meta
        run_config = _stored_run_config(ckpt.path, ckpt.config or None)
        try:
            model_cfg = run_config.model if "model" not in meta else _stored_config(meta["model"], "model")
            sensor_cfg = run_config.sensor if "sensor" not in meta else _stored_config(meta["sensor"], "sensor")
        except AttributeError:
            raise CheckpointError(f"{ckpt.path} stores neither the model/sensor config nor a run config") from None
        online = {k[len("online."):]: v for k, v in ckpt.tensors.items() if k.startswith("online.")}
        try:
            check_weights_fit(_on_meta_device(lambda: QNetwork(model_cfg, sensor_cfg)), online)
        except ModelError as exc:
            raise CheckpointError(f"{ckpt.path}: the online weights do not fit the stored config: {exc}") from None
        net = QNetwork(model_cfg, sensor_cfg)
        load_tensors(net, online)
        net = net.to(dev).eval()
        return LoadedModel(net, ckpt.path, "checkpoint", ckpt.policy_version, architecture_fingerprint(net),
                           weights_sha256(net), run_config)
    try:
        net, meta = load_exported_weights(path, dev)
    except WrongFileFormat as exc:
        errors.append(str(exc))
        raise CheckpointError(f"{path} is neither a checkpoint nor a weights export: " + " | ".join(errors)) from None
    policy_version = meta.get("policy_version", 0)
    if not (is_whole(policy_version) and policy_version >= 0):
        raise CheckpointError(f"{path}: policy_version {policy_version!r} is not a whole number >= 0")
    return LoadedModel(net, path, "weights", policy_version, architecture_fingerprint(net),
                       weights_sha256(net), _stored_run_config(path, meta.get("run_config")),
                       averaged_from=_averaged_from(meta),
                       ensemble_of=_ensemble_of(meta, net))


def _stored_run_config(path: Path, stored: Any) -> RunConfig | None:
    """The run config a checkpoint or an export (``export_weights(run_config=...)``) keeps, checked;
    None for a file without one (the shipped models, older exports)."""
    if stored is None:
        return None
    if not isinstance(stored, dict):
        raise CheckpointError(f"{path}: its stored run config is not a table of sections")
    try:
        return from_dict(stored)
    except ConfigError as exc:
        raise CheckpointError(f"{path}: its stored run config is invalid: {exc}") from None


def _require_same_robot(models: Sequence[LoadedModel], what: str) -> None:
    """CheckpointError when two of ``models`` were trained for different robots
    (:data:`~shared.config.ROBOT_FIELDS`: speeds, control period, collision rule). A joined model plays
    in its first (an ensemble) or last (a mean) model's environment, and another robot's network would
    be scored on moves it never made. Models without a stored run config (the shipped ones) are not
    compared."""
    known = [m for m in models if m.run_config is not None]
    for other in known[1:]:
        robot_differences = [d for d in config_differences(other.run_config, known[0].run_config)
                             if d[0] in ROBOT_FIELDS]
        if robot_differences:
            name, theirs, first = robot_differences[0]
            raise CheckpointError(f"cannot make {what}: {other.path} was trained with {name} = {theirs!r}, "
                                  f"{known[0].path} with {first!r}; its models must share the robot")


def ensemble_models(models: Sequence[LoadedModel]) -> LoadedModel:
    """A Q-value ensemble (:class:`QEnsemble`) of several loaded models, labelled ``a@v+b@w``, with
    the first model's file, update and run config; one model is returned as is. An ensemble among
    them joins with all its networks. CheckpointError when one is not a Q-network, the networks
    read different cameras or were trained for different robots."""
    if not models:
        raise CheckpointError("an ensemble needs at least one model")
    if len(models) == 1:
        return models[0]
    first = models[0]
    _require_same_robot(models, "an ensemble")
    try:  # QEnsemble refuses what is not a Q-network (a supervised model) and another camera
        net = QEnsemble([m.net for m in models])
    except ModelError as exc:
        raise CheckpointError(f"cannot make an ensemble of these models: {exc}") from None
    entries = tuple(e for m in models for e in m.member_entries())
    return dataclasses.replace(first, net=net.eval(), fingerprint=architecture_fingerprint(net),
                               weights_sha256=weights_sha256(net), averaged_from=(), ensemble_of=entries,
                               name="+".join(m.label for m in models))


def ensemble_members(model: LoadedModel, picks: Sequence[str]) -> LoadedModel:
    """The networks ``picks`` names out of an ensemble, in the order given (``model export
    pretrained --members R3,X2``): each pick is a member's label as the ensemble records it
    (``R3@104000``), that label without its update (``R3``) or the member's index. One pick gives
    that network alone, several a smaller ensemble. CheckpointError when the model is one network,
    a pick names no member or more than one, or the picks name a member twice."""
    if not model.ensemble_of:
        raise CheckpointError(f"{model.path} is one network, not an ensemble: --members picks networks out of an "
                              "ensemble")
    entries = model.ensemble_of
    labels = [str(e["label"]) for e in entries]
    chosen: list[int] = []
    for pick in picks:
        hits = [i for i, label in enumerate(labels) if pick in (label, label.rsplit("@", 1)[0])]
        if not hits and pick.isascii() and pick.isdigit() and len(pick) <= 3 and int(pick) < len(entries):
            hits = [int(pick)]
        if len(hits) != 1:
            members = ", ".join(f"{i}: {label}" for i, label in enumerate(labels))
            raise CheckpointError(f"--members {pick!r} names {'no' if not hits else 'more than one'} member of "
                                  f"{model.path}: its members are {members}")
        if hits[0] in chosen:
            raise CheckpointError(f"--members names member {hits[0]} ({labels[hits[0]]}) twice")
        chosen.append(hits[0])
    if not chosen:
        raise CheckpointError("--members names no member")
    nets = [model.net.members[i] for i in chosen]
    picked = tuple(entries[i] for i in chosen)
    net = nets[0] if len(nets) == 1 else QEnsemble(nets).eval()
    return dataclasses.replace(
        model, net=net, policy_version=int(picked[0]["policy_version"]), fingerprint=architecture_fingerprint(net),
        weights_sha256=weights_sha256(net), ensemble_of=picked if len(nets) > 1 else (),
        averaged_from=tuple(picked[0].get("averaged_from", ())) if len(nets) == 1 else (),
        name="+".join(labels[i] for i in chosen))


def average_models(models: Sequence[LoadedModel]) -> LoadedModel:
    """The element-wise mean of several loaded models' weights (one run's later checkpoints),
    labelled with the last one's file, update and run config; one model is returned as is.
    CheckpointError when their networks differ or they were trained for different robots."""
    if len(models) == 1:
        return models[0]
    if not models:
        raise CheckpointError("nothing to average")
    ensembles = [m.label for m in models if m.ensemble_of]
    if ensembles:  # member i of each with member i of the others: networks of unrelated runs
        raise CheckpointError(f"{', '.join(ensembles)}: Q-value ensembles are not averaged; average each "
                              "member's checkpoints, then make the ensemble of the means (model export --ensemble)")
    _require_same_robot(models, "a mean")
    last = models[-1]
    net = copy.deepcopy(last.net)
    try:
        load_tensors(net, average_weights([m.net for m in models]))
    except ModelError as exc:
        raise CheckpointError(f"cannot average these checkpoints: {exc}") from None
    return dataclasses.replace(last, net=net.eval(), weights_sha256=weights_sha256(net),
                               averaged_from=tuple({"source": str(m.path), "policy_version": m.policy_version}
                                                   for m in models))


def load_replay(source: str | Path) -> ReplayMemory:
    """The replay memory saved with the newest checkpoint that kept one, of a run folder, its
    checkpoints directory or one checkpoint file; built to the saved memory's own shape."""
    path = Path(source)
    if path.is_file():
        candidates = [path]
    else:
        folder = path / "checkpoints" if (path / "checkpoints").is_dir() else path
        candidates = CheckpointManager(folder).checkpoints()[::-1]
    for ckpt_path in candidates:
        ckpt = load_checkpoint(ckpt_path)
        if ckpt.replay_path is None or not ckpt.replay_path.exists():
            continue
        arrays, meta = load_tensors_file(ckpt.replay_path, FORMAT + "-replay", framework="numpy")
        if meta.get("digest") != ckpt.replay_digest:
            raise CheckpointError(f"{ckpt.replay_path} belongs to another checkpoint")
        try:
            state = meta["replay"]
            # the sizes the metadata declares are the arrays' own before anything is built to them: a
            # declared frame_capacity of 2e8 in a 600 kB file took 5 GB, then failed
            declared = (int(state["capacity"]), int(state["frame_capacity"]), tuple(state["frame_shape"]))
            held = (len(arrays["tid"]), len(arrays["frame_id"]), tuple(arrays["frames"].shape[1:]))
            if declared != held:
                raise ValueError(f"its metadata declares capacity, frame capacity and frame shape {declared}, "
                                 f"its arrays hold {held}")
            memory = ReplayMemory(ReplayConfig(capacity=declared[0], prioritized=bool(state["prioritized"])),
                                  declared[2], frame_capacity=declared[1])
            memory.load_state_dict(arrays, state)
        except (ReplayError, ConfigError, KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{ckpt.replay_path} is not a readable replay memory: {exc}") from None
        return memory
    raise CheckpointError(f"{source}: no checkpoint there kept its replay memory (only the newest "
                          "train.keep_replays do)")


def load_supervised_model(source: str | Path, device: str | torch.device = "cpu") -> LoadedModel:
    """Load a supervised model file (``cogexplore pretrain``) for the ``sl`` policy, labelled SL."""
    path = resolve_checkpoint("pretrained:sl" if str(source) == "pretrained" else source)
    if path is None or not path.is_file():
        raise CheckpointError(f"the sl policy needs --checkpoint <supervised model .safetensors> (written by "
                              f"`cogexplore pretrain`); {str(source)!r} is not a file")
    net, _meta = load_supervised(path, resolve_device(device))
    return LoadedModel(net, path, "supervised", 0, architecture_fingerprint(net), weights_sha256(net), None,
                       name="SL")


def _averaged_from(meta: Mapping[str, Any]) -> tuple[dict[str, Any], ...]:
    """The sources an export says it averages (``model export`` of several checkpoints); a
    malformed list is ignored, not trusted: it only labels the model."""
    sources = meta.get("averaged_from")
    if not isinstance(sources, list) or not all(
            isinstance(s, dict) and isinstance(s.get("source"), str) and isinstance(s.get("policy_version"), int)
            for s in sources):
        return ()
    return tuple({"source": s["source"], "policy_version": s["policy_version"]} for s in sources)


def _ensemble_of(meta: Mapping[str, Any], net: torch.nn.Module) -> tuple[dict[str, Any], ...]:
    """One entry per network of an ensemble's export (``model export --ensemble``): where the file
    says each member came from, and its weights digest recomputed from the file. Like
    ``_averaged_from`` this only labels the model, so a malformed list is dropped, not trusted."""
    if not isinstance(net, QEnsemble):
        return ()
    stored = meta.get("ensemble_of")
    if not (isinstance(stored, list) and len(stored) == len(net.members) and all(
            isinstance(e, dict) and isinstance(e.get("source"), str) and isinstance(e.get("policy_version"), int)
            for e in stored)):
        stored = [{"source": f"member {i}", "policy_version": 0} for i in range(len(net.members))]
    entries = []
    for e, member in zip(stored, net.members):
        entry = {"source": e["source"], "label": str(e.get("label") or e["source"]),
                 "policy_version": e["policy_version"], "weights_sha256": weights_sha256(member)}
        averaged = _averaged_from(e)
        if averaged:
            entry["averaged_from"] = list(averaged)
        entries.append(entry)
    return tuple(entries)


def _stored_config(data: Any, section: str) -> Any:
    # from_dict checks that ``data`` is a table: a forged checkpoint's may be anything JSON holds
    try:
        return getattr(from_dict({section: data}), section)
    except ConfigError as exc:
        raise CheckpointError(f"stored {section} config is invalid: {exc}") from None
