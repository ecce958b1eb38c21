"""The SLAM update, one seam: the gated update and the 1-point RANSAC update behind one
signature, chosen once from ``MonoSlamConfig.update`` by ``slam_update``."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_ekf import UpdateOutcome, gated_update
from monoslam_shadow_node.monoslam.core.monoslam_ransac import ransac_update
from monoslam_shadow_node.monoslam.core.monoslam_state import FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel

SlamUpdate = Callable[
    [
        FilterState,
        CameraModel,
        dict[int, FloatArray],
        list[tuple[FloatArray, FloatArray]],
        MonoSlamConfig,
        np.random.Generator,
    ],
    UpdateOutcome,
]
"""Correct the state with one frame's measurements: observed pixels (2,) by feature id and
(known point (3,) m, pixel (2,)) pairs; the generator draws any hypotheses."""


def _gated(
    state: FilterState,
    camera: CameraModel,
    observed: dict[int, FloatArray],
    known: list[tuple[FloatArray, FloatArray]],
    config: MonoSlamConfig,
    rng: np.random.Generator,
) -> UpdateOutcome:
    """Every measurement inside the chi-square gate (draws nothing)."""
    return gated_update(state, camera, observed, known, config)


SLAM_UPDATES: dict[str, SlamUpdate] = {'gated': _gated, 'ransac': ransac_update}


def slam_update(name: str) -> SlamUpdate:
    """The update ``MonoSlamConfig.update`` names."""
    return SLAM_UPDATES[name]
