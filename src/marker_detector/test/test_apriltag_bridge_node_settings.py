"""The apriltag_bridge parameters: its defaults make apriltag_ros's config, and bad values
are refused naming the parameter."""

from __future__ import annotations

from pathlib import Path

import pytest

from marker_detector.apriltag_bridge.settings import PARAMETERS, bridge_config, parse_tag_frames
from slam_core.errors import ParameterError

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'apriltag_bridge.yaml'


def test_the_defaults_make_a_config_like_apriltag_ros_names() -> None:
    config = bridge_config(PARAMETERS.defaults())
    assert config.tag_frame(3) == 'tag36h11:3'
    assert config.is_tag_frame('tag36h11:3') and not config.is_tag_frame('base_link')
    named = bridge_config({**PARAMETERS.defaults(), 'tag_frames': ['9:base', '14:object']})
    assert named.tag_frame(14) == 'object' and named.tag_frame(3) == 'tag36h11:3'
    assert named.is_tag_frame('object')


@pytest.mark.parametrize(
    ('name', 'value', 'says'),
    [
        ('tag_family', '36h11', "apriltag_bridge.tag_family='36h11': must be one of"),
        ('marker_size_m', 0.0, 'apriltag_bridge.marker_size_m=0.0'),
        ('marker_sizes_m', ['5:0.0'], 'apriltag_bridge.marker_sizes_m'),
        ('marker_sizes_m', ['5=0.1'], "must look like 'id:size_m'"),
        ('tag_frames', ['9'], "must look like 'id:frame'"),
        ('tag_frames', ['9:a', '10:a'], 'given twice'),
        ('camera_model', 'fisheye', 'apriltag_bridge.camera_model'),
        ('tf_wait_s', 0.0, 'apriltag_bridge.tf_wait_s=0.0'),
        ('allowed_ids', ['3-1'], 'apriltag_bridge.allowed_ids'),
        ('base_frame', '', 'base_frame'),
    ],
)
def test_bad_values_are_refused_naming_the_parameter(name: str, value: object, says: str) -> None:
    with pytest.raises(ParameterError, match=None) as caught:
        bridge_config({**PARAMETERS.defaults(), name: value})
    assert says in str(caught.value)


def test_tag_frames_parse() -> None:
    assert parse_tag_frames(['9:base', ' 14 : object ']) == {9: 'base', 14: 'object'}
