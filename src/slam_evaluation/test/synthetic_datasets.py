"""Small data sets in the real file formats, written into a test's tmp_path: an MRCLAM-style
directory (robot 1 circling static barcodes while robot 2 walks back and forth) and a
Victoria Park-style GTSAM text file (a circuit past trees, one of which is moved)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

ROBOT_SPEED_MPS = 0.3
ROBOT_TURN_RPS = 0.2  # a 1.5 m circle, one lap in 31 s
ODOMETRY_PERIOD_S = 0.05
SIGHTING_PERIOD_S = 0.5
FIELD_OF_VIEW_RAD = 0.6  # half angle
MAX_RANGE_M = 5.0
RANGE_NOISE_M = 0.02  # well inside mrclam_import's default sigma 0.079 m
BEARING_NOISE_RAD = 0.004  # inside its 0.011 rad
T0_S = 1000.0
STATIC_SUBJECTS = tuple(range(6, 14))
SWAPPED = (11, 12)  # exchanged in Landmark_Groundtruth.dat, as data set 1's 11 and 17


def barcode(subject: int) -> int:
    """Return the (made-up) barcode of a subject."""
    return 10 * subject + 3


def static_positions() -> dict[int, np.ndarray]:
    """Return the barcodes' true positions (m): a ring of radius 3 m around the circle."""
    angles = np.linspace(0.0, 2.0 * np.pi, len(STATIC_SUBJECTS), endpoint=False)
    return {
        s: 3.0 * np.array([np.cos(a), np.sin(a)])
        for s, a in zip(STATIC_SUBJECTS, angles, strict=True)
    }


def robot1_pose(t_s: np.ndarray) -> np.ndarray:
    """Return robot 1's true poses (n,3) at times since the start: a circle about (0, 0)."""
    heading = ROBOT_TURN_RPS * t_s
    radius = ROBOT_SPEED_MPS / ROBOT_TURN_RPS
    return np.column_stack([radius * np.sin(heading), -radius * np.cos(heading), heading])


def robot2_position(t_s: np.ndarray) -> np.ndarray:
    """Return robot 2's positions (n,2): back and forth along y = 2.2 m, x in [-1, 1] m, at
    0.15 m/s (between robot 1's circle and the barcodes)."""
    phase = np.mod(0.15 * t_s, 4.0)
    x = np.where(phase < 2.0, phase - 1.0, 3.0 - phase)
    return np.column_stack([x, np.full(len(t_s), 2.2)])


def _write(path: Path, rows: list[str]) -> None:
    path.write_text('# synthetic\n' + ''.join(row + '\n' for row in rows), encoding='utf-8')


