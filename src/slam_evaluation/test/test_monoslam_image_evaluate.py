"""monoslam_image_evaluate: the SLAM frames built from rendered images against the renderer's
truth (static tracks follow their 3D points, moving ones do not; detected target corners),
a bag's frames against the rendered ones, a short run's report, the acceptance's tracking
rule, and the CLI's errors."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from slam_core.blas import single_threaded_blas
from slam_evaluation.monoslam_front_end import FrontEnd, moving_near
from slam_evaluation.monoslam_image_evaluate import REPORT_NAME, TABLE_NAME, main
from slam_evaluation.monoslam_image_report import acceptance, image_tracking, level_ratio
from slam_evaluation.monoslam_image_sources import ImageFrame, bag_source, rendered_source
from slam_evaluation.monoslam_pipeline import MeasurementFrame
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_render import DynamicRenderer
from slam_sim.dynamic_camera_bag import write_dynamic_camera_bag

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'
FIG5_SHORT = DynamicSceneConfig(duration_s=1.5, objects=8, points_per_object=8)
"""monoslam_evaluate's Fig. 5 scene, 45 frames."""
LATER_FRAMES = 10
"""Reprojections are compared this many frames after a track's first image."""


@pytest.fixture(scope='module', autouse=True)
def _one_blas_thread() -> None:
    single_threaded_blas()


def _finite(value: Any) -> bool:
    return isinstance(value, float) and bool(np.isfinite(value))


Built = tuple[list[ImageFrame], list[MeasurementFrame], FrontEnd]


@pytest.fixture(scope='module')
def built() -> Built:
    """Seed 0 of the short Fig. 5 scene, rendered and through the front end."""
    source = rendered_source(0, FIG5_SHORT)
    front_end = FrontEnd(source.camera, source.target)
    images = list(source.frames())
    return images, [front_end.frame(image) for image in images], front_end


def _reprojection_errors(images: list[ImageFrame], frames: list[MeasurementFrame]) -> Any:
    """Return the pixel errors of the tracks LATER_FRAMES or more after their first image
    against the projection of the 3D point the renderer hit there: of tracks flagged static,
    and of tracks flagged moving that started on a moving object's surface."""
    renderer = DynamicRenderer(FIG5_SHORT, 0)
    camera = FIG5_SHORT.camera()
    first: dict[int, tuple[int, Any, bool]] = {}
    static, moving = [], []
    for index, (image, frame) in enumerate(zip(images, frames, strict=True)):
        ids, pixels = frame.measurements.ids, frame.measurements.pixels
        new = np.array([int(i) not in first for i in ids], dtype=bool)
        depth_m, labels = renderer.probe(index, pixels[new])
        rays, _ = camera.unproject(pixels[new])
        points_m = np.c_[rays * depth_m[:, None], depth_m] @ image.rotation.T + image.centre_m
        for track, point, label in zip(ids[new].tolist(), points_m, labels, strict=True):
            first[track] = (index, point, bool(label >= 0))
        for track, pixel, flagged in zip(ids.tolist(), pixels, frame.moving, strict=True):
            start, point, on_object = first[track]
            if index - start < LATER_FRAMES:
                continue
            projected = camera.project((point - image.centre_m) @ image.rotation)[0]
            error = float(np.linalg.norm(projected - pixel))
            if not flagged:
                static.append(error)
            elif on_object:
                moving.append(error)
    return np.array(static), np.array(moving)


def test_static_tracks_follow_their_points_and_moving_ones_do_not(built: Built) -> None:
    images, frames, _ = built
    static, moving = _reprojection_errors(images, frames)
    assert len(static) > 1000 and len(moving) > 100
    assert np.median(static) < 0.6 and np.percentile(static, 95) < 2.0
    assert np.median(moving) > 5.0


def test_features_on_moving_labels_are_flagged_and_flags_persist(built: Built) -> None:
    images, frames, front_end = built
    flagged: set[int] = set()
    for image, frame in zip(images, frames, strict=True):
        ids, pixels = frame.measurements.ids, frame.measurements.pixels
        rounded = np.rint(pixels).astype(int)
        on_object = image.labels[rounded[:, 1], rounded[:, 0]] >= 0
        assert np.all(frame.moving[on_object])
        was_flagged = np.isin(ids, list(flagged))
        assert np.all(frame.moving[was_flagged])
        flagged.update(ids[frame.moving].tolist())
        np.testing.assert_array_equal(frame.true_centre, image.centre_m)
    stats = front_end.stats.summary()
    assert 0.02 < stats['moving_share'] < 0.5
    assert stats['moving_tracks'] == len(flagged)


