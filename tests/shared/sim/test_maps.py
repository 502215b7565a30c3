"""Occupancy grids, connectivity, visit heatmaps, coverage and map figures, on real worlds."""

import math

import matplotlib.image
import mujoco
import numpy as np
import pytest

from shared.config import EnvConfig, SensorConfig
from shared.sim import maps
from shared.sim.robot import Robot, build_model
from shared.sim.sensor import DepthCamera
from shared.sim.world import SceneBuilder, StartPose, World, load_world


def _one_box_world() -> World:
    b = SceneBuilder("one-box", (-2.0, -2.0, 2.0, 2.0))
    b.box(0.5, -0.5, 0.4, 0.2)  # covers x [0.1, 0.9], y [-0.7, -0.3]
    return b.build("one-box", [StartPose(-1.0, 1.0, 0.0, "a")])


def test_occupancy_grid_marks_a_known_box():
    grid = maps.occupancy_grid(_one_box_world(), resolution_m=0.05)
    assert grid.shape == (80, 80) and grid.extent == pytest.approx((-2.0, -2.0, 2.0, 2.0))
    for x, y in [(0.5, -0.5), (0.12, -0.68), (0.88, -0.32)]:
        assert not grid.is_free(x, y)
    for x, y in [(0.0, -0.5), (1.0, -0.5), (0.5, -0.8), (0.5, -0.2), (-1.0, 1.0)]:
        assert grid.is_free(x, y)
    box_area = 0.8 * 0.4
    assert maps.free_area_m2(grid) == pytest.approx(16.0 - box_area, abs=0.1)
    assert grid.free_area_m2 == maps.free_area_m2(grid)
    assert maps.occupancy_grid(_one_box_world(), resolution_m=0.05) is grid  # cached
    with pytest.raises(ValueError, match="read-only"):
        grid.occupied[0, 0] = True  # cached grids are read-only


def test_world_cell_conversion_round_trips():
    grid = maps.occupancy_grid(_one_box_world(), resolution_m=0.1)
    ix, iy = grid.world_to_cell(np.array([-1.99, 0.05, 1.99]), np.array([-1.99, -0.05, 1.99]))
    assert ix.tolist() == [0, 20, 39] and iy.tolist() == [0, 19, 39]
    x, y = grid.cell_to_world(ix, iy)
    assert x.tolist() == pytest.approx([-1.95, 0.05, 1.95]) and y.tolist() == pytest.approx([-1.95, -0.05, 1.95])
    assert grid.contains(ix, iy).all() and not grid.contains(40, 0) and not grid.contains(0, -1)


def test_grid_works_for_any_geom_shape_at_robot_height(tmp_path):
    path = tmp_path / "shapes.xml"
    path.write_text("""
<mujoco>
  <asset><mesh name="wedge" vertex="0 0 0  1 0 0  0 1 0  0 0 1  1 0 1  0 1 1"/></asset>
  <worldbody>
    <geom name="low_box" type="box" pos="-1 -1 0.05" size="0.2 0.2 0.05"/>
    <geom name="high_ball" type="sphere" pos="1 -1 1.5" size="0.3"/>
    <geom name="lying_capsule" type="capsule" fromto="-1.5 1 0.15 -0.5 1 0.15" size="0.1"/>
    <geom name="wedge" type="mesh" mesh="wedge" pos="0.5 0.5 0"/>
    <site name="start_a" pos="0 -1.5 0"/>
  </worldbody>
</mujoco>""")
    world = load_world(str(path))
    grid = maps.occupancy_grid(world, resolution_m=0.05)
    assert not grid.is_free(-1.0, -1.0)      # 10 cm tall: the robot would hit it
    assert grid.is_free(1.0, -1.0)           # floats above the robot and camera
    assert not grid.is_free(-1.0, 1.0)       # capsule lying on its side
    assert not grid.is_free(0.7, 0.7) and grid.is_free(1.1, 1.1)  # mesh footprint: a right triangle


