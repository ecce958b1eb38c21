"""monoslam_evaluate's options: --undeclared (the simulated tracking noise is
not told to the filters), --undecided-probation (fills wait on probation) and --first-order
(MonoSLAM without its second-order inverse-depth term) and --new-probation ((a)'s new
features wait on probation until linear; (b) stays classic)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam_evaluation.monoslam_evaluate import _arguments


def test_undeclared_noise_leaves_the_filters_white_and_probation_reaches_slam() -> None:
    common = ['--tracking-offset-px', '2', '--tracking-jump-probability', '0.02']
    declared = _arguments([*common, '--out', 'unused'])
    undeclared = _arguments([*common, '--undeclared', '--undecided-probation'])
    markers = declared.markers()
    told, untold = declared.pipeline(markers), undeclared.pipeline(markers)
    assert told.slam.tracking_offset_px > 0.0 and untold.slam.tracking_offset_px == 0.0
    assert untold.shadow.ekf.tracking_noise.white
    assert undeclared.scene().tracking_offset_px == 2.0  # the simulation still has them
    assert untold.slam.undecided_probation and not told.slam.undecided_probation
    assert declared.out == Path('unused')


def test_first_order_reaches_slam() -> None:
    default, first = _arguments([]), _arguments(['--first-order'])
    assert default.pipeline(default.markers()).slam.second_order
    assert not first.pipeline(first.markers()).slam.second_order


def test_new_probation_reaches_slam_for_a_and_not_for_b() -> None:
    from slam_evaluation.monoslam_pipeline import PipelineConfig, run_variant, simulation_frames
    from slam_evaluation.shadow_runs import camera_model
    from slam_sim.core.dynamic_scene import simulate_dynamic_scene

    default, waits = _arguments([]), _arguments(['--new-probation', '--duration-s', '0.2'])
    assert not default.pipeline(default.markers()).slam.new_probation
    markers = waits.markers()
    config = waits.pipeline(markers)
    assert config.slam.new_probation
    run = simulate_dynamic_scene(0, waits.scene())
    frames = simulation_frames(run, markers, rng=np.random.default_rng(0))
    # (b), the paper's baseline, runs classic MonoSLAM whatever the flag
    seen: list[bool] = []
    pipeline = PipelineConfig(slam=config.slam, shadow=config.shadow)
    for variant in ('a', 'b'):
        attach = lambda slam: seen.append(slam.config.new_probation)  # noqa: E731
        run_variant(variant, frames, camera_model(run), pipeline, attach=attach)
    assert seen == [True, False]
