"""Node parameters declared once in a ``ParamTable``; ROS-free (docs/design/ros_and_core.md)."""

from __future__ import annotations

import dataclasses
import difflib
import enum
import math
import numbers
import re
import textwrap
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import yaml

from slam_core.errors import ParameterError

ParamValue = bool | int | float | str | list[bool] | list[int] | list[float] | list[str]
Validator = Callable[[Any], str | None]
"""A validator gets the typed value and returns the rule it breaks, or None when it is valid."""

ROS_PARAMETERS = ('use_sim_time', 'start_type_description_service')
"""Parameters every rclpy node declares itself; accepted in any node's files."""
ROS_PARAMETER_PREFIXES = ('qos_overrides.',)

ConfigT = TypeVar('ConfigT')
_FIELD_ERROR = re.compile(r'(?:parameter |[\w -]+ setting )?(\w+)=(.*)', re.DOTALL)


class ParamType(enum.Enum):
    """The ROS parameter types a node parameter can have (value: the name in --help)."""

    BOOL = 'bool'
    INTEGER = 'int'
    DOUBLE = 'double'
    STRING = 'string'
    BOOL_ARRAY = 'bool[]'
    INTEGER_ARRAY = 'int[]'
    DOUBLE_ARRAY = 'double[]'
    STRING_ARRAY = 'string[]'

    @property
    def is_array(self) -> bool:
        """Whether values are lists."""
        return self.value.endswith('[]')

    @property
    def element(self) -> ParamType:
        """The type of one value (of one item, for arrays)."""
        return ParamType(self.value.removesuffix('[]'))

    @classmethod
    def of(cls, value: object) -> ParamType:
        """Return the type of a non-empty default value (raises TypeError)."""
        if isinstance(value, list):
            if not value:
                raise TypeError('an empty list default needs an explicit type')
            return cls(cls.of(value[0]).value + '[]')
        for python_type, param_type in _SCALAR_TYPES:
            if isinstance(value, python_type):
                return param_type
        raise TypeError(f'{value!r} is not a ROS parameter value')


_SCALAR_TYPES: tuple[tuple[type, ParamType], ...] = (
    (bool, ParamType.BOOL),  # before int: bool is an int in Python
    (int, ParamType.INTEGER),
    (float, ParamType.DOUBLE),
    (str, ParamType.STRING),
)


@dataclass(frozen=True)
class Range:
    """The numbers a value may take: ``low``/``high`` (None: unbounded), open or closed."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def __contains__(self, value: float) -> bool:
        above = self.low is None or value > self.low or (value == self.low and not self.low_open)
        below = (
            self.high is None or value < self.high or (value == self.high and not self.high_open)
        )
        return above and below

    def rule(self) -> str:
        """Return the rule in words: 'must be > 0', 'must be in (0, 1]'."""
        if self.low is not None and self.high is not None:
            left, right = '(' if self.low_open else '[', ')' if self.high_open else ']'
            return f'must be in {left}{_number(self.low)}, {_number(self.high)}{right}'
        if self.low is not None:
            return f'must be {">" if self.low_open else ">="} {_number(self.low)}'
        if self.high is not None:
            return f'must be {"<" if self.high_open else "<="} {_number(self.high)}'
        return 'any number'


POSITIVE = Range(0.0, low_open=True)
NON_NEGATIVE = Range(0.0)
AT_LEAST_ONE = Range(1)
PROBABILITY = Range(0.0, 1.0, low_open=True, high_open=True)
"""Common ranges: > 0, >= 0, >= 1 and the open unit interval."""


def _number(value: float) -> str:
    return f'{value:g}' if isinstance(value, float) else str(value)


def number_problem(number: float, range_: Range | None, allow_inf: bool = False) -> str | None:
    """The rule a number breaks (finite unless ``allow_inf``, never -inf, in ``range_``)."""
    if math.isnan(number) or (math.isinf(number) and not allow_inf):
        return 'must be a finite number' + (' or .inf' if allow_inf else '')
    if math.isinf(number) and number < 0:
        return 'must not be -.inf'
    if range_ is not None and number not in range_:
        return range_.rule()
    return None


RULE = 'slam_core.params.rule'
"""The metadata key of a core config field's ``FieldRule``."""


