"""trajectory_evaluate: a camera trajectory (TUM file or pose topic) against a reference.

Design notes: docs/design/evaluation.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from slam_core.arrays import FloatArray
from slam_core.cli import console_main
from slam_core.files import write_json
from slam_core.geometry.quaternion import log_rotation
from slam_core.stamps import stamp_to_ns
from slam_evaluation.classification_figure import read_messages
from slam_evaluation.monoslam_metrics import DIVERGED_ATE_M, rms, umeyama_alignment
from slam_evaluation.sequence_files import read_poses
from slam_sim.core.reference_error import ReferencePoseError

MIN_SCALE = 0.5
"""A Sim(3) alignment that must scale the estimate by less than this (or more than its
inverse) says the estimate lost its scale: the run diverged, whatever its aligned ATE."""


def read_tum(path: Path) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """Return stamps (K,) int ns, centres (K, 3) m and rotations (K, 3, 3) of a TUM file
    (``sequence_files.read_poses``); ValueError names the file and line."""
    return read_poses(Path(path))


POSE_TOPIC = '/monoslam/pose'


def read_record(
    path: Path, topic: str
) -> tuple[NDArray[np.int64], FloatArray, FloatArray, FloatArray]:
    """Return stamps (K,) int ns, centres (K, 3) m, rotations (K, 3, 3), covariances
    (K, 6, 6) on ``topic``; ValueError: no topic, or a bad quaternion."""
    stamps, centres, quaternions, covariances = [], [], [], []
    for _, message in read_messages(path, [topic], topic):
        pose = message.pose.pose
        q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z,
                      pose.orientation.w])  # fmt: skip
        stamp = stamp_to_ns(message.header.stamp)
        if not (np.all(np.isfinite(q)) and np.linalg.norm(q) > 0.0):
            raise ValueError(f'{path}: {topic} at stamp {stamp} ns: orientation {q.tolist()}')
        stamps.append(stamp)
        centres.append((pose.position.x, pose.position.y, pose.position.z))
        quaternions.append(q)
        covariances.append(np.reshape(np.asarray(message.pose.covariance, np.float64), (6, 6)))
    order = np.argsort(np.array(stamps, np.int64), kind='stable')
    rotations = Rotation.from_quat(np.array(quaternions)).as_matrix()
    return (
        np.array(stamps, np.int64)[order], np.array(centres, np.float64)[order],
        rotations[order], np.array(covariances)[order],
    )  # fmt: skip


def pose_nees(errors: FloatArray, covariances: FloatArray) -> tuple[dict[str, Any], FloatArray]:
    """Return the NEES figures of errors (K, 6) against covariances (K, 6, 6), and per pose
    (NaN where the covariance is not positive definite)."""
    values = np.full(len(errors), np.nan)
    position = np.full(len(errors), np.nan)
    rotation = np.full(len(errors), np.nan)
    for k, (error, covariance) in enumerate(zip(errors, covariances, strict=True)):
        symmetric = 0.5 * (covariance + covariance.T)
        if not (np.all(np.isfinite(symmetric)) and np.all(np.isfinite(error))):
            continue
        try:
            whitened = np.linalg.solve(np.linalg.cholesky(symmetric), error)  # not PD: raises
            values[k] = float(whitened @ whitened)
            position[k] = error[:3] @ np.linalg.solve(symmetric[:3, :3], error[:3])
            rotation[k] = error[3:] @ np.linalg.solve(symmetric[3:, 3:], error[3:])
        except np.linalg.LinAlgError:
            continue
    used = np.isfinite(values)
    figures = {
        'poses_with_covariance': int(np.count_nonzero(used)),
        'poses_without_covariance': int(np.count_nonzero(~used)),
        'pose_nees_mean': float(values[used].mean()) if used.any() else None,
        'pose_nees_median': float(np.median(values[used])) if used.any() else None,
        'position_nees_mean': float(position[used].mean()) if used.any() else None,
        'rotation_nees_mean': float(rotation[used].mean()) if used.any() else None,
    }
    return figures, values


def evaluate(
    estimate: tuple[NDArray[np.int64], FloatArray, FloatArray],
    truth: tuple[NDArray[np.int64], FloatArray, FloatArray],
    tolerance_ns: int,
    anchor: bool,
    covariances: FloatArray | None = None,
    reference_error: ReferencePoseError | None = None,
) -> dict[str, Any]:
    """Return ATE, scale, anchored ATE and NEES figures, and the paired centres for the plot."""
    e_stamps, e_centres, e_rotations = estimate
    t_stamps, t_centres, t_rotations = truth
    index = np.searchsorted(t_stamps, e_stamps)
    pairs = []
    for k, stamp in enumerate(e_stamps):
        near = [j for j in (index[k] - 1, index[k]) if 0 <= j < len(t_stamps)]
        j = min(near, key=lambda j: abs(int(t_stamps[j]) - int(stamp)))
        if abs(int(t_stamps[j]) - int(stamp)) <= tolerance_ns:
            pairs.append((k, j))
    if len(pairs) < 3:
        raise ValueError(f'{len(pairs)} estimated poses pair with a reference pose: too few')
    k, j = np.array(pairs).T
    source, target = e_centres[k], t_centres[j]
    similarity = umeyama_alignment(source, target)
    aligned = similarity.apply(source)
    result: dict[str, Any] = {
        'estimated_poses': len(e_stamps),
        'reference_poses': len(t_stamps),
        'paired': len(pairs),
        'tracked_share': len(set(j.tolist())) / len(t_stamps),
        'ate_sim3_m': rms(np.linalg.norm(aligned - target, axis=1)),
        'sim3_scale': similarity.scale,
        'max_error_sim3_m': float(np.max(np.linalg.norm(aligned - target, axis=1))),
    }
    diverged = not MIN_SCALE <= similarity.scale <= 1.0 / MIN_SCALE
    if anchor:  # the estimate's world -> the reference's, through the first paired pose
        first = int(j[0])
        world = t_rotations[first] @ e_rotations[int(k[0])].T
        raw = target[0] + (source - source[0]) @ world.T
        result['ate_anchored_m'] = rms(np.linalg.norm(raw - target, axis=1))
        diverged |= result['ate_anchored_m'] > DIVERGED_ATE_M
        if covariances is not None:  # errors in the estimate's world axes, as its covariance
            errors = np.zeros((len(k), 6))
            errors[:, :3] = (raw - target) @ world
            for row, (ek, tj) in enumerate(zip(k.tolist(), j.tolist(), strict=True)):
                true_rotation = world.T @ t_rotations[tj]
                errors[row, 3:] = log_rotation(e_rotations[ek] @ true_rotation.T)
            figures, _ = pose_nees(errors, covariances[k])
            result.update(figures)
            if reference_error is not None:
                since_s = (e_stamps[k] - e_stamps[k[0]]) * 1e-9
                sigmas = np.array([reference_error.at(s) for s in since_s])  # (rotation, centre)
                widened = np.array(covariances[k], dtype=np.float64)
                widened[:, :3, :3] += sigmas[:, 1, None, None] ** 2 * np.eye(3)
                widened[:, 3:, 3:] += sigmas[:, 0, None, None] ** 2 * np.eye(3)
                figures, _ = pose_nees(errors, widened)
                result.update({f'reference_{name}': v for name, v in figures.items()})
    result['diverged'] = bool(diverged)
    result['_plot'] = (aligned, target)
    return result


def read_reference_error(path: Path) -> ReferencePoseError:
    """Return the reference's pose error table of a JSON file; ValueError if unusable."""
    try:
        content = json.loads(Path(path).read_text())
        measured = content.get('reference_pose_error')
        if isinstance(measured, dict) and measured.get('table') is None:
            raise ValueError(f'the import measured none: {measured.get("reason")}')
        return ReferencePoseError.from_json(measured['table'] if measured else content)
    except (json.JSONDecodeError, AttributeError, KeyError, TypeError, ValueError) as error:
        raise ValueError(
            f'{path}: no reference error table (separations_s, rotation_sigmas_rad, '
            f"translation_sigmas_m, or a sequence import.json's reference_pose_error): {error}"
        ) from error


