"""`ManagedNode`: a `ProtocadNode` that is also a ROS 2 managed (lifecycle) node.

The state machine, its services (`<node>/change_state`, `get_state`, `get_available_states`,
`get_available_transitions`, `get_transition_graph`) and the `<node>/transition_event` topic
are rclpy's own (`rclpy.lifecycle`), i.e. what `ros2 lifecycle set/get/list` talks to. A
subclass fills in five hooks:

- `configure_node()`: build what the node works with (env, model); raise `ConfigError` when
  the configuration cannot work (the transition fails, the node stays unconfigured);
- `activate_node()` / `deactivate_node()`: start / stop doing its work (lifecycle publishers
  are enabled before `activate_node` and disabled after `deactivate_node`, so nothing of a
  half-stopped node goes out);
- `cleanup_node()`: release what configure built; it must work on a half-built node, since it
  is also what a failed configure and the error state run.

Transitions are never fatal: a hook that raises is logged with its traceback, counted
(`transition_errors`) and answered like rclpy does, `success=False`: a `ConfigError` in
configure is a FAILURE (back to unconfigured); anything else is an ERROR, whose error
processing releases everything and returns the node to unconfigured, alive, ready to be
configured again. Transitions the current state does not have (activate from unconfigured)
are refused by the state machine itself.

`autostart` (every managed protocad node has the parameter, default true) runs configure and
activate in the constructor, so `ros2 run ...` stays one command; there a failed configure
raises what made it fail (`ConfigError`: exit 2, as a bad parameter). After `shutdown` the
state is finalized and the process exits (code 0) once the answer to `change_state` is out.
"""
from __future__ import annotations

import traceback
from typing import Any, Callable

from rclpy.lifecycle import LifecycleNodeMixin, TransitionCallbackReturn

from sim_bridge.nodekit.param_table import ConfigError
from sim_bridge.nodekit.rosbase import ProtocadNode

SUCCESS, FAILURE, ERROR = (TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE,
                           TransitionCallbackReturn.ERROR)
#: Primary states (lifecycle_msgs/msg/State labels).
PRIMARY_STATES = ("unconfigured", "inactive", "active", "finalized")
#: After the shutdown transition: time for the change_state answer to reach its caller.
EXIT_AFTER_SHUTDOWN_S = 0.5


