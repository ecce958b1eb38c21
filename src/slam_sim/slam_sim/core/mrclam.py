"""UTIAS MRCLAM runs, parsed without ROS; see docs/design/simulation.md."""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_core.errors import DatasetError
from slam_core.geometry.se2 import wrap_angle
from slam_sim.core.dataset_text import Kind, Table, read_table
from slam_sim.core.odometry import integrate_increments

ROBOT_SUBJECTS = (1, 2, 3, 4, 5)
UNKNOWN_SUBJECT = 0
# Scale of the median absolute deviation that estimates a Gaussian's standard deviation.
MAD_TO_SIGMA = 1.4826


def _inside(stamps_ns: IntArray, start_ns: int | None, end_ns: int) -> BoolArray:
    """Return which stamps (n,) lie in [``start_ns``, ``end_ns``] (None: no lower bound)."""
    keep: BoolArray = stamps_ns <= end_ns
    if start_ns is not None:
        keep &= stamps_ns >= start_ns
    return keep


@dataclass(frozen=True)
class Trajectory:
    """Ground-truth poses (T, 3) (x m, y m, theta rad) in ``map`` at ``stamps_ns`` (T,)."""

    stamps_ns: IntArray
    poses: FloatArray

    def covers(self, stamps_ns: IntArray) -> BoolArray:
        """Return which stamps (n,) lie within the trajectory's time span."""
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        first, last = int(self.stamps_ns[0]), int(self.stamps_ns[-1])
        return np.logical_and(stamps >= first, stamps <= last)

    def poses_at(self, stamps_ns: IntArray) -> FloatArray:
        """Return poses (n, 3) linearly interpolated at ``stamps_ns`` (clamped at the ends)."""
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        relative = (stamps - self.stamps_ns[0]).astype(np.float64)
        knots = (self.stamps_ns - self.stamps_ns[0]).astype(np.float64)
        x = np.interp(relative, knots, self.poses[:, 0])
        y = np.interp(relative, knots, self.poses[:, 1])
        theta = np.interp(relative, knots, np.unwrap(self.poses[:, 2]))
        return np.stack([x, y, wrap_angle(theta)], axis=-1)

    def within(self, start_ns: int | None, end_ns: int) -> Trajectory | None:
        """Return the samples in [start_ns, end_ns] (None: from the first), None if < 2."""
        keep = _inside(self.stamps_ns, start_ns, end_ns)
        if np.count_nonzero(keep) < 2:
            return None
        return Trajectory(self.stamps_ns[keep], self.poses[keep])


@dataclass(frozen=True)
class Odometry:
    """Wheel odometry: stamps (N,), twists (N, 2) (m/s, rad/s), poses (N, 3) in ``odom``."""

    stamps_ns: IntArray
    twists: FloatArray
    poses: FloatArray

    def within(self, start_ns: int | None, end_ns: int) -> Odometry:
        """Return the samples in [start_ns, end_ns] (None: from the first)."""
        keep = _inside(self.stamps_ns, start_ns, end_ns)
        return Odometry(self.stamps_ns[keep], self.twists[keep], self.poses[keep])


@dataclass(frozen=True)
class Sightings:
    """Range-bearing sightings (K): stamps, barcodes, subjects (0: unknown), m, rad, lines."""

    stamps_ns: IntArray
    barcodes: IntArray
    subjects: IntArray
    range_m: FloatArray
    bearing_rad: FloatArray
    line_numbers: IntArray

    def __len__(self) -> int:
        """Return the number of sightings."""
        return len(self.stamps_ns)

    def select(self, rows: BoolArray | IntArray) -> Sightings:
        """Return the sightings at ``rows`` (a mask or indices)."""
        return Sightings(
            self.stamps_ns[rows],
            self.barcodes[rows],
            self.subjects[rows],
            self.range_m[rows],
            self.bearing_rad[rows],
            self.line_numbers[rows],
        )


@dataclass(frozen=True)
class LandmarkTruth:
    """Static landmarks: subjects (L,), positions (L, 2) m, Vicon std (L, 2) m in ``map``."""

    subjects: IntArray
    positions: FloatArray
    std_m: FloatArray