def write_topview(path: Path, aligned: FloatArray, target: FloatArray) -> None:
    """Write the aligned estimate against the reference, x-y and x-z views (PNG)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(11, 5))
    for axis, (a, b) in zip(axes, ((0, 1), (0, 2)), strict=True):
        axis.plot(target[:, a], target[:, b], 'k-', label='reference (motion capture)')
        axis.plot(aligned[:, a], aligned[:, b], 'r-', label='estimate (Sim(3)-aligned)')
        axis.set_xlabel(f'{"xyz"[a]} (m)')
        axis.set_ylabel(f'{"xyz"[b]} (m)')
        axis.set_aspect('equal', adjustable='datalim')
        axis.grid(True, alpha=0.3)
    axes[0].legend(loc='best')
    figure.suptitle('camera trajectory against the reference')
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix('.tmp.png')
    figure.savefig(temporary, dpi=100)
    plt.close(figure)
    temporary.replace(path)


@console_main('trajectory_evaluate')
def main(argv: list[str] | None = None) -> int:
    """Command line (module docstring)."""
    parser = argparse.ArgumentParser(
        prog='trajectory_evaluate',
        description="a node's camera trajectory (TUM text) against a reference (TUM text)",
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument('--trajectory', type=Path, help='estimate, TUM text')
    source.add_argument(
        '--record', type=Path,
        help='estimate, a bag with the pose topic (PoseWithCovarianceStamped): also the NEES',
    )  # fmt: skip
    parser.add_argument('--pose-topic', default=POSE_TOPIC, help=f'default {POSE_TOPIC}')
    parser.add_argument('--truth', type=Path, required=True, help='reference, TUM text')
    parser.add_argument('--out', type=Path, default=Path('out/trajectory_eval'))
    parser.add_argument('--tolerance-ms', type=float, default=1.0, help='stamp pairing, ms')
    parser.add_argument(
        '--anchor', action='store_true',
        help="also the raw ATE with the estimate's world anchored at the first pose's reference",
    )  # fmt: skip
    parser.add_argument(
        '--reference-error', type=Path, metavar='JSON',
        help="the reference's rotation and centre error by separation (a sequence's "
        'import.json): the NEES again with it added',
    )  # fmt: skip
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    covariances = None
    try:
        reference_error = (
            None if args.reference_error is None else read_reference_error(args.reference_error)
        )
        if args.record is not None:
            stamps, centres, rotations, covariances = read_record(args.record, args.pose_topic)
            estimate = stamps, centres, rotations
        else:
            estimate = read_tum(args.trajectory)
        result = evaluate(
            estimate, read_tum(args.truth), round(args.tolerance_ms * 1e6), args.anchor,
            covariances, reference_error,
        )  # fmt: skip
    except (OSError, ValueError) as error:
        print(f'trajectory_evaluate: error: {error}', file=sys.stderr)  # noqa: T201
        return 2
    if covariances is not None and not args.anchor:
        note = "the NEES needs --anchor (the estimate in the reference's world)"
        print(f'trajectory_evaluate: {note}', file=sys.stderr)  # noqa: T201
    if reference_error is not None and covariances is None:
        note = '--reference-error is for the NEES, which needs --record (its covariances)'
        print(f'trajectory_evaluate: {note}', file=sys.stderr)  # noqa: T201
    aligned, target = result.pop('_plot')
    write_json(args.out / 'trajectory_eval.json', result)
    write_topview(args.out / 'trajectory_topview.png', aligned, target)
    anchored = result.get('ate_anchored_m')
    verdict = 'DIVERGED' if result['diverged'] else 'kept'
    print(  # noqa: T201
        f'{verdict}: {result["paired"]} of {result["estimated_poses"]} poses paired with the '
        f'{result["reference_poses"]} reference poses ({100 * result["tracked_share"]:.1f} % '
        f'of them estimated); ATE after Sim(3) {result["ate_sim3_m"]:.3f} m (scale '
        f'{result["sim3_scale"]:.3f}, max {result["max_error_sim3_m"]:.3f} m)'
        + (f'; anchored at the first pose {anchored:.3f} m' if anchored is not None else '')
        + (
            f'; pose NEES mean {result["pose_nees_mean"]:.1f}, median '
            f'{result["pose_nees_median"]:.1f} (6 dof), position and rotation NEES means '
            f'{result["position_nees_mean"]:.1f} and {result["rotation_nees_mean"]:.1f} (3 dof '
            f'each), over {result["poses_with_covariance"]} '
            f'poses ({result["poses_without_covariance"]} without a usable covariance)'
            if result.get('pose_nees_mean') is not None
            else ''
        )
        + (
            f"; with the reference's own error added: pose NEES mean "
            f'{result["reference_pose_nees_mean"]:.1f}, position and rotation '
            f'{result["reference_position_nees_mean"]:.1f} and '
            f'{result["reference_rotation_nees_mean"]:.1f}'
            if result.get('reference_pose_nees_mean') is not None
            else ''
        )
    )
    print(f'wrote {args.out / "trajectory_eval.json"}, {args.out / "trajectory_topview.png"}')  # noqa: T201
    return 1 if result['diverged'] else 0
