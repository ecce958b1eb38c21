"""The Jazzy main() of a node: init, construct, spin until Ctrl-C, destroy, try_shutdown."""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from slam_core.blas import single_threaded_libraries
from slam_core.cli import help_requested, node_help
from slam_core.params import ParamTable
from slam_ros.params import check_parameter_files

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
SPIN_TIMEOUT_S = 0.1  # how soon the loop sees a stop request when no callback is due


def spin_node(
    prog: str,
    factory: Callable[[], Node],
    argv: list[str] | None = None,
    *,
    parameters: ParamTable | None = None,
    doc: str | None = None,
) -> int:
    """Run the node ``factory()`` builds until Ctrl-C, SIGTERM or shutdown; return 0.

    ``-h``/``--help`` (before any ``--ros-args``) prints the node's help (``doc``, its module
    docstring, and the ``parameters`` table) and returns 0 without initializing rclpy.
    ``destroy_node`` always runs, so nodes that finalize (write reports) do it there. Errors
    raised by the constructor or a callback propagate (wrap main with cli.console_main to
    print them), except those raised once the context has been shut down. Ctrl-C during
    the constructor lets it finish, then the node is destroyed as after any other stop.
    """
    args = sys.argv[1:] if argv is None else argv
    if help_requested(args):
        if parameters is None:
            print(f'usage: {prog} [-h] [--ros-args ...]\n\n{(doc or "").strip()}')  # noqa: T201
        else:
            print(node_help(prog, doc, parameters))  # noqa: T201
        return 0
    if parameters is not None:
        check_parameter_files(args, parameters)
    single_threaded_libraries()
    # Ctrl-C and SIGTERM only ask the loop to stop: the context stays valid until the node is
    # destroyed, so what it logs and publishes on the way out (final report, checkpoint)
    # still reaches /rosout instead of failing on an invalid publisher.
    stop = threading.Event()
    rclpy.init(args=[prog, *args], signal_handler_options=SignalHandlerOptions.NO)
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in STOP_SIGNALS}
    executor = SingleThreadedExecutor()
    node = None
    try:
        node = factory()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as err:
        if rclpy.ok():
            raise
        # the context was shut down while the executor was taking a message (rclpy then
        # raises from inside take_message): a race of the shutdown, not a failure of the node.
        print(f'{prog}: shutting down: ignored {type(err).__name__}: {err}', file=sys.stderr)  # noqa: T201
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if node is not None:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown()
    return 0
