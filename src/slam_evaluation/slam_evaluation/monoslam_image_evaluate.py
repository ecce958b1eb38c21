"""monoslam_image_evaluate: paper 001's Fig. 5 from rendered images, against the measurement
level (the full pipeline from images reaches (c) within 1.5x of its measurement-level
ATE).

    monoslam_image_evaluate --out out/monoslam_image_eval [--seeds 0-9] [--duration-s 20]
                            [--target-every-n-frames 1]
    monoslam_image_evaluate --out out/bag_eval --bag bags/dynamic_camera.mcap [more bags]
                            [--unchecked-directions 1]

Sources. Without ``--bag`` every seed renders monoslam_evaluate's Fig. 5 scene (its
``Settings.scene()``: 8 moving objects, drawn as textured spheres by
``slam_sim.core.dynamic_render``) frame by frame. Each ``--bag`` is one run written by
``dynamic_camera_sim``: its images, camera_info, true camera pose, labels, true target
corners and scene JSON (seed, scene config and target); every bag's topics, scene and first
camera_info are read before the work starts.

Front end (``FrontEnd``, the same for every variant): the feature tracker
(``core.feature_tracker``, the node's defaults, no predictions: one set of tracks feeds all
variants) and the marker detector (``marker_detector.core.detection``, the node's defaults,
only the target's id and side; with ``--target-every-n-frames`` n only on every n-th
image, as the node's detect_every_n_frames) on each image give ``MonoSlamFrame``: track ids
with raw pixels, and the known points 0-3 (the detected corners, TL TR BR BL as
``target_known_points``) when the target is detected. Truth: the camera pose of the image,
and per feature whether it is on a moving object: a feature is moving if a label within
``MOVING_RADIUS_PX`` pixels (a square window about its rounded pixel) is a moving object, so
that features on object silhouettes (corners made by an object and what lies behind it)
count as moving; once moving, a track stays moving (a static track that an object passes over
is dragged along or lost). Pixels labelled 'nothing' (no surface: only beyond the lens
model's fold, never inside the closed room in practice) count as not moving; how many
features sit on one is reported.

Runs per seed: variants a, b and c (``monoslam_pipeline.run_variant``) on the image-level
frames, and variant c on the measurement-level frames of the same seed, scene config and
target (``simulation_frames``, target noise from ``default_rng(1000 + seed)`` as
monoslam_evaluate). Metrics are monoslam_evaluate's (ATE raw and sim(3)-aligned, divergence);
the ratio is image c / measurement c per seed, and the acceptance is the ratio of the means
over seeds (raw ATE) <= ``IMAGE_OVER_MEASUREMENT_MAX`` with image c keeping tracking on every
seed: never lost, and at least 95 % of the frames image a tracks (``tracked image (c)/(a)``,
also a point of its own; per seed in the table's ``c/a frames``). Front-end figures: features per
frame, the share of features (and of tracks) on moving objects, the target detection rate
(frames detected among those in which the target is fully visible and unoccluded) and the
detected corners' error against the true ones (px).

Writes ``monoslam_image_eval.json``, the table as ``monoslam_image_eval.md`` and PNG figures
(top views of the trajectories, image and measurement level; position error over time) into
``--out`` (atomically), prints the table, and logs progress on stderr (images through the
front end, with rate and ETA: rendering, tracking and detection take most of the time; the
four filter runs follow each seed's images) and a line per seed. A run a filter raises on is
listed under ``failures`` and makes the exit status 1.

Modules: ``monoslam_image_sources``, ``monoslam_front_end``, ``monoslam_image_runs``,
``monoslam_image_report`` (with the table), ``monoslam_image_figures``; this one is the
command line.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from slam_core.blas import single_threaded_blas
from slam_core.cli import console_main
from slam_core.errors import BagError
from slam_core.files import write_atomically, write_json
from slam_core.progress import ProgressReporter
from slam_evaluation.evaluation_cli import parse_seeds

if TYPE_CHECKING:
    from slam_evaluation.monoslam_image_runs import Settings

PROG = 'monoslam_image_evaluate'

REPORT_NAME = 'monoslam_image_eval.json'
TABLE_NAME = 'monoslam_image_eval.md'


# --- command line ---------------------------------------------------------------------------


def _arguments(argv: list[str] | None) -> Settings:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument(
        '--out',
        type=Path,
        default=Path('out/monoslam_image_eval'),
        help='output directory (default out/monoslam_image_eval)',
    )
    parser.add_argument('--seeds', help='seeds to render, e.g. 0-9 (default) or 1,4')
    parser.add_argument('--duration-s', type=float, help='rendered run length, s (default 20)')
    parser.add_argument(
        '--bag',
        type=Path,
        nargs='+',
        action='extend',
        default=[],
        help='dynamic_camera_sim bags to evaluate instead of rendering (one run each)',
    )
    parser.add_argument(
        '--unchecked-directions',
        type=int,
        default=1,
        choices=(0, 1, 2),
        help="the Shadow filter's STATIC rule as monoslam_evaluate (default 1)",
    )
    parser.add_argument(
        '--target-every-n-frames',
        type=int,
        default=1,
        help="search the target in every n-th image only (marker_detector's "
        'detect_every_n_frames; default 1)',
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    # the pipeline (OpenCV, the renderer, the filters): imported once --help is out of the way
    from slam_evaluation import monoslam_runs
    from slam_evaluation.monoslam_image_runs import Settings
    from slam_evaluation.monoslam_image_sources import bag_source, rendered_source
    from slam_evaluation.monoslam_pipeline import VARIANTS

    if args.target_every_n_frames < 1:
        parser.error(f'--target-every-n-frames {args.target_every_n_frames}: must be >= 1')
    if args.bag and (args.seeds is not None or args.duration_s is not None):
        parser.error('--bag: a bag brings its own seed and duration; drop --seeds/--duration-s')
    try:
        seeds = parse_seeds(args.seeds or '0-9')
    except ValueError as error:
        parser.error(str(error))
    duration_s = args.duration_s if args.duration_s is not None else 20.0
    evaluation = monoslam_runs.Settings(
        seeds, duration_s, VARIANTS, args.out, args.unchecked_directions
    )
    try:
        scene = evaluation.scene()
    except ValueError as error:
        parser.error(f'--duration-s {duration_s:g}: {error}')
    sources = [rendered_source(seed, scene) for seed in seeds]
    if args.bag:
        missing = [str(path) for path in args.bag if not path.exists()]
        if missing:
            parser.error(f'--bag: {", ".join(missing)}: no such file or directory')
        try:
            sources = [bag_source(path) for path in args.bag]
        except BagError as error:
            parser.error(f'--bag: {error}')
    return Settings(tuple(sources), evaluation, args.out, args.target_every_n_frames)


@console_main(PROG)
def main(argv: list[str] | None = None) -> int:
    """Run the evaluation; print the table; write the JSON report, the table and the figures
    to --out. Exit status 1 if a filter raised on a run (listed in the report)."""
    settings = _arguments(argv)
    from slam_evaluation.monoslam_image_figures import write_figures
    from slam_evaluation.monoslam_image_report import report, table_text
    from slam_evaluation.monoslam_image_runs import evaluate_source, seed_line

    single_threaded_blas()
    started = time.perf_counter()
    total = sum(source.frame_count for source in settings.sources)
    progress = ProgressReporter(total, label=PROG, unit=' images')
    results, done = [], 0

    def advance() -> None:
        nonlocal done
        done += 1
        progress.update(done)

    for source in settings.sources:
        results.append(evaluate_source(source, settings, advance))
        print(f'{PROG}: {seed_line(results[-1])}', file=sys.stderr)  # noqa: T201
    progress.finish()
    content = report(settings, results, time.perf_counter() - started)
    figures = write_figures(settings.out, results, content['curves']['rate_hz'])
    content['figures'] = [path.name for path in figures]
    content['runtime']['wall_s'] = time.perf_counter() - started
    write_json(settings.out / REPORT_NAME, content)
    table = table_text(content)
    write_atomically(settings.out / TABLE_NAME, table + '\n')
    print(table)  # noqa: T201
    print(f'wrote {settings.out / REPORT_NAME}, {TABLE_NAME} and {len(figures)} figures')  # noqa: T201
    return 1 if content['failures'] else 0


if __name__ == '__main__':
    sys.exit(main())
