"""monoslam_pipeline and monoslam_evaluate: the frames, the three variants on short simulated
runs, the alignment and NEES statistics on inputs with known answers, and the CLI."""

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

from monoslam_shadow_node.core.monoslam_types import MonoSlamConfig, MonoSlamFrame
from monoslam_shadow_node.shadow_processor import pose_gate_refusal
from slam_core.blas import single_threaded_blas
from slam_evaluation import monoslam_runs
from slam_evaluation.monoslam_evaluate import main
from slam_evaluation.monoslam_metrics import (
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
    parse_pose_gate,
    run_variant,
    simulation_frames,
    target_known_points,
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


def _config(gate: tuple[float, float] = (0.03, 0.01)) -> PipelineConfig:
    slam = MonoSlamConfig(known_points=target_known_points(TARGET))
    return PipelineConfig(slam=slam, shadow_max_pose_sigma=gate)


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
    run = simulate_dynamic_scene(1, DynamicSceneConfig(**{**vars(FEW_MOVERS), 'duration_s': 4.0}))
    frames = _frames(run, 1)
    record = run_variant('c', frames, camera_model(run), _config((math.inf, math.inf)))
    handed = {event.feature_id for event in record.handovers}
    assert len(record.handovers) == record.static_decisions >= 5  # measured 13
    assert all(event.refused is None for event in record.handovers)
    assert record.map_points and {p.source for p in record.map_points} == {'handover'}
    assert {p.id for p in record.map_points} <= handed
    assert record.shadow_frames == len(frames) and record.shadow_gated_frames == 0
    assert _ate(record, frames) < 0.15  # measured 0.07 m


def test_variant_c_skips_the_shadow_filter_above_the_pose_gate() -> None:
    run = simulate_dynamic_scene(1, FEW_MOVERS)
    frames = _frames(run, 1)
    record = run_variant('c', frames, camera_model(run), _config((1e-4, 1e-4)))
    assert record.shadow_frames == 0 and not record.handovers
    assert record.shadow_gated_frames + record.shadow_no_pose_frames == len(frames)
    assert record.shadow_gated_frames == int(record.tracked.sum())
    assert not record.map_points  # SLAM adds nothing on its own in handover mode


def test_variant_c_diagnostics_truth_poses_skip_the_gate_and_the_oracle_drops_movers() -> None:
    scene = DynamicSceneConfig(duration_s=3.0, static_points=80, objects=6, points_per_object=6)
    run = simulate_dynamic_scene(4, scene)
    frames = _frames(run, 4)
    gated = dataclasses.replace(_config((1e-4, 1e-4)), shadow_poses='truth')
    record = run_variant('c', frames, camera_model(run), gated)
    assert record.shadow_gated_frames == 0 and record.shadow_frames == int(record.tracked.sum())
    assert record.handovers  # the true poses let the Shadow filter decide despite the gate
    assert record.dynamic_in_map  # seed 4: a mover is called STATIC (measured 5)
    oracle = dataclasses.replace(gated, oracle_handovers=True)
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


# --- pose gate, alignment and statistics ----------------------------------------------------


def test_pose_gate_compares_the_largest_position_and_rotation_sigma() -> None:
    covariance = np.diag([0.02, 0.03, 0.01, 0.005, 0.01, 0.002]) ** 2
    assert pose_gate_refusal(covariance, (0.03, 0.01)) is None
    assert pose_gate_refusal(covariance, (0.029, 0.01)) is not None
    assert pose_gate_refusal(covariance, (0.03, 0.009)) is not None
    assert pose_gate_refusal(np.full((6, 6), np.nan), (math.inf, math.inf)) is not None
    assert parse_pose_gate('0.03, 0.01') == (0.03, 0.01)
    assert parse_pose_gate('inf') == (math.inf, math.inf)
    for text in ('0.03', '0,0.01', 'nan,1', 'a,b'):
        with pytest.raises(ValueError, match='shadow max pose sigma'):
            parse_pose_gate(text)
    with pytest.raises(ValueError, match='shadow_max_pose_sigma'):
        PipelineConfig(shadow_max_pose_sigma=(0.0, 0.01))


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
    assert main([*arguments, '--shadow-max-pose-sigma', 'inf', '--unchecked-directions', '0']) == 0
    content = _strict_json(out / 'monoslam_eval.json')
    assert content['config']['pipeline']['shadow_max_pose_sigma'] == [None, None]
    assert content['config']['pipeline']['shadow']['classifier']['unchecked_directions'] == 0
    variants = content['variants']
    assert set(variants) == {'a', 'c'}
    assert variants['c']['totals']['shadow']['frames_skipped_pose_gate'] == 0
    assert [p['name'] for p in content['acceptance']] == ['ATE(c)/ATE(a)']
    for name in content['figures']:
        assert (out / name).read_bytes().startswith(PNG_MAGIC)
    printed = capsys.readouterr().out
    assert 'ATE(c)/ATE(a)' in printed and ('PASS' in printed or 'FAIL' in printed)
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
        (['--shadow-max-pose-sigma', '0.03'], '--shadow-max-pose-sigma'),
        (['--shadow-max-pose-sigma', '-1,0.01'], '--shadow-max-pose-sigma'),
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
