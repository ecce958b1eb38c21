"""spin_node: an error raised by a callback fails the node, unless Ctrl-C shut the context
down first (rclpy can raise from inside take_message then: a race of the shutdown).

Each case runs in its own Python process, as a node does, since spin_node owns rclpy.init.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

PROGRAM = textwrap.dedent(
    """
    import sys
    import rclpy
    from rclpy.node import Node
    from slam_ros.spin import spin_node

    SHUT_DOWN_FIRST = {shut_down_first}

    class Failing(Node):
        def __init__(self):
            super().__init__('failing')
            self.create_timer(0.05, self.tick)

        def tick(self):
            if SHUT_DOWN_FIRST:
                rclpy.shutdown()
            raise RuntimeError('Unable to convert call argument')

    sys.exit(spin_node('failing', Failing, []))
    """
)


def run(shut_down_first: bool) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, '-c', PROGRAM.format(shut_down_first=shut_down_first)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_an_error_in_a_callback_fails_the_node() -> None:
    result = run(shut_down_first=False)
    assert result.returncode == 1, result.stderr
    assert 'RuntimeError: Unable to convert call argument' in result.stderr


def test_an_error_after_the_context_was_shut_down_is_a_clean_exit() -> None:
    result = run(shut_down_first=True)
    assert result.returncode == 0, result.stderr
    assert 'failing: shutting down: ignored RuntimeError' in result.stderr


RACE_PROGRAM = textwrap.dedent(
    """
    import sys
    import rclpy
    from rclpy.node import Node
    from slam_ros.spin import spin_node

    class Interrupted(Node):
        def __init__(self):
            super().__init__('interrupted')
            self.create_timer(0.05, self.tick)

        def tick(self):
            # rclpy's signal thread shuts the context down between try_shutdown's check and
            # its call: the call then meets a context shut down already
            context = rclpy.get_default_context()
            rclpy.try_shutdown = context.shutdown
            context.shutdown()
            raise KeyboardInterrupt

    sys.exit(spin_node('interrupted', Interrupted, []))
    """
)


def test_ctrl_c_racing_the_signal_threads_shutdown_is_a_clean_exit() -> None:
    """Under load, a Ctrl-C's own shutdown lost the race to rclpy's signal thread and
    odometry_ingest exited with 'rcl_shutdown already called on the given context'."""
    result = subprocess.run(
        [sys.executable, '-c', RACE_PROGRAM], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert 'rcl_shutdown already called' not in result.stderr


TAKE_PROGRAM = textwrap.dedent(
    """
    import sys
    import rclpy
    from rclpy.executors import Executor
    from rclpy.node import Node
    from std_msgs.msg import Int32
    from slam_ros.diagnostics import Diagnostics
    from slam_ros.spin import spin_node

    take = Executor._take_subscription
    takes = []

    def take_failing_once(self, sub):
        # rclpy under load: the message is taken from the queue, then converting it fails
        work = take(self, sub)
        takes.append(sub.topic_name)
        if len(takes) == 3:
            raise RuntimeError("Unable to convert call argument '0' to Python object")
        return work

    Executor._take_subscription = take_failing_once

    class Listener(Node):
        def __init__(self):
            super().__init__('listener')
            self.diagnostics = Diagnostics(self, dict)
            self.taken = []
            self.create_subscription(
                Int32, 'numbers', self.diagnostics.timed(self.on_number, 'numbers'), 10
            )
            self.publisher = self.create_publisher(Int32, 'numbers', 10)
            self.timer = self.create_timer(0.05, self.tick)
            self.sent = 0

        def tick(self):
            if self.publisher.get_subscription_count() and self.sent < 6:
                self.publisher.publish(Int32(data=self.sent))
                self.sent += 1

        def on_number(self, message):
            self.taken.append(message.data)
            if message.data == 5:
                status = {v.key: v.value for v in self.diagnostics.status().values}
                print('taken', self.taken, 'failed', status['failed takes'],
                      'lost', status['lost numbers'], flush=True)
                rclpy.shutdown()

    sys.exit(spin_node('listener', Listener, []))
    """
)


def test_a_message_rclpy_fails_to_take_is_counted_lost_and_the_node_goes_on() -> None:
    """Under load rclpy's take_message raised from pybind11 and odometry_ingest died with it."""
    result = subprocess.run(
        [sys.executable, '-c', TAKE_PROGRAM], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert 'taken [0, 1, 3, 4, 5] failed 1 lost 1' in result.stdout, result.stdout
    assert '/numbers: rclpy failed to take a message, which is lost' in result.stderr
