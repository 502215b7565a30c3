"""The supervised data: the expert drives through the worlds, every frame labelled with its command.

:func:`generate_dataset` drives the robot through the worlds with the expert mixed with noise
(single random commands and bursts of one repeated random command), so that the data also covers
recoveries from poses the expert would not drive into; every frame the robot acts on is labelled
with the expert's command (``shared.expert.expert.CommandExpert``). Episodes start at a world
start pose or at a random free pose and end at a collision or after ``episode_steps``. The
episodes run through the one rollout loop (``shared.rollout``). On disk (never pickled)::

    <dir>/manifest.json    what was generated, with which settings, and the test split
    <dir>/depth_mm.npy     (N, H, W) uint16 millimetres, 0 = no return
    <dir>/labels.npy       (N,) uint8 expert command (shared.config.ACTION_NAMES)
    <dir>/episodes.npy     (N,) int32 episode id (the split is by episode, never by frame)
    <dir>/worlds.npy       (N,) uint8 index into manifest["worlds"] (uint16 past 256 worlds)
    <dir>/poses.npy        (N, 3) float64 robot x, y, yaw (the expert labels exactly these)
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.config import ACTION_NAMES, NUM_ACTIONS, EnvConfig, SensorConfig, is_whole
from shared.errors import CogexploreError
from shared.expert.expert import CommandExpert, ExpertConfig, SupervisedError
from shared.files import TMP_MARK, atomic_write_text, fsync_path, nearest_existing, write_atomically
from shared.jsontext import SMALL_JSON_BYTES, read_json_file
from shared.rollout import Rollout, Step

DATA_FORMAT = "cogexplore-sl-data"


VERSION = 1


MANIFEST = "manifest.json"


_ARRAYS = ("depth_mm", "labels", "episodes", "worlds", "poses")
DATASET_FILES = frozenset({MANIFEST, *(f"{name}.npy" for name in _ARRAYS)})
"""The files of a dataset folder: all a new dataset may replace there."""
_WRITING = tuple(f".{name}{TMP_MARK}" for name in sorted(DATASET_FILES))
"""How the temporary files of :func:`shared.files.write_atomically` for them begin."""


def _clear_dataset_files(out: Path) -> None:
    """Make ``out`` an empty folder for a new dataset. It may hold an earlier dataset's files (they
    go) and nothing else: a mistyped ``--data`` must not delete a user's folder."""
    if out.exists() and not out.is_dir():
        raise SupervisedError(f"{out} is a file, not a dataset folder")
    if out.is_dir():
        foreign = sorted(p.name for p in out.iterdir() if not (p.is_file() and (
            p.name in DATASET_FILES or p.name.startswith(_WRITING))))  # a file a killed writer left
        if foreign:
            raise SupervisedError(f"{out} holds what is not a dataset's ({', '.join(foreign[:5])}"
                                  f"{', ...' if len(foreign) > 5 else ''}): give --data a new or empty folder")
        # The manifest goes first, and durably: after a power cut, an old manifest beside new arrays of
        # the same shapes would pass for a whole dataset.
        if (out / MANIFEST).is_file():
            (out / MANIFEST).unlink()
            fsync_path(out)
        for p in out.iterdir():
            p.unlink()
    out.mkdir(parents=True, exist_ok=True)


MIN_EPISODES = 8
"""Episodes are capped at frames / MIN_EPISODES steps, so that a split by episode has some."""


@dataclass(frozen=True)
class DriveConfig:
    """How the data-collection driver mixes the expert with noise and starts its episodes."""

    episode_steps: int = 150
    """Episode cap (an episode also ends at a collision); at most frames / MIN_EPISODES."""
    noise_prob: float = 0.15
    """Probability that a step takes a uniformly random command instead of the expert's."""
    burst_prob: float = 0.04
    """Probability per step of starting a burst: one random command held for a few steps."""
    burst_steps: tuple[int, int] = (2, 5)
    """Burst length range (inclusive)."""
    random_start_prob: float = 0.75
    """Probability that an episode starts at a random free pose instead of a world start."""
    min_start_clearance_m: float = 0.45
    """A random start keeps this far from every obstacle (and must not read a collision)."""

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, allowed: str) -> None:
            if not ok:
                raise SupervisedError(f"drive {name} = {getattr(self, name)!r} is invalid: {allowed}")

        need(isinstance(self.episode_steps, int) and self.episode_steps >= 1, "episode_steps", "an integer >= 1")
        for name in ("noise_prob", "burst_prob", "random_start_prob"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and 0 <= v <= 1, name, "a probability in [0, 1]")
        lo, hi = self.burst_steps
        need(isinstance(lo, int) and isinstance(hi, int) and 1 <= lo <= hi, "burst_steps",
             "two integers 1 <= low <= high")
        need(isinstance(self.min_start_clearance_m, (int, float)) and 0 < self.min_start_clearance_m < 5,
             "min_start_clearance_m", "metres in (0, 5)")


