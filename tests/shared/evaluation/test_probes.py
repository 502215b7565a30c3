"""Probe scenes rendered for another sensor: the camera's image at the pose, never its noise."""

from __future__ import annotations

import numpy as np

from shared.config import SensorConfig
from shared.evaluation import PROTOCOLS
from shared.evaluation.probes import PROBE_SCENES, load_probes, render_probe


def test_a_probe_for_a_noisy_sensor_is_the_noise_free_image() -> None:
    # A robust run's network carries its training noise (robust-40x30's is the Kinect's, the
    # distance-dependent part included); Table II rendered it into the probes, differently each time.
    noisy = PROTOCOLS["robust"].sensor(SensorConfig(width=40, height=30))
    assert noisy.noise_quadratic_per_m > 0
    scene = PROBE_SCENES[1]
    clean = render_probe(scene, noisy.noise_free())
    np.testing.assert_array_equal(render_probe(scene, noisy), clean)
    by_name = {p.name: p.depth_m for p in load_probes(sensor_cfg=noisy)}
    np.testing.assert_array_equal(by_name[scene.name], clean)


def test_the_stored_probe_images_stand_only_for_the_camera_that_took_them() -> None:
    # The stored images are the paper sensor's 160 x 120; a camera of that size mounted higher, further
    # forward or with another field of view sees another image at the pose, and Table II and the
    # receptive fields of its network must be drawn from that one.
    for camera in (SensorConfig(mount_height_m=0.6), SensorConfig(mount_forward_m=0.1),
                   SensorConfig(hfov_deg=70.0, vfov_deg=54.0)):
        by_name = {p.name: p for p in load_probes(sensor_cfg=camera)}
        scene = PROBE_SCENES[0]
        np.testing.assert_array_equal(by_name[scene.name].depth_m, render_probe(scene, camera))
        assert by_name[scene.name].notes  # the figure says it was rendered, not the stored image
    # the paper's own camera (noise aside) still reads the stored images
    assert not any(p.notes for p in load_probes(sensor_cfg=SensorConfig(noise_std_m=0.01)))


def test_a_user_probe_is_range_gated_at_both_ends_as_the_camera_reports_it(tmp_path) -> None:
    # a camera blind below 0.5 m reports 0 there; the network was never shown a nearer depth, and
    # Table II's Q-values for a probe holding one were of an image no camera of it gives
    from shared.evaluation.probes import load_probe_image

    sensor = SensorConfig(width=40, height=30, min_range_m=0.5, max_range_m=3.0)
    depth = np.full((30, 40), 2.0, np.float32)
    depth[:, :10], depth[:, 30:] = 0.3, 3.5
    np.save(tmp_path / "near.npy", depth)
    seen, notes = load_probe_image(tmp_path / "near.npy", sensor)
    assert (seen[:, :10] == 0).all() and (seen[:, 30:] == 0).all() and (seen[:, 10:30] == 2.0).all()
    assert any("nearer than the sensor's 0.5 m" in n for n in notes) and any("beyond" in n for n in notes)
