"""Rerun logging for evaluation and training: one entity layout, three timelines, one blueprint.

Entity layout (``world`` is metric, z up). What a person reads numbers the start poses from 1
as the paper and ``shared.sim.maps.render_map_png`` do (start N is ``start_index`` N - 1 of the
results JSON); episodes keep their 0-based index::

    world/map                     static GridMap of the occupancy grid (light free, dark occupied)
    world/map/extent              static outline of the world's extent
    world/map/starts              static arrows: start poses, labelled 1..N
    world/robot                   Transform3D (x, y, yaw) per step, with a static disc + heading arrow
    world/trajectory/start_<N>/episode_<k>
                                  LineStrips3D: the episode's path so far, re-logged each step
    camera                        static Pinhole (the sensor's intrinsics, RDF)
    camera/depth                  DepthImage, uint16 millimetres (meter = 1000)
    policy/q/<command>            Scalars, one series per command (left ... right)
    policy/action                 Scalars: the chosen command's index
    eval/episode/<metric>         Scalars per finished episode (steps, distance_m, ...)
    eval/<metric>                 Scalars per evaluation of a policy version (mean_steps, ...)
    train/<metric>                Scalars per learner update (loss, mean_q, epsilon, ...)
    log/episodes                  TextLog: one line per finished episode

An actor's stream (:class:`EpisodeStream`) plays its episodes in several worlds (``extra_worlds``):
there ``world/map`` and its children are logged at each episode's first frame instead of
statically, and ``world/trajectory`` is cleared then, so an episode is seen over its own world.

Timelines: ``episode_step`` (step within the episode), ``episode`` (running episode count of
this recording), ``update`` (learner update / policy version) and ``eval_frame`` (a step
counter over the whole recording). ``eval_frame`` is extra: ``episode_step`` restarts each
episode, so only a monotonic counter lets a person scrub through all episodes in order; the
blueprint makes it the active timeline. ``train/*`` and ``eval/<metric>`` live on ``update``
only: switch the timeline to ``update`` to see them plotted.

Depth goes out as uint16 millimetres, the project's wire format: half the bytes of float32
metres, and Rerun shows the same metres through ``meter=1000``.

Live viewing. A recorder can stream to a running viewer (``connect_url``) or host a gRPC
server (and the web viewer) itself (``serve``). Rerun's gRPC client behaves badly toward a
viewer that is down (measured with rerun-sdk 0.41): ``set_sinks`` blocks 5 s trying to
connect, the sink then drops everything and ``flush`` raises. So callers check the viewer with
:class:`ViewerLink` (a TCP connect, milliseconds) before each stream, ``close`` turns a failed
live flush into a warning, and :class:`EpisodeStream` does all of it on a worker thread for
the training actors, whose env loop must never wait on a viewer.
"""

from __future__ import annotations

import dataclasses
import errno
import fcntl
import glob
import logging
import math
import os
import queue
import re
import shutil
import socket
import threading
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit

os.environ.setdefault("RERUN_ANALYTICS", "0")  # offline machines: never phone home

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from shared.config import ACTION_NAMES, EnvConfig, SensorConfig
from shared.depth import MM_PER_M, UINT16_MAX, depth_to_mm, range_gate
from shared.errors import CogexploreError
from shared.evaluation import PAPER_MAX_STEPS
from shared.files import TMP_MARK, fsync_path
from shared.sim.maps import OccupancyGrid, occupancy_grid
from shared.sim.world import World, load_world

log = logging.getLogger("cogexplore.rerun")
LEGACY_PARTIAL_STALE_S = 600.0
"""How long a ``<name>.partial`` (an unlocked temporary of an earlier release) must lie untouched
before a recorder opening ``<name>`` deals with it as an orphan."""

APPLICATION_ID = "cogexplore"
TIMELINE_STEP = "episode_step"
TIMELINE_EPISODE = "episode"
TIMELINE_UPDATE = "update"
TIMELINE_FRAME = "eval_frame"

MAP = "world/map"
STARTS = "world/map/starts"
EXTENT = "world/map/extent"
ROBOT = "world/robot"
TRAJECTORY = "world/trajectory"
CAMERA = "camera"
DEPTH = "camera/depth"
Q_PREFIX = "policy/q"
ACTION = "policy/action"
EPISODE_LOG = "log/episodes"

DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090
VIEWER_URL_SCHEMES = {"rerun+http": 80, "rerun+https": 443, "rerun": 443}
"""The schemes Rerun's gRPC client accepts, with the port each implies when the URL has none."""

TRAJECTORY_Z_M = 0.02  # just above the map so the line is never hidden in it
_COMMAND_COLORS = [(230, 97, 1), (253, 184, 99), (90, 90, 90), (178, 171, 210), (94, 60, 153)]
_METRIC_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


class RerunLogError(CogexploreError):
    """Bad input to the recorder: wrong shapes, unknown metric names, use after close."""


def depth_image_mm(depth_m: np.ndarray) -> np.ndarray:
    """A float depth image (metres) as the uint16 millimetres a recording holds: NaN, infinity and
    depths <= 0 (or past what uint16 holds) are no return, 0, as ``shared.depth`` reads them; an
    infinity saturated to 65.5 m would show as the farthest return."""
    return depth_to_mm(range_gate(depth_m, 0.0, UINT16_MAX / MM_PER_M))


def q_entity(action: int) -> str:
    """Entity path of one command's Q-value series, e.g. ``policy/q/half-left``."""
    return f"{Q_PREFIX}/{ACTION_NAMES[action]}"


def trajectory_entity(start_index: int, episode: int) -> str:
    """Entity path of one episode's path; starts are numbered from 1 as in the paper."""
    return f"{TRAJECTORY}/start_{start_index + 1}/episode_{episode}"


def parse_viewer_url(url: str) -> tuple[str, int]:
    """Host and port of a Rerun viewer's gRPC proxy URL such as ``rerun+http://host:9876/proxy``
    (the form ``rerun --connect`` and ``rr.GrpcSink`` take); RerunLogError when it is not one."""
    try:
        parts = urlsplit(str(url))
        port = parts.port
    except ValueError as exc:
        raise RerunLogError(f"bad Rerun viewer URL {url!r}: {exc}") from None
    if parts.scheme not in VIEWER_URL_SCHEMES:
        raise RerunLogError(f"bad Rerun viewer URL {url!r}: the scheme must be one of "
                            f"{sorted(f'{k}://' for k in VIEWER_URL_SCHEMES)}, e.g. rerun+http://127.0.0.1:9876/proxy")
    if not parts.hostname:
        raise RerunLogError(f"bad Rerun viewer URL {url!r}: no host")
    if parts.path != "/proxy":
        raise RerunLogError(f"bad Rerun viewer URL {url!r}: the path must be /proxy")
    return parts.hostname, port if port is not None else VIEWER_URL_SCHEMES[parts.scheme]


