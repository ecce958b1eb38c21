"""monoslam_loop_evaluate's command line: the report, the acceptance and the plots, on one
short loop; bad arguments are refused naming the option."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from slam_evaluation.monoslam_loop_evaluate import MIN_REMATCHED_IMAGES, acceptance, main

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


def test_one_loop_writes_the_report_and_the_plots(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / 'loop'
    status = main(['--out', str(out), '--seeds', '1', '--variants', 'a', '--movers', 'without'])
    assert status == 0
    content = json.loads((out / 'monoslam_loop.json').read_text())
    group = content['groups']['a/without']
    run = group['runs'][0]
    assert run['seed'] == 1 and not run['lost'] and run['returned'] >= 10
    assert run['rematched'] >= 0.8 * run['returned'] and run['closed']
    assert group['acceptance']['points']['never_lost']['pass']
    for name in ('loop_map_a_without.png', 'loop_error_a_without.png'):
        assert (out / name).read_bytes().startswith(PNG_MAGIC)
    printed = capsys.readouterr().out
    assert 're-matched' in printed and ' met' in printed and 'PASS' not in printed


def test_the_acceptance_fails_a_lost_run_and_a_duplicate_map() -> None:
    good = {'returned': 10, 'rematched': 9, 'duplicate_share': 0.0, 'closed': True,
            'lost': False}  # fmt: skip
    assert all(point['pass'] for point in acceptance([good])['points'].values())
    lost = {**good, 'lost': True}
    assert not acceptance([good, lost])['points']['never_lost']['pass']
    duplicated = {**good, 'duplicate_share': 0.05}
    assert not acceptance([duplicated])['points']['duplicates']['pass']
    few = {**good, 'rematched': 7}
    assert not acceptance([few])['points']['rematched']['pass']
    # from images the target is 60 %: 7 of 10 pass it
    assert acceptance([few], MIN_REMATCHED_IMAGES)['points']['rematched']['pass']
    assert not acceptance([{**good, 'rematched': 5}], MIN_REMATCHED_IMAGES)['points']['rematched'][
        'pass'
    ]


@pytest.mark.parametrize(
    ('arguments', 'named'),
    [
        (['--variants', 'b'], '--variants'),
        (['--movers', 'some'], '--movers'),
        (['--away-s', '0'], '--away-s'),
        (['--away-s', '30'], 'loop_away_s'),
    ],
)
def test_bad_arguments_are_refused_naming_the_option(
    arguments: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(arguments)
    assert exit_info.value.code == 2
    assert named in capsys.readouterr().err
