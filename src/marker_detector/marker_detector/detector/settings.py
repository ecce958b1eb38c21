"""marker_detector's parameters (``PARAMETERS``, read by the node and by marker_detect_bag)
and their validation into configs (ROS-free). Design notes: docs/design/marker_core.md"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import yaml

from marker_detector.core.detector_config import DetectorConfig
from marker_detector.core.frame_types import EXTRINSICS_SOURCES, ExtrinsicsConfig
from marker_detector.core.roi import SearchPlan
from slam_core.errors import ParameterError
from slam_core.images import DEFAULT_MAX_IMAGE_PIXELS
from slam_core.params import (
    NON_NEGATIVE,
    Param,
    ParamTable,
    ParamType,
    Range,
    config_param,
)

NODE_NAME = 'marker_detector'
IMAGE_TRANSPORTS = ('raw', 'compressed')


def _rule_of(parse: Any) -> Any:
    """Turn a parser that raises ValueError into a validator returning the broken rule."""

    def validator(entries: list[str]) -> str | None:
        try:
            parse(entries)
        except ValueError as err:
            return str(err).partition(': ')[2] or str(err)
        return None

    return validator


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


_DEFAULTS = SimpleNamespace(detector=DetectorConfig(), extrinsics=ExtrinsicsConfig())


def _detector(field: str, description: str, name: str = '') -> Param:
    return config_param(_DEFAULTS, f'detector.{field}', description, name, read_only=False)


DETECTOR_PARAMETERS = (
    _detector('dictionary', 'cv2.aruco dictionary name'),
    _detector('default_marker_size_m', 'black square side of every marker, m', 'marker_size_m'),
    Param(
        'marker_sizes_m',
        [],
        "per-id marker sizes, entries 'id:size_m'",
        type=ParamType.STRING_ARRAY,
        validator=_rule_of(parse_marker_sizes),
        read_only=False,
        field='detector.marker_sizes_m',
        to_field=parse_marker_sizes,
    ),
    _detector('corner_refinement', 'corner refinement'),
    _detector('min_side_px', 'shortest accepted marker side, px'),
    _detector(
        'max_reprojection_error_px', 'largest accepted RMS reprojection error, px (.inf: no limit)'
    ),
    _detector('max_range_m', 'farthest accepted marker, m (.inf: no limit)'),
    _detector('max_viewing_angle_rad', 'most oblique accepted view of a marker, rad'),
    Param(
        'allowed_ids',
        [],
        "accepted marker ids, entries 'id' or 'first-last' (empty: all)",
        type=ParamType.STRING_ARRAY,
        validator=_rule_of(parse_id_ranges),
        read_only=False,
        field='detector.allowed_ids',
        to_field=parse_id_ranges,
    ),
    _detector('pixel_noise_px', 'corner noise sigma for the pose covariance, px'),
)
PARAMETERS = ParamTable(
    NODE_NAME,
    (
        *DETECTOR_PARAMETERS,
        Param(
            'image_transport',
            'raw',
            "'raw' (Image) or 'compressed' (CompressedImage)",
            choices=IMAGE_TRANSPORTS,
        ),
        Param(
            'max_image_pixels',
            DEFAULT_MAX_IMAGE_PIXELS,
            'larger images are refused before decoding, pixels (0: no limit)',
            range=NON_NEGATIVE,
        ),
        Param('base_frame', 'base_link', 'frame of the range-bearing observations'),
        config_param(
            _DEFAULTS,
            'extrinsics.source',
            'where the camera mount comes from',
            name='extrinsics_source',
            choices=EXTRINSICS_SOURCES,
        ),
        Param(
            'camera_xyz_m',
            [0.0, 0.0, 0.0],
            "camera_link position in base_frame, m (extrinsics_source 'parameters')",
            length=3,
        ),
        Param(
            'camera_rpy_rad',
            [0.0, 0.0, 0.0],
            "camera_link roll, pitch, yaw in base_frame, rad (extrinsics_source 'parameters')",
            length=3,
        ),
        Param(
            'search_period_frames',
            1,
            'search the whole image every this many frames, between them only about the '
            'markers of the frame before (1: every frame; none while every allowed id is '
            'followed)',
            range=Range(1.0, None),
        ),
        Param(
            'search_margin_px',
            32.0,
            'a box search looks this far (plus half the marker) round a followed marker, px',
            range=NON_NEGATIVE,
        ),
        Param(
            'detect_every_n_frames',
            1,
            'detect in every this many images; the images between get an empty fiducials '
            'message (1: every image)',
            range=Range(1.0, None),
        ),
        Param('publish_debug_image', False, 'publish the image with the detections drawn'),
    ),
)


def search_plan(values: dict[str, Any]) -> SearchPlan:
    """Validate the search parameters into a SearchPlan (raises ParameterError)."""
    period = PARAMETERS.validate_one('search_period_frames', values['search_period_frames'])
    margin = PARAMETERS.validate_one('search_margin_px', values['search_margin_px'])
    allowed = PARAMETERS.validate_one('allowed_ids', values['allowed_ids'])
    return PARAMETERS.build(
        lambda: SearchPlan(
            period=int(period),
            margin_px=float(margin),
            wanted=frozenset(parse_id_ranges(allowed)),
        )
    )


def detector_config(values: dict[str, Any]) -> DetectorConfig:
    """Validate the detector parameters into a DetectorConfig (raises ParameterError)."""
    checked = {
        p.name: PARAMETERS.validate_one(p.name, values[p.name]) for p in DETECTOR_PARAMETERS
    }
    return PARAMETERS.build(lambda: DetectorConfig(**PARAMETERS.fields(checked, 'detector')))


def extrinsics_config(values: dict[str, Any]) -> ExtrinsicsConfig:
    """Validate the extrinsics parameters into an ExtrinsicsConfig (raises ParameterError)."""
    names = ('extrinsics_source', 'base_frame', 'camera_xyz_m', 'camera_rpy_rad')
    checked = {name: PARAMETERS.validate_one(name, values[name]) for name in names}
    return PARAMETERS.build(
        lambda: ExtrinsicsConfig(
            source=checked['extrinsics_source'],
            base_frame=checked['base_frame'],
            camera_xyz_m=tuple(checked['camera_xyz_m']),
            camera_rpy_rad=tuple(checked['camera_rpy_rad']),
        )
    )


def apply_overrides(values: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Return ``values`` with 'name=value' overrides (YAML values); ParameterError if bad."""
    result = dict(values)
    for override in overrides:
        name, sep, text = override.partition('=')
        if not sep:
            raise ParameterError(f'override {override!r}: expected NAME=VALUE')
        PARAMETERS.check_names([name], where=f'override {override!r}')
        try:
            result[name] = yaml.safe_load(text)
        except yaml.YAMLError as err:
            raise ParameterError(f'override {override!r}: {err}') from None
    return result