@pytest.mark.parametrize("max_m", [0.15, 0.6, 5.0])
def test_a_capped_clearance_map_is_exact_below_its_cap(max_m):
    rng = np.random.default_rng(4)
    occ = np.zeros((30, 300), dtype=bool)
    occ[:, :100] = rng.random((30, 100)) < 0.01
    occ[0, 0] = True  # the right of the grid lies up to 10 m from any occupied cell
    exact = maps.clearance_map(occ, 0.05)
    capped = maps.clearance_map(occ, 0.05, max_m)
    below = exact < max_m
    assert below.any() and (~below).any()
    np.testing.assert_array_equal(capped[below], exact[below])
    assert np.all(capped[~below] >= max_m)


def test_label_components_on_a_known_mask():
    mask = np.array([[1, 1, 0, 1],
                     [0, 1, 0, 1],
                     [1, 1, 0, 0],
                     [0, 0, 0, 1]], dtype=bool)
    labels, count = maps.label_components(mask)
    assert count == 3
    assert labels[0, 0] == labels[2, 0] == labels[1, 1] == 0  # a U joined below
    assert labels[0, 3] == labels[1, 3] == 1 and labels[3, 3] == 2  # diagonal cells stay apart
    assert (labels[~mask] == -1).all()


@pytest.mark.parametrize("gap, connected", [(0.3, False), (0.8, True)])
def test_connectivity_respects_the_robot_radius(gap, connected):
    b = SceneBuilder("split", (-3.0, -2.0, 3.0, 2.0))
    b.boundary()
    b.rect(-0.05, -2.0, 0.05, -gap / 2)  # a dividing wall with a door of width `gap`
    b.rect(-0.05, gap / 2, 0.05, 2.0)
    world = b.build("split", [StartPose(-1.5, 0.0, 0.0)])
    grid = maps.occupancy_grid(world)
    assert grid.is_free(0.0, 0.0)  # the door is open space either way
    assert maps.is_connected(grid, EnvConfig().robot_radius_m) is connected
    assert maps.free_components(grid, EnvConfig().robot_radius_m)[1] == (1 if connected else 2)


def test_visit_counts_and_normalised_heatmap():
    grid = maps.occupancy_grid(_one_box_world(), resolution_m=0.5)
    xy = np.array([[-1.9, -1.9], [-1.8, -1.6], [0.1, 0.1], [5.0, 5.0], [-2.1, 0.0]])
    counts = maps.visit_counts(grid, xy)
    assert counts.shape == grid.shape and counts.sum() == 3  # two points lie off the grid
    assert counts[0, 0] == 2 and counts[4, 4] == 1
    heat = maps.normalize_heatmap(counts)
    assert heat.max() == 1.0 and heat[4, 4] == 0.5 and heat.min() == 0.0
    assert maps.normalize_heatmap(np.zeros((3, 3))).max() == 0.0
    assert maps.visit_counts(grid, np.zeros((0, 2))).sum() == 0
    with pytest.raises(maps.MapError, match="finite and non-negative"):
        maps.normalize_heatmap(np.array([[-1.0]]))
    with pytest.raises(maps.MapError, match=r"xy must be \(N, 2\) points, got shape \(3,\)"):
        maps.visit_counts(grid, np.array([1.0, 2.0, 3.0]))


def test_coverage_of_an_empty_view_is_the_sensor_sector():
    b = SceneBuilder("open", (-6.0, -6.0, 6.0, 6.0))
    world = b.build("open", [StartPose(0.0, 0.0, 0.0)])
    sensor = SensorConfig()
    tracker = maps.CoverageTracker(maps.occupancy_grid(world, 0.05), sensor)
    gained = tracker.observe(0.0, 0.0, 0.0, np.zeros((sensor.height, sensor.width), np.float32))
    # Depth <= 4 m along the axis within +-28.5 degrees: a triangle of area r^2 tan(hfov/2).
    expected = sensor.max_range_m ** 2 * math.tan(math.radians(sensor.hfov_deg) / 2)
    assert gained == tracker.seen_area_m2 == pytest.approx(expected, rel=0.08)
    assert tracker.seen_fraction == pytest.approx(expected / 144.0, rel=0.08)
    seen = tracker.seen
    assert seen[120, 150] and not seen[120, 90]  # 1.5 m ahead is seen, 1.5 m behind is not
    with pytest.raises(ValueError, match="shape"):
        tracker.observe(0.0, 0.0, 0.0, np.zeros((10, 10)))