@dataclass(frozen=True)
class FieldRule:
    """The rule of a core config field: range (numbers, or each item), choices, .inf allowed,
    number of items (tuples)."""

    range: Range | None = None
    choices: tuple[Any, ...] = ()
    allow_inf: bool = False
    length: int | None = None

    def problem(self, value: object, annotation: object) -> str | None:
        """The rule ``value`` breaks, or None; ``annotation`` is the field's type (its text)."""
        if str(annotation) == 'bool':
            return None if isinstance(value, bool) else 'must be true or false'
        if self.choices:
            boolean = isinstance(value, bool) and not any(
                isinstance(choice, bool) for choice in self.choices
            )
            if value in self.choices and not boolean:
                return None
            return 'must be one of ' + ', '.join(repr(choice) for choice in self.choices)
        items = value if isinstance(value, tuple | list) else (value,)
        if self.length is not None and len(items) != self.length:
            return f'must have {self.length} items'
        integer = str(annotation).startswith(('int', 'tuple[int'))
        for item in items:
            kind = type(item)
            if kind is not int and (kind is not float or integer):  # the common cases first
                if isinstance(item, bool) or not isinstance(item, numbers.Real):
                    return 'must be an integer' if integer else 'must be a number'
                if integer and not isinstance(item, numbers.Integral):
                    return 'must be an integer'
            problem = number_problem(float(item), self.range, self.allow_inf)
            if problem is not None:
                return problem
        return None


def ruled(
    default: Any,
    *,
    range: Range | None = None,
    choices: Iterable[Any] = (),
    allow_inf: bool = False,
    length: int | None = None,
) -> Any:
    """A core config dataclass field with its rule, written once: ``check_fields`` holds the
    config to it, and ``config_param`` gives it to the node parameter that sets the field."""
    rule = FieldRule(range, tuple(choices), allow_inf, length)
    return dataclasses.field(default=default, metadata={RULE: rule})


def field_rule(config: object, name: str) -> FieldRule | None:
    """The rule of field ``name`` of a config dataclass (class or instance), if it has one."""
    for item in dataclasses.fields(config):  # type: ignore[arg-type]
        if item.name == name:
            rule = item.metadata.get(RULE)
            return rule if isinstance(rule, FieldRule) else None
    raise AttributeError(f'{type(config).__name__} has no field {name!r}')


def check_fields(config: object, prefix: str = '') -> None:
    """Raise ValueError('<prefix><field>=<value>: <rule>') for the first field of a config
    dataclass that breaks its rule (``ruled``)."""
    for name, rule, annotation in _ruled_fields(type(config)):
        value = getattr(config, name)
        problem = rule.problem(value, annotation)
        if problem is not None:
            raise ValueError(f'{prefix}{name}={value!r}: {problem}')


_RULED_FIELDS: dict[type, tuple[tuple[str, FieldRule, str], ...]] = {}


def _ruled_fields(config_type: type) -> tuple[tuple[str, FieldRule, str], ...]:
    ruled_fields = _RULED_FIELDS.get(config_type)
    if ruled_fields is None:
        ruled_fields = tuple(
            (item.name, item.metadata[RULE], str(item.type))
            for item in dataclasses.fields(config_type)
            if isinstance(item.metadata.get(RULE), FieldRule)
        )
        _RULED_FIELDS[config_type] = ruled_fields
    return ruled_fields


@dataclass(frozen=True)
class Param:
    """One node parameter: name with unit suffix, default, meaning and rules."""

    name: str
    default: ParamValue
    description: str
    type: ParamType | None = None
    range: Range | None = None
    choices: tuple[str | int, ...] = ()
    length: int | None = None
    validator: Validator | None = None
    read_only: bool = True
    allow_inf: bool = False
    field: str = ''
    to_field: Callable[[Any], Any] | None = None

    def __post_init__(self) -> None:
        if self.type is None:
            object.__setattr__(self, 'type', ParamType.of(self.default))

    @property
    def param_type(self) -> ParamType:
        """The ROS type (never None after construction)."""
        if self.type is None:  # pragma: no cover - set in __post_init__
            raise TypeError(f'parameter {self.name} has no type')
        return self.type

    def rules(self) -> list[str]:
        """Return the declared rules in words, for descriptors and --help."""
        rules = []
        if self.range is not None:
            rules.append(self.range.rule())
        if self.choices:
            rules.append('one of ' + ', '.join(repr(c) for c in self.choices))
        if self.length is not None:
            rules.append(f'{self.length} items')
        if self.allow_inf:
            rules.append('.inf allowed')
        return rules

    def default_value(self) -> ParamValue:
        """Return the default (a fresh list for arrays)."""
        if isinstance(self.default, list):
            return self.default.copy()
        return self.default


