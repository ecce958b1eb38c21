"""shadow_evaluate: confusion counting, NEES and 3-sigma statistics on inputs with known
answers, the sample selection on a tiny simulated run, and a --quick smoke run."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC
from monoslam_shadow_node.shadow_filter import processor as shadow_processor
from monoslam_shadow_node.shadow_filter.core.shadow_filter import (
    FrameInput,
    FrameResult,
    ShadowFilter,
)
from slam_core.files import jsonable
from slam_evaluation.evaluation_cli import parse_seeds
from slam_evaluation.shadow_classification import (
    Outcome,
    classification_rates,
    confusion_counts,
    latency_summary,
    status_timeline,
    track_outcomes,
)
from slam_evaluation.shadow_consistency import (
    ErrorSamples,
    average_nees_band,
    consistency_summary,
    error_samples,
    nees,
    nees_by_age,
    within_sigma,
)
from slam_evaluation.shadow_evaluate import main
from slam_evaluation.shadow_runs import FilterRecord, view_parallax_rad
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import simulate_dynamic_scene

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


def _outcome(track_id: int, moving: bool, status: int, frames: int = -1, **kw: object) -> Outcome:
    fields: dict[str, object] = {
        'motion': 'turning' if moving else 'static',
        'decision_parallax_rad': math.nan,
        'decision_baseline_m': math.nan,
        'window_parallax_rad': math.nan,
        'window_baseline_m': math.nan,
        'parallax_allows': False,
    }
    fields.update(kw)
    return Outcome(track_id, moving, status=status, frames_to_decide=frames, **fields)


def test_confusion_counts_every_truth_and_status_and_the_rates() -> None:
    outcomes = [
        _outcome(1, False, STATIC, 10),
        _outcome(2, False, STATIC, 12),
        _outcome(3, False, DYNAMIC, 20),
        _outcome(4, False, PENDING),
        _outcome(5, True, DYNAMIC, 8),
        _outcome(6, True, STATIC, 40, motion='stop_and_go'),
    ]
    table = confusion_counts(outcomes)
    assert table == {
        'static': {'STATIC': 2, 'DYNAMIC': 1, 'PENDING': 1},
        'moving': {'STATIC': 1, 'DYNAMIC': 1, 'PENDING': 0},
    }
    by_motion = confusion_counts(outcomes, by_motion=True)
    assert by_motion['stop_and_go'] == {'STATIC': 1, 'DYNAMIC': 0, 'PENDING': 0}
    rates = classification_rates(table)
    assert rates['static_called_dynamic_of_decided'] == pytest.approx(1 / 3)
    assert rates['static_called_dynamic_of_all'] == pytest.approx(1 / 4)
    assert rates['moving_called_static'] == 1
    assert rates['moving_called_dynamic_of_all'] == pytest.approx(1 / 2)


def test_confusion_keeps_a_status_the_core_does_not_name() -> None:
    table = confusion_counts([_outcome(1, False, 7, 3)])
    assert table['static'] == {'7': 1, 'STATIC': 0, 'DYNAMIC': 0, 'PENDING': 0}
    assert math.isnan(classification_rates(table)['static_called_dynamic_of_decided'])


def test_latency_counts_undecided_only_in_the_share_of_all() -> None:
    outcomes = [_outcome(i, False, STATIC, f) for i, f in enumerate([10, 30, 31, 50])]
    outcomes.append(_outcome(9, False, PENDING))
    summary = latency_summary(outcomes, window_frames=30)
    assert summary['decided'] == 4
    assert summary['median_frames'] == pytest.approx(30.5)
    assert summary['within_window_of_decided'] == pytest.approx(0.5)
    assert summary['within_window_of_all'] == pytest.approx(0.4)


def test_nees_of_known_errors_and_a_singular_covariance() -> None:
    square_root = np.array([[2.0, 0.0, 0.0], [1.0, 3.0, 0.0], [0.5, -1.0, 0.7]])
    whitened = np.array([1.0, -2.0, 0.5])
    errors = np.array([[1.0, 2.0, 2.0], square_root @ whitened, [1.0, 0.0, 0.0]])
    covariances = np.array(
        [np.diag([1.0, 4.0, 4.0]), square_root @ square_root.T, np.diag([1.0, 1.0, 0.0])]
    )
    values = nees(errors, covariances)
    assert values[0] == pytest.approx(3.0)
    assert values[1] == pytest.approx(float(whitened @ whitened))
    assert math.isnan(values[2])


def test_within_sigma_uses_each_axis_standard_deviation() -> None:
    errors = np.array([[2.9, 3.1, -3.0], [5.9, 0.0, -6.1]])
    covariances = np.array([np.eye(3), np.diag([4.0, 1.0, 4.0])])
    expected = [[True, False, True], [True, True, False]]
    np.testing.assert_array_equal(within_sigma(errors, covariances), expected)


def test_average_nees_band_is_the_chi2_of_the_summed_samples() -> None:
    low, high = average_nees_band(np.array([1, 100, 0]))
    assert low[0] == pytest.approx(0.2158, abs=1e-4)
    assert high[0] == pytest.approx(9.3484, abs=1e-4)
    assert low[1] == pytest.approx(chi2.ppf(0.025, 300) / 100)
    assert 2.4 < low[1] < 3.0 < high[1] < 3.7
    assert math.isnan(low[2]) and math.isnan(high[2])


def test_nees_by_age_averages_finite_values_per_age() -> None:
    ages = np.array([0, 0, 1, 2, 2, 2])
    values = np.array([1.0, 3.0, np.nan, 2.0, 4.0, 6.0])
    unique, means, counts = nees_by_age(ages, values)
    np.testing.assert_array_equal(unique, [0, 2])
    np.testing.assert_allclose(means, [2.0, 4.0])
    np.testing.assert_array_equal(counts, [2, 3])


def _samples(rng: np.random.Generator, scale: float) -> ErrorSamples:
    count = 6000
    factors = rng.normal(size=(count, 3, 3)) + 2.0 * np.eye(3)
    covariances = factors @ np.swapaxes(factors, 1, 2)
    errors = scale * (factors @ rng.normal(size=(count, 3, 1)))[:, :, 0]
    ages = np.repeat(np.arange(60), 100)
    return ErrorSamples(errors, covariances, ages, np.arange(count), ages)


def test_consistency_summary_accepts_errors_drawn_from_their_covariance() -> None:
    summary, curve = consistency_summary(_samples(np.random.default_rng(3), 1.0))
    assert summary['nees_mean'] == pytest.approx(3.0, abs=0.15)
    assert summary['fraction_nees_above_chi2_95'] == pytest.approx(0.05, abs=0.01)
    assert summary['within_3sigma']['pooled'] == pytest.approx(0.9973, abs=0.003)
    assert summary['by_age']['fraction_of_ages_inside_band_95'] >= 0.85
    assert len(curve['mean_nees']) == 60


def test_consistency_summary_flags_errors_twice_their_sigma() -> None:
    summary, _ = consistency_summary(_samples(np.random.default_rng(4), 2.0))
    assert summary['nees_mean'] == pytest.approx(12.0, rel=0.1)
    assert summary['within_3sigma']['pooled'] < 0.9
    assert summary['by_age']['fraction_of_ages_inside_band_95'] < 0.1


def test_track_means_test_the_nees_over_independent_tracks() -> None:
    good = _samples(np.random.default_rng(5), 1.0)
    tracks = np.repeat(np.arange(60), 100)  # 60 tracks of 100 samples
    good = dataclasses.replace(good, track_ids=tracks)
    summary, _ = consistency_summary(ErrorSamples.concatenate([good, good]))
    per_track = summary['nees_track_means']
    assert per_track['tracks'] == 120  # the same ids in two runs are different tracks
    assert summary['tracks'] == 120
    assert per_track['consistent'] and per_track['ci95'][0] < 3.0 < per_track['ci95'][1]
    bad = dataclasses.replace(_samples(np.random.default_rng(6), 1.3), track_ids=tracks)
    summary, _ = consistency_summary(bad)
    assert summary['nees_track_means']['consistent'] is False  # 1.3 sigma: mean 5


def test_view_parallax_is_the_angle_at_the_point() -> None:
    point = np.array([1.0, 1.0, 0.0])
    angle = view_parallax_rad(point, np.array([2.0, 1.0, 0.0]), np.array([1.0, 3.0, 0.0]))
    assert angle == pytest.approx(math.pi / 2)


def test_status_timeline_counts_a_status_from_its_decision_frame_on() -> None:
    ids = [np.array([1, 2]), np.array([1, 2, 3]), np.array([2, 3])]
    decided = {1: (1, STATIC), 2: (2, DYNAMIC)}
    counts = status_timeline(ids, decided)
    np.testing.assert_array_equal(counts, [[2, 0, 0], [2, 1, 0], [1, 0, 1]])


def test_parse_seeds() -> None:
    assert parse_seeds('0-3,7') == (0, 1, 2, 3, 7)
    assert parse_seeds('5') == (5,)
    with pytest.raises(ValueError, match='--seeds'):
        parse_seeds('a-b')
    with pytest.raises(ValueError, match='5-2 is reversed'):
        parse_seeds('0,5-2')


def _record(
    track_ids: list[int], frames: list[int], positions: np.ndarray, **kw: object
) -> FilterRecord:
    count = len(track_ids)
    fields: dict[str, object] = {
        'status': np.full(count, PENDING),
        'defined': np.ones(count, dtype=bool),
        'covariance': np.tile(np.eye(3), (count, 1, 1)),
        'decisions': {},
        'handovers': [],
        'redecided': 0,
        'runtime_s': 0.0,
    }
    fields.update(kw)
    return FilterRecord(np.array(track_ids), np.array(frames), position=positions, **fields)


def test_error_samples_take_defined_ekf_reports_of_the_asked_truth() -> None:
    config = DynamicSceneConfig(duration_s=1.0, static_points=30, objects=1)
    run = simulate_dynamic_scene(1, config)
    static_id = next(i for i, p in run.track_point.items() if not run.point_moving[p])
    moving_id = next(i for i, p in run.track_point.items() if run.point_moving[p])
    frame = 5
    assert static_id in run.frames[frame].track_ids and moving_id in run.frames[frame].track_ids
    truth = run.point_positions[frame, [run.track_point[i] for i in (static_id, moving_id)]]
    offset = np.array([0.1, -0.2, 0.3])
    record = _record(
        [static_id, static_id, static_id, moving_id],
        [frame, frame + 1, frame + 2, frame],
        np.vstack([truth[0] + offset, truth[0], truth[0], truth[1]]),
        status=np.array([PENDING, PENDING, STATIC, DYNAMIC]),
        defined=np.array([True, False, True, True]),
    )
    samples = error_samples(run, record, moving=False)
    np.testing.assert_allclose(samples.errors, [offset])
    assert samples.skipped_undefined == 1
    assert samples.ages.tolist() == [frame]  # the track is seen from frame 0
    moving = error_samples(run, record, moving=True)
    np.testing.assert_allclose(moving.errors, np.zeros((1, 3)), atol=1e-12)


def test_track_outcomes_apply_the_parallax_rule_on_true_geometry() -> None:
    config = DynamicSceneConfig(duration_s=1.5, static_points=30, objects=1)
    run = simulate_dynamic_scene(2, config)
    some_id = int(run.frames[0].track_ids[0])
    record = _record([], [], np.zeros((0, 3)))
    window = 10
    found = track_outcomes(run, record, window_frames=window, min_parallax_rad=math.radians(1.0))
    outcomes = {outcome.track_id: outcome for outcome in found}
    assert set(outcomes) == set(run.track_point)
    assert all(o.status == PENDING and o.frames_to_decide == -1 for o in outcomes.values())
    point = run.point_positions[0, run.track_point[some_id]]
    expected = view_parallax_rad(
        point, run.frames[0].camera_position, run.frames[window].camera_position
    )
    assert outcomes[some_id].window_parallax_rad == pytest.approx(expected)
    assert outcomes[some_id].parallax_allows == (expected >= math.radians(1.0))
    seen = [set(frame.track_ids.tolist()) for frame in run.frames]
    for track_id, outcome in outcomes.items():
        first = next(k for k, ids in enumerate(seen) if track_id in ids)
        still_seen = first + window < len(seen) and track_id in seen[first + window]
        assert math.isnan(outcome.window_parallax_rad) != still_seen


def test_jsonable_makes_strict_json() -> None:
    text = json.dumps(jsonable({'a': np.float64('nan'), 'b': (np.int64(2), Path('x'))}))
    assert json.loads(text) == {'a': None, 'b': [2, 'x']}


def test_quick_cli_writes_a_json_report_and_png_figures(tmp_path: Path) -> None:
    out = tmp_path / 'eval'
    assert (
        main(['--quick', '--duration-s', '3', '--unchecked-directions', '0', '--out', str(out)])
        == 0
    )

    def reject(constant: str) -> None:
        raise ValueError(f'non-strict JSON constant {constant}')

    content = json.loads((out / 'shadow_eval.json').read_text(), parse_constant=reject)
    assert content['config']['seeds'] == [0]
    assert content['config']['shadow']['classifier']['unchecked_directions'] == 0  # strict rule
    assert {'moving_first_seen_at_birth', 'static_handovers'} <= set(
        content['consistency']['totals']
    )
    assert content['consistency']['totals']['moving']['nees_track_means']['tracks'] >= 1
    confusion = content['classification']['totals']['confusion']
    assert (
        sum(sum(row.values()) for row in confusion.values())
        == (content['classification']['totals']['tracks'])
    )
    assert {'moving', 'static', 'static_classification_runs'} <= set(
        content['consistency']['totals']
    )
    assert 'shadow_classification.png' in content['figures']
    assert len(content['figures']) >= 5
    for name in content['figures']:
        assert (out / name).read_bytes()[:8] == PNG_MAGIC
    assert not list(out.glob('.*'))  # no temporary files left behind


def test_an_invalid_rule_is_refused_by_name(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(['--quick', '--unchecked-directions', '3'])
    assert stopped.value.code == 2
    assert 'unchecked_directions=3' in capsys.readouterr().err


def test_a_run_the_filter_raises_on_is_reported_and_fails_the_exit_status(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    class Failing(ShadowFilter):
        def process(self, frame: FrameInput) -> FrameResult:
            if self.frame_count == 7:
                raise np.linalg.LinAlgError('Singular matrix')
            return super().process(frame)

    monkeypatch.setattr(shadow_processor, 'ShadowFilter', Failing)  # run_filter's processor
    out = tmp_path / 'eval'
    assert main(['--quick', '--duration-s', '1', '--out', str(out)]) == 1
    content = json.loads((out / 'shadow_eval.json').read_text())
    assert [f['runs'] for f in content['failures']] == ['classification', 'consistency']
    assert 'frame 7: LinAlgError' in content['failures'][0]['error']
    assert content['classification']['totals']['tracks'] == 0