def viewer_reachable(url: str, timeout_s: float = 1.0) -> bool:
    """Whether something accepts TCP connections at the viewer URL's host and port."""
    host, port = parse_viewer_url(url)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return True
    except OSError:
        return False


def check_port_free(port: int, what: str = "port") -> None:
    """RerunLogError naming ``what`` unless TCP ``port`` can be bound on all interfaces now
    (Rerun's gRPC server only logs a failed bind and then drops what it is sent)."""
    if not (isinstance(port, int) and 0 < port < 65536):
        raise RerunLogError(f"{what} must be in 1..65535, got {port!r}")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("0.0.0.0", port))
        except OSError as exc:
            raise RerunLogError(f"{what} {port} is not free ({exc.strerror}): pick another") from None


def local_viewer_url(port: int, host: str = "127.0.0.1") -> str:
    """The gRPC proxy URL of a server on ``port``: what ``rerun --connect`` takes."""
    return f"rerun+http://{host}:{port}/proxy"


def web_viewer_address(grpc_url: str, web_port: int, host: str = "localhost") -> str:
    """The page of the web viewer on ``web_port`` that opens the stream at ``grpc_url``."""
    return f"http://{host}:{web_port}/?url={quote(grpc_url, safe='')}"


class ViewerLink:
    """A viewer URL that may be down: ``up()`` checks it (a TCP connect, milliseconds) before
    each stream, so a missing viewer costs nothing instead of Rerun's 5 s connect stall. The
    first failure is logged as a warning, later changes (down again, back up) at info. ``rechecks``:
    whether the caller checks again later (the warning tells the user whether a viewer started
    afterwards will be found)."""

    def __init__(self, url: str, what: str = "streaming", timeout_s: float = 1.0, rechecks: bool = True):
        parse_viewer_url(url)  # a malformed URL fails at start-up, not at the first stream
        self.url = url
        self.what = what
        self.rechecks = rechecks
        self.timeout_s = timeout_s
        self._up: bool | None = None
        self._warned = False
        self.failures = 0

    def up(self) -> bool:
        ok = viewer_reachable(self.url, self.timeout_s)
        if not ok:
            self.failures += 1
            if not self._warned:
                self._warned = True
                if self.rechecks:
                    log.warning("no Rerun viewer at %s: %s live is off until one answers (checked again each "
                                "time; files are written as usual)", self.url, self.what)
                else:
                    log.warning("no Rerun viewer at %s: %s live is off for this run (checked only at its start: "
                                "start the viewer first; a file is written as usual)", self.url, self.what)
            elif self._up:
                log.info("Rerun viewer at %s went away: %s live is off", self.url, self.what)
        elif self._up is False:
            log.info("Rerun viewer at %s answers again: %s live", self.url, self.what)
        self._up = ok
        return ok


def default_blueprint(world: World | None = None) -> rrb.Blueprint:
    """Map and camera on the left, Q-values, command and metrics on the right; the map is
    seen from straight above its centre; ``eval_frame`` is the active timeline."""
    eye = None
    if world is not None:
        xmin, ymin, xmax, ymax = world.extent
        cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
        height = 1.3 * max(xmax - xmin, ymax - ymin)
        eye = rrb.EyeControls3D(position=(cx, cy, height), look_target=(cx, cy, 0.0), eye_up=(0.0, 1.0, 0.0))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="world", name="Map, robot, trajectories", eye_controls=eye),
                rrb.Spatial2DView(origin=CAMERA, name="Depth camera"),
                row_shares=[3, 2],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin=Q_PREFIX, name="Q-values"),
                rrb.TimeSeriesView(origin=ACTION, name="Chosen command (0 = left ... 4 = right)"),
                rrb.Tabs(
                    rrb.TimeSeriesView(origin="eval", name="Evaluation"),
                    rrb.TimeSeriesView(origin="train", name="Training"),
                    rrb.TextLogView(origin="log", name="Episodes"),
                ),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline=TIMELINE_FRAME),
        collapse_panels=False,
    )


def remove_orphan_recordings(folder: Path, prefix: str = "eval-") -> list[Path]:
    """Remove every temporary of a recording named ``prefix...`` in ``folder`` that a killed process left
    (``.<name>.rrd.tmp-...``, which nobody holds; one a live recorder is writing is left alone) and
    return them: the evaluator's own kind only (a killed `drive`'s partial log, which it keeps, may lie
    there too). A
    :class:`RecordingFile` removes one only when a recorder next opens its very path, which a resumed
    run's evaluator never does: it goes on from newer versions. The evaluator service calls it as it
    starts."""
    return [orphan for orphan in folder.glob(f".{glob.escape(prefix)}*.rrd{TMP_MARK}*")
            if _act_on_orphan(orphan, orphan.unlink)]


def _act_on_orphan(orphan: Path, act: Callable[[], Any]) -> bool:
    """``act()`` under the exclusive lock a live recorder holds on its temporary for the whole recording
    (:class:`RecordingFile`): False, nothing done, when one holds it or the file is gone meanwhile."""
    try:
        with open(orphan, "rb") as held:
            fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
            act()
    except OSError:
        return False
    return True


MIN_FREE_BYTES = 16 * 2**20
"""Free space a recording needs on its disk to be started (its scene and first episode)."""