def _jsonable(obj: Any) -> Any:
    return json.loads(json.dumps(obj))


@dataclass
class SupervisedDataset:
    """A generated dataset folder, opened read-only (arrays memory-mapped)."""

    root: Path
    manifest: dict[str, Any]
    depth_mm: np.ndarray
    labels: np.ndarray
    episodes: np.ndarray
    worlds: np.ndarray
    poses: np.ndarray

    @classmethod
    def open(cls, root: str | Path) -> SupervisedDataset:
        """Open and check a dataset folder; SupervisedError if missing, partial or inconsistent."""
        root = Path(root)
        path = root / MANIFEST
        if not path.is_file():
            raise SupervisedError(f"{root} is not a complete dataset: {MANIFEST} is missing")
        manifest = read_json_file(path, "dataset manifest", SupervisedError,
                                  max_bytes=SMALL_JSON_BYTES)
        if not isinstance(manifest, dict) or manifest.get("format") != DATA_FORMAT or manifest.get("version") != VERSION:
            raise SupervisedError(f"{path}: not a {DATA_FORMAT} v{VERSION} manifest")
        _check_manifest(manifest, path)
        arrays = {}
        for name in _ARRAYS:
            f = root / f"{name}.npy"
            want = manifest["files"][name]
            if not f.is_file():  # np.load would wait for ever for a FIFO's writer
                raise SupervisedError(f"{f} is missing or not a regular file")
            try:
                a = np.load(f, mmap_mode="r", allow_pickle=False)
            except (OSError, ValueError, EOFError) as exc:  # EOFError: an empty file
                raise SupervisedError(f"{f} cannot be read: {exc}") from None
            if list(a.shape) != want["shape"] or str(a.dtype) != want["dtype"]:
                raise SupervisedError(f"{f} is {a.dtype} {list(a.shape)}, the manifest says "
                                      f"{want['dtype']} {want['shape']}")
            arrays[name] = a
        labels = np.asarray(arrays["labels"])
        if labels.size and int(labels.max()) >= NUM_ACTIONS:
            raise SupervisedError(f"{root}: labels must be in 0..{NUM_ACTIONS - 1}, found {int(labels.max())}")
        ds = cls(root, manifest, **arrays)
        # refused here, so that open_or_generate makes a new one, not at training, for every run
        train, test = ds.split()
        if not (len(train) and len(test)):
            raise SupervisedError(f"{path}: test_episodes leave {len(train)} train and {len(test)} test frames")
        return ds

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    @property
    def sensor_cfg(self) -> SensorConfig:
        return SensorConfig(**self.manifest["sensor"])

    def split(self) -> tuple[np.ndarray, np.ndarray]:
        """(train, test) frame indices; whole episodes go to one side."""
        test = np.isin(self.episodes, np.asarray(self.manifest["test_episodes"], dtype=self.episodes.dtype))
        return np.flatnonzero(~test), np.flatnonzero(test)

    def label_counts(self, indices: np.ndarray | None = None) -> dict[str, int]:
        labels = self.labels if indices is None else self.labels[indices]
        counts = np.bincount(np.asarray(labels), minlength=NUM_ACTIONS)
        return {name: int(c) for name, c in zip(ACTION_NAMES, counts)}


def world_index_dtype(n_worlds: int) -> np.dtype:
    """The dtype of ``worlds.npy`` for a dataset of ``n_worlds`` worlds: one byte up to 256 worlds (the
    layout every dataset had before, so those stay readable and reusable), wider past that, where a
    byte could not hold the index."""
    for dtype in (np.uint8, np.uint16, np.uint32):
        if n_worlds <= np.iinfo(dtype).max + 1:
            return np.dtype(dtype)
    raise SupervisedError(f"{n_worlds} worlds are more than a dataset can index")