@pytest.mark.parametrize("width, height", [(40, 30), (160, 120)])
@pytest.mark.parametrize("yaw", [0.0, 0.3, -2.0])
def test_coverage_of_an_empty_view_is_every_cell_centre_in_the_view(width, height, yaw):
    # The shipped models' 40 x 30 images see the same floor as 160 x 120 ones. One ray per column
    # left a fifth of the view unseen between 40 rays, and counted cells only grazed at 160.
    world = SceneBuilder("open", (-6.0, -6.0, 6.0, 6.0)).build("open", [StartPose(0.0, 0.0, 0.0)])
    sensor = SensorConfig(width=width, height=height, mount_forward_m=0.3)
    grid = maps.occupancy_grid(world, 0.05)
    tracker = maps.CoverageTracker(grid, sensor)
    x, y = 0.1, -0.2
    tracker.observe(x, y, yaw, np.zeros((height, width), np.float32))
    ix, iy = np.meshgrid(np.arange(grid.shape[1]), np.arange(grid.shape[0]))
    cx, cy = grid.cell_to_world(ix, iy)
    dx = cx - x - sensor.mount_forward_m * math.cos(yaw)
    dy = cy - y - sensor.mount_forward_m * math.sin(yaw)
    axial = dx * math.cos(yaw) + dy * math.sin(yaw)
    lateral = -dx * math.sin(yaw) + dy * math.cos(yaw)
    view = (axial > 0) & (axial < sensor.max_range_m) & \
        (np.abs(lateral) <= axial * math.tan(math.radians(sensor.hfov_deg) / 2))
    assert np.count_nonzero(tracker.seen ^ view) <= 2


def test_coverage_stops_at_a_wall_on_the_camera_side_it_is_on():
    b = SceneBuilder("left-wall", (-6.0, -6.0, 6.0, 6.0))
    b.wall(0.5, 1.0, 5.0, 1.0)  # on the robot's left (+y) when it faces +x
    world = b.build("left-wall", [StartPose(0.0, 0.0, 0.0)])
    sensor = SensorConfig(width=40, height=30)
    model = build_model(world.mjcf, EnvConfig(), sensor)
    data = mujoco.MjData(model)
    robot, camera = Robot(model, data), DepthCamera(model, sensor)
    robot.set_pose(0.0, 0.0, 0.0)
    grid = maps.occupancy_grid(world)
    tracker = maps.CoverageTracker(grid, sensor)
    tracker.observe(0.0, 0.0, 0.0, camera.capture(data))
    _, cy = grid.cell_to_world(0, np.arange(grid.shape[0]))
    seen_y = cy[np.nonzero(tracker.seen)[0]]
    assert seen_y.max() < 0.95  # nothing on or behind the wall
    assert seen_y.min() < -1.5  # the open right side is seen out to range


def test_coverage_does_not_see_through_an_obstacle_nearer_than_the_minimum_range():
    b = SceneBuilder("near-wall", (-6.0, -6.0, 6.0, 6.0))
    b.wall(0.6, -3.0, 0.6, 3.0)  # face at x = 0.55 m: inside the blind zone
    world = b.build("near-wall", [StartPose(0.0, 0.0, 0.0)])
    sensor = SensorConfig(width=40, height=30, min_range_m=0.6)
    model = build_model(world.mjcf, EnvConfig(), sensor)
    data = mujoco.MjData(model)
    robot, camera = Robot(model, data), DepthCamera(model, sensor)
    robot.set_pose(0.0, 0.0, 0.0)
    depth = camera.capture(data)
    assert not depth.any()  # the wall reads 0, as an open view would on the horizon
    grid = maps.occupancy_grid(world)
    tracker = maps.CoverageTracker(grid, sensor)
    tracker.observe(0.0, 0.0, 0.0, depth)
    assert tracker.seen_area_m2 == 0.0
    robot.set_pose(-1.5, 0.0, math.pi)  # facing the open half: the floor shows, the view is open
    tracker.observe(-1.5, 0.0, math.pi, camera.capture(data))
    assert tracker.seen_area_m2 == pytest.approx(16 * math.tan(math.radians(sensor.hfov_deg) / 2), rel=0.01)