class RecordingFile:
    """An ``.rrd`` written under a temporary name beside ``path`` that takes its name only when the
    recording is whole (:meth:`commit`, :meth:`finish`): a recording that fails, is cancelled or is
    killed leaves the file it would have replaced (an earlier evaluation of the same version) as it
    was. The temporary is named as :func:`shared.files.write_atomically` names its own
    (``.<name>.tmp-<pid>-<n>``) and held under an exclusive ``flock`` while it is written, so the one a
    killed process left, which nobody holds, is dealt with when a recorder next opens for ``path``
    (``orphans``: "remove" it, or "keep" it as ``<stem>.unfinished-<pid><suffix>``, never over an
    earlier one, for a log whose every step until a kill counts, as drive's); one another live
    process is writing is left alone. An earlier release's unlocked ``<name>.partial`` is dealt with
    the same way once it has lain untouched for :data:`LEGACY_PARTIAL_STALE_S` (kept as
    ``<stem>.unfinished-earlier<suffix>``).
    RerunLogError when ``path`` is a folder; OSError (ENOSPC) when its disk has under
    :data:`MIN_FREE_BYTES` free."""

    def __init__(self, path: str | Path, orphans: str = "remove"):
        self.path = Path(path)
        if self.path.is_dir():
            # now, not at the rename that names the file: that comes after the whole run was played
            raise RerunLogError(f"the recording {self.path} is a folder: name a file in it, e.g. "
                                f"{self.path / 'recording.rrd'}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(self.path.parent).free
        if free < MIN_FREE_BYTES:
            # Rerun's file sink that cannot write its first bytes fails inside set_sinks (a RuntimeError: a
            # traceback from `evaluate --rrd`, the evaluator stopped), or waits there for ever where the write
            # fails past a file size limit: refused before it opens, as the full disk it is
            raise OSError(errno.ENOSPC, f"{self.path} is not started: {free / 2**20:.1f} MiB free on its disk, "
                                        f"under {MIN_FREE_BYTES // 2**20} MiB")
        self._handle_orphans(orphans)
        tag = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
        # Locked under a name the orphan search does not match, then renamed (the lock goes with the
        # file): created under the temporary's name, another recorder could take it for an orphan
        # between the open and the lock, and delete it.
        locking = self.path.with_name(f".{self.path.name}.lock-{tag}")
        self._lock: Any = open(locking, "wb")  # Rerun's sink then writes into this same file
        fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self.partial: Path | None = self.path.with_name(f".{self.path.name}{TMP_MARK}{tag}")
        locking.rename(self.partial)

    def _handle_orphans(self, orphans: str) -> None:
        legacy = self.path.with_name(f"{self.path.name}.partial")
        try:
            # Releases before the lock wrote ``<name>.partial`` unlocked: one untouched for
            # LEGACY_PARTIAL_STALE_S has no writer left (a live one writes every few seconds).
            stale = time.time() - legacy.stat().st_mtime > LEGACY_PARTIAL_STALE_S
        except OSError:
            stale = False
        candidates = self.path.parent.glob(f".{glob.escape(self.path.name)}{TMP_MARK}*")
        for orphan in [*candidates, *([legacy] if stale else [])]:
            if orphans != "keep":
                if _act_on_orphan(orphan, orphan.unlink):
                    log.info("removed %s, a recording its process left unfinished", orphan)
                continue
            kept: list[Path] = []
            if _act_on_orphan(orphan, lambda orphan=orphan: kept.append(self._keep(orphan, orphan == legacy))):
                log.warning("%s, a recording its process left unfinished (killed?), is now %s", orphan, kept[0])

    def _keep(self, orphan: Path, legacy: bool) -> Path:
        """Rename ``orphan`` to ``<stem>.unfinished-<writer's pid><suffix>`` (an earlier release's name
        carries none), never over one kept before (a pid comes round again); the name it took."""
        writer = "earlier" if legacy else orphan.name.rsplit("-", 2)[-2]
        kept = self.path.with_name(f"{self.path.stem}.unfinished-{writer}{self.path.suffix}")
        n = 1
        while kept.exists():
            n += 1
            kept = self.path.with_name(f"{self.path.stem}.unfinished-{writer}-{n}{self.path.suffix}")
        orphan.rename(kept)
        return kept

    def commit(self) -> None:
        """Give the file its name (once its sink has closed: Rerun writes a file's footer as it closes)."""
        if self.partial is None:
            return
        try:
            fsync_path(self.partial)  # what the sink wrote so far, on disk before it has the name (a power loss)
            self.partial.replace(self.path)
            fsync_path(self.path.parent)
        except BaseException:
            self.discard()
            raise
        self.partial = None

    def discard(self) -> None:
        """Delete the unfinished file and drop the lock."""
        if self.partial is not None:
            self.partial.unlink(missing_ok=True)
            self.partial = None
        self.release()

    def finish(self, keep: bool) -> None:
        """Name the file (``keep``) or delete it; either way the temporary is gone afterwards."""
        try:
            if keep:
                self.commit()
        finally:
            self.discard()

    def release(self) -> None:
        if self._lock is not None:
            self._lock.close()  # closing drops the lock
            self._lock = None


class EvalRecorder:
    """Logs evaluation episodes (and optionally training metrics) to a Rerun recording.

    ``target`` is a path (an ``.rrd`` file is written), an ``rr.RecordingStream`` whose sinks
    the caller has set, or None when only live sinks are wanted. Live sinks, alone or next to
    the file (``set_sinks`` tees to all of them; the sinks are what ``connect_grpc`` and
    ``serve_grpc`` set up): ``connect_url`` streams to a running viewer
    (``rerun+http://host:9876/proxy``; check it with :class:`ViewerLink` first, as Rerun
    stalls 5 s on one that is down); ``serve=True`` hosts a gRPC server on ``serve_port``
    that viewers connect to (``viewer_url``; it lives until ``close``), and ``serve_web``
    also serves the web viewer on ``web_port`` (``web_url``; it lives until the process
    ends). Each recorder has its own ``RecordingStream``; only the web viewer is global.
    ``recording_id``: recorders with the same id add to one recording in the viewer (the
    actors' streams); ``scene_per_episode`` logs the map at each episode's start (and clears the
    trajectories before it) for such a recording, whose episodes may be in different worlds.
    ``image_every`` logs every n-th depth image only (a full 12 x 10 x 200-step protocol is
    24,000 images, ~0.9 GB of millimetres).

    The file is written under a temporary name (:class:`RecordingFile`) and takes its name at
    :meth:`commit` or ``close(keep=True)``: a recording that fails or is cancelled leaves the file
    it would have replaced (an earlier evaluation of the same version) as it was.
    """

    def __init__(self, target: str | Path | rr.RecordingStream | None, world: World, grid: OccupancyGrid | None,
                 sensor_cfg: SensorConfig, *, connect_url: str | None = None,
                 serve: bool = False, serve_port: int = DEFAULT_GRPC_PORT, serve_web: bool = False,
                 web_port: int = DEFAULT_WEB_PORT, recording_name: str | None = None,
                 recording_id: str | None = None, image_every: int = 1,
                 robot_radius_m: float = 0.18, blueprint: rrb.Blueprint | None = None,
                 scene_per_episode: bool = False):
        if not isinstance(image_every, int) or image_every < 1:
            raise RerunLogError(f"image_every must be an integer >= 1, got {image_every!r}")
        self.world = world
        self.grid = grid
        self.sensor_cfg = sensor_cfg
        self.image_every = image_every
        self.scene_per_episode = scene_per_episode
        self.path: Path | None = None
        """The recording's file (its final name: it exists once committed)."""
        self.file: RecordingFile | None = None
        self.server_uri: str | None = None
        self.viewer_url: str | None = None
        """Where a viewer on this machine connects to the served stream (``serve``)."""
        self.web_url: str | None = None
        """The web viewer's page on this machine, opening the served stream (``serve_web``)."""
        self.live = bool(connect_url or serve or serve_web)
        bp = blueprint if blueprint is not None else default_blueprint(world)
        if isinstance(target, rr.RecordingStream):
            if self.live or recording_id is not None:
                raise RerunLogError("pass either a RecordingStream (with its own sinks) or live options, not both")
            self.rec = target
            self._owns_stream = False
            self.rec.send_blueprint(bp, make_active=False, make_default=True)
        else:
            if connect_url:
                parse_viewer_url(connect_url)
            if serve or serve_web:
                check_port_free(serve_port, "the Rerun gRPC port")
            if serve_web:
                check_port_free(web_port, "the Rerun web viewer port")
            if target is None and not self.live:
                raise RerunLogError("nothing to log to: give a file path, connect_url or serve=True")
            if target is not None:
                self.path = Path(target)
                self.file = RecordingFile(self.path)
            try:
                self._open_stream(connect_url, serve or serve_web, serve_port, serve_web, web_port, recording_id, bp)
            except BaseException:
                if self.file is not None:
                    self.file.discard()
                raise
        if recording_name:
            self.rec.send_recording_name(recording_name)
        self._closed = False
        self._frame = 0
        self._episode_count = 0
        self._episode: tuple[int, int] | None = None
        self._trajectory: list[tuple[float, float]] = []
        self._step = 0
        self._log_static(robot_radius_m)

    def _open_stream(self, connect_url: str | None, serve: bool, serve_port: int, serve_web: bool, web_port: int,
                     recording_id: str | None, bp: rrb.Blueprint) -> None:
        sinks: list[Any] = []
        if self.file is not None:
            sinks.append(rr.FileSink(self.file.partial))
        if connect_url:
            sinks.append(rr.GrpcSink(connect_url))
        if serve:
            server = rr.GrpcServerSink(port=serve_port)
            self.server_uri = server.uri
            self.viewer_url = local_viewer_url(serve_port)
            sinks.append(server)
        if serve_web:
            assert self.viewer_url is not None
            try:  # before the sinks: a web port taken in the meantime leaves nothing open
                rr.serve_web_viewer(web_port=web_port, connect_to=self.viewer_url, open_browser=False)
            except RuntimeError as exc:
                raise RerunLogError(f"cannot serve the Rerun web viewer on port {web_port}: {exc}") from None
            self.web_url = web_viewer_address(self.viewer_url, web_port)
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        self._owns_stream = True
        self.rec.set_sinks(*sinks, default_blueprint=bp)

    # -- static scene --------------------------------------------------------------------

    def _log_static(self, robot_radius_m: float) -> None:
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if not self.scene_per_episode:
            self._log_scene(static=True)
        circle = [(robot_radius_m * math.cos(a), robot_radius_m * math.sin(a), 0.05)
                  for a in np.linspace(0.0, 2 * math.pi, 33)]
        rec.log(ROBOT, rr.LineStrips3D([circle], colors=[(30, 90, 200)], radii=0.015),
                rr.Arrows3D(origins=[(0.0, 0.0, 0.05)], vectors=[(2 * robot_radius_m, 0.0, 0.0)],
                            colors=[(30, 90, 200)], radii=0.02), static=True)
        from shared.sim.sensor import intrinsics

        fx, fy, cx, cy = intrinsics(self.sensor_cfg)
        rec.log(CAMERA, rr.Pinhole(focal_length=[fx, fy], principal_point=[cx, cy],
                                   resolution=[self.sensor_cfg.width, self.sensor_cfg.height],
                                   camera_xyz=rr.ViewCoordinates.RDF), static=True)
        for a, name in enumerate(ACTION_NAMES):
            rec.log(q_entity(a), rr.SeriesLines(names=name, colors=_COMMAND_COLORS[a]), static=True)
        rec.log(ACTION, rr.SeriesPoints(names="command", markers="circle", marker_sizes=4.0), static=True)

    def _log_scene(self, static: bool) -> None:
        """The world's map, extent and start poses: static, or from now on (what an earlier world
        logged there is cleared)."""
        rec = self.rec
        if not static:
            rec.log(MAP, rr.Clear(recursive=True))
        if self.grid is not None:
            ny, nx = self.grid.shape
            x0, y0 = self.grid.origin_xy
            # Free light, occupied dark. Row 0 of OccupancyGrid.occupied is the lowest y, but a
            # GridMap's buffer is an image whose lower-left corner lies at ``translation``: its first
            # row is the top one. Unflipped, the map showed mirrored in y under the robot, its path
            # and the starts.
            pixels = np.where(np.flipud(self.grid.occupied), 60, 235).astype(np.uint8)
            rec.log(MAP, rr.GridMap(
                data=pixels.tobytes(),
                format=rr.components.ImageFormat(width=nx, height=ny, color_model="L", channel_datatype="U8"),
                cell_size=self.grid.resolution_m, translation=[x0, y0, 0.0]), static=static)
        xmin, ymin, xmax, ymax = self.world.extent
        rec.log(EXTENT, rr.LineStrips3D([[(xmin, ymin, 0.01), (xmax, ymin, 0.01), (xmax, ymax, 0.01),
                                           (xmin, ymax, 0.01), (xmin, ymin, 0.01)]],
                                         colors=[(120, 120, 120)], radii=0.01), static=static)
        starts = self.world.starts
        if starts:
            length = 0.4
            rec.log(STARTS, rr.Arrows3D(
                origins=[(s.x, s.y, 0.03) for s in starts],
                vectors=[(length * math.cos(s.yaw), length * math.sin(s.yaw), 0.0) for s in starts],
                labels=[str(i + 1) for i in range(len(starts))], colors=[(220, 30, 30)], radii=0.025),
                static=static)

    # -- episodes ------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise RerunLogError("the recorder is closed")

    def _set_episode_time(self, step: int) -> None:
        rec = self.rec
        rec.reset_time()  # no timeline leaks from one kind of log call into another
        rec.set_time(TIMELINE_EPISODE, sequence=self._episode_count)
        rec.set_time(TIMELINE_STEP, sequence=step)
        rec.set_time(TIMELINE_FRAME, sequence=self._frame)

    def set_position(self, episode_count: int, frame: int) -> None:
        """Continue the ``episode`` and ``eval_frame`` timelines from these values: a recorder
        that adds to a recording other recorders began (same ``recording_id``) starts where
        they stopped instead of at 0."""
        self._check_open()
        for name, value in (("episode_count", episode_count), ("frame", frame)):
            if not (isinstance(value, (int, np.integer)) and value >= 0):
                raise RerunLogError(f"{name} must be an integer >= 0, got {value!r}")
        self._episode_count = int(episode_count)
        self._frame = int(frame)

    @property
    def frame(self) -> int:
        """The next ``eval_frame`` value."""
        return self._frame

    def begin_episode(self, start_index: int, episode: int) -> None:
        """Start logging an episode from start pose ``start_index`` (its ``episode``-th there)."""
        self._check_open()
        n = len(self.world.starts)
        if not (isinstance(start_index, (int, np.integer)) and 0 <= start_index < max(n, 1)):
            raise RerunLogError(f"start_index {start_index!r} out of range [0, {n})")
        if not (isinstance(episode, (int, np.integer)) and episode >= 0):
            raise RerunLogError(f"episode must be an integer >= 0, got {episode!r}")
        if self._episode is not None:
            self._episode_count += 1  # the previous episode was never ended
        self._episode = (int(start_index), int(episode))
        self._trajectory = []
        self._step = 0
        if self.scene_per_episode:
            # At the episode's first frame: scrubbed to any episode, the viewer shows its own world,
            # and no path of an earlier episode (of another world, perhaps) over it.
            self._set_episode_time(0)
            self.rec.log(TRAJECTORY, rr.Clear(recursive=True))
            self._log_scene(static=False)

    def log_step(self, step: int, pose: Sequence[float], depth_m: np.ndarray | None,
                 q_values: Sequence[float] | np.ndarray | None, action: int | None) -> None:
        """One decision: the pose it was taken at, the depth image the policy saw, its Q-values
        and the chosen command. ``depth_m`` (H, W) float metres; None skips the image."""
        self._check_open()
        if self._episode is None:
            raise RerunLogError("log_step before begin_episode")
        if len(pose) != 3 or not all(math.isfinite(float(v)) for v in pose):
            raise RerunLogError(f"pose must be three finite numbers (x, y, yaw), got {pose!r}")
        x, y, yaw = (float(v) for v in pose)
        self._step = int(step)
        self._set_episode_time(self._step)
        rec = self.rec
        rec.log(ROBOT, rr.Transform3D(translation=[x, y, 0.0],
                                      rotation_axis_angle=rr.RotationAxisAngle(axis=[0, 0, 1], radians=yaw)))
        self._trajectory.append((x, y))
        self._log_trajectory(self._trajectory)
        if depth_m is not None and self._step % self.image_every == 0:
            rec.log(DEPTH, self._depth_image(depth_m))
        if q_values is not None:
            q = np.asarray(q_values, dtype=np.float64).reshape(-1)
            if q.shape != (len(ACTION_NAMES),):
                raise RerunLogError(f"q_values must have {len(ACTION_NAMES)} entries, got {q.shape}")
            for a in range(len(ACTION_NAMES)):
                rec.log(q_entity(a), rr.Scalars(q[a]))
        if action is not None:
            if not (isinstance(action, (int, np.integer)) and 0 <= action < len(ACTION_NAMES)):
                raise RerunLogError(f"action must be in 0..{len(ACTION_NAMES) - 1}, got {action!r}")
            rec.log(ACTION, rr.Scalars(float(action)))
        self._frame += 1

    def _depth_image(self, depth_m: np.ndarray) -> rr.DepthImage:
        depth = np.asarray(depth_m)
        want = (self.sensor_cfg.height, self.sensor_cfg.width)
        if depth.shape != want:
            raise RerunLogError(f"depth_m must be {want} (the sensor's H, W), got {depth.shape}")
        if depth.dtype != np.uint16:
            depth = depth_image_mm(depth)
        return rr.DepthImage(depth, meter=MM_PER_M,
                             depth_range=(0.0, self.sensor_cfg.max_range_m * MM_PER_M))

    def _log_trajectory(self, points: Sequence[tuple[float, float]]) -> None:
        assert self._episode is not None
        strip = np.array([(px, py, TRAJECTORY_Z_M) for px, py in points], dtype=np.float32)
        color = _COMMAND_COLORS[self._episode[0] % len(_COMMAND_COLORS)]
        self.rec.log(trajectory_entity(*self._episode), rr.LineStrips3D([strip], colors=[color], radii=0.02))

    def end_episode(self, summary: Any) -> None:
        """Close the current episode with its result (an ``EpisodeResult`` or a mapping with
        its fields): the final path is logged from ``trajectory_xy`` when it has one, and the
        episode's metrics go to ``eval/episode/*`` and ``log/episodes``."""
        self._check_open()
        if self._episode is None:
            raise RerunLogError("end_episode before begin_episode")
        fields = asdict(summary) if is_dataclass(summary) else dict(summary)
        steps = int(fields.get("steps", self._step))
        self._set_episode_time(steps)
        trajectory = fields.get("trajectory_xy")
        if trajectory is not None and len(trajectory) > 0:
            self._log_trajectory([(float(p[0]), float(p[1])) for p in trajectory])
        rec = self.rec
        for key in ("steps", "distance_m", "path_length_m", "coverage_m2", "coverage_fraction"):
            if fields.get(key) is not None:
                rec.log(f"eval/episode/{key}", rr.Scalars(float(fields[key])))
        start, episode = self._episode
        cause = fields.get("collision_cause")
        ending = f"collision ({cause})" if cause else ("step cap" if fields.get("truncated") else "ended")
        distance = fields.get("distance_m")
        text = f"start {start + 1} episode {episode}: {steps} steps, {ending}" + (
            f", {float(distance):.2f} m from start" if distance is not None else "")
        rec.log(EPISODE_LOG, rr.TextLog(text, level="WARN" if cause else "INFO"))
        self._episode = None
        self._episode_count += 1
        self._frame += 1

    # -- learner and evaluation summaries -------------------------------------------------

    def log_training(self, update: int, metrics: Mapping[str, float]) -> None:
        """Learner metrics at ``update`` as ``train/<name>`` (loss, mean_q, epsilon,
        updates_per_s, episode_length, ...); names are lower_snake_case, values finite."""
        self._log_metrics("train", update, metrics)

    def log_evaluation(self, update: int, summary: Mapping[str, Any],
                       protocol: Mapping[str, Any] | None = None) -> None:
        """An evaluation of the policy of ``update``: the numeric entries of ``summary`` (an
        ``aggregate(...)`` result or its ``overall`` part) as ``eval/<name>``; collisions by
        cause become ``eval/collisions_<cause>``. ``protocol`` (``ProtocolConfig.to_dict()``)
        becomes the recording's ``protocol`` property: which test conditions the figures are of."""
        if protocol is not None:
            self._check_open()
            self.rec.send_property("protocol", rr.AnyValues(**{k: [v] for k, v in protocol.items()}))
        overall = summary.get("overall", summary)
        flat: dict[str, float] = {}
        for key, value in overall.items():
            if isinstance(value, Mapping):
                for sub, v in value.items():
                    if isinstance(v, (int, float)) and not isinstance(v, bool):
                        flat[f"{key}_{sub}"] = float(v)
            elif isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                flat[key] = float(value)
        self._log_metrics("eval", update, flat)

    def _log_metrics(self, prefix: str, update: int, metrics: Mapping[str, float]) -> None:
        self._check_open()
        if not (isinstance(update, (int, np.integer)) and update >= 0):
            raise RerunLogError(f"update must be an integer >= 0, got {update!r}")
        for name, value in metrics.items():
            if not _METRIC_NAME.match(str(name)):
                raise RerunLogError(f"metric name {name!r} must be lower_snake_case")
            if not (isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool)
                    and math.isfinite(float(value))):
                raise RerunLogError(f"metric {name!r} must be a finite number, got {value!r}")
        self.rec.reset_time()
        self.rec.set_time(TIMELINE_UPDATE, sequence=int(update))
        for name, value in metrics.items():
            self.rec.log(f"{prefix}/{name}", rr.Scalars(float(value)))

    # -- lifetime ---------------------------------------------------------------------------

    def _flush(self) -> None:
        try:
            self.rec.flush(timeout_sec=30.0)
        except RuntimeError as exc:
            if not self.live or "grpc" not in str(exc).lower():  # a file that fails is an error
                raise
            log.warning("Rerun live stream failed (%s); the recording file, if any, is complete", exc)

    def close(self, keep: bool = True) -> None:
        """Flush everything and close the sinks this recorder opened; a stream passed in by the
        caller is flushed, not closed. The file takes its name with ``keep`` and is deleted
        without it (a failed or cancelled evaluation). A live stream whose viewer went away is
        logged as a warning, not raised: the file sink is flushed and closed all the same."""
        if self._closed:
            return
        self._closed = True
        flushed = False
        try:
            self._flush()
            flushed = True
        finally:
            try:
                if self._owns_stream:
                    self.rec.disconnect()
            finally:
                if self.file is not None:
                    self.file.finish(keep and flushed)  # a failed rename deletes the temporary too

    def __enter__(self) -> EvalRecorder:
        return self

    def __exit__(self, exc_type: Any, *exc: object) -> None:
        self.close(keep=exc_type is None)