def _files_layout(frames: int, height: int, width: int, n_worlds: int) -> dict[str, dict[str, Any]]:
    """The manifest's ``files``: each array's dtype and shape for ``frames`` images of height x width
    collected in ``n_worlds`` worlds."""
    return {"depth_mm": {"dtype": "uint16", "shape": [frames, height, width]},
            "labels": {"dtype": "uint8", "shape": [frames]},
            "episodes": {"dtype": "int32", "shape": [frames]},
            "worlds": {"dtype": str(world_index_dtype(n_worlds)), "shape": [frames]},
            "poses": {"dtype": "float64", "shape": [frames, 3]}}


def _check_manifest(manifest: dict[str, Any], path: Path) -> None:
    """SupervisedError unless every field the dataset is read by has its type: an edited or
    foreign manifest must be refused (and regenerated by ``open_or_generate``), not crash later
    with a KeyError in the split or the model card."""
    def bad(field: str, want: str) -> SupervisedError:
        return SupervisedError(f"{path}: {field} must be {want}, got {manifest.get(field)!r:.80}")

    files = manifest.get("files")
    if not isinstance(files, dict):
        raise bad("files", "a table of the arrays' dtype and shape")
    for name in _ARRAYS:
        want = files.get(name)
        if not (isinstance(want, dict) and isinstance(want.get("dtype"), str) and isinstance(want.get("shape"), list)
                and all(is_whole(n) and n >= 0 for n in want["shape"])):
            raise SupervisedError(f"{path}: files.{name} must give a dtype and a shape, got {want!r:.80}")
    if not (is_whole(manifest.get("episodes")) and manifest["episodes"] >= 0):
        raise bad("episodes", "an integer >= 0")
    test = manifest.get("test_episodes")
    if not (isinstance(test, list) and all(is_whole(e) and 0 <= e < 2**31 for e in test)):
        raise bad("test_episodes", "a list of episode numbers")
    worlds = manifest.get("worlds")
    if not (isinstance(worlds, list) and all(isinstance(w, str) for w in worlds)):
        raise bad("worlds", "a list of world names")
    sensor = manifest.get("sensor")
    if not isinstance(sensor, dict):
        raise bad("sensor", "a sensor config")
    try:
        sensor_cfg = SensorConfig(**sensor)
    except (CogexploreError, TypeError) as exc:  # an unknown field is a TypeError
        raise SupervisedError(f"{path}: sensor is not a sensor config: {exc}") from None
    # The arrays' layout, as generate_dataset writes it: one frame count, the sensor's image size.
    labels_shape = files["labels"]["shape"]
    n = labels_shape[0] if len(labels_shape) == 1 else -1
    for name, want in _files_layout(n, sensor_cfg.height, sensor_cfg.width, len(worlds)).items():
        dtype, shape = want["dtype"], want["shape"]
        if files[name]["dtype"] != dtype or files[name]["shape"] != shape:
            raise SupervisedError(f"{path}: files.{name} is {files[name]['dtype']} {files[name]['shape']}; a dataset "
                                  f"of {n} {sensor_cfg.width} x {sensor_cfg.height} frames has {dtype} {shape}")


def dataset_request(worlds: Sequence[str], frames: int, sensor_cfg: SensorConfig, env_cfg: EnvConfig,
                    expert_cfg: ExpertConfig, drive_cfg: DriveConfig, seed: int,
                    test_fraction: float) -> dict[str, Any]:
    """Everything that determines a dataset's content: a reused dataset must match it."""
    return _jsonable({"worlds": list(worlds), "frames": int(frames), "sensor": asdict(sensor_cfg),
                      "env": asdict(env_cfg), "expert": asdict(expert_cfg), "drive": asdict(drive_cfg),
                      "seed": int(seed), "test_fraction": float(test_fraction)})