def test_known_points_are_the_detected_target_corners(built: Built) -> None:
    images, frames, front_end = built
    detected = 0
    for image, frame in zip(images, frames, strict=True):
        keys, pixels = frame.measurements.known_keys, frame.measurements.known_pixels
        if len(keys) == 0:
            continue
        detected += 1
        np.testing.assert_array_equal(keys, [0, 1, 2, 3])
        assert image.target_corners_px is not None
        np.testing.assert_allclose(pixels, image.target_corners_px, atol=0.5)
    visible = sum(image.target_corners_px is not None for image in images)
    assert visible > 0.9 * len(images) and detected >= 0.9 * visible
    stats = front_end.stats.summary()
    assert stats['detection_rate'] == detected / visible
    assert stats['corner_rms_px'] < 0.3


def test_the_target_every_n_frames_is_searched_in_every_nth_image_only(built: Built) -> None:
    images, frames, _ = built
    source = rendered_source(0, FIG5_SHORT)
    front_end = FrontEnd(source.camera, source.target, target_every_n_frames=3)
    every_third = [front_end.frame(image) for image in images[:9]]
    for index, (frame, every) in enumerate(zip(frames[:9], every_third, strict=True)):
        expected = frame.measurements.known_pixels if index % 3 == 0 else np.zeros((0, 2))
        np.testing.assert_array_equal(every.measurements.known_pixels, expected)
    assert front_end.stats.target_visible == sum(
        images[k].target_corners_px is not None for k in (0, 3, 6)
    )


def test_moving_near_looks_at_a_square_window_clipped_at_the_border() -> None:
    labels = np.full((20, 30), -1, dtype=np.int16)
    labels[10, 20] = 2  # one pixel of moving object 2
    labels[0, 0] = -2  # nothing: not moving
    pixels = np.array([[20.4, 9.6], [23.0, 13.0], [24.0, 10.0], [0.0, 0.0], [29.9, 19.9]])
    np.testing.assert_array_equal(
        moving_near(labels, pixels, 3), [True, True, False, False, False]
    )
    np.testing.assert_array_equal(
        moving_near(labels, pixels, 0), [True, False, False, False, False]
    )


@pytest.fixture(scope='module')
def short_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, Path]:
    """The CLI on seed 0 of the Fig. 5 scene, 1.5 s."""
    out = tmp_path_factory.mktemp('monoslam_image_eval')
    status = main(['--out', str(out), '--seeds', '0', '--duration-s', '1.5'])
    return status, out


@pytest.mark.slow
def test_short_run_writes_the_report_table_and_figures(short_run: tuple[int, Path]) -> None:
    status, out = short_run
    assert status == 0
    content = json.loads((out / REPORT_NAME).read_text())
    (entry,) = content['per_seed']
    assert (entry['seed'], entry['source'], entry['frames']) == (0, 'rendered', 45)
    assert set(entry['image']) == {'a', 'b', 'c'} and set(entry['measurement']) == {'c'}
    for key in ('features_per_frame', 'moving_share', 'detection_rate', 'corner_rms_px'):
        assert _finite(entry['front_end'][key])
    image_c, measurement_c = entry['image']['c'], entry['measurement']['c']
    assert entry['ratio_c']['ate_m'] == pytest.approx(image_c['ate_m'] / measurement_c['ate_m'])
    assert content['ratio_c']['ratio_of_means'] == pytest.approx(entry['ratio_c']['ate_m'])
    ratio_point, tracked_point = content['acceptance']
    (tracking,) = content['tracking_c']['per_seed']
    assert (tracking['frames_tracked'], tracking['frames_tracked_a']) == (
        image_c['frames_tracked'],
        entry['image']['a']['frames_tracked'],
    )
    assert tracked_point['passed'] == tracking['kept']
    assert ratio_point['passed'] == (entry['ratio_c']['ate_m'] <= 1.5 and tracking['kept'])
    assert content['config']['sources'][0]['scene']['objects'] == 8
    for name in content['figures']:
        assert (out / name).read_bytes().startswith(PNG_MAGIC)
    assert len(content['figures']) == 2 and content['failures'] == []
    table = (out / TABLE_NAME).read_text().splitlines()
    assert table[0].startswith('| seed | a ATE') and table[3].startswith('| mean |')
    assert 'c/a frames' in table[0]
    assert any(line.startswith('tracked image (c)/(a) = ') for line in table)


def test_variant_a_from_images_tracks_the_camera(short_run: tuple[int, Path]) -> None:
    _, out = short_run
    (entry,) = json.loads((out / REPORT_NAME).read_text())['per_seed']
    run = entry['image']['a']
    assert run['frames_tracked'] == 45 and not run['diverged']
    assert 0.0 < run['ate_m'] < 0.05 and 0.0 < run['ate_sim3_m'] <= run['ate_m']


