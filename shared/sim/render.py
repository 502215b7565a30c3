"""The env's ``rgb_array`` frames, drawn with numpy alone (matplotlib takes seconds to import and
a video asks for a frame every step): the depth image colour-mapped beside a top-down map of the
world with the robot's path and pose.

    frame = MapCanvas(occupancy_grid(world)).frame(depth_m, max_range_m, trail, pose, radius_m)
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from shared.sim.maps import MAP_FREE_RGB, MAP_OBSTACLE_RGB, OccupancyGrid

FRAME_HEIGHT_PX = 240
"""Height of both panels: the paper's 120-row depth image at 2x."""
PANEL_GAP_PX = 4
PATH_RGB = (31, 119, 180)
ROBOT_RGB = (20, 60, 150)
HEADING_RGB = (214, 39, 40)
GAP_RGB = (255, 255, 255)

# Inferno at 0, 1/4, ..., 1: black through purple and red to pale yellow. Indexed by nearness, so
# near obstacles are warm and bright and far space (and "no return") dark.
_INFERNO_ANCHORS = np.array([(0, 0, 4), (87, 16, 110), (188, 55, 84), (249, 142, 9), (252, 255, 164)],
                            dtype=np.float64)
DEPTH_LUT = np.stack([np.interp(np.linspace(0, 1, 256), np.linspace(0, 1, len(_INFERNO_ANCHORS)),
                                _INFERNO_ANCHORS[:, c]) for c in range(3)], axis=1).round().astype(np.uint8)
"""(256, 3) uint8: colour of nearness 0 (at or beyond the maximum range) .. 255 (touching)."""


def resize_nearest(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """``image`` (H, W, ...) resampled to ``height`` x ``width`` by nearest neighbour."""
    rows = (np.arange(height) * image.shape[0]) // height
    cols = (np.arange(width) * image.shape[1]) // width
    return image[rows[:, None], cols[None, :]]


def depth_colours(depth_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """(H, W) depth in metres (0 = no return) -> (H, W, 3) uint8 through :data:`DEPTH_LUT`, by
    nearness ``1 - depth / max_range_m``; no return reads as far."""
    depth = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0)
    nearness = np.where(depth > 0, 1.0 - np.clip(depth / max_range_m, 0.0, 1.0), 0.0)
    return DEPTH_LUT[np.rint(nearness * 255).astype(np.intp)]


class MapCanvas:
    """A top-down map of an occupancy grid, ``height_px`` tall (aspect kept), on which
    :meth:`draw` puts a path and the robot; the map itself is rasterised once."""

    def __init__(self, grid: OccupancyGrid, height_px: int = FRAME_HEIGHT_PX):
        ny, nx = grid.shape
        width_px = max(1, round(height_px * nx / ny))
        colours = np.array([MAP_FREE_RGB, MAP_OBSTACLE_RGB], dtype=np.uint8)
        # Row 0 of the grid is the lowest y; row 0 of an image is its top.
        self.background = resize_nearest(colours[grid.occupied[::-1].astype(np.intp)], height_px, width_px)
        self.background.flags.writeable = False
        xmin, ymin, xmax, ymax = grid.extent
        self._origin = (xmin, ymax)
        self._px_per_m = (width_px / (xmax - xmin), height_px / (ymax - ymin))

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        return self.background.shape[:2]  # type: ignore[return-value]

    def to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """World (N, 2) metres -> (N, 2) float (column, row) pixel coordinates."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return np.stack([(xy[:, 0] - self._origin[0]) * self._px_per_m[0],
                         (self._origin[1] - xy[:, 1]) * self._px_per_m[1]], axis=1)

    def draw(self, trail: Sequence[Sequence[float]], pose: Sequence[float], radius_m: float) -> np.ndarray:
        """The map with the path ``trail`` ((x, y) points, oldest first) and the robot at
        ``pose`` = (x, y, yaw): a disc of ``radius_m`` and a heading tick. (H, W, 3) uint8."""
        image = self.background.copy()
        _polyline(image, self.to_pixels(np.asarray(trail, dtype=np.float64)), PATH_RGB, width=2)
        x, y, yaw = (float(v) for v in pose[:3])
        (cx, cy), = self.to_pixels(np.array([[x, y]]))
        r_px = max(2.0, radius_m * self._px_per_m[0])
        h, w = self.shape
        r0, r1 = int(np.clip(cy - r_px, 0, h)), int(np.clip(cy + r_px + 1, 0, h))
        c0, c1 = int(np.clip(cx - r_px, 0, w)), int(np.clip(cx + r_px + 1, 0, w))
        rows, cols = np.ogrid[r0:r1, c0:c1]
        image[r0:r1, c0:c1][(cols + 0.5 - cx) ** 2 + (rows + 0.5 - cy) ** 2 <= r_px ** 2] = ROBOT_RGB
        tip = (cx + 1.6 * r_px * math.cos(yaw), cy - 1.6 * r_px * math.sin(yaw))
        _polyline(image, np.array([(cx, cy), tip]), HEADING_RGB, width=2)
        return image

    def frame(self, depth_m: np.ndarray, max_range_m: float, trail: Sequence[Sequence[float]],
              pose: Sequence[float], radius_m: float) -> np.ndarray:
        """The depth image (colour-mapped, scaled to the map's height) beside :meth:`draw`'s
        map: (H, W, 3) uint8, W even (video encoders want even sizes)."""
        h = self.shape[0]
        depth = np.asarray(depth_m)
        depth_panel = resize_nearest(depth_colours(depth, max_range_m), h,
                                     max(1, round(h * depth.shape[1] / depth.shape[0])))
        map_panel = self.draw(trail, pose, radius_m)
        width = depth_panel.shape[1] + PANEL_GAP_PX + map_panel.shape[1]
        frame = np.empty((h + h % 2, width + width % 2, 3), np.uint8)
        frame[:] = GAP_RGB
        frame[:h, :depth_panel.shape[1]] = depth_panel
        frame[:h, depth_panel.shape[1] + PANEL_GAP_PX:width] = map_panel
        return frame


def _polyline(image: np.ndarray, points: np.ndarray, rgb: tuple[int, int, int], width: int = 1) -> None:
    """Draw the segments joining ``points`` ((N, 2) column, row) into ``image`` in place, ``width``
    pixels thick; parts outside the image are clipped."""
    if len(points) == 0:
        return
    if len(points) == 1:
        samples = points
    else:
        start, end = points[:-1], points[1:]
        # Half-pixel steps along each segment: no gaps in the line.
        n = int(max(1, math.ceil(2 * float(np.abs(end - start).max(initial=0.0)))))
        t = np.linspace(0.0, 1.0, n + 1)[None, :, None]
        samples = (start[:, None, :] + t * (end - start)[:, None, :]).reshape(-1, 2)
    h, w = image.shape[:2]
    for dc in range(width):
        for dr in range(width):
            c = np.floor(samples[:, 0] - (width - 1) / 2 + dc).astype(np.intp)
            r = np.floor(samples[:, 1] - (width - 1) / 2 + dr).astype(np.intp)
            keep = (c >= 0) & (c < w) & (r >= 0) & (r < h)
            image[r[keep], c[keep]] = rgb
