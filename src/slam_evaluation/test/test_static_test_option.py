"""The Shadow filter's static test (``ClassifierConfig.static_test``) through the evaluators:
``--static-test`` reaches the classifier the runs use, bad values are refused by name, and a
run records the test in its report and summary."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from monoslam_shadow_node.shadow_filter.core.shadow_classifier import (
    STATIC_TESTS,
    ClassifierConfig,
)
from slam_evaluation import monoslam_evaluate, monoslam_runs, shadow_evaluate, shadow_experiments


def test_the_settings_default_to_the_classifier_default() -> None:
    default = ClassifierConfig().static_test
    assert default in STATIC_TESTS
    shadow = shadow_experiments.Settings((0,), (0,), 0.05, (0.05,), 3.0, 500.0, 30, 1, Path('x'))
    monoslam = monoslam_runs.Settings((0,), 1.0, ('c',), Path('x'))
    assert shadow.static_test == monoslam.static_test == default
    assert shadow_evaluate._arguments(['--quick']).shadow(0.05).classifier.static_test == default
    evaluate = monoslam_evaluate._arguments([])
    assert evaluate.pipeline(evaluate.markers()).shadow.classifier.static_test == default


@pytest.mark.parametrize('test', STATIC_TESTS)
def test_shadow_evaluate_passes_the_static_test_to_every_alpha(test: str) -> None:
    settings = shadow_evaluate._arguments(['--quick', '--alphas', '0.01', '--static-test', test])
    assert settings.static_test == test
    assert {settings.shadow(alpha).classifier.static_test for alpha in settings.alphas} == {test}


@pytest.mark.parametrize('test', STATIC_TESTS)
def test_monoslam_evaluate_passes_the_static_test_to_the_shadow_filter(test: str) -> None:
    settings = monoslam_evaluate._arguments(['--static-test', test, '--unchecked-directions', '0'])
    classifier = settings.pipeline(settings.markers()).shadow.classifier
    assert (classifier.static_test, classifier.unchecked_directions) == (test, 0)


@pytest.mark.parametrize('main', [shadow_evaluate.main, monoslam_evaluate.main])
def test_an_unknown_static_test_is_refused_by_name(
    main: object, capsys: pytest.CaptureFixture[str]
) -> None:
    assert callable(main)
    with pytest.raises(SystemExit) as stopped:
        main(['--static-test', 'four_ray'])
    assert stopped.value.code == 2
    error = capsys.readouterr().err
    assert '--static-test' in error and 'four_ray' in error


def test_a_quick_run_records_the_static_test(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / 'eval'
    arguments = ['--quick', '--duration-s', '3', '--static-test', 'three_ray', '--out', str(out)]
    assert shadow_evaluate.main(arguments) == 0
    content = json.loads((out / 'shadow_eval.json').read_text())
    assert content['config']['shadow']['classifier']['static_test'] == 'three_ray'
    assert 'static test three_ray' in capsys.readouterr().out


def test_a_short_monoslam_run_records_the_static_test(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / 'eval'
    arguments = ['--out', str(out), '--seeds', '0', '--duration-s', '1.0', '--variants', 'c']
    assert monoslam_evaluate.main([*arguments, '--static-test', 'all_view']) == 0
    content = json.loads((out / monoslam_evaluate.REPORT_NAME).read_text())
    assert content['config']['pipeline']['shadow']['classifier']['static_test'] == 'all_view'
    assert 'static test all_view' in capsys.readouterr().out
