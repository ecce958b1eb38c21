"""The Jazzy main() of a node: init, construct, spin until Ctrl-C, destroy, try_shutdown."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from slam_core.blas import single_threaded_libraries
from slam_core.cli import config_requested, help_requested, node_help
from slam_core.params import ParamTable
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import check_parameter_files


def spin_node(
    prog: str,
    factory: Callable[[], Node],
    argv: list[str] | None = None,
    *,
    parameters: ParamTable | None = None,
    doc: str | None = None,
) -> int:
    """Run the node ``factory()`` builds until Ctrl-C or shutdown; return exit code 0.

    ``-h``/``--help`` prints ``doc`` and the ``parameters`` table without starting rclpy;
    ``--print-config`` prints the table as a parameter file (``ParamTable.to_yaml``).
    """
    args = sys.argv[1:] if argv is None else argv
    if help_requested(args):
        if parameters is None:
            print(f'usage: {prog} [-h] [--ros-args ...]\n\n{(doc or "").strip()}')  # noqa: T201
        else:
            print(node_help(prog, doc, parameters))  # noqa: T201
        return 0
    if parameters is not None and config_requested(args):
        print(parameters.to_yaml(), end='')  # noqa: T201
        return 0
    if parameters is not None:
        check_parameter_files(args, parameters)
    single_threaded_libraries()
    rclpy.init(args=[prog, *args])
    node = None
    executor = None
    try:
        node = factory()
        executor = TakeSafeExecutor()
        rclpy.spin(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        # rclpy's signal thread shuts the context down at a moment of its own: shut it down
        # here, so that the wind-down below always takes the console path, never a /rosout
        # that dies halfway through it.
        _shut_down()
    except Exception as err:
        if rclpy.ok():
            raise
        # Ctrl-C shut the context down while the executor was taking a message (rclpy then
        # raises from inside take_message): a race of the shutdown, not a failure of the node.
        print(f'{prog}: shutting down: ignored {type(err).__name__}: {err}', file=sys.stderr)  # noqa: T201
    finally:
        if node is not None:
            if not rclpy.ok():
                # Ctrl-C shut the context down, and /rosout with it: what the node says on
                # the way out (report and checkpoint written) goes to the console alone.
                console = ConsoleLogger(node.get_logger().name)
                node.get_logger = lambda: console  # type: ignore[method-assign]
            node.destroy_node()
        if executor is not None:
            executor.shutdown(timeout_sec=0.0)
        _shut_down()
    return 0


class TakeSafeExecutor(SingleThreadedExecutor):
    """A SingleThreadedExecutor that goes on when rclpy fails to take a message.

    Under load, rclpy's take_message can raise RuntimeError (pybind11: "Unable to convert
    call argument '0' to Python object"). Stock rclpy ends the spin with it, and the node.
    Here that one message is lost: the subscription's node logs an error naming the topic and
    counts it on /diagnostics ('failed takes'; the next message's sequence gap counts it lost).
    """

    def _take_subscription(self, sub: Any) -> Any:
        try:
            return super()._take_subscription(sub)
        except RuntimeError as err:
            if not self.context.ok():
                raise  # a race of Ctrl-C: spin_node's shutdown path
            node = next((n for n in self.get_nodes() if sub in n.subscriptions), None)
            if node is not None:
                _report_failed_take(node, sub.topic_name, err)
            return None


def _report_failed_take(node: Node, topic: str, error: Exception) -> None:
    diagnostics = getattr(node, 'diagnostics', None)
    if isinstance(diagnostics, Diagnostics):
        diagnostics.failed_takes += 1
    node.get_logger().error(
        f'{topic}: rclpy failed to take a message, which is lost ({type(error).__name__}: '
        f'{error}); going on'
    )


class ConsoleLogger:
    """A node's logger once its context is shut down: stderr, INFO and above."""

    def __init__(self, name: str) -> None:
        self.name = name

    def _say(self, level: str, message: str) -> bool:
        print(f'[{level}] [{time.time():.9f}] [{self.name}]: {message}', file=sys.stderr)  # noqa: T201
        return True

    def debug(self, message: str, **_: Any) -> bool:
        return False

    def info(self, message: str, **_: Any) -> bool:
        return self._say('INFO', message)

    def warning(self, message: str, **_: Any) -> bool:
        return self._say('WARN', message)

    warn = warning

    def error(self, message: str, **_: Any) -> bool:
        return self._say('ERROR', message)

    def fatal(self, message: str, **_: Any) -> bool:
        return self._say('FATAL', message)


def _shut_down() -> None:
    """Shut the context down, unless rclpy's signal thread did it first (a race on Ctrl-C:
    try_shutdown then raises that rcl_shutdown was called already)."""
    try:
        rclpy.try_shutdown()
    except Exception:
        if rclpy.ok():
            raise