def write_mrclam(directory: Path, *, duration_s: float, vicon: bool, seed: int = 0) -> Path:
    """Write an MRCLAM-style data set (only robot 1 has odometry and measurements; Vicon
    tracks of robots 1 and 2 only if ``vicon``); return its directory."""
    rng = np.random.default_rng(seed)
    directory.mkdir()
    positions = static_positions()
    _write(directory / 'Barcodes.dat', [f'{s}\t{barcode(s)}' for s in range(1, 14)])
    truth_rows = []
    for s in STATIC_SUBJECTS:
        listed = SWAPPED[1] if s == SWAPPED[0] else SWAPPED[0] if s == SWAPPED[1] else s
        x, y = positions[listed]
        truth_rows.append(f'{s}\t{x:.4f}\t{y:.4f}\t0.001\t0.001')
    _write(directory / 'Landmark_Groundtruth.dat', truth_rows)
    t_s = np.arange(0.0, duration_s + 1e-9, ODOMETRY_PERIOD_S)
    odometry = [f'{T0_S + t:.3f}\t{ROBOT_SPEED_MPS}\t{ROBOT_TURN_RPS}' for t in t_s]
    _write(directory / 'Robot1_Odometry.dat', odometry)
    sightings = []
    for t in np.arange(0.0, duration_s, SIGHTING_PERIOD_S):
        pose = robot1_pose(np.array([t]))[0]
        targets = {**positions, 2: robot2_position(np.array([t]))[0]}
        for subject, target in sorted(targets.items()):
            offset = target - pose[:2]
            range_m = float(np.hypot(*offset))
            bearing = float(np.arctan2(offset[1], offset[0]) - pose[2])
            bearing = float(np.arctan2(np.sin(bearing), np.cos(bearing)))
            if range_m < MAX_RANGE_M and abs(bearing) < FIELD_OF_VIEW_RAD:
                range_m += rng.normal(0.0, RANGE_NOISE_M)
                bearing += rng.normal(0.0, BEARING_NOISE_RAD)
                sightings.append(
                    f'{T0_S + t:.3f}\t{barcode(subject)}\t{range_m:.4f}\t{bearing:.5f}'
                )
    _write(directory / 'Robot1_Measurement.dat', sightings)
    if vicon:
        stamps = np.arange(0.0, duration_s + 1e-9, 0.01)
        poses = robot1_pose(stamps)
        _write(
            directory / 'Robot1_Groundtruth.dat',
            [
                f'{T0_S + t:.3f}\t{x:.5f}\t{y:.5f}\t{th:.5f}'
                for t, (x, y, th) in zip(stamps, poses, strict=True)
            ],
        )
        xy2 = robot2_position(stamps)
        _write(
            directory / 'Robot2_Groundtruth.dat',
            [
                f'{T0_S + t:.3f}\t{x:.5f}\t{y:.5f}\t0.0'
                for t, (x, y) in zip(stamps, xy2, strict=True)
            ],
        )
    return directory


VP_POSES = 300
VP_TREES = 1000  # tree ids start here (pose and tree ids share one number space)
VP_MOVED_TREE = VP_TREES + 2
VP_COV = '0.0001 0 0 0.0001 0 0.00004'  # odometry covariance xx xy xt yy yt tt
VP_SIGHTING_CXX = 0.01  # sigma_r 0.1 m, sigma_b sqrt(0.001) rad (GTSAM load2D)


def write_victoria_park(path: Path, seed: int = 0) -> Path:
    """Write a GTSAM 2D file: 300 poses on a 10 m circle (3 laps), 8 trees around it; tree
    VP_MOVED_TREE jumps 3 m outwards halfway; return the path."""
    rng = np.random.default_rng(seed)
    step_rad = 3 * 2.0 * np.pi / VP_POSES
    radius = 10.0
    angles = np.arange(VP_POSES) * step_rad
    poses = np.column_stack([radius * np.sin(angles), radius - radius * np.cos(angles), angles])
    trees = {
        VP_TREES + k: np.array([0.0, radius]) + 15.0 * np.array([np.cos(a), np.sin(a)])
        for k, a in enumerate(np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False))
    }
    lines = []
    for i in range(VP_POSES):
        if i:
            dx = radius * np.sin(step_rad) + rng.normal(0.0, 0.01)
            dy = radius * (1.0 - np.cos(step_rad)) + rng.normal(0.0, 0.01)
            dtheta = step_rad + rng.normal(0.0, 0.006)
            lines.append(f'ODOMETRY {i - 1} {i} {dx:.6f} {dy:.6f} {dtheta:.6f} {VP_COV}')
        for tree, position in trees.items():
            if tree == VP_MOVED_TREE and i >= VP_POSES // 2:
                position = position + 3.0 * (position - [0.0, radius]) / 15.0
            cos, sin = np.cos(poses[i, 2]), np.sin(poses[i, 2])
            offset = position - poses[i, :2]
            local = np.array(
                [cos * offset[0] + sin * offset[1], -sin * offset[0] + cos * offset[1]]
            )
            if np.hypot(*local) < 12.0 and local[0] > 0.0 and i % 3 == 0:
                local = local + rng.normal(0.0, 0.05, 2)
                lines.append(
                    f'LANDMARK {i} {tree} {local[0]:.4f} {local[1]:.4f} '
                    f'{VP_SIGHTING_CXX} 0 {VP_SIGHTING_CXX}'
                )
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')
    return path
