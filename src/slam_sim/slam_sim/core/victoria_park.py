"""The Victoria Park data set (GTSAM text), parsed; see docs/design/simulation.md."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam_core.arrays import FloatArray, IntArray
from slam_core.errors import DatasetError
from slam_core.geometry.se2 import wrap_angle
from slam_sim.core.dataset_text import data_lines, line_error, parse_float, parse_int, read_lines

ODOMETRY_TAG = 'ODOMETRY'
LANDMARK_TAG = 'LANDMARK'
ODOMETRY_NUMBERS = 11
LANDMARK_NUMBERS = 7
# GTSAM load2D: the x-y covariance of a sighting is taken as the uncertainty at this range.
GTSAM_LANDMARK_REFERENCE_RANGE_M = 10.0


@dataclass(frozen=True)
class VictoriaPark:
    """A parsed GTSAM 2D data set: odometry edges (M) and sightings (K), poses 0..N-1."""

    path: Path
    num_poses: int
    pose_ids: IntArray
    odometry_from: IntArray
    odometry_to: IntArray
    odometry_between: FloatArray
    odometry_cov: FloatArray
    obs_pose: IntArray
    obs_landmark: IntArray
    obs_xy: FloatArray
    obs_range: FloatArray
    obs_bearing: FloatArray
    obs_sigma_range: FloatArray
    obs_sigma_bearing: FloatArray

    @property
    def landmark_ids(self) -> IntArray:
        """Return the distinct landmark ids (L,), ascending."""
        return np.unique(self.obs_landmark)


class _Lines:
    """What the line-by-line pass collects; ids are the file's."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.chain: list[int] = []  # pose file ids in chain order
        self.visited: set[int] = set()
        self.between: list[list[float]] = []
        self.odometry_cov6: list[list[float]] = []
        self.odometry_lines: list[int] = []
        self.obs_pose_id: list[int] = []
        self.obs_landmark: list[int] = []
        self.obs_values: list[list[float]] = []  # x, y, cxx, cxy, cyy
        self.obs_lines: list[int] = []

    def numbers(self, line_no: int, tag: str, tokens: list[str], expected: int) -> list[float]:
        """Return a line's numbers after its two ids, checked for count and finiteness."""
        if len(tokens) != expected:
            raise line_error(
                self.path, line_no, f'{tag} needs {expected} numbers, got {len(tokens)}'
            )
        try:
            names = ('first id', 'second id', *(f'number {n}' for n in range(3, expected + 1)))
            return [parse_float(token, name) for token, name in zip(tokens, names, strict=True)]
        except ValueError as err:
            raise line_error(self.path, line_no, f'{tag}: {err}') from None

    def ids(self, line_no: int, tag: str, tokens: list[str]) -> tuple[int, int]:
        """Return a line's two ids, non-negative integers."""
        try:
            first, second = parse_int(tokens[0], 'first id'), parse_int(tokens[1], 'second id')
        except ValueError as err:
            raise line_error(self.path, line_no, f'{tag}: {err}') from None
        if first < 0 or second < 0:
            raise line_error(self.path, line_no, f'{tag}: ids must be >= 0, got {first} {second}')
        return first, second

    def odometry(self, line_no: int, tokens: list[str]) -> None:
        values = self.numbers(line_no, ODOMETRY_TAG, tokens, ODOMETRY_NUMBERS)
        pose_from, pose_to = self.ids(line_no, ODOMETRY_TAG, tokens)
        if not self.chain:
            self.chain.append(pose_from)
            self.visited.add(pose_from)
        elif pose_from != self.chain[-1]:
            raise line_error(
                self.path,
                line_no,
                f'ODOMETRY {pose_from} -> {pose_to} does not continue the odometry chain, '
                f'which ends at pose {self.chain[-1]}; the importer needs the ODOMETRY lines '
                'to form one chain in file order',
            )
        if pose_to in self.visited:
            raise line_error(
                self.path,
                line_no,
                f'ODOMETRY {pose_from} -> {pose_to} returns to pose {pose_to}; the importer '
                'needs one chain of distinct poses (loop closures are not supported)',
            )
        self.chain.append(pose_to)
        self.visited.add(pose_to)
        self.between.append(values[2:5])
        self.odometry_cov6.append(values[5:])
        self.odometry_lines.append(line_no)

    def landmark(self, line_no: int, tokens: list[str]) -> None:
        values = self.numbers(line_no, LANDMARK_TAG, tokens, LANDMARK_NUMBERS)
        pose_id, landmark_id = self.ids(line_no, LANDMARK_TAG, tokens)
        if values[2] == 0.0 and values[3] == 0.0:
            raise line_error(
                self.path, line_no, f'LANDMARK {landmark_id} seen at range 0 (x = y = 0)'
            )
        self.obs_pose_id.append(pose_id)
        self.obs_landmark.append(landmark_id)
        self.obs_values.append(values[2:])
        self.obs_lines.append(line_no)


