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