@dataclass(frozen=True)
class MrclamRun:
    """One robot of an MRCLAM data set, with the ground truth of everything it can see."""

    dataset_dir: Path
    robot: int
    barcode_of: dict[int, int]
    odometry: Odometry
    sightings: Sightings
    dropped_unknown: Sightings
    dropped_own: Sightings
    duplicate_odometry_stamps: int
    misplaced_odometry_rows: int
    truth: Trajectory | None
    robot_truth: dict[int, Trajectory]
    landmarks: LandmarkTruth

    @property
    def dropped_counts(self) -> dict[str, int]:
        """Return the number of dropped sightings per reason."""
        return {'unknown_barcode': len(self.dropped_unknown), 'own_subject': len(self.dropped_own)}

    @property
    def other_robots(self) -> tuple[int, ...]:
        """Return the subjects of the other robots, ascending (with or without Vicon track)."""
        return tuple(k for k in ROBOT_SUBJECTS if k != self.robot)

    @property
    def start_ns(self) -> int:
        """Return the run's first odometry stamp, int ns (where a time window starts)."""
        return int(self.odometry.stamps_ns[0])

    def until(self, end_ns: int) -> MrclamRun:
        """Return the run with every stamped item after ``end_ns`` removed (see ``within``)."""
        return self.within(None, end_ns)

    def within(self, start_ns: int | None, end_ns: int) -> MrclamRun:
        """Return the run within [start_ns, end_ns]; DatasetError if < 2 odometry samples."""

        def crop(sightings: Sightings) -> Sightings:
            return sightings.select(_inside(sightings.stamps_ns, start_ns, end_ns))

        odometry = self.odometry.within(start_ns, end_ns)
        if len(odometry.stamps_ns) < 2:
            raise DatasetError(
                f'{self.dataset_dir / f"Robot{self.robot}_Odometry.dat"}: fewer than 2 odometry '
                f'samples up to {end_ns / 1e9:.3f} s; choose a longer time window'
            )
        cropped = {k: t.within(start_ns, end_ns) for k, t in self.robot_truth.items()}
        return replace(
            self,
            odometry=odometry,
            sightings=crop(self.sightings),
            dropped_unknown=crop(self.dropped_unknown),
            dropped_own=crop(self.dropped_own),
            truth=None if self.truth is None else self.truth.within(start_ns, end_ns),
            robot_truth={k: t for k, t in cropped.items() if t is not None},
        )

    def first_seconds(self, duration_s: float) -> MrclamRun:
        """Return the first ``duration_s`` s of the run; ValueError, DatasetError."""
        if not (math.isfinite(duration_s) and duration_s > 0.0):
            raise ValueError(
                f'a time window must be a finite number of seconds > 0, got {duration_s}'
            )
        return self.within(self.start_ns, self.start_ns + round(duration_s * 1e9))


def _read_barcodes(path: Path) -> dict[int, int]:
    table = read_table(path, [('subject', Kind.INT), ('barcode', Kind.INT)])
    barcode_of: dict[int, int] = {}
    seen: dict[int, int] = {}
    for row, (subject, barcode) in enumerate(
        zip(table.ints('subject').tolist(), table.ints('barcode').tolist(), strict=True)
    ):
        if subject <= 0:
            raise table.error(row, f'subject {subject} must be > 0')
        if subject in barcode_of or barcode in seen:
            raise table.error(row, f'subject {subject} or barcode {barcode} is listed twice')
        barcode_of[subject] = barcode
        seen[barcode] = subject
    missing = [s for s in ROBOT_SUBJECTS if s not in barcode_of]
    if missing:
        raise DatasetError(f'{path}: no barcode for the robot subjects {missing}')
    return barcode_of


def _read_landmarks(path: Path, barcode_of: dict[int, int]) -> LandmarkTruth:
    columns = [('subject', Kind.INT), ('x', Kind.FLOAT), ('y', Kind.FLOAT)]
    table = read_table(path, [*columns, ('x_std', Kind.FLOAT), ('y_std', Kind.FLOAT)])
    subjects = table.ints('subject')
    std = np.column_stack([table.floats('x_std'), table.floats('y_std')])
    for row, subject in enumerate(subjects.tolist()):
        if subject not in barcode_of or subject in ROBOT_SUBJECTS:
            raise table.error(row, f'subject {subject} is not a landmark in Barcodes.dat')
        if subject in subjects[:row]:
            raise table.error(row, f'landmark {subject} is listed twice')
        if np.any(std[row] < 0.0):
            raise table.error(row, f'negative standard deviation {std[row].tolist()}')
    positions = np.column_stack([table.floats('x'), table.floats('y')])
    return LandmarkTruth(subjects, positions, std)


