"""Node parameter values -> validated marker_detector configs (ROS-free).

Shared by the node and the offline tool (``marker_detect_bag``), which reads the node's
YAML file, so both accept exactly the same settings.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from marker_detector.core.detection import DetectorConfig
from marker_detector.processor import ExtrinsicsConfig


def parse_marker_sizes(entries: list[str]) -> dict[int, float]:
    """Parse ['id:size_m', ...] (raises ValueError naming the bad entry)."""
    sizes: dict[int, float] = {}
    for entry in entries:
        marker_id, sep, size = entry.partition(':')
        try:
            if not sep:
                raise ValueError
            key, value = int(marker_id), float(size)
        except ValueError:
            raise ValueError(
                f'marker_detector setting marker_sizes_m entry {entry!r}: '
                "must look like 'id:size_m'"
            ) from None
        if key in sizes:
            raise ValueError(f'marker_detector setting marker_sizes_m: id {key} given twice')
        sizes[key] = value
    return sizes


def parse_id_ranges(entries: list[str]) -> tuple[int, ...]:
    """Parse ['7', '0-28', ...] into sorted unique ids (raises ValueError naming the entry)."""
    ids: set[int] = set()
    for entry in entries:
        first, sep, last = entry.strip().partition('-')
        try:
            low = int(first)
            high = int(last) if sep else low
        except ValueError:
            raise ValueError(
                f'marker_detector setting allowed_ids entry {entry!r}: '
                "must look like 'id' or 'first-last'"
            ) from None
        if low < 0 or high < low:
            raise ValueError(
                f'marker_detector setting allowed_ids entry {entry!r}: ids are >= 0, first <= last'
            )
        ids.update(range(low, high + 1))
    return tuple(sorted(ids))


def detector_config(values: dict[str, Any]) -> DetectorConfig:
    """Validate the detector parameters into a DetectorConfig (raises ValueError)."""
    return DetectorConfig(
        dictionary=str(values['dictionary']),
        default_marker_size_m=float(values['marker_size_m']),
        marker_sizes_m=parse_marker_sizes([str(e) for e in values['marker_sizes_m']]),
        corner_refinement=str(values['corner_refinement']),
        min_side_px=float(values['min_side_px']),
        max_reprojection_error_px=float(values['max_reprojection_error_px']),
        max_range_m=float(values['max_range_m']),
        max_viewing_angle_rad=float(values['max_viewing_angle_rad']),
        allowed_ids=parse_id_ranges([str(e) for e in values['allowed_ids']]),
        pixel_noise_px=float(values['pixel_noise_px']),
    )


def extrinsics_config(values: dict[str, Any]) -> ExtrinsicsConfig:
    """Validate the extrinsics parameters into an ExtrinsicsConfig (raises ValueError)."""
    return ExtrinsicsConfig(
        source=str(values['extrinsics_source']),
        base_frame=str(values['base_frame']),
        camera_xyz_m=tuple(float(v) for v in values['camera_xyz_m']),
        camera_rpy_rad=tuple(float(v) for v in values['camera_rpy_rad']),
    )


def parameters_from_yaml(path: Path, defaults: dict[str, Any]) -> dict[str, Any]:
    """Return ``defaults`` updated with the ``/**: ros__parameters`` (or ``<node>:``) of a
    node YAML file; raise ValueError naming the file and the unknown key."""
    try:
        document: Any = yaml.safe_load(Path(path).read_text(encoding='utf-8'))
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f'parameter file {str(path)!r}: {err}') from None
    if not isinstance(document, dict) or len(document) != 1:
        raise ValueError(f'parameter file {str(path)!r}: expected one "<node>: ros__parameters:"')
    section = next(iter(document.values()))
    if not isinstance(section, dict) or not isinstance(section.get('ros__parameters'), dict):
        raise ValueError(f'parameter file {str(path)!r}: no ros__parameters mapping')
    values = dict(defaults)
    for name, value in section['ros__parameters'].items():
        if name not in defaults:
            raise ValueError(
                f'parameter file {str(path)!r}: {name} is not a marker_detector parameter'
            )
        if isinstance(value, list):
            value = [item for item in value if item != '']
        values[name] = value
    return values


def apply_overrides(values: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Return ``values`` with 'name=value' overrides applied (values parsed as YAML)."""
    result = dict(values)
    for override in overrides:
        name, sep, text = override.partition('=')
        if not sep or name not in values:
            raise ValueError(
                f'override {override!r}: expected NAME=VALUE with NAME one of the '
                f'parameters ({", ".join(sorted(values))})'
            )
        try:
            result[name] = yaml.safe_load(text)
        except yaml.YAMLError as err:
            raise ValueError(f'override {override!r}: {err}') from None
    return result
