"""apriltag_bridge's parameters (marker_detector's detector parameters, read-only, and its
own) and their validation into a BridgeConfig (ROS-free)."""

from __future__ import annotations

import dataclasses
from typing import Any

from marker_detector.apriltag_bridge.processor import CAMERA_MODELS, FAMILIES, BridgeConfig
from marker_detector.core.tag_pose import TagGates
from marker_detector.detector.settings import (
    DETECTOR_PARAMETERS,
    _rule_of,
    parse_id_ranges,
    parse_marker_sizes,
)
from slam_core.params import POSITIVE, Param, ParamTable, ParamType

NODE_NAME = 'apriltag_bridge'
SHARED = (
    'marker_size_m',
    'marker_sizes_m',
    'allowed_ids',
    'min_side_px',
    'max_reprojection_error_px',
    'max_range_m',
    'max_viewing_angle_rad',
    'pixel_noise_px',
)
GATES = SHARED[3:]


def parse_tag_frames(entries: list[str]) -> dict[int, str]:
    """Parse ['id:frame', ...] (raises ValueError naming the bad entry)."""
    frames: dict[int, str] = {}
    for entry in entries:
        tag_id, sep, frame = entry.partition(':')
        try:
            if not sep or not frame.strip():
                raise ValueError
            key = int(tag_id)
        except ValueError:
            raise ValueError(
                f"apriltag_bridge setting tag_frames entry {entry!r}: must look like 'id:frame'"
            ) from None
        if key in frames or frame.strip() in frames.values():
            raise ValueError(
                f'apriltag_bridge setting tag_frames entry {entry!r}: id or frame given twice'
            )
        frames[key] = frame.strip()
    return frames


_SHARED = {p.name: dataclasses.replace(p, read_only=True) for p in DETECTOR_PARAMETERS}
PARAMETERS = ParamTable(
    NODE_NAME,
    (
        Param(
            'tag_family',
            'tag36h11',
            "the family apriltag_ros detects, as in its detections ('tag' + its family)",
            choices=FAMILIES,
        ),
        _SHARED['marker_size_m'],
        _SHARED['marker_sizes_m'],
        _SHARED['allowed_ids'],
        Param(
            'tag_frames',
            [],
            "tag frame names apriltag_ros uses instead of '<family>:<id>' (its tag.frames), "
            "entries 'id:frame'",
            type=ParamType.STRING_ARRAY,
            validator=_rule_of(parse_tag_frames),
        ),
        Param(
            'camera_model',
            'rectified',
            "the image apriltag_ros detects in: 'rectified' (camera_info P) or 'raw' (K, D)",
            choices=CAMERA_MODELS,
        ),
        *(_SHARED[name] for name in GATES),
        Param('base_frame', 'base_link', 'frame of the range-bearing observations'),
        Param(
            'tf_wait_s',
            0.5,
            "how long a detection waits for its tags' transforms, s (wall time)",
            range=POSITIVE,
        ),
    ),
)


def bridge_config(values: dict[str, Any]) -> BridgeConfig:
    """Validate the parameters into a BridgeConfig (raises ParameterError)."""
    checked = PARAMETERS.validate(values)
    return PARAMETERS.build(
        lambda: BridgeConfig(
            tag_family=checked['tag_family'],
            default_marker_size_m=checked['marker_size_m'],
            marker_sizes_m=parse_marker_sizes(checked['marker_sizes_m']),
            allowed_ids=parse_id_ranges(checked['allowed_ids']),
            tag_frames=parse_tag_frames(checked['tag_frames']),
            camera_model=checked['camera_model'],
            base_frame=checked['base_frame'],
            tf_wait_s=checked['tf_wait_s'],
            gates=TagGates(**{name: checked[name] for name in GATES}),
        )
    )
