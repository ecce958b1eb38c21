"""On-disk sequences (``sequence_files``): the committed fixture is the simulator's run written
by ``write_sequence``, reads back exactly, runs through the pipeline like the simulator's own
frames, and bad files are named with their line."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, STATIC
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig
from monoslam_shadow_node.shadow_filter.core.shadow_filter import ShadowConfig
from slam_evaluation import monoslam_evaluate, shadow_evaluate
from slam_evaluation.monoslam_pipeline import (
    PipelineConfig,
    run_variant,
    simulation_frames,
)
from slam_evaluation.sequence_files import (
    KNOWN_ID_BASE,
    Sequence,
    SequenceError,
    Tracker,
    measurement_frames,
    read_sequence,
    simulated_sequence,
    write_sequence,
)
from slam_evaluation.shadow_runs import run_filter
from slam_evaluation.shadow_sequence import evaluate_sequence
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import simulate_dynamic_scene
from slam_sim.core.init_target import InitTarget

FIXTURE = Path(__file__).parent / 'data' / 'sim_sequence'
FIXTURE_SCENE = DynamicSceneConfig(
    duration_s=1.0, static_points=60, objects=2, points_per_object=4
)  # fmt: skip
FIXTURE_SEED = 3


def fixture_sequence() -> Sequence:
    """The fixture's content, from the simulator (regenerate it with ``write_sequence``)."""
    run = simulate_dynamic_scene(FIXTURE_SEED, FIXTURE_SCENE)
    return simulated_sequence(run, InitTarget(), np.random.default_rng(1000 + FIXTURE_SEED))


def test_the_fixture_is_the_simulated_run_and_reads_back() -> None:
    made = fixture_sequence()
    read = read_sequence(FIXTURE)
    assert read.camera == made.camera
    np.testing.assert_array_equal(read.stamps_ns, made.stamps_ns)
    np.testing.assert_allclose(read.centres, made.centres, atol=1e-9)
    np.testing.assert_allclose(read.rotations, made.rotations, atol=1e-8)
    np.testing.assert_array_equal(read.frame, made.frame)
    np.testing.assert_array_equal(read.ids, made.ids)
    np.testing.assert_allclose(read.pixels, made.pixels, atol=1e-4)  # written to 1e-4 px
    assert read.labels == made.labels and any(read.labels.values())
    assert read.known_points is not None and made.known_points is not None
    assert sorted(read.known_points) == [KNOWN_ID_BASE + k for k in range(4)]
    for key, point in made.known_points.items():
        np.testing.assert_allclose(read.known_points[key], point, atol=1e-6)


def test_a_sequence_runs_like_the_simulators_frames(tmp_path: Path) -> None:
    run = simulate_dynamic_scene(FIXTURE_SEED, FIXTURE_SCENE)
    sequence = read_sequence(FIXTURE)
    assert sequence.known_points is not None
    frames = measurement_frames(sequence)
    direct = simulation_frames(run, InitTarget(), rng=np.random.default_rng(1000 + FIXTURE_SEED))
    assert len(frames) == len(direct)
    for mine, theirs in zip(frames, direct, strict=True):
        np.testing.assert_array_equal(mine.measurements.ids, theirs.measurements.ids)
        np.testing.assert_array_equal(mine.moving, theirs.moving)
        assert len(mine.measurements.known_keys) == len(theirs.measurements.known_keys)
    known = {k: tuple(p) for k, p in sequence.known_points.items()}
    config = PipelineConfig(slam=MonoSlamConfig(known_points=known))
    record = run_variant('c', frames, sequence.camera, config)
    assert record.tracked.all() and not record.lost_frames
    assert record.shadow_frames == len(frames)
    errors = np.linalg.norm(record.centres - sequence.centres, axis=1)
    assert np.sqrt(np.mean(errors**2)) < 0.3  # the target alone over 1 s (measured 0.07 m)


def test_an_id_may_disappear_and_reappear(tmp_path: Path) -> None:
    sequence = read_sequence(FIXTURE)
    feature = int(sequence.ids[sequence.ids < KNOWN_ID_BASE][0])
    gap = (sequence.ids == feature) & (sequence.frame >= 10) & (sequence.frame < 20)
    keep = ~gap
    cut = Sequence(
        sequence.camera, sequence.stamps_ns, sequence.centres, sequence.rotations,
        sequence.frame[keep], sequence.ids[keep], sequence.pixels[keep], sequence.labels,
        sequence.known_points,
    )  # fmt: skip
    write_sequence(tmp_path / 'cut', cut)
    again = read_sequence(tmp_path / 'cut')
    frames_seen = np.unique(again.frame[again.ids == feature])
    assert (
        frames_seen.min() < 10
        and frames_seen.max() >= 20
        and not np.any((frames_seen >= 10) & (frames_seen < 20))
    )
    known = {k: tuple(p) for k, p in (again.known_points or {}).items()}
    record = run_variant(
        'c', measurement_frames(again), again.camera,
        PipelineConfig(slam=MonoSlamConfig(known_points=known)),
    )  # fmt: skip
    assert record.tracked.all()


