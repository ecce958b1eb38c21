"""rclpy messages to and from plain data (YAML), for the command-line tools."""

from __future__ import annotations

import array
import difflib
import math
import re
from collections.abc import Mapping
from typing import Any

import numpy as np
import yaml

from slam_core.errors import SlamError
from slam_ros.typesys import message_class

_SEQUENCE = re.compile(r'^sequence<([^,>]+)(?:,\s*\d+)?>$')
_ARRAY = re.compile(r'^(.+)\[(\d+)\]$')
_BOUNDED_STRING = re.compile(r'^w?string<\d+>$')
_INTEGER_TYPES = {
    'octet', 'char', 'byte', 'int8', 'uint8', 'int16', 'uint16', 'int32', 'uint32',
    'int64', 'uint64',
}  # fmt: skip
_BYTE_TYPES = {'octet', 'byte'}
_FLOAT_TYPES = {'float', 'double', 'long double'}


class MessageFieldError(SlamError):
    """A value given for a message field does not fit the field."""


def is_message(value: object) -> bool:
    """Whether ``value`` is an rclpy message (or service request/response) instance."""
    return hasattr(type(value), 'get_fields_and_field_types')


def message_to_data(message: Any, *, truncate: int | None = 128, arrays: bool = True) -> Any:
    """``message`` as plain data (longer than ``truncate``: cut, '...'; see ``arrays``)."""
    if is_message(message):
        data: dict[str, Any] = {}
        for name, field_type in message.get_fields_and_field_types().items():
            value = getattr(message, name)
            if field_type in _BYTE_TYPES and isinstance(value, bytes):
                data[name] = int.from_bytes(value, 'little')  # an octet scalar is bytes
            else:
                data[name] = message_to_data(value, truncate=truncate, arrays=arrays)
        return data
    if isinstance(message, np.ndarray | array.array | bytes | list | tuple):
        if not arrays:
            return f'<sequence of {len(message)}>'
        cut = truncate is not None and len(message) > truncate
        kept = message[:truncate]  # before any conversion: an image is a million items
        items = list(kept.tolist() if isinstance(kept, np.ndarray) else kept)
        converted = [message_to_data(item, truncate=truncate) for item in items]
        return [*converted, '...'] if cut else converted
    if isinstance(message, str) and truncate is not None and len(message) > truncate:
        return message[:truncate] + '...'
    if isinstance(message, np.generic):
        return message.item()
    return message


def to_yaml(data: Any) -> str:
    """YAML of plain data (from ``message_to_data``), keys in field order."""
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False, allow_unicode=True)


def _element_type(field_type: str) -> str | None:
    match = _SEQUENCE.match(field_type) or _ARRAY.match(field_type)
    return match.group(1).strip() if match else None


def _scalar(field: str, field_type: str, value: object) -> object:
    if field_type == 'boolean':
        if not isinstance(value, bool):
            raise MessageFieldError(f'{field}: expected true or false, got {value!r}')
        return value
    if field_type in _INTEGER_TYPES:
        if isinstance(value, bool) or not isinstance(value, int):
            raise MessageFieldError(f'{field}: expected an integer ({field_type}), got {value!r}')
        if field_type in _BYTE_TYPES:
            if not 0 <= value <= 255:
                raise MessageFieldError(f'{field}: expected 0-255 ({field_type}), got {value}')
            return bytes([value])
        return value
    if field_type in _FLOAT_TYPES:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise MessageFieldError(f'{field}: expected a number ({field_type}), got {value!r}')
        number = float(value)
        if not math.isfinite(number):
            raise MessageFieldError(f'{field}: expected a finite number, got {value!r}')
        return number
    if field_type in ('string', 'wstring') or _BOUNDED_STRING.match(field_type):
        if not isinstance(value, str):
            raise MessageFieldError(f'{field}: expected a string, got {value!r}')
        return value
    raise MessageFieldError(f'{field}: fields of type {field_type!r} cannot be set here')


def _message_type_name(field_type: str) -> str:
    package, _, name = field_type.partition('/')
    return f'{package}/msg/{name}'


def _value(field: str, field_type: str, value: object, current: object) -> object:
    element = _element_type(field_type)
    if element is not None:
        if not isinstance(value, list):
            raise MessageFieldError(f'{field}: expected a list ({field_type}), got {value!r}')
        if '/' in element:
            cls = message_class(_message_type_name(element))
            return [
                fill_message(cls(), item, where=f'{field}[{i}]') for i, item in enumerate(value)
            ]
        return [_scalar(f'{field}[{i}]', element, item) for i, item in enumerate(value)]
    if '/' in field_type:
        return fill_message(current, value, where=field)
    return _scalar(field, field_type, value)


def fill_message(message: Any, values: object, *, where: str = '') -> Any:
    """Set ``message``'s fields from the mapping ``values``; MessageFieldError names a misfit."""
    if values is None:
        return message
    prefix = f'{where}.' if where else ''
    if not isinstance(values, Mapping):
        raise MessageFieldError(
            f'{where or "the message"}: expected a mapping of field names to values, '
            f'got {values!r}'
        )
    fields = message.get_fields_and_field_types()
    for key, value in values.items():
        if key not in fields:
            close = difflib.get_close_matches(str(key), list(fields), n=1)
            hint = f"; did you mean '{close[0]}'?" if close else ''
            known = ', '.join(fields) or 'none'
            raise MessageFieldError(
                f'{prefix}{key} is not a field of {type(message).__name__} (fields: {known}){hint}'
            )
        try:
            setattr(message, key, _value(prefix + key, fields[key], value, getattr(message, key)))
        except (AssertionError, TypeError, ValueError) as err:
            raise MessageFieldError(f'{prefix}{key}: {value!r} does not fit: {err}') from None
    return message