def _read(path: Path) -> _Lines:
    collected = _Lines(path)
    for line_no, tokens in data_lines(read_lines(path), comment=None):
        tag, rest = tokens[0], tokens[1:]
        if tag == ODOMETRY_TAG:
            collected.odometry(line_no, rest)
        elif tag == LANDMARK_TAG:
            collected.landmark(line_no, rest)
        else:
            raise line_error(
                path, line_no, f'unknown tag {tag!r}; expected {ODOMETRY_TAG} or {LANDMARK_TAG}'
            )
    if not collected.chain:
        raise DatasetError(f'{path}: no {ODOMETRY_TAG} lines; not a GTSAM 2D odometry file')
    return collected


def _first_not_positive_definite(matrices: FloatArray) -> int | None:
    """Return the index of the first matrix (..., n, n) that is not positive definite."""
    if len(matrices) == 0:
        return None
    eigenvalues = np.linalg.eigvalsh(matrices)
    bad = np.flatnonzero(~(eigenvalues[:, 0] > 0.0))
    return int(bad[0]) if len(bad) else None


def _odometry_covariances(collected: _Lines) -> FloatArray:
    xx, xy, xt, yy, yt, tt = np.array(collected.odometry_cov6, dtype=np.float64).reshape(-1, 6).T
    cov = np.stack(
        [np.stack([xx, xy, xt], -1), np.stack([xy, yy, yt], -1), np.stack([xt, yt, tt], -1)], -2
    )
    bad = _first_not_positive_definite(cov)
    if bad is not None:
        raise line_error(
            collected.path,
            collected.odometry_lines[bad],
            f'ODOMETRY covariance {collected.odometry_cov6[bad]} (xx xy xt yy yt tt) is not '
            'positive definite',
        )
    return cov


def _check_sightings(collected: _Lines, index_of: dict[int, int]) -> None:
    values = np.array(collected.obs_values, dtype=np.float64).reshape(-1, 5)
    cxx, cxy, cyy = values[:, 2], values[:, 3], values[:, 4]
    cov = np.stack([np.stack([cxx, cxy], -1), np.stack([cxy, cyy], -1)], -2)
    bad = _first_not_positive_definite(cov)
    if bad is not None:
        raise line_error(
            collected.path,
            collected.obs_lines[bad],
            f'LANDMARK covariance {collected.obs_values[bad][2:]} (cxx cxy cyy) is not '
            'positive definite',
        )
    for pose_id, landmark_id, line_no in zip(
        collected.obs_pose_id, collected.obs_landmark, collected.obs_lines, strict=True
    ):
        if pose_id not in index_of:
            raise line_error(
                collected.path,
                line_no,
                f'LANDMARK {landmark_id} seen from pose {pose_id}, which no ODOMETRY line reaches',
            )
        if landmark_id in index_of:
            raise line_error(
                collected.path,
                line_no,
                f'LANDMARK id {landmark_id} is also a pose id; pose and landmark ids share one '
                'number space',
            )