@pytest.mark.parametrize(
    ('file', 'edit', 'message'),
    [
        ('camera.yaml', None, 'camera.yaml: missing'),
        ('camera.yaml', 'width: 640\n', 'camera.yaml: needs the fields'),
        ('poses.txt', '1.0 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n', 'poses.txt:2: stamp does not'),
        ('poses.txt', '1.0 0 0 0 0 0 0 2\n', 'poses.txt:1: quaternion norm 2.000000'),
        ('poses.txt', '1.0 0 0 0\n', 'poses.txt:1: expected "stamp_s x y z qx qy qz qw"'),
        ('tracks.csv', 'frame,id,x,y\n', 'tracks.csv:1: the header must be frame,id,u,v'),
        ('tracks.csv', 'frame,id,u,v\n0,1,2.0,nan\n', 'tracks.csv:2: expected 4 numbers'),
        ('tracks.csv', 'frame,id,u,v\n999,1,2.0,3.0\n', 'tracks.csv:2: frame 999 is not in'),
        ('tracks.csv', 'frame,id,u,v\n0,1.5,2.0,3.0\n', 'tracks.csv:2: frame, id must be'),
        ('tracks.csv', 'frame,id,u,v\n0,1,2,3\n0,1,4,5\n', 'an id is seen twice in one frame'),
        ('labels.csv', 'id,moving\n4,2\n', 'labels.csv:2: moving must be 0 or 1'),
        ('tracker.yaml', 'offset_px: 2\n', 'tracker.yaml: fields may be pixel_sigma_px'),
        ('tracker.yaml', 'tracking_offset_px: -1\n', 'tracker.yaml: tracking_offset_px=-1'),
    ],
)
def test_bad_files_are_named_with_their_line(
    tmp_path: Path, file: str, edit: str | None, message: str
) -> None:
    directory = tmp_path / 'sequence'
    shutil.copytree(FIXTURE, directory)
    if edit is None:
        (directory / file).unlink()
    else:
        (directory / file).write_text(edit, encoding='utf-8')
    with pytest.raises(SequenceError, match=message.replace('(', r'\(')):
        read_sequence(directory)


def test_monoslam_evaluate_runs_a_sequence(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / 'eval'
    assert monoslam_evaluate.main(['--sequence', str(FIXTURE), '--out', str(out)]) == 0
    printed = capsys.readouterr().out
    assert f'sequence {FIXTURE}' in printed and 'tracked (c)/(a)' in printed
    content = json.loads((out / 'monoslam_eval.json').read_text())
    assert content['config']['sequence'] == str(FIXTURE)
    runs = {v: data['per_seed'] for v, data in content['variants'].items()}
    assert set(runs) == {'a', 'b', 'c'} and all(len(r) == 1 for r in runs.values())
    assert runs['c'][0]['frames_tracked'] == 30 and runs['c'][0]['shadow']['frames_processed']
    unlabelled = tmp_path / 'unlabelled'
    shutil.copytree(FIXTURE, unlabelled)
    (unlabelled / 'labels.csv').unlink()
    assert monoslam_evaluate.main(['--sequence', str(unlabelled), '--out', str(out)]) == 2
    assert 'variant a needs labels.csv' in capsys.readouterr().err
    arguments = ['--sequence', str(unlabelled), '--variants', 'b,c', '--out', str(out)]
    assert monoslam_evaluate.main(arguments) == 0
    assert monoslam_evaluate.main(['--sequence', str(tmp_path / 'none'), '--out', str(out)]) == 2
    assert 'not a directory' in capsys.readouterr().err


def test_shadow_evaluate_runs_a_sequence_like_the_simulated_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = simulate_dynamic_scene(FIXTURE_SEED, FIXTURE_SCENE)
    record = run_filter(run, ShadowConfig())
    content = evaluate_sequence(read_sequence(FIXTURE), ShadowConfig(), 'fixture')
    statuses = [d.status for _, d in record.decisions.values()]
    assert content['decided'] == {
        'STATIC': statuses.count(STATIC),
        'DYNAMIC': statuses.count(DYNAMIC),
    }
    assert content['handovers'] == len(record.handovers) > 0
    assert content['confusion']['moving']['DYNAMIC'] > 0
    out = tmp_path / 'shadow'
    assert shadow_evaluate.main(['--sequence', str(FIXTURE), '--out', str(out)]) == 0
    assert 'truth x final status' in capsys.readouterr().out
    assert json.loads((out / 'shadow_eval_sequence.json').read_text())['frames'] == 30
    assert shadow_evaluate.main(['--sequence', str(tmp_path / 'none'), '--out', str(out)]) == 2


def test_a_declared_tracker_reads_back_and_reaches_both_filters(tmp_path: Path) -> None:
    """``tracker.yaml``: the tracker's noise, read back and given to SLAM (the whole
    per-sighting variance) and to the Shadow filter (the offsets' model)."""
    sequence = read_sequence(FIXTURE)
    assert sequence.tracker is None
    declared = Tracker(pixel_sigma_px=0.8, tracking_offset_px=2.0, tracking_offset_time_s=0.6)
    directory = tmp_path / 'tracked'
    write_sequence(directory, dataclasses.replace(sequence, tracker=declared))
    assert read_sequence(directory).tracker == declared
    config = declared.declared(PipelineConfig(slam=MonoSlamConfig()))
    assert config.slam.pixel_sigma_px == 0.8 and config.slam.tracking_offset_px == 2.0
    assert config.slam.feature_sigma_px == pytest.approx((0.8**2 + 2.0**2) ** 0.5)
    noise = config.shadow.ekf.tracking_noise
    assert (noise.offset_px, noise.offset_time_s) == (2.0, 0.6)
    assert config.shadow.ekf.pixel_sigma_px == 0.8