def _check_time_order(table: Table, stamps_ns: IntArray, *, strict: bool, what: str) -> None:
    steps = np.diff(stamps_ns)
    bad = np.flatnonzero(steps <= 0 if strict else steps < 0)
    if len(bad):
        row = int(bad[0]) + 1
        relation = 'not after' if strict else 'before'
        raise table.error(
            row,
            f'time {stamps_ns[row] / 1e9:.6f} s is {relation} the previous one '
            f'({stamps_ns[row - 1] / 1e9:.6f} s, line {table.line_numbers[row - 1]}); '
            f'{what} times must {"increase" if strict else "not decrease"}',
        )


def misplaced_rows(stamps_ns: IntArray) -> int:
    """Return the fewest rows that must move to sort ``stamps_ns`` (N,)."""
    tails: list[int] = []
    for stamp in stamps_ns.tolist():
        index = bisect.bisect_right(tails, stamp)
        if index == len(tails):
            tails.append(stamp)
        else:
            tails[index] = stamp
    return len(stamps_ns) - len(tails)


def _read_odometry(path: Path) -> tuple[Odometry, int, int]:
    """Return the odometry of ``path``, the rows out of order and repeats dropped."""
    columns = [('time', Kind.STAMP), ('v', Kind.FLOAT), ('w', Kind.FLOAT)]
    table = read_table(path, columns)
    stamps = table.ints('time')
    twists = np.column_stack([table.floats('v'), table.floats('w')])
    misplaced = misplaced_rows(stamps)
    if misplaced:
        order = np.argsort(stamps, kind='stable')
        stamps, twists = stamps[order], twists[order]
    keep = np.ones(len(stamps), dtype=bool)
    keep[:-1] = np.diff(stamps) != 0  # of equal times keep the last
    stamps = stamps[keep]
    if len(stamps) < 2:
        raise DatasetError(f'{path}: fewer than 2 odometry samples')
    twists = twists[keep]
    dt_s = np.diff(stamps).astype(np.float64) / 1e9
    poses = integrate_increments(twists[:-1, 0] * dt_s, twists[:-1, 1] * dt_s)
    return Odometry(stamps, twists, poses), misplaced, int(np.count_nonzero(~keep))


def _read_measurements(path: Path, barcode_of: dict[int, int]) -> Sightings:
    columns = [('time', Kind.STAMP), ('barcode', Kind.INT)]
    table = read_table(path, [*columns, ('range', Kind.FLOAT), ('bearing', Kind.FLOAT)])
    stamps = table.ints('time')
    _check_time_order(table, stamps, strict=False, what='measurement')
    range_m = table.floats('range')
    bad = np.flatnonzero(range_m <= 0.0)
    if len(bad):
        raise table.error(int(bad[0]), f'range {range_m[bad[0]]} m must be > 0')
    subject_of = {barcode: subject for subject, barcode in barcode_of.items()}
    barcodes = table.ints('barcode')
    subjects = np.array([subject_of.get(b, UNKNOWN_SUBJECT) for b in barcodes.tolist()])
    return Sightings(
        stamps,
        barcodes,
        subjects.astype(np.int64),
        range_m,
        table.floats('bearing'),
        table.line_numbers,
    )


def _read_groundtruth(path: Path) -> Trajectory | None:
    """Return the Vicon track in ``path``, or None if the file does not exist."""
    if not path.exists():
        return None
    columns = [('time', Kind.STAMP), ('x', Kind.FLOAT), ('y', Kind.FLOAT)]
    table = read_table(path, [*columns, ('theta', Kind.FLOAT)])
    stamps = table.ints('time')
    if len(stamps) < 2:
        raise DatasetError(f'{path}: fewer than 2 ground-truth poses')
    _check_time_order(table, stamps, strict=True, what='ground-truth')
    poses = np.column_stack([table.floats('x'), table.floats('y'), table.floats('theta')])
    return Trajectory(stamps, poses)