class EpisodeStream:
    """Streams every ``every_episodes``-th episode of a training actor live to a viewer,
    without ever making the env loop wait on the network or the viewer.

    The env loop's calls (``begin_episode``, ``log_step``, ``end_episode``) only copy the step's
    small arrays onto a bounded queue (a full queue drops the item and counts it). A worker
    thread checks the viewer (:class:`ViewerLink`) at each streamed episode's start, opens an
    :class:`EvalRecorder` for that episode and closes it at its end: a viewer that is down
    costs one refused TCP connect per streamed episode, and one that restarts gets the next
    episode. All recorders share one ``recording_id``, so the viewer shows one recording per
    actor (``recording_name``) whose ``episode`` timeline is the actor's episode number and
    whose ``eval_frame`` runs on across episodes. Depth goes out every ``image_every``-th step.
    """

    _STOP = ("stop",)

    def __init__(self, url: str, world: World, sensor_cfg: SensorConfig, *, recording_name: str,
                 every_episodes: int = 20, image_every: int = 5, robot_radius_m: float = 0.18,
                 queue_size: int = 4096):
        for name, value in (("every_episodes", every_episodes), ("image_every", image_every),
                            ("queue_size", queue_size)):
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise RerunLogError(f"{name} must be an integer >= 1, got {value!r}")
        self.link = ViewerLink(url, what=f"streaming {recording_name!r}")
        self.url = url
        self.world = world
        self.sensor_cfg = sensor_cfg
        self.recording_name = recording_name
        self.recording_id = f"{APPLICATION_ID}-{uuid.uuid4().hex}"
        self.every_episodes = every_episodes
        self.image_every = image_every
        self.robot_radius_m = robot_radius_m
        self.episodes_streamed = 0
        """Episodes the worker sent to a viewer, begin to end."""
        self.episodes_skipped = 0
        """Episodes due for streaming that found no viewer."""
        self.steps_logged = 0
        self.dropped = 0
        """Items the env loop could not queue (the worker fell behind)."""
        self._active = False  # env-loop side: the current episode is being streamed
        self._frame = 0  # worker side: the next eval_frame of the shared recording
        self._grids: dict[str, OccupancyGrid] = {}  # per world, built when first streamed
        self._failed_once = False
        self._queue: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=queue_size)
        self._closed = False
        self._thread = threading.Thread(target=self._work, name="rerun-episode-stream", daemon=True)
        self._thread.start()

    # -- env-loop side: copies and a non-blocking put, nothing else ------------------------

    def begin_episode(self, episode: int, start_index: int, world: World | None = None) -> bool:
        """A new episode of the actor, in ``world`` (default: the stream's); returns whether it is
        streamed (every n-th is)."""
        self._active = not self._closed and int(episode) % self.every_episodes == 0
        if self._active:
            # a begin that found the queue full streams none of its steps: the worker would take
            # them for the episode before's (its end may have been dropped too)
            self._active = self._put(("begin", int(episode), int(start_index), world or self.world))
        return self._active

    def log_step(self, step: int, pose: Sequence[float], depth_m: np.ndarray | None,
                 q_values: Sequence[float] | np.ndarray | None, action: int | None) -> None:
        """One decision of a streamed episode (a no-op otherwise); as ``EvalRecorder.log_step``."""
        if not self._active:
            return
        depth = None
        if depth_m is not None and int(step) % self.image_every == 0:
            depth = np.array(depth_m, dtype=np.float32, copy=True)  # the env may reuse its buffer
        q = None if q_values is None else np.array(q_values, dtype=np.float64, copy=True)
        self._put(("step", int(step), tuple(float(v) for v in pose), depth, q,
                   None if action is None else int(action)))

    def end_episode(self, summary: Mapping[str, Any], final_pose: Sequence[float] | None = None) -> None:
        """The end of a streamed episode (a no-op otherwise): ``summary`` as for
        ``EvalRecorder.end_episode`` (steps, distance_m, path_length_m, collision_cause,
        truncated); ``final_pose`` closes the trajectory."""
        if not self._active:
            return
        self._active = False
        fields = dict(summary)
        if final_pose is not None:
            fields["final_pose"] = tuple(float(v) for v in final_pose)
        self._put(("end", fields))

    def _put(self, item: tuple[Any, ...]) -> bool:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            if self.dropped == 0:
                log.warning("Rerun stream %r falls behind: dropping steps (the actor goes on)", self.recording_name)
            self.dropped += 1
            return False
        return True

    def close(self, timeout_s: float = 10.0) -> None:
        """Finish what is queued (at most ``timeout_s``), close the stream and stop the worker."""
        if self._closed:
            return
        self._closed = True
        self._active = False
        try:
            self._queue.put(self._STOP, timeout=timeout_s)
        except queue.Full:
            log.warning("Rerun stream %r: the worker is stuck; leaving it behind", self.recording_name)
            return
        self._thread.join(timeout_s)

    def __enter__(self) -> EpisodeStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- worker side -------------------------------------------------------------------------

    def _work(self) -> None:
        recorder: EvalRecorder | None = None
        trajectory: list[tuple[float, float]] = []
        while True:
            item = self._queue.get()
            kind = item[0]
            if kind == "stop":
                break
            try:
                if kind == "begin":
                    self._finish(recorder)  # an 'end' that was dropped
                    recorder = None
                    _, episode, start_index, world = item
                    if not self.link.up():
                        self.episodes_skipped += 1
                        continue
                    recorder = self._open(world)
                    recorder.set_position(episode, self._frame)
                    recorder.begin_episode(start_index, episode)
                    trajectory = []
                elif recorder is None:
                    continue  # the steps of an episode that is not streamed (no viewer)
                elif kind == "step":
                    _, step, pose, depth, q, action = item
                    recorder.log_step(step, pose, depth, q, action)
                    trajectory.append((pose[0], pose[1]))
                    self.steps_logged += 1
                elif kind == "end":
                    fields = item[1]
                    final = fields.pop("final_pose", None)
                    if final is not None:
                        trajectory.append((final[0], final[1]))
                    fields.setdefault("trajectory_xy", tuple(trajectory))
                    recorder.end_episode(fields)
                    self.episodes_streamed += 1
                    self._finish(recorder)
                    recorder = None
            except Exception as exc:  # noqa: BLE001  the viewer must never take the actor down
                if not self._failed_once:
                    self._failed_once = True
                    log.warning("Rerun stream %r: %s: %s (this episode is dropped; the actor goes on)",
                                self.recording_name, type(exc).__name__, exc)
                self._finish(recorder)
                recorder = None
        self._finish(recorder)

    def _open(self, world: World) -> EvalRecorder:
        grid = self._grids.get(world.name)
        if grid is None:
            from shared.sim.maps import occupancy_grid

            grid = self._grids[world.name] = occupancy_grid(world)
        return EvalRecorder(None, world, grid, self.sensor_cfg, connect_url=self.url,
                            recording_name=self.recording_name, recording_id=self.recording_id,
                            robot_radius_m=self.robot_radius_m, scene_per_episode=True)

    def _finish(self, recorder: EvalRecorder | None) -> None:
        if recorder is not None:
            self._frame = recorder.frame
            try:
                recorder.close()
            except Exception as exc:  # noqa: BLE001
                log.warning("Rerun stream %r: closing failed: %s", self.recording_name, exc)


