"""The node configurations for simulated runs agree with what the simulators draw."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from ament_index_python.packages import get_package_share_directory

from monoslam_shadow_node.monoslam import settings as monoslam_settings
from slam_sim.core.init_target import InitTarget

SIMULATION_CONFIG = (
    Path(get_package_share_directory('monoslam_shadow_node'))
    / 'config'
    / 'monoslam_dynamic_camera.yaml'
)


def test_the_simulation_config_places_the_simulated_target() -> None:
    """monoslam_dynamic_camera.yaml sets only parameters, and puts the corners where
    slam_sim draws them."""
    values = monoslam_settings.PARAMETERS.read_yaml(SIMULATION_CONFIG)
    target = monoslam_settings.target_settings(values)
    simulated = InitTarget()
    np.testing.assert_allclose(target.corners_m, simulated.corners_m, atol=1e-12)
    np.testing.assert_allclose(target.rotation, simulated.rotation, atol=1e-12)
    assert target.marker_id == simulated.marker_id and target.dictionary == simulated.dictionary
