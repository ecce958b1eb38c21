"""The robust mode's first E-step: an incremental robust solve over growing time prefixes.

A robust kernel needs a starting point where the static sightings agree with it. Dead
reckoning over a whole run is not one: odometry drift makes most late sightings of early
landmarks look like outliers. Solving prefixes of the run in time order, each warm-started
from the previous solution and odometry for the new part, keeps the static sightings
consistent as they come in, while a landmark that moved disagrees with where it was first
mapped. Sightings of one landmark form two self-consistent clusters when it moved, which a
per-sighting kernel cannot reject, so the seed splits them: when a mapped landmark's new
sightings (placed through the odometry-extended trajectory) lie more than
``split_distance_m`` from where it was mapped, they start a new, virtual landmark. The
redescending kernel then only has isolated outliers to deal with.

Each step solves only a window of the recent ``window_s`` of keyframes, anchored at the
window's first pose as solved before; landmarks mapped before the window are held fixed, a
known map that the window's poses are localized against (which closes loops). The cost per
step is bounded by the window, so the seed grows linearly with the run.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from em_sam_node.core.assembly import MappingData, build_problem, dead_reckoning
from em_sam_node.core.problem import Estimate, FloatArray, SlamProblem
from em_sam_node.core.se2 import apply_increment, range_bearing_to_point
from em_sam_node.core.structure import anchor_pieces, with_weak_priors

Solver = Callable[[SlamProblem, Estimate], Estimate]


def prefix(data: MappingData, count: int) -> MappingData:
    """Return the data of the first ``count`` keyframes."""
    odometry = data.odometry_to < count
    observations = data.obs_keyframe < count
    return dataclasses.replace(
        data,
        keyframe_stamps_ns=data.keyframe_stamps_ns[:count],
        odometry_from=data.odometry_from[odometry],
        odometry_to=data.odometry_to[odometry],
        odometry_u=data.odometry_u[odometry],
        odometry_cov=data.odometry_cov[odometry],
        obs_keyframe=data.obs_keyframe[observations],
        obs_landmark_id=data.obs_landmark_id[observations],
        obs_z=data.obs_z[observations],
        obs_cov=data.obs_cov[observations],
    )


def chunk_ends(stamps_ns: np.ndarray, chunk_s: float) -> list[int]:
    """Return prefix lengths (keyframe counts) every ``chunk_s`` of keyframe time, ending at N."""
    elapsed = (stamps_ns - stamps_ns[0]) / 1e9
    ends = np.searchsorted(elapsed, np.arange(chunk_s, elapsed[-1], chunk_s), side='right')
    return sorted({int(e) for e in ends if 1 < e < len(stamps_ns)} | {len(stamps_ns)})


def _extend_poses(data: MappingData, solved: FloatArray, count: int) -> FloatArray:
    """Solved poses for the first keyframes, odometry composed on them for the rest."""
    poses = dead_reckoning(prefix(data, count))
    known = len(solved)
    poses[:known] = solved
    incoming = {int(t): m for m, t in enumerate(data.odometry_to.tolist())}
    for index in range(known, count):
        m = incoming.get(index)
        if m is not None and data.odometry_from[m] == index - 1:
            poses[index] = apply_increment(poses[index - 1][None], data.odometry_u[m][None])[0]
        else:
            poses[index] = poses[index - 1]
    return poses


def _split_moved(
    data: MappingData,
    virtual_ids: np.ndarray,
    rows: np.ndarray,
    poses: FloatArray,
    landmarks: dict[int, FloatArray],
    split_distance_m: float,
    next_virtual: int,
) -> int:
    """Give sightings in ``rows`` that disagree with their landmark's map position a new id.

    Changes ``virtual_ids`` in place for these rows and every later sighting of the same
    landmark; returns the next free virtual id.
    """
    points = range_bearing_to_point(poses[data.obs_keyframe[rows]], data.obs_z[rows])
    for landmark_id in np.unique(virtual_ids[rows]).tolist():
        if landmark_id not in landmarks:
            continue
        mine = rows[virtual_ids[rows] == landmark_id]
        offsets = np.linalg.norm(points[np.isin(rows, mine)] - landmarks[landmark_id], axis=1)
        if np.median(offsets) > split_distance_m:
            later = (virtual_ids == landmark_id) & (np.arange(len(virtual_ids)) >= mine[0])
            virtual_ids[later] = next_virtual
            next_virtual -= 1
    return next_virtual


def window(data: MappingData, start: int, end: int, anchor: FloatArray) -> MappingData:
    """Return keyframes [start, end) re-indexed from 0, with the prior at ``anchor`` (3,)."""
    odometry = (data.odometry_from >= start) & (data.odometry_to < end)
    observations = (data.obs_keyframe >= start) & (data.obs_keyframe < end)
    return dataclasses.replace(
        data,
        keyframe_stamps_ns=data.keyframe_stamps_ns[start:end],
        odometry_from=data.odometry_from[odometry] - start,
        odometry_to=data.odometry_to[odometry] - start,
        odometry_u=data.odometry_u[odometry],
        odometry_cov=data.odometry_cov[odometry],
        obs_keyframe=data.obs_keyframe[observations] - start,
        obs_landmark_id=data.obs_landmark_id[observations],
        obs_z=data.obs_z[observations],
        obs_cov=data.obs_cov[observations],
        prior_pose=anchor.copy(),
        prior_cov=np.diag([1e-6, 1e-6, 1e-6]),
    )


def incremental_seed(
    data: MappingData,
    solver: Solver,
    *,
    chunk_s: float = 20.0,
    split_distance_m: float = 0.5,
    window_s: float = 60.0,
) -> tuple[FloatArray, dict[int, FloatArray]]:
    """Return poses (N,3) and landmark positions by (real) id from windowed robust solves.

    A landmark split in the seed reports the position of its first mapped cluster.
    """
    virtual_ids = data.obs_landmark_id.copy()
    next_virtual = min(int(virtual_ids.min(initial=0)), 0) - 1
    origin = {int(i): int(i) for i in np.unique(virtual_ids).tolist()}
    first_seen: dict[int, int] = {}  # landmark (virtual) id -> keyframe of its first sighting
    solved_poses = np.zeros((0, 3))
    landmarks: dict[int, FloatArray] = {}
    done = 0
    stamps = data.keyframe_stamps_ns
    for count in chunk_ends(stamps, chunk_s):
        poses = _extend_poses(data, solved_poses, count)
        rows = np.flatnonzero((data.obs_keyframe >= done) & (data.obs_keyframe < count))
        before = next_virtual
        next_virtual = _split_moved(
            data, virtual_ids, rows, poses, landmarks, split_distance_m, next_virtual
        )
        for new_id in range(before, next_virtual, -1):
            origin[new_id] = int(data.obs_landmark_id[virtual_ids == new_id][0])
        for row in rows.tolist():
            first_seen.setdefault(int(virtual_ids[row]), int(data.obs_keyframe[row]))
        start = int(np.searchsorted(stamps, stamps[max(done, 1) - 1] - round(window_s * 1e9)))
        start = min(start, max(done - 1, 0))
        done = count
        part = window(
            dataclasses.replace(data, obs_landmark_id=virtual_ids), start, count, poses[start]
        )
        built = build_problem(part)
        if built.problem.num_landmarks == 0:
            solved_poses = poses
            continue
        ids = built.landmark_ids.tolist()
        fixed = np.array([lid in landmarks and first_seen[lid] < start for lid in ids])
        problem = dataclasses.replace(built.problem, fixed_landmarks=fixed)
        local = poses[start:count]
        initial = np.zeros((problem.num_landmarks, 2))
        for index, landmark_id in enumerate(ids):
            if landmark_id in landmarks:
                initial[index] = landmarks[landmark_id]
            else:  # first sighting, through the extended trajectory
                first = int(np.flatnonzero(problem.obs_landmark == index)[0])
                initial[index] = range_bearing_to_point(
                    local[problem.obs_pose[first]][None], problem.obs_z[first][None]
                )[0]
        anchored = anchor_pieces(problem, local)
        problem = with_weak_priors(problem, anchored.extra_prior_poses, anchored.extra_prior_means)
        estimate = solver(problem, Estimate(local, initial))
        solved_poses = np.concatenate([poses[:start], estimate.poses])
        for index, landmark_id in enumerate(ids):
            if not fixed[index]:
                landmarks[landmark_id] = estimate.landmarks[index]
    real = {lid: pos for lid, pos in landmarks.items() if origin[lid] == lid}
    return solved_poses, real
