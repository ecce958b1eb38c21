"""shadow_evaluate's runs: the Shadow filter on a simulated run, its record, the truth.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.common.core.inputs import CameraPose, Features
from monoslam_shadow_node.shadow_filter.core.rays import ray_angle
from monoslam_shadow_node.shadow_filter.core.shadow_classifier import Decision
from monoslam_shadow_node.shadow_filter.core.shadow_filter import (
    Handover,
    InputError,
    ShadowConfig,
)
from monoslam_shadow_node.shadow_filter.processor import ShadowProcessor, ShadowStep
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_sim.core.dynamic_scene import DynamicSceneRun

BoolArray = NDArray[np.bool_]


class FilterRunError(RuntimeError):
    """The Shadow filter raised on a simulated run (the message names seed and frame)."""


@dataclass(frozen=True, eq=False)
class FilterRecord:
    """One run's filter output: track reports over samples S (id, frame, status, defined,
    position (S, 3) m, covariance (S, 3, 3) m^2), last decisions, handovers, wall time (s)."""

    track_id: IntArray
    frame: IntArray
    status: IntArray
    defined: BoolArray
    position: FloatArray
    covariance: FloatArray
    decisions: dict[int, tuple[int, Decision]]
    handovers: list[tuple[int, Handover]]
    redecided: int
    runtime_s: float


def camera_model(run: DynamicSceneRun) -> CameraModel:
    """Return the filter's camera model of the run's CameraInfo."""
    info = run.camera.camera_info()
    return CameraModel.from_camera_info(
        info.width, info.height, info.k, info.d, info.distortion_model
    )


FilterInput = tuple[int, IntArray, FloatArray, FloatArray, FloatArray]
"""One frame for ``run_frames``: stamp (int ns), track ids (N,), raw pixels (N, 2),
R_world_camera (3, 3) and the optical centre (3,) m."""


def run_filter(run: DynamicSceneRun, config: ShadowConfig) -> FilterRecord:
    """Feed every frame to a new ShadowProcessor (true poses as known); FilterRunError on error."""
    inputs = [
        (f.stamp_ns, f.track_ids, f.pixels, f.camera_rotation, f.camera_position)
        for f in run.frames
    ]
    return run_frames(camera_model(run), inputs, config, f'seed {run.seed}')


def run_frames(
    camera: CameraModel, inputs: Sequence[FilterInput], config: ShadowConfig, name: str
) -> FilterRecord:
    """``run_filter`` over any frames (known poses); ``name`` names the run in errors."""
    shadow = ShadowProcessor(config)
    shadow.set_camera(camera)
    ids: list[int] = []
    frames: list[int] = []
    statuses: list[int] = []
    defined: list[bool] = []
    positions: list[FloatArray] = []
    covariances: list[FloatArray] = []
    decisions: dict[int, tuple[int, Decision]] = {}
    handovers: list[tuple[int, Handover]] = []
    redecided, runtime_s = 0, 0.0
    for index, (stamp_ns, track_ids, pixels, rotation, centre) in enumerate(inputs):
        started = time.perf_counter()
        try:
            outcome = shadow.process(
                Features(stamp_ns, '', track_ids, pixels),
                CameraPose(stamp_ns, '', rotation, centre, None),
            )
            if not isinstance(outcome, ShadowStep):
                raise InputError(str(outcome))
        except Exception as error:
            raise FilterRunError(
                f'{name}, frame {index}: {type(error).__name__}: {error}'
            ) from error
        result = outcome.result
        runtime_s += time.perf_counter() - started
        for decision in result.decisions:
            redecided += decision.id in decisions
            decisions[decision.id] = (index, decision)
        handovers += [(index, handover) for handover in result.handovers]
        for track in result.tracks:
            ids.append(track.id)
            frames.append(index)
            statuses.append(track.status)
            defined.append(bool(track.defined))
            positions.append(track.position)
            covariances.append(track.position_covariance)
    return FilterRecord(
        np.array(ids, dtype=np.int64),
        np.array(frames, dtype=np.int64),
        np.array(statuses, dtype=np.int64),
        np.array(defined, dtype=bool),
        np.array(positions, dtype=np.float64).reshape(-1, 3),
        np.array(covariances, dtype=np.float64).reshape(-1, 3, 3),
        decisions,
        handovers,
        redecided,
        runtime_s,
    )


# --- truth ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrackTruth:
    """A track's point, whether it moves, motion kind, first and last sighting frame."""

    point: int
    moving: bool
    motion: str
    first_frame: int
    last_frame: int


def track_truths(run: DynamicSceneRun) -> dict[int, TrackTruth]:
    """Return the truth of every track id in the run."""
    spans: dict[int, list[int]] = {}
    for index, frame in enumerate(run.frames):
        for track_id in frame.track_ids.tolist():
            spans.setdefault(track_id, [index, index])[1] = index
    truths = {}
    for track_id, (first, last) in spans.items():
        point = run.track_point[track_id]
        owner = int(run.point_object[point])
        motion = run.object_motion[owner] if owner >= 0 else 'static'
        truths[track_id] = TrackTruth(point, bool(run.point_moving[point]), motion, first, last)
    return truths


def view_parallax_rad(point: FloatArray, centre_a: FloatArray, centre_b: FloatArray) -> float:
    """Return the angle (rad) at ``point`` (3,) between the directions to two centres (3,)."""
    a, b = centre_a - point, centre_b - point
    norm_a, norm_b = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if norm_a == 0.0 or norm_b == 0.0:
        return math.nan
    return ray_angle(a / norm_a, b / norm_b)
