"""Which other robots an MRCLAM window scores as positives (moved landmarks).

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import numpy as np

from em_sam_node.core.assembly import MappingData
from slam_sim.core.mrclam import MrclamRun

MIN_SEPARATION_M = 0.5
MIN_PLACE_SIGHTINGS = 5
PLACE_RADIUS_M = MIN_SEPARATION_M / 2  # two places this far apart share no sighting
MIN_SIGHTINGS = 20


def seen_at_two_places(positions: np.ndarray) -> bool:
    """Whether the positions (n, 2) m hold two places more than MIN_SEPARATION_M apart."""
    if len(positions) < 2 * MIN_PLACE_SIGHTINGS:
        return False
    distances = np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=-1)
    near = np.count_nonzero(distances <= PLACE_RADIUS_M, axis=1)
    places = positions[near >= MIN_PLACE_SIGHTINGS]
    if len(places) < 2:
        return False
    spread = np.linalg.norm(places[:, None, :] - places[None, :, :], axis=-1)
    return bool(spread.max() > MIN_SEPARATION_M)


def mrclam_positives(run: MrclamRun, data: MappingData, *, whole_run: bool) -> list[int]:
    """The other robots (subjects) ``run``'s window scores as positives; ``data``: the window."""
    positives = []
    for subject in run.other_robots:
        rows = data.obs_landmark_id == subject
        stamps = data.keyframe_stamps_ns[data.obs_keyframe[rows]]
        track = run.robot_truth.get(subject)
        if track is None:
            if whole_run and len(stamps) >= MIN_SIGHTINGS:
                positives.append(subject)
            continue
        covered = stamps[track.covers(stamps)]
        if seen_at_two_places(track.poses_at(covered)[:, :2]):
            positives.append(subject)
    return positives