def config_param(
    defaults: object, field: str, description: str, name: str = '', **rules: Any
) -> Param:
    """A parameter that sets ``field`` of a core config (dotted: ``section.field``), named
    ``name`` (default: the field's name), its default read from ``defaults`` (the config,
    or an object holding its sections): the core config is the value's one source.
    ``rules`` are Param's keywords (range, choices, ...), and a ruled field's rule
    (``ruled``) is the parameter's; a tuple field takes the list back as a tuple, and any
    other ``to_field`` conversion needs an explicit Param."""
    if 'to_field' in rules:
        raise TypeError(f'config_param({field!r}): a converted field needs an explicit Param')
    owner: Any = defaults
    *sections, last = field.split('.')
    for part in sections:
        owner = getattr(owner, part)
    value = getattr(owner, last)
    if isinstance(value, tuple):
        value = list(value)
        rules['to_field'] = tuple
    rule = field_rule(owner, last) if dataclasses.is_dataclass(owner) else None
    if rule is not None:
        written = sorted(rules.keys() & {'range', 'choices', 'allow_inf', 'length'})
        if written:
            raise TypeError(f"config_param({field!r}): {written} is the config field's rule")
        rules = {**rules, 'range': rule.range, 'choices': rule.choices}
        rules.update(allow_inf=rule.allow_inf, length=rule.length)
    return Param(name or last, value, description, field=field, **rules)


