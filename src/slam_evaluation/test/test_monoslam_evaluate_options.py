"""monoslam_evaluate's options for issue 43: --undeclared (the simulated tracking noise is
not told to the filters), --undecided-probation (fills wait on probation) and --first-order
(MonoSLAM without its second-order inverse-depth term)."""

from __future__ import annotations

from pathlib import Path

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