# ---------------------------------------------------------------------------------------------
# Recording an evaluation
# ---------------------------------------------------------------------------------------------

def live_viewer_url(url: str | None, writes_file: bool = False) -> str | None:
    """``url`` when a Rerun viewer answers there, else None with a warning: Rerun's own client
    would stall 5 s on it and then drop everything. RerunLogError when ``url`` is malformed."""
    if url is None:
        return None
    try:
        parse_viewer_url(url)
    except ValueError as exc:
        raise RerunLogError(str(exc)) from None
    if viewer_reachable(url):
        return url
    log.warning("no Rerun viewer answers at %s: not streaming this evaluation%s", url,
                " (the .rrd file is written)" if writes_file else "")
    return None


def open_recorder(world: Any, sensor_cfg: SensorConfig, env_cfg: EnvConfig, rrd: str | Path | None = None, *,
                  connect_url: str | None = None, serve: bool = False, serve_port: int = 9876,
                  web_port: int = 9090, image_every: int = 1, recording_name: str | None = None) -> Any:
    """An ``EvalRecorder`` for the protocol in ``world`` (a World or its name): a file, a live
    viewer, a hosted gRPC server + web viewer (``serve``), or several; RerunLogError for bad
    options (a malformed URL, a port in use, a folder for ``rrd``)."""
    if not (isinstance(image_every, int) and not isinstance(image_every, bool) and image_every >= 1):
        # named as the option of the commands that record the protocol (evaluate, the evaluator)
        raise RerunLogError(f"--image-every must be a whole number >= 1, got {image_every!r}")
    world_obj = load_world(world) if isinstance(world, str) else world
    try:
        return EvalRecorder(rrd, world_obj, occupancy_grid(world_obj), sensor_cfg, connect_url=connect_url,
                            serve=serve, serve_port=serve_port, serve_web=serve, web_port=web_port,
                            image_every=image_every, recording_name=recording_name,
                            robot_radius_m=env_cfg.robot_radius_m)
    except ValueError as exc:
        raise RerunLogError(str(exc)) from None