def _random_free_pose(expert: CommandExpert, rng: np.random.Generator, min_clear: float) -> tuple[float, float, float]:
    cells = np.argwhere(expert.clearance >= min_clear)  # exact: min_clear is below the map's cap
    if cells.size == 0:
        raise SupervisedError(f"world {expert.world.name!r} has no point {min_clear} m from every obstacle")
    iy, ix = cells[rng.integers(len(cells))]
    x, y = expert.grid.cell_to_world(ix, iy)
    r = expert.grid.resolution_m
    return float(x + rng.uniform(-r / 2, r / 2)), float(y + rng.uniform(-r / 2, r / 2)), float(rng.uniform(-math.pi, math.pi))


def _start_episode(env: Any, expert: CommandExpert, drive: DriveConfig, rng: np.random.Generator,
                   reset_seed: int) -> np.ndarray:
    """Reset the env at a world start or a random free pose; returns the first image."""
    from shared.sim.env import min_valid_depth

    obs, _ = env.reset(seed=reset_seed, options={"start_index": int(rng.integers(len(env.world.starts)))})
    if rng.random() >= drive.random_start_prob:
        return obs
    for _ in range(100):
        x, y, yaw = _random_free_pose(expert, rng, drive.min_start_clearance_m)
        env.robot.set_pose(x, y, yaw)
        obs = env.camera.capture(env.data)
        if (min_valid_depth(obs) >= env.env_config.collision_distance_m + 0.1
                and expert.best_safe_steps(x, y, yaw) >= 2):
            return obs
    obs, _ = env.reset(seed=reset_seed)  # a crowded world: fall back to a (validated) start pose
    return obs


@dataclass(frozen=True)
class _Drive:
    """One step of the data-collection driver: the command taken, the expert's label, the pose."""

    action: int
    label: int
    pose: tuple[float, float, float]


class _ExpertDriver:
    """The data-collection policy: the expert's command, with single random commands
    (``noise_prob``) and bursts of one repeated random command (``burst_prob``) mixed in; every
    step also carries the expert's label for the frame."""

    def __init__(self, env: Any, expert: CommandExpert, drive: DriveConfig, rng: np.random.Generator):
        self.env, self.expert, self.drive, self.rng = env, expert, drive, rng
        self.reset()

    def reset(self) -> None:
        self.burst_left, self.burst_action = 0, 0

    def __call__(self, _obs: np.ndarray, _info: Any, _env_steps: int) -> _Drive:
        d, rng = self.drive, self.rng
        x, y, yaw = self.env.robot.pose()  # the robot may have been placed after the reset
        label = self.expert.label(x, y, yaw)
        if self.burst_left > 0:
            action, self.burst_left = self.burst_action, self.burst_left - 1
        elif rng.random() < d.burst_prob:
            self.burst_action = int(rng.integers(NUM_ACTIONS))
            self.burst_left = int(rng.integers(d.burst_steps[0], d.burst_steps[1] + 1)) - 1
            action = self.burst_action
        elif rng.random() < d.noise_prob:
            action = int(rng.integers(NUM_ACTIONS))
        else:
            action = label
        return _Drive(action, label, (x, y, yaw))


class _Frames:
    """Rollout observer: every frame the robot acts on, with its label, into the dataset arrays."""

    def __init__(self, depth: np.ndarray, labels: np.ndarray, episodes: np.ndarray, worlds: np.ndarray,
                 poses: np.ndarray, taken: np.ndarray, bar: Any):
        self.depth, self.labels, self.episodes, self.worlds, self.poses = depth, labels, episodes, worlds, poses
        self.taken, self.bar = taken, bar
        self.n = 0
        self.episode = self.world = 0

    def on_step(self, step: Step) -> None:
        n, choice = self.n, step.choice
        self.depth[n] = np.rint(np.clip(step.obs, 0.0, 65.535) * 1000.0).astype(np.uint16)
        self.labels[n], self.episodes[n], self.worlds[n] = choice.label, self.episode, self.world
        self.poses[n] = choice.pose
        self.taken[choice.action] += 1
        self.n += 1
        self.bar.update(1)


def _check_room(out: Path, frames: int, height: int, width: int) -> None:
    """SupervisedError unless the disk of ``out`` has room for the depth file, counting what the
    dataset files already there would free: checked before they are deleted, so that a refused
    request does not cost the dataset a run with the old settings would reuse."""
    need = frames * height * width * 2
    old = [out / name for name in DATASET_FILES] if out.is_dir() else []
    free = shutil.disk_usage(nearest_existing(out)).free + sum(p.stat().st_size for p in old if p.is_file())
    if need > free:
        raise SupervisedError(f"{frames} frames of {width} x {height} need {need / 1e6:.1f} MB, "
                              f"{out} has {free / 1e6:.1f} MB free: collect fewer frames")


