"""Lifecycle (managed) versions of our nodes on rclpy's API, driven through
``~/change_state`` (lifecycle_msgs/srv/ChangeState). Design notes: docs/design/ros_and_core.md."""

from __future__ import annotations

from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from slam_core.params import ParamTable
from slam_ros.params import current_values, declare_parameters

ENTITY_KINDS = (
    ('publishers', 'destroy_publisher'),
    ('subscriptions', 'destroy_subscription'),
    ('services', 'destroy_service'),
    ('clients', 'destroy_client'),
    ('timers', 'destroy_timer'),
)


def managed(behaviour: type, name: str, parameters: ParamTable) -> type:
    """Lifecycle class of ``behaviour`` (its ``_configure``, ``_activate``, ``_deactivate``)."""

    class Managed(behaviour, LifecycleNode):
        __doc__ = f'{name} as a lifecycle node (slam_ros.lifecycle).'

        def __init__(self, **kwargs: Any) -> None:
            LifecycleNode.__init__(self, name, **kwargs)
            declare_parameters(self, parameters)
            self._values: dict[str, Any] | None = None
            self._before_configure: dict[str, set[Any]] = {}
            self._is_active = False

        def _entities(self) -> dict[str, set[Any]]:
            return {kind: set(getattr(self, kind)) for kind, _ in ENTITY_KINDS}

        def _destroy_since(self, before: dict[str, set[Any]]) -> None:
            for kind, destroy in ENTITY_KINDS:
                for entity in set(getattr(self, kind)) - before[kind]:
                    getattr(self, destroy)(entity)

        def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
            before = self._entities()
            try:
                self._values = current_values(self, parameters)
                self._configure(self._values)
            except Exception as err:  # any reason: the transition fails, the node stays
                self._destroy_since(before)
                self._values = None
                self.get_logger().error(f'{name}: configure failed: {err}')
                return TransitionCallbackReturn.FAILURE
            self._before_configure = before
            self.get_logger().info(f'{name}: configured')
            return TransitionCallbackReturn.SUCCESS

        def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
            assert self._values is not None
            self._activate(self._values)
            self._is_active = True
            self.get_logger().info(f'{name}: active, taking inputs')
            return super().on_activate(state)

        def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
            self._deactivate()
            self._is_active = False
            self.get_logger().info(f'{name}: inactive, inputs paused (what it holds stays)')
            return super().on_deactivate(state)

        def _release(self) -> None:
            if self._values is None:
                return
            if self._is_active:
                self._deactivate()
                self._is_active = False
            finalize = getattr(self, '_finalize', None)
            if finalize is not None:
                finalize()
            self._destroy_since(self._before_configure)
            self._values = None

        def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
            self._release()
            self.get_logger().info(f'{name}: cleaned up (unconfigured)')
            return TransitionCallbackReturn.SUCCESS

        def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
            self._release()
            return TransitionCallbackReturn.SUCCESS

        def destroy_node(self) -> None:
            """Ctrl-C in any state: what a configured node holds is written first."""
            self._release()
            LifecycleNode.destroy_node(self)

    Managed.__name__ = Managed.__qualname__ = f'{behaviour.__name__}Lifecycle'
    return Managed
