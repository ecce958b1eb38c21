"""Topic-level: the loopback DDS profile delivers camera images to best-effort subscribers.

Sensor inputs subscribe with the sensor-data profile (best effort). Over UDP alone, Fast DDS
lost most 640x480 images (each is many fragments); the profile's shared-memory transport
fixes that. This test fails if the profile regresses.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from bag_fixtures import tool_env

from slam_ros.qos import sensor_qos
from slam_ros.testing.harness import RosHarness
from slam_ros.testing.messages import RELIABLE_QOS, BagTopic, write_bag
from slam_ros.typesys import TypeRegistry, message_class

pytestmark = pytest.mark.topic


def test_best_effort_subscriber_gets_camera_images(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    registry = TypeRegistry()
    topic = BagTopic('/camera/image_raw', 'sensor_msgs/msg/Image', 30.0)
    written = write_bag(
        tmp_path / 'images',
        (topic,),
        duration_s=2.0,
        registry=registry,
        seed=31,
        qos=RELIABLE_QOS._replace(reliability=RELIABLE_QOS.reliability.BEST_EFFORT),
        message_factory=lambda rng: _image(registry, rng),
    )
    images = ros_harness.collect(topic.name, message_class(topic.msgtype), sensor_qos())
    player = ros_harness.start_process(
        'player',
        ['bag_player', str(tmp_path / 'images'), '--wait-for-subscribers', '20'],
        env=tool_env(),
    )
    assert player.process.wait(timeout=60) == 0, player.log()
    # Best effort promises nothing, but on one host nearly every image must arrive.
    images.wait_for_count(int(0.95 * len(written)), timeout_s=10)
    assert all(len(m.data) == 640 * 480 * 3 for m in images.messages)


def _image(registry: TypeRegistry, rng: object) -> object:
    import numpy as np

    assert isinstance(rng, np.random.Generator)
    store = registry.typestore
    header = store.types['std_msgs/msg/Header'](
        stamp=store.types['builtin_interfaces/msg/Time'](sec=0, nanosec=0), frame_id='camera'
    )
    return store.types['sensor_msgs/msg/Image'](
        header=header,
        height=480,
        width=640,
        encoding='rgb8',
        is_bigendian=0,
        step=640 * 3,
        data=rng.integers(0, 256, 640 * 480 * 3, dtype=np.uint8),
    )