def _open_depth_file(path: Path, frames: int, height: int, width: int) -> np.memmap:
    """The (frames, height, width) uint16 memmap at ``path``, its blocks reserved: a disk that fills
    while the frames are written would end the process with SIGBUS, without a word."""
    try:
        depth = np.lib.format.open_memmap(path, mode="w+", dtype=np.uint16, shape=(frames, height, width))
        if hasattr(os, "posix_fallocate"):  # the free space may have gone since it was measured
            fd = os.open(path, os.O_WRONLY)
            try:
                os.posix_fallocate(fd, 0, os.fstat(fd).st_size)
            finally:
                os.close(fd)
    except OSError as exc:
        path.unlink(missing_ok=True)
        raise SupervisedError(f"{path}: no room for {frames} frames of {width} x {height}: "
                              f"{exc.strerror or exc}") from None
    return depth


def _save_array(path: Path, arr: np.ndarray) -> None:
    """``arr`` as a plain .npy at ``path``, whole and on disk before the manifest is written."""
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:  # a file object: np.save would add ".npy" to the temporary name
            np.save(fh, arr, allow_pickle=False)

    write_atomically(path, write)


def generate_dataset(out_dir: str | Path, *, worlds: Sequence[str], frames: int,
                     sensor_cfg: SensorConfig | None = None, env_cfg: EnvConfig | None = None,
                     expert_cfg: ExpertConfig | None = None, drive_cfg: DriveConfig | None = None,
                     seed: int = 0, test_fraction: float = 0.2, progress: bool = True) -> SupervisedDataset:
    """Drive through ``worlds`` (frames split evenly) and write a labelled dataset to ``out_dir``.

    The env's robot and task come from ``env_cfg`` (its ``world`` is replaced per world; the
    speed table is the one the data is collected at). A folder left by an interrupted run is
    replaced; the manifest is written last, so a folder with a manifest is complete.
    """
    from tqdm import tqdm

    from shared.sim.env import ExploreEnv
    from shared.sim.world import load_world

    sensor_cfg = sensor_cfg or SensorConfig()
    env_cfg = env_cfg or EnvConfig(speed_table="test")
    expert_cfg = expert_cfg or ExpertConfig()
    drive_cfg = drive_cfg or DriveConfig()
    worlds = list(worlds)
    if not worlds:
        raise SupervisedError("give at least one world to collect data in")
    if not (isinstance(frames, int) and frames >= 2 * len(worlds)):
        raise SupervisedError(f"frames must be an integer >= {2 * len(worlds)} (two per world), got {frames!r}")
    if not (isinstance(test_fraction, (int, float)) and 0 < test_fraction < 1):
        raise SupervisedError(f"test_fraction must be in (0, 1), got {test_fraction!r}")
    world_objs = [load_world(w) for w in worlds]  # fail early on an unknown world
    out = Path(out_dir)
    h, w = sensor_cfg.height, sensor_cfg.width
    _check_room(out, frames, h, w)
    _clear_dataset_files(out)
    depth = _open_depth_file(out / "depth_mm.npy", frames, h, w)
    labels = np.zeros(frames, np.uint8)
    episodes = np.zeros(frames, np.int32)
    world_idx = np.zeros(frames, world_index_dtype(len(worlds)))
    poses = np.zeros((frames, 3), np.float64)
    rng = np.random.default_rng(seed)
    started = time.monotonic()
    quota = [frames // len(worlds) + (1 if i < frames % len(worlds) else 0) for i in range(len(worlds))]
    # A split by episode needs several episodes: small datasets get shorter episodes.
    episode_cap = max(1, min(drive_cfg.episode_steps, frames // MIN_EPISODES))
    episode = 0
    episode_worlds: list[int] = []
    episode_lengths: list[int] = []
    taken = np.zeros(NUM_ACTIONS, np.int64)
    with tqdm(total=frames, desc="collect", unit="frame", disable=not progress) as bar:
        frames_out = _Frames(depth, labels, episodes, world_idx, poses, taken, bar)
        for wi, (world, want) in enumerate(zip(world_objs, quota)):
            env = ExploreEnv(env_cfg, sensor_cfg, world=world, max_episode_steps=episode_cap,
                             start_index=None)
            expert = CommandExpert(world, env.env_config, sensor_cfg, expert_cfg)
            loop = Rollout(env, _ExpertDriver(env, expert, drive_cfg, rng), [frames_out])
            end = frames_out.n + want
            try:
                while frames_out.n < end:
                    first = frames_out.n
                    frames_out.episode, frames_out.world = episode, wi
                    loop.begin_episode(obs=_start_episode(env, expert, drive_cfg, rng, int(rng.integers(2**31))))
                    while frames_out.n < end and not loop.step().last:
                        pass
                    episode_worlds.append(wi)
                    episode_lengths.append(frames_out.n - first)
                    episode += 1
            finally:
                env.close()
    depth.flush()  # msync(MS_SYNC): on disk before the manifest that declares it whole
    del depth
    if episode < 2:
        _clear_dataset_files(out)
        raise SupervisedError(f"only {episode} episode(s) were collected: a split by episode needs two; "
                              "collect more frames or lower the episode cap")
    # The test split: whole episodes, shuffled, until test_fraction of the frames is covered.
    order = rng.permutation(episode)
    lengths = np.asarray(episode_lengths)
    target = test_fraction * frames
    test_eps: list[int] = []
    covered = 0
    for e in order[:-1]:  # at least one episode stays for training
        if covered >= target:
            break
        test_eps.append(int(e))
        covered += int(lengths[e])
    for name, arr in (("labels", labels), ("episodes", episodes), ("worlds", world_idx), ("poses", poses)):
        _save_array(out / f"{name}.npy", arr)
    counts = np.bincount(labels, minlength=NUM_ACTIONS)
    manifest = {
        "format": DATA_FORMAT, "version": VERSION, "created_unix": time.time(),
        "request": dataset_request(worlds, frames, sensor_cfg, env_cfg, expert_cfg, drive_cfg, seed, test_fraction),
        "frames": frames, "episodes": episode, "worlds": worlds, "sensor": asdict(sensor_cfg),
        "speed_table": env_cfg.speed_table,
        "frames_per_world": {wname: int(q) for wname, q in zip(worlds, quota)},
        "episodes_per_world": {wname: int(sum(1 for x in episode_worlds if x == i)) for i, wname in enumerate(worlds)},
        "episode_cap": episode_cap,
        "mean_episode_steps": float(lengths.mean()),
        "label_counts": {name: int(c) for name, c in zip(ACTION_NAMES, counts)},
        "action_counts": {name: int(c) for name, c in zip(ACTION_NAMES, taken)},
        "test_episodes": sorted(test_eps),
        "test_frames": int(covered),
        "seconds": round(time.monotonic() - started, 3),
        "files": _files_layout(frames, h, w, len(worlds)),
    }
    atomic_write_text(out / MANIFEST, json.dumps(manifest, indent=1))
    return SupervisedDataset.open(out)


def open_or_generate(out_dir: str | Path, request: Mapping[str, Any], progress: bool = True
                     ) -> tuple[SupervisedDataset, bool]:
    """The dataset in ``out_dir`` if its request matches ``request`` (from :func:`dataset_request`),
    else a freshly generated one. Returns (dataset, reused)."""
    out = Path(out_dir)
    if (out / MANIFEST).is_file():
        try:
            ds = SupervisedDataset.open(out)
            if ds.manifest.get("request") == _jsonable(dict(request)):
                return ds, True
        except SupervisedError:
            pass  # partial or foreign: regenerate below
    r = request
    ds = generate_dataset(out, worlds=r["worlds"], frames=r["frames"], sensor_cfg=SensorConfig(**r["sensor"]),
                          env_cfg=EnvConfig(**r["env"]),
                          expert_cfg=ExpertConfig(**{k: tuple(v) if isinstance(v, list) else v
                                                     for k, v in r["expert"].items()}),
                          drive_cfg=DriveConfig(**{k: tuple(v) if isinstance(v, list) else v
                                                   for k, v in r["drive"].items()}),
                          seed=r["seed"], test_fraction=r["test_fraction"], progress=progress)
    return ds, False
