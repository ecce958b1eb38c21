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
