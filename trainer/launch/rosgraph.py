"""The launchers' view of their nodes over ROS (trainer/launch/rosprocs.py, loop, stack, evaluation):
lifecycle states of the managed nodes, the ROS graph for the unmanaged ones, /diagnostics.

Readiness is decided from what the nodes expose over ROS, never from their log text (the logs
are for people):

- a managed node (sim bridge, policy) is ready when `<node>/get_state` answers `active`;
- an unmanaged node (recorder, random actor) is ready when the graph shows the endpoints it
  must have (e.g. the recorder's subscription to `action`), endpoints of an earlier process
  of the same name not counted (their graph entries may outlive it for a moment);
- what a node serves (the policy's checkpoint update counter) is read from its /diagnostics.

Only from the nodes this launcher started (`expect(fqn, pid)`): anyone on the domain can publish
a /diagnostics status under any name, so each message is taken with its writer's GID
(sim_bridge/nodekit/sender_gid.py) and a status is believed only when that writer belongs to the
process started for the status's node (its process id in the GID, this machine's host bytes)
and, once the graph knows the writer, to a node of that name. Anything else is ignored and
counted (`forged`), with one line on stderr per name. A managed node is ready when its
get_state answers `active` and its own diagnostics say so too (a stranger can answer
get_state as well).

`RosGraph` is one rclpy node in its own Context, in the launcher's process, on the stack's
domain (DDS on this machine only). It spins only inside its calls, so a launcher that trains
between calls runs no ROS thread.
"""
from __future__ import annotations

import os
import sys
from typing import Callable, Iterable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.srv import GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from sim_bridge.contract import qos
from sim_bridge.contract import topics as T
from sim_bridge.nodekit.sender_gid import SenderSubscription, gid_pid
from trainer.console import wait_until
from trainer.launch import discovery

#: How long one get_state call may take before it is asked again.
GET_STATE_TIMEOUT_S = 2.0