def _level_runs(tracked_c: int, lost_c: bool) -> dict[str, Any]:
    """A seed's report entry: image a tracks 100 frames at 0.02 m, image c ``tracked_c``
    frames at 0.01 m (lost or not), measurement c 100 frames at 0.01 m."""

    def run(ate_m: float, tracked: int, lost: bool = False) -> dict[str, Any]:
        lost_frames = [50] if lost else []
        return {
            'ate_m': ate_m,
            'frames_tracked': tracked,
            'lost_frames': lost_frames,
            'diverged': lost,
        }

    return {
        'seed': 0,
        'image': {'a': run(0.02, 100), 'c': run(0.01, tracked_c, lost_c)},
        'measurement': {'c': run(0.01, 100)},
    }


@pytest.mark.parametrize(
    ('tracked_c', 'lost_c', 'passed'), [(100, False, True), (94, False, False), (100, True, False)]
)
def test_image_c_fails_its_acceptance_when_it_does_not_keep_tracking(
    tracked_c: int, lost_c: bool, passed: bool
) -> None:
    per_seed = [_level_runs(tracked_c, lost_c)]
    ratio = level_ratio(per_seed, 'ate_m')
    assert ratio is not None and ratio['ratio_of_means'] == pytest.approx(1.0)
    points = acceptance(ratio, image_tracking(per_seed))
    assert [point['passed'] for point in points] == [passed, passed]


@pytest.fixture(scope='module')
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One second of seed 3 of the Fig. 5 scene as a dynamic_camera_sim bag."""
    path = tmp_path_factory.mktemp('bag') / 'run.mcap'
    config = DynamicSceneConfig(duration_s=1.0, objects=8, points_per_object=8)
    write_dynamic_camera_bag(3, path, config=config, single_file=True)
    return path


def test_a_bag_gives_the_rendered_frames(bag: Path) -> None:
    source = bag_source(bag)
    rendered = rendered_source(
        3, DynamicSceneConfig(duration_s=1.0, objects=8, points_per_object=8)
    )
    assert (source.seed, source.config, source.frame_count) == (3, rendered.config, 30)
    np.testing.assert_array_equal(source.camera.K, rendered.camera.K)
    np.testing.assert_allclose(source.target.corners_m, rendered.target.corners_m)
    count = 0
    for read, drawn in zip(source.frames(), rendered.frames(), strict=True):
        count += 1
        assert read.stamp_ns == drawn.stamp_ns
        np.testing.assert_array_equal(read.labels, drawn.labels)
        np.testing.assert_allclose(read.rotation, drawn.rotation, atol=1e-12)
        np.testing.assert_allclose(read.centre_m, drawn.centre_m)
        assert np.abs(read.image.astype(float) - drawn.image).mean() < 4.0  # JPEG
        if drawn.target_corners_px is None:
            assert read.target_corners_px is None
        else:
            assert read.target_corners_px is not None
            np.testing.assert_allclose(read.target_corners_px, drawn.target_corners_px)
    assert count == 30


def test_the_cli_evaluates_a_bag(bag: Path, tmp_path: Path) -> None:
    assert main(['--out', str(tmp_path), '--bag', str(bag)]) == 0
    content = json.loads((tmp_path / REPORT_NAME).read_text())
    (entry,) = content['per_seed']
    assert (entry['seed'], entry['source'], entry['frames']) == (3, str(bag), 30)
    assert content['config']['sources'][0]['scene']['duration_s'] == 1.0


def _cli_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI expecting a user error (exit status 2); return stderr."""
    status: object
    try:
        status = main(argv)
    except SystemExit as stop:
        status = stop.code
    assert status == 2
    return capsys.readouterr().err


@pytest.mark.parametrize(
    ('argv', 'named'),
    [
        (['--seeds', '5-2'], "--seeds '5-2'"),
        (['--seeds', 'one'], "--seeds 'one'"),
        (['--duration-s', '0'], '--duration-s 0'),
        (['--bag', 'some.mcap', '--seeds', '1'], '--bag: a bag brings its own seed'),
        (['--shadow-max-pose-sigma', '0.1,0.1'], '--shadow-max-pose-sigma'),  # removed
    ],
)
def test_bad_arguments_are_named(
    argv: list[str], named: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert named in _cli_error(['--out', str(tmp_path), *argv], capsys)


def test_a_missing_bag_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / 'nowhere.mcap'
    error = _cli_error(['--out', str(tmp_path), '--bag', str(missing)], capsys)
    assert str(missing) in error and 'no such file' in error


def test_a_corrupt_bag_is_named(
    bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    corrupt = tmp_path / 'corrupt.mcap'
    corrupt.write_bytes(bag.read_bytes()[: bag.stat().st_size // 3])
    error = _cli_error(['--out', str(tmp_path / 'out'), '--bag', str(corrupt)], capsys)
    assert str(corrupt) in error and 'corrupt' in error
    assert not (tmp_path / 'out' / REPORT_NAME).exists()