class ParamTable:
    """The parameters of one node, in declaration order, by name."""

    def __init__(self, node: str, params: Iterable[Param]) -> None:
        self.node = node
        self._params: dict[str, Param] = {}
        for param in params:
            if param.name in self._params:
                raise ValueError(f'{node}: parameter {param.name} is declared twice')
            self._params[param.name] = param

    def __iter__(self) -> Iterator[Param]:
        return iter(self._params.values())

    def __len__(self) -> int:
        return len(self._params)

    def __contains__(self, name: object) -> bool:
        return name in self._params

    def __getitem__(self, name: str) -> Param:
        return self._params[name]

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names in declaration order."""
        return tuple(self._params)

    def subset(self, names: Iterable[str]) -> tuple[Param, ...]:
        """Return the named parameters (KeyError for a name not declared)."""
        return tuple(self._params[name] for name in names)

    def defaults(self) -> dict[str, ParamValue]:
        """Return every default by name."""
        return {param.name: param.default_value() for param in self}

    # -- errors ------------------------------------------------------------------------
    def fail(self, name: str, value: object, rule: str) -> ParameterError:
        """Return ``ParameterError('parameter <node>.<name>=<value>: <rule>')``."""
        return ParameterError(f'parameter {self.node}.{name}={value!r}: {rule}')

    def check_names(self, names: Iterable[object], *, where: str) -> None:
        """Raise ParameterError for a name that is not a parameter (with the closest)."""
        for name in names:
            if self.accepts(name):
                continue
            close = difflib.get_close_matches(str(name), self.names, n=1)
            hint = f"; did you mean '{close[0]}'?" if close else ''
            raise ParameterError(
                f'{where}: {name!r} is not a parameter of node {self.node}{hint} '
                f'(run `{self.node} --help` for the list)'
            )

    def accepts(self, name: object) -> bool:
        """Whether ``name`` is one of the parameters or one rclpy declares itself."""
        text = str(name)
        return (
            text in self._params
            or text in ROS_PARAMETERS
            or text.startswith(ROS_PARAMETER_PREFIXES)
        )

    # -- validation --------------------------------------------------------------------
    def validate(self, values: Mapping[str, object]) -> dict[str, Any]:
        """Return every parameter checked and typed; ParameterError if missing or invalid."""
        checked: dict[str, Any] = {}
        for param in self:
            if param.name not in values:
                raise ParameterError(
                    f'parameter {self.node}.{param.name} is missing ({param.description})'
                )
            checked[param.name] = self.validate_one(param.name, values[param.name])
        return checked

    def validate_one(self, name: str, value: object) -> Any:
        """Return one parameter's value checked and typed (raises ParameterError)."""
        param = self._params[name]
        kind = param.param_type
        if kind.is_array:
            if not isinstance(value, list | tuple):
                raise self.fail(name, value, f'must be a list ({kind.value})')
            items = [self._scalar(param, item, value) for item in value]
            if kind is ParamType.STRING_ARRAY:
                items = [item for item in items if item != '']
            if param.length is not None and len(items) != param.length:
                raise self.fail(name, value, f'must have {param.length} items')
            typed: Any = items
        else:
            typed = self._scalar(param, value, value)
        if param.choices and typed not in param.choices:
            choices = ', '.join(repr(c) for c in param.choices)
            raise self.fail(name, value, f'must be one of {choices}')
        if param.validator is not None:
            rule = param.validator(typed)
            if rule is not None:
                raise self.fail(name, value, rule)
        return typed

    def check_ros_type(self, name: str, value: object) -> None:
        """Raise ParameterError when a file's value is not of the declared ROS type."""
        param = self._params[name]
        if param.param_type.element is not ParamType.DOUBLE:
            return
        items = value if isinstance(value, list) else [value]
        if any(isinstance(item, int) and not isinstance(item, bool) for item in items):
            raise self.fail(name, value, 'must be a double for a ROS node (write 1.0, not 1)')

    def _scalar(self, param: Param, item: object, value: object) -> Any:
        element = param.param_type.element
        of = ' items' if param.param_type.is_array else ''
        if element is ParamType.BOOL:
            if not isinstance(item, bool):
                raise self.fail(param.name, value, f'must be true or false{of}')
            return item
        if element is ParamType.STRING:
            if not isinstance(item, str):
                raise self.fail(param.name, value, f'must be a string{of}')
            return item
        if element is ParamType.INTEGER:
            if isinstance(item, bool) or not isinstance(item, int):
                raise self.fail(param.name, value, f'must be an integer{of}')
            number: float = item
        else:
            if isinstance(item, bool) or not isinstance(item, int | float):
                raise self.fail(param.name, value, f'must be a number{of}')
            number = float(item)
        problem = number_problem(number, param.range, param.allow_inf)  # an int is finite
        if problem is not None:
            raise self.fail(param.name, value, problem + of)
        return number

    # -- core configs ------------------------------------------------------------------
    def fields(self, values: Mapping[str, Any], section: str = '') -> dict[str, Any]:
        """``{field: value}`` of the parameters setting fields of ``section``, unit converted."""
        result: dict[str, Any] = {}
        for param in self:
            if not param.field:
                continue
            head, dot, field = param.field.rpartition('.')
            if (head if dot else '') != section:
                continue
            value = values[param.name]
            result[field] = param.to_field(value) if param.to_field is not None else value
        return result

    def build(self, build: Callable[[], ConfigT]) -> ConfigT:
        """Return ``build()``; a config field's ValueError names the parameter (ParameterError)."""
        try:
            return build()
        except ValueError as err:
            text = str(err)
            match = _FIELD_ERROR.match(text)
            if match is not None:
                field, rest = match.groups()
                for param in self:
                    if (param.field or param.name).rpartition('.')[2] == field:
                        message = f'parameter {self.node}.{param.name}={rest}'
                        raise ParameterError(message) from None
            raise ParameterError(f'{self.node} parameters rejected: {text}') from None

    # -- files ---------------------------------------------------------------------------
    def read_yaml(
        self, path: Path | str, base: Mapping[str, object] | None = None
    ) -> dict[str, Any]:
        """``base`` (default: the defaults) updated from the node's section of a YAML file."""
        where = f'parameter file {str(path)!r}'
        sections = node_sections(_read_document(path, where), self.node)
        if not sections:
            raise ParameterError(
                f'{where}: no "/**: ros__parameters:" (or "{self.node}: ros__parameters:") mapping'
            )
        values = dict(self.defaults() if base is None else base)
        for key, parameters in sections:
            if not isinstance(parameters, dict):
                raise ParameterError(f'{where}: {key}.ros__parameters must be a mapping')
            self.check_names(parameters, where=f'{where}, section {key!r}')
            values.update({k: v for k, v in parameters.items() if k in self})
        return values

    def check_file(self, path: Path | str, *, node_name: str | None = None) -> None:
        """Raise ParameterError when a parameter file sets an unknown key for the node."""
        where = f'parameter file {str(path)!r}'
        document = _read_document(path, where)
        for key, parameters in node_sections(document, node_name or self.node):
            if isinstance(parameters, dict):
                self.check_names(parameters, where=f'{where}, section {key!r}')

    def load(self, paths: Iterable[Path | str]) -> dict[str, Any]:
        """Return the defaults updated with each YAML file in order, validated."""
        values: dict[str, Any] = self.defaults()
        for path in paths:
            values = self.read_yaml(path, values)
        return self.validate(values)

    # -- documentation -------------------------------------------------------------------
    def render(self) -> str:
        """Return the table as text: one entry per parameter with type, default, rules."""
        lines = [f'Parameters of {self.node} (declared; set with --ros-args -p name:=value):']
        for param in self:
            rules = param.rules() + ([] if param.read_only else ['dynamic'])
            extra = f' [{"; ".join(rules)}]' if rules else ''
            default = _yaml_text(param.default)
            lines.append(f'  {param.name} ({param.param_type.value}, default {default}){extra}')
            lines.append(f'      {param.description}')
        return '\n'.join(lines)

    def to_yaml(self) -> str:
        """Return the node's parameter file of defaults, each parameter under a comment
        that is its description and rules (the text ``--help`` shows)."""
        lines = [
            f'# {self.node} parameters, their defaults; written by `{self.node} --print-config`.',
            '/**:',
            '  ros__parameters:',
        ]
        for param in self:
            rules = param.rules() + ([] if param.read_only else ['dynamic'])
            comment = param.description + (f' [{"; ".join(rules)}]' if rules else '')
            lines += textwrap.wrap(
                comment,
                width=YAML_WIDTH,
                initial_indent='    # ',
                subsequent_indent='    # ',
                break_on_hyphens=False,
            )
            value = _yaml_text(param.default)
            if param.param_type is ParamType.STRING_ARRAY and not param.default:
                # A ROS parameter file cannot type an empty list; [''] is read as [] here.
                value = "['']"
            elif param.param_type.is_array and not param.default:
                raise ValueError(f'{self.node}.{param.name}: an empty {param.param_type.value}')
            lines.append(f'    {param.name}: {value}')
        return '\n'.join(lines) + '\n'


YAML_WIDTH = 99
"""The line width of a written parameter file (the project's line length)."""


def _read_document(path: Path | str, where: str) -> object:
    try:
        document: object = yaml.safe_load(Path(path).read_text(encoding='utf-8'))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise ParameterError(f'{where}: {err}') from None
    return document


def node_sections(document: object, node: str) -> list[tuple[str, object]]:
    """``[(key, ros__parameters)]`` of the sections of a parameter file for ``node``."""
    if not isinstance(document, dict):
        return []
    keys = ('/**', node, f'/{node}')
    return [
        (str(key), section['ros__parameters'])
        for key, section in document.items()
        if key in keys and isinstance(section, dict) and 'ros__parameters' in section
    ]


def _yaml_text(value: ParamValue) -> str:
    if isinstance(value, float) and math.isinf(value):
        return '.inf'
    if isinstance(value, float):
        mantissa, e, exponent = repr(value).partition('e')
        # YAML reads '1e-06' as a string: a float's mantissa needs its point.
        return mantissa + ('' if '.' in mantissa else '.0') + e + exponent
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, list):
        return '[' + ', '.join(_yaml_text(item) for item in value) + ']'
    return repr(value)