def robots_with_odometry(dataset_dir: Path | str) -> tuple[int, ...]:
    """Return the robots (ascending) with ``RobotN_Odometry.dat``; DatasetError if none."""
    directory = Path(dataset_dir)
    if not directory.is_dir():
        raise DatasetError(f'{directory}: no such data set directory')
    robots = tuple(k for k in ROBOT_SUBJECTS if (directory / f'Robot{k}_Odometry.dat').is_file())
    if not robots:
        raise DatasetError(
            f'{directory}: no RobotN_Odometry.dat (N = 1-5); not an MRCLAM data set directory'
        )
    return robots


def parse_mrclam(dataset_dir: Path | str, robot: int) -> MrclamRun:
    """Return robot ``robot`` (1-5) of ``dataset_dir``; ValueError, DatasetError (file:line)."""
    if robot not in ROBOT_SUBJECTS:
        raise ValueError(f'robot must be one of {ROBOT_SUBJECTS}, got {robot}')
    directory = Path(dataset_dir)
    if not directory.is_dir():
        raise DatasetError(f'{directory}: no such data set directory')
    barcode_of = _read_barcodes(directory / 'Barcodes.dat')
    landmarks = _read_landmarks(directory / 'Landmark_Groundtruth.dat', barcode_of)
    odometry, misplaced, duplicates = _read_odometry(directory / f'Robot{robot}_Odometry.dat')
    sightings = _read_measurements(directory / f'Robot{robot}_Measurement.dat', barcode_of)
    truth = {k: _read_groundtruth(directory / f'Robot{k}_Groundtruth.dat') for k in ROBOT_SUBJECTS}
    robot_truth = {k: t for k, t in truth.items() if k != robot and t is not None}
    unknown = sightings.subjects == UNKNOWN_SUBJECT
    own = sightings.subjects == robot
    return MrclamRun(
        dataset_dir=directory,
        robot=robot,
        barcode_of=barcode_of,
        odometry=odometry,
        sightings=sightings.select(~unknown & ~own),
        dropped_unknown=sightings.select(unknown),
        dropped_own=sightings.select(own),
        duplicate_odometry_stamps=duplicates,
        misplaced_odometry_rows=misplaced,
        truth=truth[robot],
        robot_truth=robot_truth,
        landmarks=landmarks,
    )


def true_targets(run: MrclamRun, sightings: Sightings) -> tuple[FloatArray, BoolArray]:
    """Return the true positions (K, 2) m of sightings in ``map`` and which have one (K,)."""
    positions = np.full((len(sightings), 2), np.nan)
    known = np.zeros(len(sightings), dtype=bool)
    landmark_rows = {int(s): k for k, s in enumerate(run.landmarks.subjects.tolist())}
    for subject in np.unique(sightings.subjects).tolist():
        rows = sightings.subjects == subject
        if subject in landmark_rows:
            positions[rows] = run.landmarks.positions[landmark_rows[subject]]
            known[rows] = True
        elif subject in run.robot_truth:
            trajectory = run.robot_truth[subject]
            positions[rows] = trajectory.poses_at(sightings.stamps_ns[rows])[:, :2]
            known[rows] = trajectory.covers(sightings.stamps_ns[rows])
    return positions, known


def sighting_residuals(run: MrclamRun) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Return measured minus true range (K,) m and bearing (K,) rad, and a truth mask."""
    if run.truth is None:
        raise DatasetError(
            f'{run.dataset_dir / f"Robot{run.robot}_Groundtruth.dat"}: no such file; the '
            "sighting residuals need the robot's Vicon track"
        )
    sightings = run.sightings
    targets, known = true_targets(run, sightings)
    known &= run.truth.covers(sightings.stamps_ns)
    sensor = run.truth.poses_at(sightings.stamps_ns)
    offset = targets - sensor[:, :2]
    range_residual = sightings.range_m - np.hypot(offset[:, 0], offset[:, 1])
    bearing = np.arctan2(offset[:, 1], offset[:, 0]) - sensor[:, 2]
    bearing_residual = wrap_angle(sightings.bearing_rad - bearing)
    range_residual[~known] = np.nan
    bearing_residual[~known] = np.nan
    return range_residual, bearing_residual, known


def robust_sigma(residuals: FloatArray) -> float:
    """Return 1.4826 times the median absolute deviation of ``residuals`` (n,) (NaN ignored)."""
    values = np.asarray(residuals, dtype=np.float64)
    values = values[np.isfinite(values)]
    if len(values) == 0:
        raise ValueError('robust_sigma needs at least one finite residual')
    return float(MAD_TO_SIGMA * np.median(np.abs(values - np.median(values))))