def evaluate_recorded(policy_fn: Any, *, world: str, sensor_cfg: SensorConfig, env_cfg: EnvConfig | None = None,
                      max_steps: int = PAPER_MAX_STEPS, rrd: str | Path | None = None,
                      rerun_connect: str | None = None, image_every: int = 1, recording_name: str | None = None,
                      **protocol: Any) -> Any:
    """``shared.evaluation.protocol.evaluate_policy``, recorded: to a Rerun file (``rrd``: every
    ``image_every``-th depth image, every step's pose, Q-values/scores, command and trajectory, and
    the summary) and/or live to the viewer at ``rerun_connect`` (one that does not answer is skipped
    with a warning). Neither given: the protocol alone. A run that fails or is cancelled leaves no
    partial file, and a file of the same name from before as it was. A recording that cannot be
    finished once the protocol has (a full disk) is logged as an error and the results are returned
    all the same: they cost the whole evaluation, the recording is a view of them. ``protocol``:
    the other arguments of ``evaluate_policy``."""
    from shared.evaluation.protocol import evaluate_policy, protocol_env_config

    rerun_connect = live_viewer_url(rerun_connect, rrd is not None)
    recorder = None
    if rrd is not None or rerun_connect is not None:
        recorder = open_recorder(world, sensor_cfg, protocol_env_config(env_cfg, world, max_steps), rrd,
                                 connect_url=rerun_connect, image_every=image_every, recording_name=recording_name)
    try:
        results = evaluate_policy(policy_fn, world=world, sensor_cfg=sensor_cfg, env_cfg=env_cfg,
                                  max_steps=max_steps, recorder=recorder, **protocol)
    except BaseException:
        if recorder is not None:
            try:
                recorder.close(keep=False)
            except Exception as exc:  # noqa: BLE001  the evaluation's own error is the one to report
                log.warning("closing the recording failed too: %s", exc)
        raise
    if recorder is not None:
        try:
            recorder.close()
        except (OSError, RuntimeError, CogexploreError) as exc:
            log.error("the evaluation finished but its recording %s could not be written: %s",
                      rrd if rrd is not None else rerun_connect, exc)
            return results
        if rrd is not None:  # the results name their recording only once it is whole (an earlier one may be there)
            return dataclasses.replace(results, meta={**results.meta, "recording": str(rrd)})
    return results


