"""monoslam_pipeline and monoslam_evaluate: the frames, the three variants on short simulated
runs, the alignment and NEES statistics and the acceptance on inputs with known answers, and
the CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig, MonoSlamFrame
from slam_core.blas import single_threaded_blas
from slam_evaluation import monoslam_runs
from slam_evaluation.monoslam_evaluate import main
from slam_evaluation.monoslam_loop import map_history, run_loop
from slam_evaluation.monoslam_metrics import (
    mover_revocations,
    nees_by_frame,
    nees_summary,
    pose_errors,
    rms,
    trajectory_metrics,
    umeyama_alignment,
)
from slam_evaluation.monoslam_pipeline import (
    ORACLE_REFUSAL,
    MeasurementFrame,
    PipelineConfig,
    PipelineError,
    VariantRecord,
    run_variant,
    simulation_frames,
    target_known_points,
)
from slam_evaluation.monoslam_report import (
    acceptance,
    mover_summary,
    ratio_summary,
    tracking_summary,
)
from slam_evaluation.shadow_runs import camera_model
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import DynamicSceneRun, simulate_dynamic_scene
from slam_sim.core.init_target import InitTarget, marker_board, target_pixels

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'
TARGET = InitTarget()
FEW_MOVERS = DynamicSceneConfig(duration_s=3.0, static_points=120, objects=2, points_per_object=4)


@pytest.fixture(scope='module', autouse=True)
def _one_blas_thread() -> None:
    single_threaded_blas()  # the small EKF matrices run ~10x slower on contended threads


def _frames(run: DynamicSceneRun, seed: int = 0) -> list[MeasurementFrame]:
    return simulation_frames(run, TARGET, rng=np.random.default_rng(seed))


def _config() -> PipelineConfig:
    slam = MonoSlamConfig(known_points=target_known_points(TARGET))
    return PipelineConfig(slam=slam)


def _ate(record: VariantRecord, frames: list[MeasurementFrame]) -> float:
    return rms(np.linalg.norm(pose_errors(record, frames)[:, :3], axis=1))


# --- frames ---------------------------------------------------------------------------------


def test_frames_carry_the_target_corners_as_known_points_and_the_truth() -> None:
    run = simulate_dynamic_scene(0, DynamicSceneConfig(duration_s=1.0, static_points=50))
    frames = _frames(run)
    assert target_known_points(TARGET) == {k: tuple(c) for k, c in enumerate(TARGET.corners_m)}
    seen = 0
    for frame, source in zip(frames, run.frames, strict=True):
        truth = target_pixels(TARGET, run.camera, source.camera_rotation, source.camera_position)
        known = frame.measurements
        if truth is None:
            assert len(known.known_keys) == 0
            continue
        seen += 1
        np.testing.assert_array_equal(known.known_keys, [0, 1, 2, 3])
        assert 0.0 < np.abs(known.known_pixels - truth).max() < 5.0 * run.config.pixel_noise_px
        np.testing.assert_array_equal(known.ids, source.track_ids)
        np.testing.assert_array_equal(frame.moving, run.point_moving[source.point_ids])
        np.testing.assert_array_equal(frame.true_centre, source.camera_position)
    assert seen == len(frames)  # the target stays in view (init_target's promise)


def test_board_frames_key_each_markers_corners_as_4j_plus_corner() -> None:
    run = simulate_dynamic_scene(0, DynamicSceneConfig(duration_s=0.5, static_points=50))
    board = marker_board(TARGET, 2, 2, 0.3, 0.05)
    known = target_known_points(board)
    assert sorted(known) == list(range(16))
    np.testing.assert_allclose(known[4 * 3 + 2], board[3].corners_m[2])
    for frame, source in zip(_frames_of(run, board), run.frames, strict=True):
        keys = frame.measurements.known_keys
        for j, marker in enumerate(board):
            truth = target_pixels(
                marker, run.camera, source.camera_rotation, source.camera_position
            )
            rows = np.flatnonzero(keys // 4 == j)
            if truth is None:
                assert len(rows) == 0
                continue
            np.testing.assert_array_equal(keys[rows], 4 * j + np.arange(4))
            error = frame.measurements.known_pixels[rows] - truth
            assert 0.0 < np.abs(error).max() < 5.0 * run.config.pixel_noise_px


def _frames_of(run: DynamicSceneRun, markers: tuple[InitTarget, ...]) -> list[MeasurementFrame]:
    return simulation_frames(run, markers, rng=np.random.default_rng(0))


# --- the variants ---------------------------------------------------------------------------


def test_variant_a_tracks_the_camera_on_static_features_only() -> None:
    run = simulate_dynamic_scene(1, FEW_MOVERS)
    frames = _frames(run, 1)
    record = run_variant('a', frames, camera_model(run), _config())
    truth = np.array([frame.true_centre for frame in frames])
    assert record.tracked.all() and not record.lost_frames
    assert _ate(record, frames) < 0.06  # measured 0.03 m
    assert rms(np.linalg.norm(truth - truth[0], axis=1)) > 0.5  # a pose never updated
    assert len(record.map_points) >= 15
    assert not record.dynamic_in_map
    assert not any(run.point_moving[run.track_point[p.id]] for p in record.map_points)


def test_variant_b_lets_moving_features_into_the_map() -> None:
    scene = DynamicSceneConfig(duration_s=3.0, static_points=60, objects=16, points_per_object=8)
    run = simulate_dynamic_scene(0, scene)
    record = run_variant('b', _frames(run), camera_model(run), _config())
    assert len(record.dynamic_in_map) >= 3  # measured 8
    assert all(run.point_moving[run.track_point[i]] for i in record.dynamic_in_map)
    assert {p.source for p in record.map_points} == {'new'}


def test_variant_c_adds_only_what_the_shadow_filter_hands_over() -> None:
    """The Shadow filter gets every frame SLAM tracks, with SLAM's pose covariance; without
    fill_undecided only its handovers enter the map."""
    run = simulate_dynamic_scene(1, DynamicSceneConfig(**{**vars(FEW_MOVERS), 'duration_s': 4.0}))
    frames = _frames(run, 1)
    config = _config()
    config = dataclasses.replace(
        config, slam=dataclasses.replace(config.slam, fill_undecided=False)
    )
    record = run_variant('c', frames, camera_model(run), config)
    handed = {event.feature_id for event in record.handovers}
    assert len(record.handovers) == record.static_decisions >= 5  # measured 13
    assert all(event.refused is None for event in record.handovers)
    assert record.map_points and {p.source for p in record.map_points} == {'handover'}
    assert {p.id for p in record.map_points} <= handed
    assert record.shadow_frames == len(frames) and record.shadow_refused_frames == 0
    assert record.shadow_no_pose_frames == 0
    assert _ate(record, frames) < 0.15  # measured 0.07 m


def test_variant_c_diagnostics_truth_poses_and_the_oracle_drops_movers() -> None:
    scene = DynamicSceneConfig(duration_s=3.0, static_points=80, objects=6, points_per_object=6)
    run = simulate_dynamic_scene(4, scene)
    frames = _frames(run, 4)
    truth = dataclasses.replace(_config(), shadow_poses='truth')
    record = run_variant('c', frames, camera_model(run), truth)
    assert record.shadow_frames == int(record.tracked.sum())
    assert record.handovers
    assert record.dynamic_in_map  # seed 4: a mover is called STATIC (measured 5)
    assert [i for _, i in record.mover_entries] == record.dynamic_in_map
    movers = mover_revocations(record, run, frames)
    for judged in (movers, movers['observable']):  # every stay is judged once per rule
        outcomes = ('in_time', 'late', 'missed', 'left_view', 'radial', 'removed_early',
                    'lost_with_map')  # fmt: skip
        assert sum(judged[k] for k in outcomes) == movers['entries'] == len(record.mover_entries)
        assert len(judged['latencies']) == judged['in_time'] + judged['late']
    revoked = [i for _, i, why in record.removals if why == 'revoked']
    assert movers['revoked'] == len(revoked)
    oracle = dataclasses.replace(truth, oracle_handovers=True)
    record = run_variant('c', frames, camera_model(run), oracle)
    moving = [event for event in record.handovers if event.moving]
    assert moving and all(event.refused == ORACLE_REFUSAL for event in moving)
    assert all(event.refused is None for event in record.handovers if not event.moving)
    assert not record.dynamic_in_map
    with pytest.raises(ValueError, match='shadow_poses'):
        PipelineConfig(shadow_poses='odometry')


def test_a_frame_a_filter_rejects_names_the_variant_and_frame() -> None:
    run = simulate_dynamic_scene(0, DynamicSceneConfig(duration_s=0.5, static_points=30))
    frames = _frames(run)
    frames[3] = frames[2]  # a stamp that does not advance
    with pytest.raises(PipelineError, match='variant b, frame 3'):
        run_variant('b', frames, camera_model(run), _config())
    with pytest.raises(ValueError, match="variant 'd'"):
        run_variant('d', frames, camera_model(run), _config())


# --- alignment and statistics ---------------------------------------------------------------


def test_umeyama_recovers_a_known_similarity() -> None:
    rng = np.random.default_rng(3)
    source = rng.normal(size=(20, 3))
    rotation = Rotation.from_rotvec([0.3, -1.1, 2.0]).as_matrix()
    target = 2.5 * source @ rotation.T + [1.0, -2.0, 0.5]
    similarity = umeyama_alignment(source, target)
    assert similarity.scale == pytest.approx(2.5)
    np.testing.assert_allclose(similarity.rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(similarity.translation, [1.0, -2.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(similarity.apply(source), target, atol=1e-9)
    mirrored = source * [1.0, 1.0, -1.0]  # no rotation maps it: the best one stays proper
    assert np.linalg.det(umeyama_alignment(source, mirrored).rotation) == pytest.approx(1.0)
    with pytest.raises(ValueError, match='N >= 3'):
        umeyama_alignment(source[:2], target[:2])


def _record(centres: np.ndarray, rotations: np.ndarray, lost: list[int]) -> VariantRecord:
    count = len(centres)
    return VariantRecord(
        'a', np.arange(count), ('tracking',) * count, centres, rotations,
        np.tile(np.eye(6), (count, 1, 1)), np.zeros(count, np.int64), [], [], lost, [], 0, 0,
        0, 0, 0, 0.0,
    )  # fmt: skip


def test_pose_errors_and_divergence_of_a_known_trajectory() -> None:
    times = np.linspace(0.0, 1.0, 30)
    truth = np.column_stack([times, np.sin(times), np.zeros_like(times)])
    rotation = np.eye(3)
    empty = MonoSlamFrame(0, np.zeros(0, np.int64), np.zeros((0, 2)))
    frames = [MeasurementFrame(empty, np.zeros(0, bool), rotation, centre) for centre in truth]
    turned = Rotation.from_rotvec([0.0, 0.0, 0.02]).as_matrix()
    offset = np.array([0.1, 0.0, 0.0])
    record = _record(3.0 * truth + offset, np.tile(turned, (30, 1, 1)), [])
    errors = pose_errors(record, frames)
    np.testing.assert_allclose(errors[:, 3:], np.tile([0.0, 0.0, 0.02], (30, 1)), atol=1e-12)
    metrics = trajectory_metrics(record, errors)
    assert metrics['ate_m'] == pytest.approx(rms(np.linalg.norm(2.0 * truth + offset, axis=1)))
    assert metrics['ate_sim3_m'] == pytest.approx(0.0, abs=1e-9)
    assert metrics['sim3_scale'] == pytest.approx(1.0 / 3.0)
    assert metrics['diverged'] and metrics['divergence'] == ['ATE > 1 m']
    lost = trajectory_metrics(_record(truth, np.tile(rotation, (30, 1, 1)), [7]), errors * 0)
    assert lost['diverged'] and lost['divergence'] == ['tracking lost 1x']


def _seed_metrics(seed: int, error_m: float, tracked: int, lost: int | None = None) -> Any:
    """A seed's metrics of a run over 100 frames that waits for its first 100 - ``tracked``
    frames, then is ``error_m`` off the truth (and reports tracking lost at frame ``lost``)."""
    count = 100
    truth = np.column_stack([np.linspace(0.0, 2.0, count), np.zeros(count), np.zeros(count)])
    empty = MonoSlamFrame(0, np.zeros(0, np.int64), np.zeros((0, 2)))
    frames = [MeasurementFrame(empty, np.zeros(0, bool), np.eye(3), c) for c in truth]
    centres = truth + np.array([error_m, 0.0, 0.0])
    centres[: count - tracked] = np.nan
    record = _record(centres, np.tile(np.eye(3), (count, 1, 1)), [] if lost is None else [lost])
    status = ('waiting',) * (count - tracked) + ('tracking',) * tracked
    record = dataclasses.replace(record, status=status)
    return {'seed': seed, **trajectory_metrics(record, pose_errors(record, frames))}


def _verdicts(c_runs: list[Any], a_runs: list[Any]) -> dict[str, Any]:
    ratios = {'c_over_a': ratio_summary(c_runs, a_runs, 'ate_m')}
    points = acceptance(ratios, tracking_summary(c_runs, a_runs))
    return {point['name']: point for point in points}


def test_ate_ratio_needs_the_mean_within_1_5_and_every_seed_within_2() -> None:
    a_runs = [_seed_metrics(seed, 0.02, 100) for seed in range(4)]
    good = [_seed_metrics(seed, 0.028, 100) for seed in range(4)]  # 1.4x on every seed
    assert _verdicts(good, a_runs)['ATE(c)/ATE(a)']['passed']
    one_bad = [*good[:3], _seed_metrics(3, 0.05, 100)]  # 2.5x on one seed, mean 1.68x
    point = _verdicts(one_bad, a_runs)['ATE(c)/ATE(a)']
    assert not point['passed'] and point['seeds_meeting'] == '3/4'
    spread = [_seed_metrics(s, e, 100) for s, e in enumerate((0.022, 0.022, 0.039, 0.039))]
    point = _verdicts(spread, a_runs)['ATE(c)/ATE(a)']  # every seed <= 2x, mean 1.53x
    assert not point['passed'] and point['seeds_meeting'] == '4/4'


def test_every_mover_in_the_map_must_be_revoked_in_time() -> None:
    def outcomes(in_time: int, late: int, left: int, radial: int, latencies: list[int]) -> Any:
        return {'in_time': in_time, 'late': late, 'missed': 0, 'left_view': left,
                'radial': radial, 'removed_early': 0, 'lost_with_map': 0,
                'latencies': latencies}  # fmt: skip

    per_seed = [
        {'seed': 0, 'movers': {**outcomes(2, 0, 1, 0, [4, 9]), 'entries': 3, 'revoked': 2,
                               'observable': outcomes(2, 0, 1, 0, [4, 9])}},
        {'seed': 1, 'movers': {**outcomes(0, 1, 0, 1, [22]), 'entries': 2, 'revoked': 1,
                               'observable': outcomes(0, 0, 0, 2, [])}},
    ]  # fmt: skip
    movers = mover_summary(per_seed)
    assert movers is not None
    assert (movers['entries'], movers['in_time'], movers['late'], movers['radial']) == (5, 2, 1, 1)
    assert movers['latency_median_frames'] == 9.0 and movers['latency_max_frames'] == 22
    assert movers['observable']['radial'] == 2 and movers['observable']['late'] == 0
    (point,) = acceptance({}, None, movers)
    assert point['name'] == 'movers revoked' and not point['passed']
    assert point['seeds_meeting'] == '1/2'


def test_acceptance_fails_c_tracking_too_few_frames_whatever_its_ate() -> None:
    a_runs = [_seed_metrics(seed, 0.02, 100) for seed in (0, 1)]
    short = [_seed_metrics(0, 0.01, 100), _seed_metrics(1, 0.01, 94)]  # seed 1: 94 % of (a)
    tracking = tracking_summary(short, a_runs)
    assert [(r['frames_tracked'], r['frames_tracked_a']) for r in tracking['per_seed']] == [
        (100, 100),
        (94, 100),
    ]
    assert tracking['min_share'] == pytest.approx(0.94)
    points = _verdicts(short, a_runs)
    ate = points['ATE(c)/ATE(a)']
    assert ate['value'] == pytest.approx(0.5)  # half of (a)'s ATE over the frames it kept ...
    assert not ate['passed'] and ate['seeds_meeting'] == '1/2'  # ... and still a FAIL
    assert not points['tracked (c)/(a)']['passed']
    lost = [_seed_metrics(0, 0.01, 100), _seed_metrics(1, 0.01, 100, lost=50)]
    assert not any(point['passed'] for point in _verdicts(lost, a_runs).values())
    failed_run = [_seed_metrics(0, 0.01, 100)]  # (c) did not run on seed 1
    assert not any(point['passed'] for point in _verdicts(failed_run, a_runs).values())
    kept = [_seed_metrics(0, 0.01, 100), _seed_metrics(1, 0.01, 95)]
    assert all(point['passed'] for point in _verdicts(kept, a_runs).values())


def test_nees_band_is_the_chi2_of_6n_over_n_per_frame() -> None:
    values = np.full((10, 3), 6.0)
    values[:4, 1] = np.nan  # frame 1: 6 seeds
    values[:, 2] = 30.0  # frame 2: far above the band
    curve = nees_by_frame(values)
    np.testing.assert_array_equal(curve['count'], [10, 6, 10])
    assert curve['low'][0] == pytest.approx(chi2.ppf(0.025, 60) / 10)
    assert curve['high'][1] == pytest.approx(chi2.ppf(0.975, 36) / 6)
    summary = nees_summary(values)
    assert summary['frames_in_band'] == pytest.approx(2 / 3)
    assert summary['nees_mean'] == pytest.approx((16 * 6.0 + 10 * 30.0) / 26)


# --- the command line -----------------------------------------------------------------------


def _strict_json(path: Path) -> dict[str, Any]:
    def reject(constant: str) -> None:
        raise ValueError(f'non-strict JSON constant {constant}')

    content: dict[str, Any] = json.loads(path.read_text(), parse_constant=reject)
    return content


def test_cli_writes_a_parsable_report_and_figures(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / 'eval'
    arguments = ['--out', str(out), '--seeds', '0', '--duration-s', '1.5', '--variants', 'a,c']
    assert main([*arguments, '--unchecked-directions', '0']) == 0
    content = _strict_json(out / 'monoslam_eval.json')
    assert 'shadow_max_pose_sigma' not in content['config']['pipeline']
    assert content['config']['pipeline']['shadow']['classifier']['unchecked_directions'] == 0
    variants = content['variants']
    assert set(variants) == {'a', 'c'}
    assert variants['c']['totals']['shadow']['frames_pose_not_finite'] == 0
    assert [p['name'] for p in content['acceptance']] == [
        'ATE(c)/ATE(a)',
        'tracked (c)/(a)',
        'movers revoked',
    ]
    (tracking,) = content['tracking_c']['per_seed']
    assert tracking['frames_tracked'] == variants['c']['per_seed'][0]['frames_tracked']
    assert tracking['frames_tracked_a'] == variants['a']['per_seed'][0]['frames_tracked']
    for name in content['figures']:
        assert (out / name).read_bytes().startswith(PNG_MAGIC)
    printed = capsys.readouterr().out
    assert 'ATE(c)/ATE(a)' in printed and ' met' in printed and 'PASS' not in printed
    assert 'tracked (c)/(a)' in printed and 'c/a frames' in printed and 'pose gate' not in printed
    assert 'DIAGNOSTIC' not in printed and 'one target' in printed


def test_cli_board_and_diagnostics_are_reported_and_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / 'eval'
    arguments = ['--out', str(out), '--seeds', '0', '--duration-s', '1.0', '--variants', 'a,c']
    diagnostics = ['--known-board', '2x3', '--shadow-poses', 'truth', '--oracle-handovers']
    assert main([*arguments, *diagnostics]) == 0
    config = _strict_json(out / 'monoslam_eval.json')['config']
    assert config['known_board'] == [2, 3] and len(config['known_markers']) == 6
    assert len(config['pipeline']['slam']['known_points']) == 24
    assert config['pipeline']['shadow_poses'] == 'truth' and config['pipeline']['oracle_handovers']
    printed = capsys.readouterr().out
    assert 'board 2x3' in printed
    assert 'DIAGNOSTIC BOUND' in printed and 'TRUE camera poses' in printed


@pytest.mark.parametrize(
    ('arguments', 'named'),
    [
        (['--variants', 'a,x'], '--variants'),
        (['--shadow-max-pose-sigma', '0.03,0.01'], '--shadow-max-pose-sigma'),  # removed
        (['--seeds', 'x'], '--seeds'),
        (['--duration-s', '0'], '--duration-s'),
        (['--unchecked-directions', '3'], '--unchecked-directions'),
        (['--known-board', '3x0'], '--known-board'),
        (['--known-board', 'big'], '--known-board'),
        (['--shadow-poses', 'odometry'], '--shadow-poses'),
    ],
)
def test_cli_rejects_bad_arguments_naming_them(
    arguments: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(arguments)
    assert stopped.value.code == 2
    assert named in capsys.readouterr().err


def test_a_run_a_filter_raises_on_is_reported_and_fails_the_exit_status(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def failing(variant: str, *args: object, **kwargs: object) -> VariantRecord:
        raise PipelineError(f'variant {variant}, frame 7: singular matrix')

    monkeypatch.setattr(monoslam_runs, 'run_variant', failing)
    out = tmp_path / 'eval'
    assert main(['--out', str(out), '--seeds', '0', '--duration-s', '0.5', '--variants', 'a']) == 1
    failures = _strict_json(out / 'monoslam_eval.json')['failures']
    assert failures == [
        {'seed': 0, 'variant': 'a', 'error': 'variant a, frame 7: singular matrix'}
    ]


def test_undecided_features_fill_the_map_but_never_those_found_moving() -> None:
    """fill_undecided (default): while handovers leave fewer than target_measured features
    measured, undecided ones fill the gap, next to the handovers, and the map keeps about
    target_measured features measured. (That a feature found DYNAMIC never fills the map is
    the processor's test, test_undecided_features_fill_the_map_except_those_found_moving.)"""
    scene = DynamicSceneConfig(duration_s=4.0, static_points=120, objects=6, points_per_object=6)
    run = simulate_dynamic_scene(2, scene)
    frames = _frames(run, 2)
    record = run_variant('c', frames, camera_model(run), _config())
    sources = {p.source for p in record.map_points}
    assert sources == {'new', 'handover'}
    assert record.tracked[1:].all() and not record.lost_frames
    assert record.dynamic_decisions >= 1
    # the target and the gap-filled features keep about target_measured measured
    assert np.median(record.measured[30:]) >= 0.8 * MonoSlamConfig().target_measured


@pytest.mark.slow
def test_the_map_survives_a_turn_away_and_is_remeasured_on_return() -> None:
    """The loop scene (monoslam_loop): a 90 deg turn away for 6 s and back; (c) with the
    defaults never loses tracking and re-measures most of its map on return."""
    settings = monoslam_runs.Settings((3,), 20.0, ('c',), Path('unused'))
    loop = run_loop(settings, 3, True, 'c')
    metrics = loop.metrics
    assert not metrics['lost']
    assert metrics['returned'] >= 10
    assert metrics['rematched'] >= 0.8 * metrics['returned']
    assert metrics['duplicates'] == 0
    assert metrics['closed']
    history = map_history(loop.record, loop.scene.rate_hz)
    assert history['rematched'][-1] >= metrics['rematched']
    assert np.all(history['searched'] <= history['state'])


def test_the_ate_curve_is_nan_where_no_run_has_a_pose_and_warns_nothing() -> None:
    import warnings

    from slam_evaluation.monoslam_report import rms_over_runs

    errors = np.array([[np.nan, 3.0, np.nan], [np.nan, 4.0, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        curve = rms_over_runs(errors)
    assert np.isnan(curve[0])
    assert curve[1:] == pytest.approx([math.sqrt(12.5), 1.0])
