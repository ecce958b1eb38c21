"""The lifecycle versions of em_sam_mapper and marker_detector over real DDS: each state
takes inputs or not, a configure that cannot succeed leaves the node unconfigured with the
reason logged, and the mapper's cleanup writes its report. The transitions come from a
lifecycle_msgs client, as a launch file's or a lifecycle manager's do."""

from __future__ import annotations

import ast
import time
from pathlib import Path

import pytest
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from sensor_msgs.msg import Image

from slam_interfaces.msg import OdometryIncrement
from slam_ros.qos import replayed_qos, sensor_qos
from slam_ros.testing.harness import RosHarness, wait_until

pytestmark = pytest.mark.topic
ROOT = Path(__file__).resolve().parents[1]
CALL_TIMEOUT_S = 60.0


def call(harness: RosHarness, service_type: type, name: str, request: object) -> object:
    client = harness.node.create_client(service_type, name)
    assert client.wait_for_service(timeout_sec=CALL_TIMEOUT_S), f'{name} never came'
    future = client.call_async(request)
    wait_until(future.done, timeout_s=CALL_TIMEOUT_S, what=f'the answer of {name}')
    harness.node.destroy_client(client)
    return future.result()


def state(harness: RosHarness, node: str) -> str:
    return str(
        call(harness, GetState, f'/{node}/get_state', GetState.Request()).current_state.label
    )


def change(harness: RosHarness, node: str, transition: int) -> bool:
    request = ChangeState.Request()
    request.transition.id = transition
    return bool(call(harness, ChangeState, f'/{node}/change_state', request).success)


def subscribed(publisher: object, count: int) -> None:
    wait_until(
        lambda: publisher.get_subscription_count() == count,  # type: ignore[attr-defined]
        timeout_s=30.0,
        what=f'{count} subscriptions',
    )
    time.sleep(0.5)  # and it stays so (a late one would show now)
    assert publisher.get_subscription_count() == count  # type: ignore[attr-defined]


def test_mapper_lifecycle(ros_harness: RosHarness, tmp_path: Path) -> None:
    increments = ros_harness.publisher('/odometry_increments', OdometryIncrement, replayed_qos(10))
    mapper = ros_harness.start_process(
        'em_sam_mapper_lifecycle',
        ['em_sam_mapper_lifecycle', '--ros-args', '-p', f'report_dir:={tmp_path / "out"}'],
    )
    assert state(ros_harness, 'em_sam_mapper') == 'unconfigured'
    subscribed(increments, 0)
    assert change(ros_harness, 'em_sam_mapper', Transition.TRANSITION_CONFIGURE)
    assert state(ros_harness, 'em_sam_mapper') == 'inactive'
    subscribed(increments, 0)  # inactive: no inputs
    assert change(ros_harness, 'em_sam_mapper', Transition.TRANSITION_ACTIVATE)
    subscribed(increments, 1)
    assert change(ros_harness, 'em_sam_mapper', Transition.TRANSITION_DEACTIVATE)
    subscribed(increments, 0)
    assert change(ros_harness, 'em_sam_mapper', Transition.TRANSITION_CLEANUP)
    assert state(ros_harness, 'em_sam_mapper') == 'unconfigured'
    assert mapper.stop() == 0
    log = mapper.log()
    assert 'em_sam_mapper: cleaned up (unconfigured)' in log
    assert 'Traceback' not in log


def test_a_configure_that_cannot_succeed_is_refused_with_the_reason(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    mapper = ros_harness.start_process(
        'em_sam_mapper_lifecycle',
        [
            'em_sam_mapper_lifecycle', '--ros-args', '-p', 'mode:=localization',
            '-p', f'map_file:={tmp_path / "missing" / "em_sam_map.yaml"}',
        ],
    )  # fmt: skip
    assert not change(ros_harness, 'em_sam_mapper', Transition.TRANSITION_CONFIGURE)
    assert state(ros_harness, 'em_sam_mapper') == 'unconfigured'
    line = mapper.wait_for_line(10.0, 'configure failed')
    assert 'em_sam_map.yaml' in line
    mapper.stop()


def test_detector_lifecycle(ros_harness: RosHarness) -> None:
    images = ros_harness.publisher('/camera/image_raw', Image, sensor_qos())
    detector = ros_harness.start_process(
        'marker_detector_lifecycle', ['marker_detector_lifecycle']
    )
    assert state(ros_harness, 'marker_detector') == 'unconfigured'
    assert change(ros_harness, 'marker_detector', Transition.TRANSITION_CONFIGURE)
    subscribed(images, 0)
    assert change(ros_harness, 'marker_detector', Transition.TRANSITION_ACTIVATE)
    subscribed(images, 1)
    assert change(ros_harness, 'marker_detector', Transition.TRANSITION_DEACTIVATE)
    subscribed(images, 0)
    assert detector.stop() == 0
    assert 'Traceback' not in detector.log()


def test_the_lifecycle_launch_file_names_our_lifecycle_executables() -> None:
    """The launch file cannot run here (no launch_ros): check the executables it starts."""
    tree = ast.parse((ROOT / 'src/slam_bringup/launch/em_sam_lifecycle.launch.py').read_text())
    managed = next(
        node.value
        for node in ast.walk(tree)
        if isinstance(node, ast.Assign) and getattr(node.targets[0], 'id', '') == 'MANAGED'
    )
    entries = ast.literal_eval(managed)
    for package, executable, _, config in entries:
        setup = (ROOT / 'src' / package / 'setup.py').read_text()
        assert f"'{executable} = " in setup, executable
        assert (ROOT / 'src' / package / 'config' / config).is_file(), config
