"""trajectory_evaluate: a camera trajectory written by a node (TUM text) against a reference
(TUM text, e.g. a sequence's poses.txt or a motion-capture file).

    trajectory_evaluate --trajectory out/monoslam_shadow_rgbd/trajectory.tum \\
                        --truth out/bonn_crowd/sequence/poses.txt [--out DIR] [--anchor]

Poses pair by stamp (within ``--tolerance-ms``, 1 ms by default: the node stamps each pose
with its image's stamp, and a file may round it). Reported: poses estimated and reference
poses, the share of reference poses with an estimate, the ATE (RMS of the camera centre
error, m) after the Sim(3) alignment that minimizes it (Umeyama) with its scale, and with
``--anchor`` the raw ATE after expressing the estimate in the reference's world through the
reference pose of the first estimated stamp (the world of a depth start is that camera's
frame: a known transform, not a fit). A run diverged when the alignment's scale is off by more
than a factor 2 (``MIN_SCALE``) or the anchored ATE exceeds ``DIVERGED_ATE_M`` (exit status
1). Writes ``trajectory_eval.json`` and
``trajectory_topview.png`` (estimate, aligned, against the reference; x-y and x-z) into
``--out`` and prints a summary.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam_core.cli import console_main
from slam_core.files import write_json
from slam_evaluation.monoslam_metrics import DIVERGED_ATE_M, rms, umeyama_alignment
from slam_evaluation.sequence_files import read_poses

FloatArray = NDArray[np.float64]
MIN_SCALE = 0.5
"""A Sim(3) alignment that must scale the estimate by less than this (or more than its
inverse) says the estimate lost its scale: the run diverged, whatever its aligned ATE."""


def read_tum(path: Path) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """Return stamps (K,) int ns, centres (K, 3) m and rotations (K, 3, 3) of a TUM file
    (``sequence_files.read_poses``); ValueError names the file and line."""
    return read_poses(Path(path))


def evaluate(
    estimate: tuple[NDArray[np.int64], FloatArray, FloatArray],
    truth: tuple[NDArray[np.int64], FloatArray, FloatArray],
    tolerance_ns: int,
    anchor: bool,
) -> dict[str, Any]:
    """Return the figures of the module docstring (and the paired centres for the plot)."""
    e_stamps, e_centres, _ = estimate
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
    if anchor:
        first = int(j[0])
        raw = target[0] + source @ t_rotations[first].T - source[0] @ t_rotations[first].T
        result['ate_anchored_m'] = rms(np.linalg.norm(raw - target, axis=1))
        diverged |= result['ate_anchored_m'] > DIVERGED_ATE_M
    result['diverged'] = bool(diverged)
    result['_plot'] = (aligned, target)
    return result


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
    parser.add_argument('--trajectory', type=Path, required=True, help='estimate, TUM text')
    parser.add_argument('--truth', type=Path, required=True, help='reference, TUM text')
    parser.add_argument('--out', type=Path, default=Path('out/trajectory_eval'))
    parser.add_argument('--tolerance-ms', type=float, default=1.0, help='stamp pairing, ms')
    parser.add_argument(
        '--anchor', action='store_true',
        help="also the raw ATE with the estimate's world anchored at the first pose's reference",
    )  # fmt: skip
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        result = evaluate(
            read_tum(args.trajectory), read_tum(args.truth),
            round(args.tolerance_ms * 1e6), args.anchor,
        )  # fmt: skip
    except (OSError, ValueError) as error:
        print(f'trajectory_evaluate: error: {error}', file=sys.stderr)  # noqa: T201
        return 2
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
    )
    print(f'wrote {args.out / "trajectory_eval.json"}, {args.out / "trajectory_topview.png"}')  # noqa: T201
    return 1 if result['diverged'] else 0
