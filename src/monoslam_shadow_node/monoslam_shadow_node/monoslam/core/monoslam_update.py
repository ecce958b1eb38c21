"""The SLAM update, one seam: the gated update and the 1-point RANSAC update behind one
protocol, chosen once from ``MonoSlamConfig.update`` by ``slam_update``."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_ekf import UpdateOutcome, gated_update
from monoslam_shadow_node.monoslam.core.monoslam_ransac import ransac_update
from monoslam_shadow_node.monoslam.core.monoslam_state import FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel


class SlamUpdate(Protocol):
    """Correct ``state`` with one frame's measurements: ``observed`` pixels (2,) by feature
    id and ``known`` (point (3,) m, pixel (2,)) pairs; ``rng`` draws any hypotheses."""

    def __call__(
        self,
        state: FilterState,
        camera: CameraModel,
        observed: dict[int, FloatArray],
        known: list[tuple[FloatArray, FloatArray]],
        config: MonoSlamConfig,
        rng: np.random.Generator,
    ) -> UpdateOutcome: ...


class GatedUpdate:
    """Every measurement inside the chi-square gate (``monoslam_ekf.gated_update``)."""

    def __call__(
        self,
        state: FilterState,
        camera: CameraModel,
        observed: dict[int, FloatArray],
        known: list[tuple[FloatArray, FloatArray]],
        config: MonoSlamConfig,
        rng: np.random.Generator,
    ) -> UpdateOutcome:
        return gated_update(state, camera, observed, known, config)


class RansacUpdate:
    """The 1-point RANSAC update (``monoslam_ransac.ransac_update``)."""

    def __call__(
        self,
        state: FilterState,
        camera: CameraModel,
        observed: dict[int, FloatArray],
        known: list[tuple[FloatArray, FloatArray]],
        config: MonoSlamConfig,
        rng: np.random.Generator,
    ) -> UpdateOutcome:
        return ransac_update(state, camera, observed, known, config, rng)


SLAM_UPDATES: dict[str, SlamUpdate] = {'gated': GatedUpdate(), 'ransac': RansacUpdate()}


def slam_update(name: str) -> SlamUpdate:
    """The update ``MonoSlamConfig.update`` names."""
    return SLAM_UPDATES[name]