class RosGraph:
    def __init__(self, domain_id: int, *, name: str = "protocad_launcher", discovery_server: str | None = None):
        # Before rclpy.init: this process's own participant stays on this machine, like the
        # nodes it starts (rosprocs.ros_env), whatever the caller's environment says. With a
        # Discovery Server it is a super client: a plain client would never hear of endpoints
        # on topics it does not use itself (the recorder's subscriptions it waits for).
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
        discovery.apply_env(os.environ, discovery_server or os.environ.get(discovery.SERVER_ENV),
                            super_client=True)
        self.ctx = rclpy.Context()
        # NO signal handlers: Ctrl-C belongs to the launcher (console.StopFlag).
        rclpy.init(context=self.ctx, domain_id=domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node(name, context=self.ctx, start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self._clients: dict[str, object] = {}
        self._diag: dict[str, tuple[float, dict[str, str]]] = {}   # name -> (stamp s, values)
        self._diag_status: dict[str, tuple[int, str]] = {}          # name -> (level, message)
        self._own: dict[str, list[int]] = {}   # node fqn -> process ids started for it, newest last
        self._host: tuple[int, ...] | None = None
        self.forged: dict[str, int] = {}       # node fqn -> statuses from a stranger, ignored
        self._diag_sub = SenderSubscription(self.node, DiagnosticArray, T.DIAGNOSTICS,
                                            qos.diagnostics_qos())

    def close(self) -> None:
        try:
            self.executor.shutdown(timeout_sec=1.0)
            self._diag_sub.destroy()
            self.node.destroy_node()
        finally:
            rclpy.try_shutdown(context=self.ctx)

    def spin(self, seconds: float = 0.05) -> None:
        """Handle what arrived (diagnostics, service answers) for up to `seconds`."""
        self.executor.spin_once(timeout_sec=seconds)
        for msg, gid in self._diag_sub.take():
            self._on_diag(msg, gid)

    def expect(self, node_fqn: str, pid: int) -> None:
        """`node_fqn` is the node of process `pid`, started by this launcher: its diagnostics
        are believed from now on (an earlier process's are dropped quietly)."""
        self._own.setdefault(node_fqn, []).append(int(pid))
        self._diag.pop(node_fqn, None)
        self._diag_status.pop(node_fqn, None)

    # ------------------------------------------------------------------ lifecycle
    def lifecycle_state(self, node_fqn: str, timeout: float = GET_STATE_TIMEOUT_S) -> str | None:
        """The label of `node_fqn`'s current state from its get_state service; None when the
        service is not there (yet) or did not answer in time."""
        client = self._clients.get(node_fqn)
        if client is None:
            client = self._clients[node_fqn] = self.node.create_client(GetState, f"{node_fqn}/get_state")
        if not client.service_is_ready():
            self.spin()
            return None
        future = client.call_async(GetState.Request())
        self.executor.spin_until_future_complete(future, timeout_sec=timeout)
        if not future.done():
            client.remove_pending_request(future)
            return None
        result = future.result()
        return result.current_state.label if result is not None else None

    # ------------------------------------------------------------------ graph
    def endpoints(self, topic: str, kind: str) -> list:
        """TopicEndpointInfo of the publishers (kind 'pub') or subscriptions ('sub') of topic."""
        get = (self.node.get_publishers_info_by_topic if kind == "pub"
               else self.node.get_subscriptions_info_by_topic)
        return list(get(topic))

    def gids(self, node_name: str, node_ns: str, topic: str, kind: str) -> set[tuple[int, ...]]:
        return {tuple(e.endpoint_gid) for e in self.endpoints(topic, kind)
                if e.node_name == node_name and e.node_namespace == node_ns}

    def snapshot(self, node_name: str, node_ns: str, wants: Iterable[tuple[str, str]]) -> set:
        """The endpoints a node of this name has now (an earlier process's, about to go)."""
        return {g for topic, kind in wants for g in self.gids(node_name, node_ns, topic, kind)}

    def has_endpoints(self, node_name: str, node_ns: str, wants: Iterable[tuple[str, str]],
                      old: set = frozenset()) -> bool:
        """The node has a new endpoint (not in `old`) of every (topic, kind) in `wants`."""
        return all(self.gids(node_name, node_ns, topic, kind) - old for topic, kind in wants)

    # ------------------------------------------------------------------ diagnostics
    def _own_host(self) -> tuple[int, ...] | None:
        """This machine's host bytes in a GID (from this launcher's own writers), once known."""
        if self._host is None:
            me = os.getpid() & 0xFFFF
            for topic in ("/rosout", "/parameter_events"):
                for e in self.node.get_publishers_info_by_topic(topic):
                    gid = tuple(e.endpoint_gid)
                    if e.node_name == self.node.get_name() and gid_pid(gid) == me:
                        self._host = gid[2:4]
        return self._host

    def _sender(self, name: str, gid: tuple[int, ...]) -> str | None:
        """'own', 'old' (an earlier process of ours), or None (a stranger, or not a node we
        started) for a status named `name` written by `gid`."""
        pids = self._own.get(name)
        if not pids:
            return None
        host = self._own_host()
        if host is not None and gid[2:4] != host:
            return None
        node_ns, _, node_name = name.rpartition("/")
        for e in self.node.get_publishers_info_by_topic(T.DIAGNOSTICS):
            if tuple(e.endpoint_gid)[:len(gid)] == gid and (
                    e.node_name != node_name or e.node_namespace != (node_ns or "/")):
                return None   # the graph knows this writer: another node's
        pid = gid_pid(gid)
        return "own" if pid == pids[-1] & 0xFFFF else "old" if pid in {p & 0xFFFF for p in pids} else None

    def _on_diag(self, msg, gid: tuple[int, ...]) -> None:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        for st in msg.status:
            sender = self._sender(st.name, gid)
            if sender != "own":
                if sender is None and st.name in self._own:
                    n = self.forged[st.name] = self.forged.get(st.name, 0) + 1
                    if n == 1:
                        print(f"[launcher] ignored a /diagnostics status claiming to be {st.name} from "
                              f"a process this launcher did not start (writer {bytes(gid).hex()}); such "
                              "statuses are counted, not believed", file=sys.stderr, flush=True)
                continue
            self._diag[st.name] = (stamp, {kv.key: kv.value for kv in st.values})
            level = st.level[0] if isinstance(st.level, (bytes, bytearray)) else int(st.level)
            self._diag_status[st.name] = (level, st.message)

    def diagnostics(self, node_fqn: str, newer_than: float | None = None) -> dict[str, str] | None:
        """The latest diagnostics values of `node_fqn` (stamped after `newer_than`, wall-clock
        seconds, if given) among those received so far; None if there is none."""
        self.spin(0.0)
        got = self._diag.get(node_fqn)
        if got is None or (newer_than is not None and got[0] < newer_than):
            return None
        return got[1]

    def diagnostic_status(self, node_fqn: str) -> tuple[int, str] | None:
        """(level, message) of `node_fqn`'s latest diagnostics (level 2 = ERROR), or None."""
        self.spin(0.0)
        return self._diag_status.get(node_fqn)

    # ------------------------------------------------------------------ waiting
    def wait(self, ready: Callable[[], bool], *, what: str, timeout: float,
             alive: Callable[[], str | None] = lambda: None, stop=None) -> bool:
        """Spin until `ready()`; TimeoutError naming `what`; `alive()` returns why the node is
        gone (its exit and log tail) to raise at once; False when `stop.stop` is raised."""
        return wait_until(ready, what=what, timeout=timeout, alive=alive, stop=stop,
                          pause=lambda: self.spin(0.05))