def parse_victoria_park(path: Path | str) -> VictoriaPark:
    """Return the odometry chain and sightings of a GTSAM 2D file; DatasetError."""
    path = Path(path)
    collected = _read(path)
    index_of = {pose_id: index for index, pose_id in enumerate(collected.chain)}
    odometry_cov = _odometry_covariances(collected)
    _check_sightings(collected, index_of)
    num_edges = len(collected.between)
    obs = np.array(collected.obs_values, dtype=np.float64).reshape(-1, 5)
    obs_xy = obs[:, :2]
    return VictoriaPark(
        path=path,
        num_poses=len(collected.chain),
        pose_ids=np.array(collected.chain, dtype=np.int64),
        odometry_from=np.arange(num_edges, dtype=np.int64),
        odometry_to=np.arange(1, num_edges + 1, dtype=np.int64),
        odometry_between=np.array(collected.between, dtype=np.float64).reshape(-1, 3),
        odometry_cov=odometry_cov,
        obs_pose=np.array([index_of[i] for i in collected.obs_pose_id], dtype=np.int64),
        obs_landmark=np.array(collected.obs_landmark, dtype=np.int64),
        obs_xy=obs_xy,
        obs_range=np.hypot(obs_xy[:, 0], obs_xy[:, 1]),
        obs_bearing=np.arctan2(obs_xy[:, 1], obs_xy[:, 0]),
        obs_sigma_range=np.sqrt(obs[:, 2]),
        obs_sigma_bearing=np.sqrt(obs[:, 2] / GTSAM_LANDMARK_REFERENCE_RANGE_M),
    )


def chain_poses(between: FloatArray) -> FloatArray:
    """Return the poses (M + 1, 3) of an odometry chain ``between`` (M, 3) from the origin."""
    between = np.asarray(between, dtype=np.float64).reshape(-1, 3)
    heading = np.concatenate([[0.0], np.cumsum(between[:, 2])])
    cos_h, sin_h = np.cos(heading[:-1]), np.sin(heading[:-1])
    dx = cos_h * between[:, 0] - sin_h * between[:, 1]
    dy = sin_h * between[:, 0] + cos_h * between[:, 1]
    x = np.concatenate([[0.0], np.cumsum(dx)])
    y = np.concatenate([[0.0], np.cumsum(dy)])
    return np.stack([x, y, wrap_angle(heading)], axis=-1)


def differential_drive_increments(
    between: FloatArray, covariance: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return EM-SAM eq. 2 increments u (M, 3) and covariances (M, 3, 3)."""
    between = np.asarray(between, dtype=np.float64).reshape(-1, 3)
    covariance = np.asarray(covariance, dtype=np.float64).reshape(-1, 3, 3)
    half = 0.5 * between[:, 2]
    cos_h, sin_h = np.cos(half), np.sin(half)
    u = np.empty_like(between)
    u[:, 0] = cos_h * between[:, 0] + sin_h * between[:, 1]
    u[:, 1] = -sin_h * between[:, 0] + cos_h * between[:, 1]
    u[:, 2] = between[:, 2]
    jacobian = np.zeros_like(covariance)
    jacobian[:, 0, 0], jacobian[:, 0, 1], jacobian[:, 0, 2] = cos_h, sin_h, 0.5 * u[:, 1]
    jacobian[:, 1, 0], jacobian[:, 1, 1], jacobian[:, 1, 2] = -sin_h, cos_h, -0.5 * u[:, 0]
    jacobian[:, 2, 2] = 1.0
    propagated = jacobian @ covariance @ np.swapaxes(jacobian, -1, -2)
    return u, 0.5 * (propagated + np.swapaxes(propagated, -1, -2))


def sighting_covariances(data: VictoriaPark) -> FloatArray:
    """Return the (K, 2, 2) covariances of (range m, bearing rad): diag(sigma_r^2, sigma_b^2)."""
    cov = np.zeros((len(data.obs_range), 2, 2))
    cov[:, 0, 0] = data.obs_sigma_range**2
    cov[:, 1, 1] = data.obs_sigma_bearing**2
    return cov