def test_coverage_grows_when_the_robot_turns_and_stops_at_walls():
    world = load_world("box-room")
    sensor = SensorConfig()
    model = build_model(world.mjcf, EnvConfig(), sensor)
    data = mujoco.MjData(model)
    robot, camera = Robot(model, data), DepthCamera(model, sensor)
    grid = maps.occupancy_grid(world)
    tracker = maps.CoverageTracker(grid, sensor)
    robot.set_pose(0.0, 0.0, 0.0)
    first = tracker.observe(0.0, 0.0, 0.0, camera.capture(data))
    assert 0.5 < first < 4.0
    assert tracker.observe(0.0, 0.0, 0.0, camera.capture(data)) == 0.0  # same view: nothing new
    for k in range(1, 4):
        yaw = k * math.pi / 2
        robot.set_pose(0.0, 0.0, yaw)
        assert tracker.observe(0.0, 0.0, yaw, camera.capture(data)) > 0.3
    # Four quarter turns see most of the 4 x 4 m room but nothing beyond the walls.
    assert 0.5 < tracker.seen_fraction <= 1.0
    assert not tracker.seen[grid.occupied].any()


def test_render_map_png_writes_a_figure(tmp_path):
    world = load_world("paper-indoor")
    grid = maps.occupancy_grid(world)
    coarse = maps.occupancy_grid(world, resolution_m=0.25)
    traj = np.array([[s.x + 0.1 * k * math.cos(s.yaw), s.y + 0.1 * k * math.sin(s.yaw)]
                     for s in world.starts for k in range(8)])
    heat = maps.normalize_heatmap(maps.visit_counts(coarse, traj))
    out = maps.render_map_png(world, grid, tmp_path / "figs" / "map.png", trajectories=[traj[:8], traj[8:16]],
                              heatmap=heat, title="paper-indoor: test")
    assert out.exists() and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = matplotlib.image.imread(out)
    assert image.shape[0] > 400 and image.shape[1] > 400
    plain = maps.render_map_png(world, grid, tmp_path / "plain.png")
    assert plain.stat().st_size > 10_000


def test_a_map_names_a_world_file_with_dollars_as_written(tmp_path):
    # `worlds show` titles a file world's map with its path: "$\x$" in it failed to draw as mathtext
    import dataclasses

    import matplotlib.pyplot as plt

    world = dataclasses.replace(load_world("box-room"), name="rooms/a$\\x$.xml", kind="file")
    grid = maps.occupancy_grid(world)
    assert maps.render_map_png(world, grid, tmp_path / "odd.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fig, ax = plt.subplots()
    try:
        maps.draw_map(ax, world, grid, title="cost $5")
        assert ax.get_title() == "cost \\$5"  # drawn as "cost $5": the escape is matplotlib's
    finally:
        plt.close(fig)


def test_a_world_too_wide_for_a_map_is_named_in_the_error(tmp_path):
    # "grid of 40001 x 81 cells ... is too large" named neither the world nor what made it so
    from shared.sim.world import load_world_file

    path = tmp_path / "very-far.xml"
    path.write_text('<mujoco><worldbody><geom name="floor" type="plane" size="0 0 1"/>'
                    '<geom type="box" pos="0 2 1" size="2 0.05 1"/>'
                    '<geom type="cylinder" pos="1000000 0 1" size="0.2 1"/>'
                    '<site name="start_a" pos="-1 0 0"/></worldbody></mujoco>')
    world = load_world_file(path)
    with pytest.raises(maps.MapError, match=r"world '.*very-far.xml': grid of .* is too large: its obstacles"):
        maps.occupancy_grid(world)
