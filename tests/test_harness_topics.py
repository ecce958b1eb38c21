"""The topic-level test harness fails fast: once an exception escapes a node's callback the
executor stops, and ``wait_until`` says so at once instead of waiting out its deadline."""

from __future__ import annotations

from typing import Any

import pytest
from rclpy.node import Node
from std_msgs.msg import String

from slam_ros.qos import output_qos
from slam_ros.testing.harness import RosHarness, wait_until

pytestmark = pytest.mark.topic


# the escaped exception is this test's input: the suite's rule that one fails the test is
# relaxed here alone
@pytest.mark.filterwarnings('ignore::pytest.PytestUnhandledThreadExceptionWarning')
def test_an_escaped_exception_ends_the_wait_at_once(ros_harness: RosHarness) -> None:
    node = Node('raising_node')

    def fail(message: Any) -> None:
        raise ValueError(f'bad input {message.data!r}')

    node.create_subscription(String, 'harness_check', fail, output_qos())
    ros_harness.add_node(node)
    publisher = ros_harness.publisher('harness_check', String, output_qos())
    ros_harness.wait_for_subscribers(publisher, 1, timeout_s=20.0)
    publisher.publish(String(data='boom'))
    # a RuntimeError naming the exception, not the TimeoutError of the deadline
    with pytest.raises(RuntimeError, match="ValueError: bad input 'boom'"):
        wait_until(lambda: False, timeout_s=60.0, what='something that never comes')