TIMELINE_DECISION = "decision"
DRIVE = "drive"


class DriveRecorder:
    """What ``cogexplore drive`` sees and decides, to a Rerun file and/or a live viewer: on a
    ``decision`` timeline, the depth image the policy read, the command (or the stop and its
    reason), each Q-value, the nearest valid depth and the image-to-command latency. The file is
    written as :class:`EvalRecorder` writes its own (:class:`RecordingFile`): it takes its name at
    :meth:`close`, so an earlier recording of the same name stays until this one is whole."""

    def __init__(self, rrd: str | Path | None, *, connect_url: str | None = None, robot: str = "robot"):
        # checked once: the stream's sinks are set when it opens, a viewer started later is not added
        self.link = (ViewerLink(connect_url, "drive streaming", rechecks=False)
                     if connect_url else None)  # a bad URL: before the file
        self.path = Path(rrd) if rrd is not None else None
        # a log of a drive: what a killed drive recorded is kept for the next drive to name
        self.file = RecordingFile(self.path, orphans="keep") if self.path is not None else None
        try:
            sinks: list[Any] = [rr.FileSink(self.file.partial)] if self.file is not None else []
            if self.link is not None and self.link.up():
                sinks.append(rr.GrpcSink(connect_url))
            self.live = self.link is not None
            self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"drive-{robot}-{uuid.uuid4().hex[:8]}")
            if sinks:
                self.rec.set_sinks(*sinks)
            self.rec.send_recording_name(f"drive {robot}")
        except BaseException:
            if self.file is not None:
                self.file.discard()
            raise
        self._closed = not sinks

    def log_decision(self, diagnostics: Any, depth_m: np.ndarray | None) -> None:
        """One :class:`shared.wire.robot.DriveDiagnostics`, with the image it came from (None: a stop)."""
        if self._closed:
            return
        d = diagnostics
        rec = self.rec
        rec.set_time(TIMELINE_DECISION, sequence=int(d.decision))
        if depth_m is not None:
            rec.log(f"{DRIVE}/depth", rr.DepthImage(depth_image_mm(depth_m), meter=MM_PER_M))
        rec.log(f"{DRIVE}/command", rr.Scalars(float(d.command) if d.command is not None else -1.0))
        rec.log(f"{DRIVE}/twist/linear_mps", rr.Scalars(d.linear_mps))
        rec.log(f"{DRIVE}/twist/angular_rps", rr.Scalars(d.angular_rps))
        rec.log(f"{DRIVE}/decision", rr.TextLog(ACTION_NAMES[d.command] if d.command is not None
                                                 else f"stop: {d.stop_reason}"))
        for a, q in enumerate(d.q_values):
            rec.log(f"{DRIVE}/q/{ACTION_NAMES[a]}", rr.Scalars(q))
        if d.nearest_depth_m is not None:
            rec.log(f"{DRIVE}/nearest_depth_m", rr.Scalars(d.nearest_depth_m))
        if d.latency_ms is not None:
            rec.log(f"{DRIVE}/latency_ms", rr.Scalars(d.latency_ms))

    def close(self) -> None:
        """Flush and close the sinks; the file takes its name (it is deleted when its flush fails)."""
        if self._closed:
            return
        self._closed = True
        flushed = False
        try:
            try:
                self.rec.flush(timeout_sec=10.0)
            except RuntimeError as exc:
                if not self.live:
                    raise
                log.warning("Rerun live stream failed (%s); the recording file, if any, is complete", exc)
            flushed = True
        finally:
            try:
                self.rec.disconnect()
            finally:
                if self.file is not None:
                    self.file.finish(flushed)
