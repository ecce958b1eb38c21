"""slam_core.params: one declaration validates values, reads node YAML files with
closest-name hints for unknown keys, maps core config fields and renders --help."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

from slam_core.cli import config_requested, help_requested, node_help
from slam_core.errors import ParameterError
from slam_core.params import (
    NON_NEGATIVE,
    POSITIVE,
    PROBABILITY,
    Param,
    ParamTable,
    ParamType,
    Range,
    check_fields,
    config_param,
    ruled,
)

TABLE = ParamTable(
    'odometry_ingest',
    (
        Param('keyframe_distance_m', 0.5, 'keyframe after this much travel, m', range=POSITIVE),
        Param('max_tests', 3, 'tests per feature', range=Range(1, 10)),
        Param('mode', 'robust', 'EM-SAM mode', choices=('paper', 'robust')),
        Param('noise_alphas', [0.05, 0.001], 'alphas', length=2, range=NON_NEGATIVE),
        Param('topics', [], 'topics', type=ParamType.STRING_ARRAY),
        Param('gate_m', math.inf, 'gate, m', range=POSITIVE, allow_inf=True),
        Param('alpha', 0.05, 'level', range=PROBABILITY, field='classifier.alpha'),
        Param(
            'min_parallax_deg',
            1.0,
            'parallax, deg',
            range=Range(0.0, 180.0, low_open=True, high_open=True),
            field='classifier.min_parallax_rad',
            to_field=math.radians,
        ),
        Param('frame', 'map', 'frame', validator=lambda v: None if v else 'must name a frame'),
    ),
)


def test_defaults_validate_and_types_are_inferred() -> None:
    values = TABLE.validate(TABLE.defaults())
    assert values['keyframe_distance_m'] == 0.5
    assert TABLE['max_tests'].param_type is ParamType.INTEGER
    assert TABLE['noise_alphas'].param_type is ParamType.DOUBLE_ARRAY
    assert TABLE.validate({**TABLE.defaults(), 'keyframe_distance_m': 2})[
        'keyframe_distance_m'
    ] == pytest.approx(2.0)


@pytest.mark.parametrize(
    ('name', 'value', 'rule'),
    [
        ('keyframe_distance_m', 0.0, 'must be > 0'),
        ('keyframe_distance_m', math.nan, 'must be a finite number'),
        ('keyframe_distance_m', True, 'must be a number'),
        ('max_tests', 2.0, 'must be an integer'),
        ('max_tests', 11, 'must be in [1, 10]'),
        ('mode', 'fast', "must be one of 'paper', 'robust'"),
        ('noise_alphas', [0.1], 'must have 2 items'),
        ('noise_alphas', [0.1, -1.0], 'must be >= 0 items'),
        ('alpha', 1.0, 'must be in (0, 1)'),
        ('frame', '', 'must name a frame'),
        ('gate_m', -math.inf, 'must not be -.inf'),
    ],
)
def test_invalid_values_name_node_parameter_value_and_rule(
    name: str, value: object, rule: str
) -> None:
    with pytest.raises(ParameterError) as caught:
        TABLE.validate({**TABLE.defaults(), name: value})
    assert str(caught.value).startswith(f'parameter odometry_ingest.{name}={value!r}: ')
    assert rule in str(caught.value)


def test_missing_values_and_inf_and_empty_string_items() -> None:
    values = TABLE.defaults()
    del values['mode']
    with pytest.raises(ParameterError, match=r'odometry_ingest\.mode is missing'):
        TABLE.validate(values)
    checked = TABLE.validate({**TABLE.defaults(), 'topics': [''], 'gate_m': math.inf})
    assert checked['topics'] == []
    assert checked['gate_m'] == math.inf


def test_fields_convert_units_and_core_errors_name_the_parameter() -> None:
    values = TABLE.validate(TABLE.defaults())
    assert TABLE.fields(values, 'classifier') == {
        'alpha': 0.05,
        'min_parallax_rad': pytest.approx(math.radians(1.0)),
    }

    @dataclass(frozen=True)
    class Core:
        min_parallax_rad: float

        def __post_init__(self) -> None:
            if self.min_parallax_rad > 0.01:
                raise ValueError(f'min_parallax_rad={self.min_parallax_rad}: must be <= 0.01')

    with pytest.raises(ParameterError, match=r'^parameter odometry_ingest\.min_parallax_deg='):
        TABLE.build(lambda: Core(**{'min_parallax_rad': 1.0}))


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding='utf-8')
    return path


def test_yaml_unknown_key_names_file_node_key_and_closest_name(tmp_path: Path) -> None:
    path = write(
        tmp_path / 'ingest.yaml', '/**:\n  ros__parameters:\n    keyframe_distanse_m: 1.0\n'
    )
    with pytest.raises(ParameterError) as caught:
        TABLE.read_yaml(path)
    message = str(caught.value)
    assert str(path) in message
    assert "'keyframe_distanse_m' is not a parameter of node odometry_ingest" in message
    assert "did you mean 'keyframe_distance_m'?" in message


def test_yaml_sections_by_wildcard_or_node_name(tmp_path: Path) -> None:
    path = write(
        tmp_path / 'p.yaml',
        '/**:\n  ros__parameters:\n    max_tests: 4\n    use_sim_time: true\n'
        'odometry_ingest:\n  ros__parameters:\n    mode: paper\n'
        'other_node:\n  ros__parameters:\n    whatever: 1\n',
    )
    values = TABLE.load([path])
    assert (values['max_tests'], values['mode']) == (4, 'paper')
    empty = write(tmp_path / 'empty.yaml', 'x: 1\n')
    with pytest.raises(ParameterError, match='no "/\\*\\*: ros__parameters:"'):
        TABLE.read_yaml(empty)
    with pytest.raises(ParameterError, match='does-not-exist'):
        TABLE.read_yaml(tmp_path / 'does-not-exist.yaml')


def test_duplicate_names_are_refused() -> None:
    with pytest.raises(ValueError, match='declared twice'):
        ParamTable('n', (Param('a', 1, ''), Param('a', 2, '')))


def test_help_lists_every_parameter_and_stops_at_ros_args() -> None:
    text = node_help('odometry_ingest', 'odometry_ingest: does things.', TABLE)
    for param in TABLE:
        assert param.name in text
    assert 'gate_m (double, default .inf) [must be > 0; .inf allowed]' in text
    assert help_requested(['--help'])
    assert help_requested(['-h', '--ros-args'])
    assert not help_requested(['--ros-args', '-p', 'x:=1', '-h'])
    assert not help_requested([])


def test_print_config_writes_a_parameter_file_that_reads_back_as_the_defaults(
    tmp_path: Path,
) -> None:
    table = ParamTable(
        'n',
        (
            *TABLE,
            Param('tolerance', 1e-6, 'a small number'),
            Param('long', 1.0, 'word ' * 40, range=POSITIVE),
        ),
    )
    text = table.to_yaml()
    assert (
        '# keyframe after this much travel, m [must be > 0]\n    keyframe_distance_m: 0.5' in text
    )
    assert 'tolerance: 1.0e-06' in text  # YAML reads 1e-06 as a string
    assert "topics: ['']" in text  # a ROS parameter file cannot type an empty list
    assert 'gate_m: .inf' in text
    assert all(len(line) <= 99 for line in text.splitlines())
    path = tmp_path / 'n.yaml'
    path.write_text(text)
    assert table.load([path]) == table.validate(table.defaults())
    assert config_requested(['--print-config'])
    assert not config_requested(['--ros-args', '--print-config'])
    with pytest.raises(ValueError, match=r'n\.empty: an empty double\[\]'):
        ParamTable('n', (Param('empty', [], '', type=ParamType.DOUBLE_ARRAY),)).to_yaml()


@dataclass(frozen=True)
class _Ruled:
    gain: float = ruled(0.5, range=POSITIVE)
    mode: str = ruled('a', choices=('a', 'b'))
    count: int = ruled(2, range=Range(1))
    sigma: tuple[float, float] = ruled((1.0, 2.0), range=POSITIVE, length=2)
    name: str = 'free'

    def __post_init__(self) -> None:
        check_fields(self, prefix='setting ')


@pytest.mark.parametrize(
    ('field', 'value', 'rule'),
    [
        ('gain', 0.0, 'must be > 0'),
        ('gain', math.nan, 'must be a finite number'),
        ('gain', True, 'must be a number'),
        ('mode', 'c', "must be one of 'a', 'b'"),
        ('count', 1.5, 'must be an integer'),
        ('count', 0, 'must be >= 1'),
        ('sigma', (1.0,), 'must have 2 items'),
        ('sigma', (1.0, -1.0), 'must be > 0'),
    ],
)
def test_a_ruled_field_is_checked_by_its_config(field: str, value: object, rule: str) -> None:
    with pytest.raises(ValueError, match=rf'^setting {field}=.*: {re.escape(rule)}$'):
        _Ruled(**{field: value})  # type: ignore[arg-type]


def test_a_config_param_takes_the_rule_of_its_ruled_field() -> None:
    table = ParamTable(
        'n',
        (
            config_param(_Ruled(), 'gain', 'gain'),
            config_param(_Ruled(), 'mode', 'mode'),
            config_param(_Ruled(), 'sigma', 'sigma'),
            config_param(_Ruled(), 'name', 'name', choices=('free', 'bound')),
        ),
    )
    assert table['gain'].range == POSITIVE
    assert table['mode'].choices == ('a', 'b')
    assert (table['sigma'].length, table['sigma'].to_field) == (2, tuple)
    assert table['name'].choices == ('free', 'bound')  # a field without a rule keeps its own
    with pytest.raises(ParameterError, match=r'parameter n\.gain=-1\.0: must be > 0'):
        table.validate_one('gain', -1.0)
    assert table.fields(table.validate(table.defaults()))['sigma'] == (1.0, 2.0)
    with pytest.raises(TypeError, match=r"config_param\('gain'\): \['range'\] is the config"):
        config_param(_Ruled(), 'gain', 'gain', range=NON_NEGATIVE)
