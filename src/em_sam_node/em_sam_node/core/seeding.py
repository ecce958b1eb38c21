"""The robust mode's first E-step: an incremental robust solve over growing time prefixes.

A robust kernel needs a starting point where the static sightings agree with it. Dead
reckoning over a whole run is not one: odometry drift makes most late sightings of early
landmarks look like outliers. Solving prefixes of the run in time order, each warm-started
from the previous solution and odometry for the new part, keeps the static sightings
consistent as they come in, while a landmark that moved disagrees with where it was first
mapped.

Odometry drifts most where few landmarks are seen (a corridor), so the odometry-extended
poses of a new chunk can come back to a mapped area a metre off. Nothing about that is
robust: a redescending kernel would reject the loop-closing sightings as outliers, and the
split test below would take every static landmark for a moved one. So each chunk is first
relocalized: a rigid SE(2) correction of its new poses, the consensus of its sightings of
mapped landmarks (two-landmark hypotheses, scored by how many landmarks they bring within
``relocalize_inlier_m``, the smaller correction winning ties), is applied before the test
and the solve. Landmarks that moved independently do not agree on one correction; the
static ones do. Sightings of one landmark form two self-consistent clusters when it moved, which a
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
from itertools import combinations

import numpy as np

from em_sam_node.core.assembly import MappingData, build_problem, dead_reckoning
from em_sam_node.core.problem import Estimate, FloatArray, SlamProblem
from em_sam_node.core.structure import anchor_pieces, with_weak_priors
from slam_core.geometry.se2 import apply_increment, range_bearing_to_point

Solver = Callable[[SlamProblem, Estimate], Estimate]
MAX_MERGE_ROUNDS = 3


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


def extend_poses(data: MappingData, solved: FloatArray, count: int) -> FloatArray:
    """Solved poses for the first keyframes, odometry composed on them for the rest."""
    poses = dead_reckoning(prefix(data, count))
    known = len(solved)
    poses[:known] = solved
    incoming = {int(t): m for m, t in enumerate(data.odometry_to.tolist())}
    for index in range(max(known, 1), count):  # keyframe 0 keeps the prior
        m = incoming.get(index)
        if m is not None and data.odometry_from[m] == index - 1:
            poses[index] = apply_increment(poses[index - 1][None], data.odometry_u[m][None])[0]
        else:
            poses[index] = poses[index - 1]
    return poses


@dataclasses.dataclass(frozen=True)
class Correction:
    """A rigid SE(2) correction p' = R(angle) p + translation of poses and points."""

    angle: float
    translation: FloatArray  # (2,)

    def apply_points(self, points: FloatArray) -> FloatArray:
        """Return the corrected points (n,2)."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        result: FloatArray = points @ np.array([[c, s], [-s, c]]) + self.translation
        return result

    def apply_poses(self, poses: FloatArray) -> FloatArray:
        """Return the corrected poses (n,3), headings wrapped."""
        heading = poses[:, 2] + self.angle
        return np.column_stack(
            [self.apply_points(poses[:, :2]), np.arctan2(np.sin(heading), np.cos(heading))]
        )


def _fit_rigid(source: FloatArray, target: FloatArray) -> Correction:
    """Least-squares rigid transform taking ``source`` (n,2) onto ``target`` (n,2)."""
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    a, b = source - source_mean, target - target_mean
    angle = float(np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b)))
    rotated = Correction(angle, np.zeros(2)).apply_points(source_mean[None])[0]
    return Correction(angle, target_mean - rotated)


def relocalization(
    points: FloatArray,
    ids: np.ndarray,
    landmarks: dict[int, FloatArray],
    inlier_m: float,
    *,
    poses: FloatArray,
    max_shift_m: float,
    max_angle: float,
) -> Correction | None:
    """Return the consensus correction that maps sightings onto their mapped landmarks.

    ``points`` (n,2) are sightings placed through the uncorrected poses, ``ids`` (n,) their
    landmark ids. Each mapped landmark votes once, at the median of its sightings. Returns
    None when no hypothesis brings more landmarks within ``inlier_m`` than no correction
    does, or when fewer than two mapped landmarks were seen. A correction is plausible only
    if it turns by at most ``max_angle`` rad and moves none of ``poses`` (n,3), the poses
    it would correct, by more than ``max_shift_m``; a hypothesis needs a pair of landmarks
    at least 4 ``inlier_m`` apart, so its rotation is defined.
    """
    known = [i for i in np.unique(ids).tolist() if i in landmarks]
    if len(known) < 2:
        return None
    source = np.array([np.median(points[ids == i], axis=0) for i in known])
    target = np.array([landmarks[i] for i in known])

    def inliers(correction: Correction) -> np.ndarray:
        distance = np.linalg.norm(correction.apply_points(source) - target, axis=1)
        result: np.ndarray = distance < inlier_m
        return result

    identity = Correction(0.0, np.zeros(2))
    best, best_key = identity, (int(inliers(identity).sum()), 0.0)
    for a, b in combinations(range(len(known)), 2):
        seen, mapped = source[b] - source[a], target[b] - target[a]
        if np.linalg.norm(mapped) < 4 * inlier_m:
            continue  # too short a baseline to define a rotation
        if abs(np.linalg.norm(seen) - np.linalg.norm(mapped)) > inlier_m:
            continue  # no rigid motion maps this pair
        hypothesis = _fit_rigid(source[[a, b]], target[[a, b]])
        mask = inliers(hypothesis)
        if mask.sum() < 2:
            continue
        refined = _fit_rigid(source[mask], target[mask])
        shift = np.linalg.norm(refined.apply_points(poses[:, :2]) - poses[:, :2], axis=1)
        if abs(refined.angle) > max_angle or shift.max(initial=0.0) > max_shift_m:
            continue
        size = float(np.linalg.norm(refined.translation)) + abs(refined.angle)
        key = (int(inliers(refined).sum()), -size)
        if key > best_key:
            best, best_key = refined, key
    return None if best is identity else best


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
    relocalize_inlier_m: float = 0.25,
    relocalize_max_shift_m: float = 2.0,
    relocalize_max_angle: float = 0.3,
    refine: bool = True,
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
        poses = extend_poses(data, solved_poses, count)
        rows = np.flatnonzero((data.obs_keyframe >= done) & (data.obs_keyframe < count))
        correction = relocalization(
            range_bearing_to_point(poses[data.obs_keyframe[rows]], data.obs_z[rows]),
            virtual_ids[rows],
            landmarks,
            relocalize_inlier_m,
            poses=poses[done:],
            max_shift_m=relocalize_max_shift_m,
            max_angle=relocalize_max_angle,
        )
        if correction is not None and done > 0:
            poses[done:] = correction.apply_poses(poses[done:])
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
    if refine:
        for _ in range(MAX_MERGE_ROUNDS):
            solved_poses, landmarks = _refine(
                dataclasses.replace(data, obs_landmark_id=virtual_ids),
                solver,
                solved_poses,
                landmarks,
            )
            if not _merge_agreeing(virtual_ids, origin, landmarks, split_distance_m):
                break
    real = {lid: pos for lid, pos in landmarks.items() if origin[lid] == lid}
    return solved_poses, real


def _merge_agreeing(
    virtual_ids: np.ndarray,
    origin: dict[int, int],
    landmarks: dict[int, FloatArray],
    split_distance_m: float,
) -> bool:
    """Merge split clusters of one landmark that the refined solve put back together.

    Drift can split a static landmark as if it moved; once solved as a whole, its clusters
    land within ``split_distance_m`` of each other, and merging them restores the loop
    closure they stand for. Changes ``virtual_ids`` and ``landmarks`` in place; returns
    whether anything merged.
    """
    merged = False
    clusters: dict[int, list[int]] = {}
    for lid in sorted(landmarks, key=lambda v: (origin[v] != v, -v)):  # real id first
        clusters.setdefault(origin[lid], []).append(lid)
    for members in clusters.values():
        kept: list[int] = []
        for lid in members:
            target = next(
                (
                    k
                    for k in kept
                    if np.linalg.norm(landmarks[k] - landmarks[lid]) < split_distance_m
                ),
                None,
            )
            if target is None:
                kept.append(lid)
                continue
            virtual_ids[virtual_ids == lid] = target
            del landmarks[lid]
            merged = True
    return merged


def _refine(
    data: MappingData, solver: Solver, poses: FloatArray, landmarks: dict[int, FloatArray]
) -> tuple[FloatArray, dict[int, FloatArray]]:
    """One robust solve of the whole run (split ids) from the windowed solution.

    The windows hold landmarks mapped before them fixed, so a map made from a short early
    baseline stays as first mapped; solving everything at once lets later sightings improve
    it (and the poses with it).
    """
    built = build_problem(data)
    ids = built.landmark_ids.tolist()
    initial = np.array([landmarks[lid] for lid in ids]) if ids else np.zeros((0, 2))
    anchored = anchor_pieces(built.problem, poses)
    problem = with_weak_priors(
        built.problem, anchored.extra_prior_poses, anchored.extra_prior_means
    )
    estimate = solver(problem, Estimate(poses, initial))
    return estimate.poses, {lid: estimate.landmarks[i] for i, lid in enumerate(ids)}
