"""shadow_evaluate: the Shadow filter on simulated runs, scored like paper 001's Figs. 2-4.

    shadow_evaluate [--seeds 0-9] [--out out/shadow_eval] [--alpha 0.05] [--quick]
                    [--unchecked-directions 1] [--static-test both|three_ray|all_view]
    shadow_evaluate --sequence DIR [--out out/shadow_eval] [--alpha 0.05]

``--sequence DIR`` runs the filter over an on-disk sequence instead (``sequence_files``; its
poses as known poses): decisions, handovers and, with labels, the classification against
them, into ``shadow_eval_sequence.json`` (``shadow_sequence``).

Every run comes from ``slam_sim.core.dynamic_scene`` (true camera poses, 1 px pixel noise)
and is fed frame by frame to the shadow_filter node's processor (``ShadowProcessor``, known
poses: no pose covariance). Two run sets:

- Classification (Fig. 4): the default scene (static points, objects with constant-velocity,
  turning and stop-and-go motion) at ``--alpha`` and at every ``--alphas`` value. A track's
  truth is its point's ``point_moving`` flag (a stop-and-go object is "moving" even while it
  stands still); its status is that of its last Decision, PENDING if it never got one.
  Frames to decide is Decision.frames_since_first.
- Consistency (Figs. 2-3): scenes whose objects follow the filter's own process model
  (``motions=('model',)``, one point per object), at ``--alpha``. Static features are
  scored in these runs and, separately, in the classification runs at ``--alpha``.

Writes ``shadow_eval.json`` (configuration, totals, per seed, alpha sweep, failures) and the
PNG figures of ``shadow_report`` into ``--out``; prints a summary; logs progress with
rate and ETA on stderr.

Parallax allows (window W = ``--window-frames``): the track was observed W frames after its
first sight (tracks are contiguous in the simulation), and the angle at the point between
the directions to the camera centres of first sight and of W frames later reached the
classifier's ``min_parallax_rad``. Everything is true: the point's position at first sight
and the true centres. For a moving point the position at first sight is held fixed, so the
angle is the parallax the camera's own motion offers; the object's motion is left out
because the static-hypothesis triangulation cannot use it (it turns into a wrong depth), and
counting it would call a fast, far, barely-triangulable object "allowed". The camera's
baseline rule (``min_baseline_m``) is not part of the criterion; it is reported beside it.

Consistency runs (the paper's Fig. 3 experiment): the simulation's ``model`` objects, which
move exactly as the filter's process model says, and the filter as a tracker alone
(``classify`` off), so every feature stays in its EKF for as long as it is tracked. With the
classifier on, handing features over would choose which estimates remain: the static
features still pending late are the ones the tests could not decide or wrongly rejected, a
sample biased towards large errors (it is still reported, as ``static_classification_runs``).
A model object is born at a random frame of the run's first half with v ~ N(0, sigma^2 I3),
the filter's prior; a track first seen at its point's birth starts from exactly that prior
(``moving_first_seen_at_birth``, the consistency test proper). A model object can also leave
view and come back, and a later track of it starts from the prior while the truth has walked
on (velocity variance sigma^2 + q t): ``moving`` holds all tracks. Static points have zero
velocity, a value at the prior's mean, so their NEES is expected below 3 (conservative).

Samples: one per TrackReport with ``defined`` true (inverse depth more than 3 sigma above
zero: skipped before that, since the reported position then sits at 1000 m along the ray)
and status PENDING or DYNAMIC. A STATIC report (the handover frame) carries the handover
triangulation, not the EKF; handovers are scored separately from the classification runs,
with the Handover's own position and covariance. Error e = position - true position in that
frame (map, m); NEES e' P^-1 e (3 dof). The average NEES at age a (frames since first sight)
is the mean over the n samples of that age, with the 95 % band chi2(3n) quantiles / n. Note
that the ``defined`` selection depends on the estimate itself, and samples of one track at
successive ages are correlated.

A run the filter raises on is left out of every statistic, listed under ``failures`` in the
report and in the summary (with its traceback on stderr), and makes the exit status 1.

Modules: ``shadow_runs`` (running the filter, the truth), ``shadow_classification``,
``shadow_consistency``, ``shadow_experiments`` (per-seed runs, the report); this one is the
command line.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from monoslam_shadow_node.core.shadow_classifier import STATIC_TESTS, ClassifierConfig
from slam_core.cli import console_main
from slam_core.files import write_json
from slam_core.progress import ProgressReporter
from slam_evaluation.evaluation_cli import add_tracking_noise_arguments, parse_seeds
from slam_evaluation.sequence_files import SequenceError, read_sequence
from slam_evaluation.shadow_experiments import (
    Collected,
    Settings,
    classify_seed,
    consistency_seed,
    figure_inputs,
    report,
)
from slam_evaluation.shadow_report import summary_text, write_figures
from slam_evaluation.shadow_runs import FilterRunError
from slam_evaluation.shadow_sequence import evaluate_sequence, sequence_summary
from slam_sim.core.dynamic_config import DynamicSceneConfig

QUICK_DURATION_S = 4.0


def _parse_alphas(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(part) for part in text.split(',') if part.strip())
    except ValueError as error:
        raise argparse.ArgumentTypeError(f'--alphas {text!r}: use e.g. 0.01,0.05,0.1') from error


def _arguments(argv: list[str] | None) -> Settings:
    parser = argparse.ArgumentParser(prog='shadow_evaluate', description=__doc__.splitlines()[0])
    parser.add_argument(
        '--seeds', type=parse_seeds, help='seeds, e.g. 0-9 (default, the acceptance seeds) or 1,4'
    )
    parser.add_argument(
        '--consistency-seeds',
        type=parse_seeds,
        help='seeds of the model-motion runs (default: --seeds)',
    )
    parser.add_argument(
        '--out',
        type=Path,
        default=Path('out/shadow_eval'),
        help='output directory (default out/shadow_eval)',
    )
    parser.add_argument('--duration-s', type=float, help='run length, s (default 20)')
    parser.add_argument(
        '--alpha',
        type=float,
        default=ClassifierConfig().alpha,
        help='classifier significance level (default %(default)s)',
    )
    parser.add_argument(
        '--alphas',
        type=_parse_alphas,
        help='alpha sweep, e.g. 0.01,0.05,0.1 (default; --alpha is added)',
    )
    parser.add_argument(
        '--focal-px',
        type=float,
        default=DynamicSceneConfig().focal_px,
        help='focal length, px (default %(default)s)',
    )
    parser.add_argument(
        '--window-frames',
        type=int,
        default=30,
        help="decision window and 'parallax allows' span (default 30)",
    )
    parser.add_argument(
        '--consistency-objects',
        type=int,
        default=12,
        help='model-motion objects per consistency run (default 12)',
    )
    parser.add_argument(
        '--unchecked-directions',
        type=int,
        default=ClassifierConfig().unchecked_directions,
        help='directions of motion the STATIC rule may leave unchecked: 0 (strict: no moving '
        'feature handed over, slow), 1 (default) or 2',
    )
    parser.add_argument(
        '--static-test',
        choices=STATIC_TESTS,
        default=ClassifierConfig().static_test,
        help='the STATIC tests: both, three_ray (the three-ray test alone) or all_view (the '
        'all-view score test alone); default %(default)s',
    )
    add_tracking_noise_arguments(parser)
    parser.add_argument(
        '--sequence',
        type=Path,
        default=None,
        metavar='DIR',
        help='run the filter over an on-disk sequence (known poses; see the README) instead '
        'of the simulated runs',
    )
    parser.add_argument(
        '--quick',
        action='store_true',
        help=f'smoke run: seed 0, {QUICK_DURATION_S:g} s, no alpha sweep',
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    seeds = args.seeds or ((0,) if args.quick else tuple(range(10)))
    if args.alphas is None:
        args.alphas = () if args.quick else (0.01, 0.05, 0.1)
    if args.window_frames < 1 or args.consistency_objects < 1:
        parser.error('--window-frames and --consistency-objects must be at least 1')
    duration = args.duration_s or (
        QUICK_DURATION_S if args.quick else DynamicSceneConfig().duration_s
    )
    try:
        settings = Settings(
            seeds,
            args.consistency_seeds or seeds,
            args.alpha,
            tuple(sorted({args.alpha, *args.alphas})),
            duration,
            args.focal_px,
            args.window_frames,
            args.consistency_objects,
            args.out,
            args.unchecked_directions,
            args.static_test,
            args.sequence,
            args.tracking_offset_px,
            args.tracking_jump_probability,
        )
        (
            settings.scene(),
            settings.shadow(args.alpha),
            [settings.shadow(a) for a in settings.alphas],
        )
    except ValueError as error:
        parser.error(str(error))
    return settings


@console_main('shadow_evaluate')
def main(argv: list[str] | None = None) -> int:
    """Run the evaluation; print the summary; write the JSON report and figures to --out.
    Exit status 1 if the filter raised on a run (listed in the report, left out of it)."""
    settings = _arguments(argv)
    if settings.sequence is not None:
        return _run_sequence(settings)
    started = time.perf_counter()
    total = len(settings.seeds) * len(settings.alphas) + len(settings.consistency_seeds)
    progress = ProgressReporter(total, label='shadow_evaluate', unit=' runs', period_s=0.0)
    collected, done = Collected(), 0
    for seed in settings.seeds:
        done += classify_seed(settings, seed, collected)
        progress.update(done)
    for seed in settings.consistency_seeds:
        done += consistency_seed(settings, seed, collected)
        progress.update(done)
    progress.finish()
    content = report(settings, collected, time.perf_counter() - started)
    figures = write_figures(settings.out, figure_inputs(settings, collected, content))
    content['figures'] = [path.name for path in figures]
    content['runtime']['wall_s'] = time.perf_counter() - started
    write_json(settings.out / 'shadow_eval.json', content)
    print(summary_text(content))  # noqa: T201
    print(f'wrote {settings.out / "shadow_eval.json"} and {len(figures)} figures')  # noqa: T201
    return 1 if collected.failures else 0


def _run_sequence(settings: Settings) -> int:
    """``--sequence``: the filter over an on-disk sequence (``shadow_sequence``)."""
    assert settings.sequence is not None
    try:
        sequence = read_sequence(settings.sequence)
    except SequenceError as error:
        print(f'shadow_evaluate: error: --sequence: {error}', file=sys.stderr)  # noqa: T201
        return 2
    try:
        config = settings.shadow(settings.alpha)
        if sequence.tracker is not None:
            config = dataclasses.replace(config, ekf=sequence.tracker.ekf(config.ekf))
        content = evaluate_sequence(sequence, config, str(settings.sequence))
    except FilterRunError as error:
        print(f'shadow_evaluate: the filter failed: {error}', file=sys.stderr)  # noqa: T201
        return 1
    write_json(settings.out / 'shadow_eval_sequence.json', content)
    print(sequence_summary(content))  # noqa: T201
    print(f'wrote {settings.out / "shadow_eval_sequence.json"}')  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
