"""Probe scenes: fixed depth images for the Q-value table (the paper's Table II) and the
receptive-field maps (Fig. 7).

The paper picks five simulated samples "located in the fallible area" of its world. Ours are
five poses in hard places of ``paper-indoor`` (``PROBE_SCENES``): a gap too narrow for the
robot, a cylinder straight ahead, a dead end, obstacles at several depths, and a corridor
junction. Their depth images are stored with the project in ``shared/evaluation/probe_scenes/`` as
``<name>.npy`` (float32 metres, the paper sensor's 120 x 160) plus ``<name>.json`` (world,
pose, description); ``generate_probes`` recreates them from the poses (run it after the world
changes: ``python -m shared.evaluation.probes``), and ``render_probe`` renders a scene for any
other sensor size.

A user's own depth images come in through ``load_probe_image``: a 16-bit PNG in millimetres or
a ``.npy`` in metres, resized to the sensor's size as its camera would sample it
(``shared.depth.resize_depth``, with a note) when it does not match.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from shared.config import MUST_MATCH_FIELDS, SensorConfig
from shared.depth import MM_PER_M, resize_depth
from shared.errors import CogexploreError
from shared.jsontext import read_json_file

PROBE_DIR = Path(__file__).resolve().with_name("probe_scenes")
"""Where the stored probe scenes live (``shared/evaluation/probe_scenes/``)."""
PROBE_WORLD = "paper-indoor"
CAMERA_FIELDS: tuple[str, ...] = tuple(n.partition(".")[2] for n in MUST_MATCH_FIELDS if n.startswith("sensor."))
"""The sensor fields that decide what image a pose gives (size, field of view, range, mount):
a stored probe image stands for another camera only when they all agree."""
_ALWAYS_RECORDED = ("width", "height", "hfov_deg", "vfov_deg", "max_range_m", "mount_height_m")


class ProbeError(CogexploreError):
    """A probe image or scene that cannot be used: missing, malformed, NaN, wrong shape."""


@dataclass(frozen=True)
class ProbeScene:
    """A pose in a world whose depth image is a probe."""

    name: str
    x: float
    y: float
    yaw: float
    description: str
    world: str = PROBE_WORLD


PROBE_SCENES: tuple[ProbeScene, ...] = (
    ProbeScene("S1-narrow-gap", -1.55, 2.1, math.pi / 2,
               "two boxes 0.3 m apart, 0.95 m ahead: the gap is the deepest part of the image but too "
               "narrow for the 0.36 m robot (the paper's S4)"),
    ProbeScene("S2-cylinder-ahead", -2.3, -0.25, 0.0,
               "a 0.3 m cylinder 0.9 m straight ahead in the open hall, free space on both sides"),
    ProbeScene("S3-dead-end", -0.7, -3.5, -0.35,
               "the closed end of the dead-end corridor: its end wall and south wall meet in a corner ahead"),
    ProbeScene("S4-depths", -3.6, 1.4, -0.35,
               "hall cylinders and a pillar at several depths, the nearest at the side"),
    ProbeScene("S5-junction", -1.8, 5.25, math.pi,
               "looking west along the north corridor: its south wall ends and two openings (the hall's "
               "north door and the west corridor) branch off to the left before the end wall"),
)


@dataclass(frozen=True)
class Probe:
    """One probe image: name, depth (H, W) float32 metres, and what it is."""

    name: str
    depth_m: np.ndarray = field(repr=False)
    meta: dict[str, Any] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    """What was done to the image on loading (e.g. a resize)."""


def render_probe(scene: ProbeScene, sensor_cfg: SensorConfig | None = None) -> np.ndarray:
    """The depth image (H, W) float32 metres the sensor sees at the scene's pose, without noise
    (deterministic); the pose must not be inside an obstacle."""
    from shared.config import EnvConfig
    from shared.sim.env import ExploreEnv

    # every noise field: a robust run's sensor (load_probes(net.sensor_cfg)) adds the distance-dependent one
    clean = (sensor_cfg or SensorConfig()).noise_free()
    env = ExploreEnv(EnvConfig(world=scene.world), clean)
    try:
        env.robot.set_pose(scene.x, scene.y, scene.yaw)
        if env.robot.touching_obstacle():
            raise ProbeError(f"probe {scene.name}: pose ({scene.x}, {scene.y}) is inside an obstacle of {scene.world}")
        return env.camera.capture(env.data).astype(np.float32)
    finally:
        env.close()


def _scene_meta(scene: ProbeScene, sensor_cfg: SensorConfig) -> dict[str, Any]:
    return {"name": scene.name, "world": scene.world, "pose": {"x": scene.x, "y": scene.y, "yaw": scene.yaw},
            "description": scene.description, "units": "metres, 0 = no return",
            # fields beyond the six every description records only where they are not the default sensor's,
            # which _stored_camera reads for a field left out
            "sensor": {name: getattr(sensor_cfg, name) for name in CAMERA_FIELDS
                       if name in _ALWAYS_RECORDED or getattr(sensor_cfg, name) != getattr(SensorConfig(), name)}}


def _stored_camera(stored: dict[str, Any]) -> dict[str, Any]:
    """The camera a stored scene's image was taken with; fields its description leaves out are the
    default sensor's (``generate_probes``'s, when the description recorded fewer fields)."""
    default = SensorConfig()
    return {name: stored.get(name, getattr(default, name)) for name in CAMERA_FIELDS}


def generate_probes(out_dir: str | Path = PROBE_DIR, scenes: Sequence[ProbeScene] = PROBE_SCENES,
                    sensor_cfg: SensorConfig | None = None) -> list[Path]:
    """Render every scene and write ``<name>.npy`` + ``<name>.json`` into ``out_dir``;
    returns the written paths."""
    cfg = sensor_cfg or SensorConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for scene in scenes:
        depth = render_probe(scene, cfg)
        np.save(out / f"{scene.name}.npy", depth)
        (out / f"{scene.name}.json").write_text(json.dumps(_scene_meta(scene, cfg), indent=2) + "\n")
        written += [out / f"{scene.name}.npy", out / f"{scene.name}.json"]
    return written


def load_probes(directory: str | Path = PROBE_DIR, sensor_cfg: SensorConfig | None = None) -> list[Probe]:
    """The stored probe scenes, sorted by name, for ``sensor_cfg`` (default: the paper's).

    For another camera (``CAMERA_FIELDS``: another size, field of view, range or mount) the scenes
    are rendered again from their stored poses (a resized image would not be what it sees)."""
    cfg = sensor_cfg or SensorConfig()
    d = Path(directory)
    metas = sorted(d.glob("*.json"))
    if not metas:
        raise ProbeError(f"no probe scenes in {d} (regenerate them: python -m shared.evaluation.probes)")
    probes = []
    for meta_path in metas:
        meta = read_json_file(meta_path, "probe description", ProbeError)
        try:
            pose = meta["pose"]
            scene = ProbeScene(meta["name"], float(pose["x"]), float(pose["y"]), float(pose["yaw"]),
                               meta.get("description", ""), meta.get("world", PROBE_WORLD))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ProbeError(f"{meta_path}: not a probe description ({exc!r})") from None
        stored = meta.get("sensor") if isinstance(meta.get("sensor"), dict) else {}
        camera = {name: getattr(cfg, name) for name in CAMERA_FIELDS}
        # the size alone is not the image: a camera mounted elsewhere or with another field of view or range
        # sees another one at the pose
        if _stored_camera(stored) == camera and (d / f"{scene.name}.npy").exists():
            depth, notes = load_probe_image(d / f"{scene.name}.npy", cfg)
        else:
            depth = render_probe(scene, cfg)
            notes = (f"probe scenes rendered from their stored poses for the {cfg.width}x{cfg.height} sensor "
                     f"(the stored images are another camera's: {stored.get('width')}x{stored.get('height')}, "
                     f"{stored.get('hfov_deg')} x {stored.get('vfov_deg')} degrees)",)
        probes.append(Probe(scene.name, depth, meta, tuple(notes)))
    return probes


def load_probe_image(path: str | Path, sensor_cfg: SensorConfig | None = None,
                     resize: bool = True) -> tuple[np.ndarray, list[str]]:
    """A user depth image as (H, W) float32 metres for the sensor, and notes on what was done.

    ``.png``: 16-bit (or 8-bit, with a note) grayscale in millimetres, 0 = no return.
    ``.npy``: float metres (NaN refused; a uint16 array is taken as millimetres).
    A (H, W, 1) array is squeezed. Another size is resized to the sensor's (``resize_depth``)
    with a note, or refused when ``resize`` is False.
    """
    cfg = sensor_cfg or SensorConfig()
    p = Path(path)
    notes: list[str] = []
    if not p.is_file():
        raise ProbeError(f"probe image {p} does not exist")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise ProbeError(f"{p}: not a numpy array file ({exc})") from None
        if arr.dtype == np.uint16:
            depth = arr.astype(np.float64) / MM_PER_M
            notes.append(f"{p.name}: uint16 array read as millimetres")
        elif np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer):
            depth = arr.astype(np.float64)
        else:
            raise ProbeError(f"{p}: array of {arr.dtype}; expected float metres")
    elif suffix == ".png":
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(p) as img:
                mode = img.mode
                arr = np.array(img)
        except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as exc:
            raise ProbeError(f"{p}: not a readable PNG ({exc})") from None
        if arr.ndim == 3:
            raise ProbeError(f"{p}: a {mode} colour image; expected a single-channel 16-bit depth PNG in millimetres")
        if arr.dtype == np.uint8:
            notes.append(f"{p.name}: 8-bit PNG, read as millimetres (at most 255 mm: probably not depth)")
        depth = arr.astype(np.float64) / MM_PER_M
    else:
        raise ProbeError(f"{p}: unknown probe format {suffix!r}; use a 16-bit PNG in millimetres or a .npy in metres")
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2 or depth.size == 0:
        raise ProbeError(f"{p}: shape {depth.shape}; expected one (H, W) depth image")
    if np.isnan(depth).any():
        raise ProbeError(f"{p}: {int(np.isnan(depth).sum())} NaN pixels; mark missing returns with 0, not NaN")
    if np.isinf(depth).any() or (depth < 0).any():
        raise ProbeError(f"{p}: negative or infinite depths; expected metres >= 0 (0 = no return)")
    if depth.max() > 100.0:
        raise ProbeError(f"{p}: depths up to {depth.max():.0f}; a .npy probe must hold metres "
                         "(millimetres belong in a 16-bit PNG or a uint16 array)")
    want = (cfg.height, cfg.width)
    if depth.shape != want:
        if not resize:
            raise ProbeError(f"{p}: {depth.shape[1]}x{depth.shape[0]} image, the sensor is {cfg.width}x{cfg.height}")
        notes.append(f"{p.name}: resized from {depth.shape[1]}x{depth.shape[0]} to {cfg.width}x{cfg.height} "
                     "(as the camera samples it)")
        depth = resize_depth(depth, *want)
    beyond = depth > cfg.max_range_m
    if beyond.any():
        notes.append(f"{p.name}: {int(beyond.sum())} pixels beyond the sensor's {cfg.max_range_m} m range set to 0 "
                     "(no return), as the simulated camera reports them")
        depth = np.where(beyond, 0.0, depth)
    nearer = (depth > 0) & (depth < cfg.min_range_m)
    if nearer.any():
        notes.append(f"{p.name}: {int(nearer.sum())} pixels nearer than the sensor's {cfg.min_range_m} m range set "
                     "to 0 (no return), as the simulated camera reports them")
        depth = np.where(nearer, 0.0, depth)
    return depth.astype(np.float32), notes


if __name__ == "__main__":
    for written in generate_probes():
        print(written)
