"""The Jazzy main() of a node: init, construct, spin until Ctrl-C, destroy, try_shutdown."""

from __future__ import annotations

import sys
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from slam_core.blas import single_threaded_blas


def spin_node(prog: str, factory: Callable[[], Node], argv: list[str] | None = None) -> int:
    """Run the node ``factory()`` builds until Ctrl-C or shutdown; return exit code 0.

    ``destroy_node`` always runs, so nodes that finalize (write reports) do it there. Errors
    raised by the constructor propagate (wrap main with cli.console_main to print them).
    """
    single_threaded_blas()
    rclpy.init(args=sys.argv if argv is None else [prog, *argv])
    node = None
    try:
        node = factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