class ManagedNode(LifecycleNodeMixin, ProtocadNode):
    """ProtocadNode + rclpy's lifecycle state machine; see the module docstring."""

    def __init__(self, node_name: str, **kw: Any):
        ProtocadNode.__init__(self, node_name, **kw)
        LifecycleNodeMixin.__init__(self)
        self.transition_errors = 0
        self.last_transition_error: BaseException | None = None
        self.is_active = False   # set once activate_node ran, cleared before deactivate_node

    @property
    def lifecycle_state(self) -> str:
        """Label of the current state (unconfigured, inactive, active, finalized, or a
        transition state such as configuring while one runs)."""
        return self._state_machine.current_state[1]

    # ------------------------------------------------------------------ hooks (subclasses)
    def configure_node(self) -> None:
        pass

    def activate_node(self) -> None:
        pass

    def deactivate_node(self) -> None:
        pass

    def cleanup_node(self) -> None:
        pass

    # ------------------------------------------------------------------ remote transitions
    def refuse_remote_transitions(self) -> None:
        """Answer every change_state request with failure (remote_lifecycle:=false). The
        service stays, so a caller gets a clear 'no' instead of waiting for a server."""
        def refused(request, response):
            self.counters["remote_transitions_refused"] += 1
            label = request.transition.label or str(request.transition.id)
            self.get_logger().warning(f"lifecycle transition '{label}' requested by another "
                                      "process refused (remote_lifecycle:=false)")
            response.success = False
            return response

        self._service_change_state.callback = refused

    # ------------------------------------------------------------------ autostart / exit
    def autostart(self) -> None:
        """configure + activate; raises what made a transition fail."""
        for name, trigger in (("configure", self.trigger_configure),
                              ("activate", self.trigger_activate)):
            self.last_transition_error = None
            if trigger() != SUCCESS:
                raise self.last_transition_error or RuntimeError(f"{name} failed")

    def shutdown_lifecycle(self) -> None:
        """The shutdown transition from any primary state but finalized (the node's close())."""
        if self.lifecycle_state in ("unconfigured", "inactive", "active"):
            try:
                self.trigger_shutdown()
            except Exception as exc:  # noqa: BLE001  closing must go on
                self.get_logger().error(f"shutdown transition failed: {exc}")

    # ------------------------------------------------------------------ rclpy callbacks
    def _run_hook(self, transition: str, hook: Callable[[], None]) -> TransitionCallbackReturn:
        try:
            hook()
            return SUCCESS
        except ConfigError as exc:
            self.last_transition_error = exc
            self.get_logger().error(f"{transition} failed: {exc}")
            return FAILURE
        except Exception as exc:  # noqa: BLE001  a transition must never kill the node
            self.last_transition_error = exc
            self.transition_errors += 1
            self.get_logger().error(f"{transition} failed: {type(exc).__name__}: {exc}\n"
                                    f"{traceback.format_exc()}")
            return ERROR

    def _release(self, why: str) -> None:
        """Best effort: stop and free everything (the node is then as if unconfigured)."""
        self.is_active = False
        try:
            self.deactivate_node()
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f"{why}: deactivating failed: {type(exc).__name__}: {exc}")
        try:
            self.cleanup_node()
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f"{why}: cleanup failed: {type(exc).__name__}: {exc}")

    def on_configure(self, state) -> TransitionCallbackReturn:
        ret = self._run_hook("configure", self.configure_node)
        if ret == FAILURE:   # ERROR: on_error releases
            self._release("configure failed")
        if ret == SUCCESS:
            self.get_logger().info("configured (inactive)")
        return ret if ret != SUCCESS else super().on_configure(state)

    def on_activate(self, state) -> TransitionCallbackReturn:
        ret = super().on_activate(state)   # lifecycle publishers first: activate_node may publish
        if ret == SUCCESS:
            ret = self._run_hook("activate", self.activate_node)
        if ret == SUCCESS:
            self.is_active = True
            self.get_logger().info("active")
        else:   # FAILURE: stay inactive, publishers off again
            super().on_deactivate(state)
        return ret

    def on_deactivate(self, state) -> TransitionCallbackReturn:
        self.is_active = False
        ret = self._run_hook("deactivate", self.deactivate_node)
        super().on_deactivate(state)
        if ret == SUCCESS:
            self.get_logger().info("deactivated (inactive)")
        return ret

    def on_cleanup(self, state) -> TransitionCallbackReturn:
        ret = self._run_hook("cleanup", self.cleanup_node)
        if ret == SUCCESS:
            self.get_logger().info("cleaned up (unconfigured)")
        return ret if ret != SUCCESS else super().on_cleanup(state)

    def on_shutdown(self, state) -> TransitionCallbackReturn:
        self._release("shutdown")
        super().on_deactivate(state)
        self.get_logger().info("shut down (finalized)")
        done = getattr(self, "done", None)
        if done is not None and not done.is_set():
            # A one-shot timer: the process ends after the change_state answer went out.
            def _exit() -> None:
                self._exit_timer.cancel()
                done.set()

            self._exit_timer = self.create_timer(EXIT_AFTER_SHUTDOWN_S, _exit)
        return SUCCESS

    def on_error(self, state) -> TransitionCallbackReturn:
        # Back to unconfigured with nothing held: the node stays up and can be configured again.
        self._release("error processing")
        super().on_deactivate(state)
        self.get_logger().warning(f"error processing after a failed transition from "
                                  f"{state.label}: released everything, unconfigured")
        return SUCCESS
