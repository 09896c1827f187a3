"""Start, watch and stop the ROS node processes of the loop and of `--through-ros` evaluation.

Every node runs as its own process (`python -m sim_bridge.bridge.node`, `python -m
protocad_ros.node.policy_node`, `python -m trainer.nodes.recorder`, `python -m trainer.nodes.random_actor`)
with the environment of scripts/env.sh (AMENT_PREFIX_PATH, RMW_IMPLEMENTATION,
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, MUJOCO_GL) and one ROS_DOMAIN_ID per stack (unless given, a fresh
one: a domain no participant on this machine uses yet), output to LOG_DIR/<name>.log. Processes get their own session (a Ctrl-C
in the terminal reaches only the orchestrator, which stops them in order: bridge, actor,
recorder last so that it drains and closes its bag) and die with the orchestrator
(PR_SET_PDEATHSIG) if it is killed.

Readiness comes from ROS, not from the logs (trainer/launch/rosgraph.py): the managed nodes (bridge,
policy) are ready when their lifecycle state is `active`, the recorder and the random actor
when the graph shows their endpoints (the recorder's subscription to `action`, the actor's
action publisher and observation subscriptions). The logs stay for people.

Discovery: by default the usual way (no multicast: LOCALHOST). With a Fast DDS Discovery Server
(`discovery_server=HOST:PORT`, default $ROS_DISCOVERY_SERVER, or `start_discovery_server=(host,
port)` to run one as the stack's first process and stop it after the nodes) every node is a
discovery client of it; the recorder and the launcher's own graph view are super clients
(trainer/launch/discovery.py says why).
"""
from __future__ import annotations

import ctypes
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterable, Sequence

from protocad_ros.node.policy_params import PARAMS as POLICY_PARAMS
from sim_bridge.bridge.params import PARAMS as BRIDGE_PARAMS
from sim_bridge.contract import topics as T
from sim_bridge.nodekit.param_table import Param
from trainer.launch import discovery

ROOT = Path(__file__).resolve().parents[2]


class NodeFailed(RuntimeError):
    """A node process exited with an error or did not get ready (message has its log tail)."""


try:  # loaded here, in the parent: the child only calls the function (no loader work after fork)
    _prctl = ctypes.CDLL("libc.so.6", use_errno=True).prctl
except (OSError, AttributeError):  # pragma: no cover - not glibc
    _prctl = None


def _pdeathsig() -> None:  # runs in the child between fork and exec
    if _prctl is not None:
        _prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG: die with the orchestrator


#: The domain ids whose ports never collide with Linux's ephemeral ports (ROS 2's "safe" range).
FRESH_DOMAINS = range(1, 102)
#: Fast DDS's ports of domain d: PB + DG * d (+ offsets and 2 per participant), RTPS's defaults.
PORT_BASE, DOMAIN_GAIN = 7400, 250


def domains_in_use(tables: Sequence[str] = ("/proc/net/udp", "/proc/net/udp6")) -> set[int]:
    """The DDS domains with a participant on this machine: every Fast DDS (or other RTPS)
    participant binds unicast UDP ports in its domain's block of 250. Empty where the kernel's
    tables cannot be read (not Linux)."""
    used: set[int] = set()
    for table in tables:
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            try:
                port = int(line.split()[1].rsplit(":", 1)[1], 16)
            except (IndexError, ValueError):
                continue
            if port >= PORT_BASE:
                used.add((port - PORT_BASE) // DOMAIN_GAIN)
    return used


def fresh_domain_id(in_use: set[int] | None = None) -> int:
    """A domain id in 1..101 with no participant on this machine yet (domains_in_use), drawn
    per run: a second loop, a test suite or anyone else's nodes on this machine stay apart from
    this run's (a shared domain mixes their topics). All in use: any of them."""
    in_use = domains_in_use() if in_use is None else in_use
    free = [d for d in FRESH_DOMAINS if d not in in_use]
    return random.SystemRandom().choice(free or list(FRESH_DOMAINS))


def ros_env(domain_id: int | None = None, discovery_server: str | None = None,
            super_client: bool = False) -> dict[str, str]:
    """The environment of a node process: this machine only, the given domain, and discovery
    through `discovery_server` (a client; a super client if asked) or without one."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"    # DDS never leaves this machine
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    prefix = sys.prefix
    amp = env.get("AMENT_PREFIX_PATH", "")
    if prefix not in amp.split(os.pathsep):
        env["AMENT_PREFIX_PATH"] = os.pathsep.join(filter(None, [prefix, amp]))
    env.setdefault("MUJOCO_GL", "egl")
    env.setdefault("PYOPENGL_PLATFORM", env["MUJOCO_GL"])
    env["PYTHONUNBUFFERED"] = "1"
    if (ROOT / "trainer").is_dir() and (ROOT / "sim_bridge").is_dir():
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    env["ROS_DOMAIN_ID"] = str(domain_id if domain_id is not None else fresh_domain_id())
    return discovery.apply_env(env, discovery_server, super_client=super_client)


def recorder_endpoints(wait_topics: Iterable[str]) -> list[tuple[str, str]]:
    """What shows a recorder ready in the graph: its subscriptions to `wait_topics` (it
    subscribes only once its bag is open), or without any its /rosout publisher (it is up)."""
    return [(t, "sub") for t in wait_topics] or [("/rosout", "pub")]


class NodeProc:
    def __init__(self, name: str, args: Sequence[str], log_path: Path, env: dict[str, str]):
        self.name, self.args, self.log_path = name, list(args), Path(log_path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "ab")
        self._log.write(f"$ {' '.join(self.args)}\n".encode())
        self._log.flush()
        self.p = subprocess.Popen(self.args, stdout=self._log, stderr=subprocess.STDOUT, env=env,
                                  start_new_session=True, preexec_fn=_pdeathsig)
        self.started = time.monotonic()

    @property
    def pid(self) -> int:
        return self.p.pid

    def alive(self) -> bool:
        return self.p.poll() is None

    def output(self) -> str:
        self._log.flush()
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def tail(self, n: int = 25) -> str:
        return "\n".join(self.output().splitlines()[-n:])

    def gone(self) -> str | None:
        """Why the process is no longer running (exit code and log tail), None while it runs."""
        if self.alive():
            return None
        return f"{self.name} exited with code {self.p.returncode}"

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int | None:
        if self.alive():
            try:
                os.killpg(self.p.pid, sig)
            except ProcessLookupError:
                pass
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(self.p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self.p.wait()
        if not self._log.closed:
            self._log.close()
        return self.p.returncode


def robot_namespaces(base: str, robots: int, first: int | None = None) -> list[str]:
    """One robot: the base namespace; several: BASE/robot0, BASE/robot1, ... (each its own
    bridge, policy and /clock). With `first` (groups of a fleet on several machines, whose
    names must not collide): BASE/robotFIRST ... always, even for one."""
    if robots < 1:
        raise ValueError(f"robots must be >= 1, got {robots}")
    if first is None and robots == 1:
        return [base]
    return [T.topic_name(base, f"robot{i}") for i in range(first or 0, (first or 0) + robots)]


DISCOVERY_SERVER = "discovery_server"   # its process name in a RosStack


def node_params(node: str, table: Sequence[Param], given: dict[str, Any],
                required: Sequence[str] = ()) -> dict[str, Any]:
    """`given` as a launcher passes it to a node with `-p`: each name one of the node's Param
    table (TypeError naming the valid ones otherwise), paths as text, float parameters as
    floats; None or "" leaves the node's default."""
    rows = {p.name: p for p in table}
    unknown = sorted(set(given) - set(rows))
    missing = [k for k in required if given.get(k) in (None, "")]
    if unknown or missing:
        raise TypeError(f"the {node} node: {'no parameter ' + ', '.join(unknown) if unknown else ''}"
                        f"{'; ' if unknown and missing else ''}{'needs ' + ', '.join(missing) if missing else ''}"
                        f" (its parameters: {', '.join(sorted(rows))})")
    out = {}
    for k, v in given.items():
        if v is None or v == "":
            continue
        out[k] = float(v) if isinstance(rows[k].default, float) else str(v) if isinstance(v, Path) else v
    return out


class RosStack:
    """The node processes of one run, sharing a ROS domain: one robot in `namespace`, or
    several (`ns` of each start_* call; process names then carry '@NS')."""

    def __init__(self, log_dir: str | Path, *, domain_id: int | None = None,
                 namespace: str = T.DEFAULT_NAMESPACE, discovery_server: str | None = None,
                 start_discovery_server: tuple[str, int] | None = None, ready_timeout: float = 20.0):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, NodeProc] = {}
        self._graph = None
        self.forged: dict[str, int] = {}   # node fqn -> statuses from strangers (RosGraph)
        if start_discovery_server is not None:
            discovery_server = self._start_discovery_server(*start_discovery_server, timeout=ready_timeout)
        #: the Discovery Server every node uses (None: the usual discovery, no server)
        self.discovery_server = discovery_server or os.environ.get(discovery.SERVER_ENV) or None
        self.env = ros_env(domain_id, self.discovery_server)
        self.domain_id = int(self.env["ROS_DOMAIN_ID"])
        self.super_env = ros_env(self.domain_id, self.discovery_server, super_client=True)
        self.namespace = namespace

    def _start_discovery_server(self, host: str, port: int, timeout: float) -> str:
        warning = discovery.exposure_warning(host)
        if warning:
            print(f"[{DISCOVERY_SERVER}] {warning}", file=sys.stderr, flush=True)
        # Its own ROS_DOMAIN_ID does not matter: the server takes no domain option and serves
        # the clients that reach its address, whatever their domain.
        proc = NodeProc(DISCOVERY_SERVER, discovery.server_command(host, port),
                        self.log_dir / f"{DISCOVERY_SERVER}.log", ros_env(0))
        self.procs[DISCOVERY_SERVER] = proc
        try:
            discovery.wait_listening(proc.pid, port, proc.gone, timeout)
        except (RuntimeError, TimeoutError) as exc:
            why = f"{DISCOVERY_SERVER} on {host}:{port}: {exc}; log {proc.log_path}:\n{proc.tail()}"
            proc.stop()
            raise NodeFailed(why) from None
        return discovery.connect_address(host, port)

    def describe_discovery(self) -> str:
        """One line for the launchers' banners."""
        if not self.discovery_server:
            return "discovery without a server (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)"
        own = self.procs.get(DISCOVERY_SERVER)
        return (f"discovery through the Fast DDS Discovery Server {self.discovery_server}"
                + (f" (started here, pid {own.pid})" if own is not None else ""))

    @property
    def graph(self):
        """The launcher's RosGraph on this stack's domain (made at first use)."""
        if self._graph is None:
            # rclpy only where a launcher talks to its nodes: evaluate and compare import this
            # module at startup, on the GPU machine without ROS too.
            from trainer.launch.rosgraph import RosGraph

            self._graph = RosGraph(self.domain_id, discovery_server=self.discovery_server)
        return self._graph

    def close_graph(self) -> None:
        if self._graph is not None:
            graph, self._graph = self._graph, None
            for name, n in graph.forged.items():
                self.forged[name] = self.forged.get(name, 0) + n
            graph.close()

    def forged_note(self) -> str | None:
        """One line on the statuses strangers sent under the names of this stack's nodes."""
        if self._graph is not None:
            forged = {k: self.forged.get(k, 0) + v for k, v in self._graph.forged.items()}
        else:
            forged = self.forged
        if not forged:
            return None
        return (f"{sum(forged.values())} forged /diagnostics status(es) ignored (sent by processes this "
                "launcher did not start, under the names " + ", ".join(sorted(forged)) + ")")

    def node_fqn(self, node_name: str, ns: str | None = None) -> str:
        return T.topic_name(ns or self.namespace, node_name)

    def key(self, name: str, ns: str | None = None) -> str:
        """The process name of `name` in robot namespace `ns` ('bridge', 'bridge@/protocad/robot1')."""
        return name if ns in (None, self.namespace) else f"{name}@{ns}"

    def _ns_args(self, ns: str | None) -> list[str]:
        ns = ns or self.namespace
        out = ["-r", f"__ns:={ns}"]
        if ns != self.namespace:
            out += ["-r", f"{T.CLOCK}:={T.clock_topic(ns)}"]
        return out

    def wait_until(self, proc: NodeProc, ready, what: str, timeout: float, stop=None) -> bool:
        """Wait for `ready()` (NodeFailed with the log tail if the process exits first or the
        time runs out); False when `stop` (a console.StopFlag) is raised."""
        try:
            return self.graph.wait(ready, what=what, timeout=timeout, alive=proc.gone, stop=stop)
        except (RuntimeError, TimeoutError) as exc:
            raise NodeFailed(f"{proc.name}: {exc}; log {proc.log_path}:\n{proc.tail()}") from None

    def wait_active(self, proc: NodeProc, node_name: str, timeout: float, stop=None,
                    ns: str | None = None) -> bool:
        """A managed node: wait until its lifecycle state is `active`: get_state says so, and
        so do its own diagnostics (RosGraph believes only the process `proc`'s)."""
        fqn = self.node_fqn(node_name, ns)
        self.graph.expect(fqn, proc.pid)

        def active() -> bool:
            return (self.graph.lifecycle_state(fqn) == "active"
                    and (self.graph.diagnostics(fqn) or {}).get("lifecycle_state") == "active")

        return self.wait_until(proc, active, f"lifecycle state active of {fqn}", timeout, stop)

    def wait_endpoints(self, proc: NodeProc, node_name: str, node_ns: str,
                       wants: Sequence[tuple[str, str]], timeout: float, *, stop=None,
                       old: set = frozenset()) -> bool:
        """An unmanaged node: wait until the graph shows its new endpoints `wants`, (topic,
        'pub' | 'sub') pairs; `old` = endpoints of an earlier process (RosGraph.snapshot)."""
        what = ", ".join(f"{kind} {topic}" for topic, kind in wants)
        return self.wait_until(proc, lambda: self.graph.has_endpoints(node_name, node_ns, wants, old),
                          f"{node_name} in the ROS graph with {what}", timeout, stop)

    def _spawn(self, name: str, module: str, args: Sequence[str], log_name: str | None = None,
               super_client: bool = False) -> NodeProc:
        old = self.procs.get(name)
        if old is not None and old.alive():
            raise RuntimeError(f"{name} is already running (pid {old.pid})")
        if log_name is None:   # 'policy@/protocad/robot1' -> policy_robot1.log
            kind, _, ns = name.partition("@")
            log_name = kind + (f"_{ns.rstrip('/').rsplit('/', 1)[-1]}" if ns else "")
        proc = NodeProc(name, [sys.executable, "-m", module, *args], self.log_dir / f"{log_name}.log",
                        self.super_env if super_client else self.env)
        self.procs[name] = proc
        return proc

    @staticmethod
    def _params(**params) -> list[str]:
        out = []
        for k, v in params.items():
            if v is None:
                continue
            if isinstance(v, bool):
                v = "true" if v else "false"
            out += ["-p", f"{k}:={v}"]
        return out

    def start_bridge(self, *, log_name: str | None = None, ns: str | None = None, closed_control: bool = False,
                     **params: Any) -> NodeProc:
        """A lock-step sim bridge with these of its parameters (sim_bridge/bridge/params.py; task
        is needed; min_subscribers is 2 unless given: its actor and a recorder). closed_control:
        no reset service, no lifecycle transitions from other processes (what protocad-fleet
        gives nodes that anyone on the fleet's network can reach)."""
        values = node_params("bridge", BRIDGE_PARAMS, {"min_subscribers": 2, **params, "mode": "lockstep"},
                             required=("task",))
        if closed_control:
            values.update(reset_service=False, remote_lifecycle=False)
        args = ["--ros-args", *self._params(**values), *self._ns_args(ns)]
        return self._spawn(self.key("bridge", ns), "sim_bridge.bridge.node", args, log_name)

    def start_policy(self, *, ready_timeout: float = 120.0, ns: str | None = None, closed_control: bool = False,
                     **params: Any) -> NodeProc:
        """A policy node with these of its parameters (protocad_ros/node/policy_params.py; task is
        needed; reload_poll_s is 0.5 unless given), once it is active. trusted_keys: the public
        key(s) whose signature a checkpoint needs (the run key's); allow_unsigned: with
        checkpoint_topic and no keys, start anyway (said loudly); min_checkpoint_seq: no signed
        version below it is taken (the policy's floor from the start). closed_control: no
        lifecycle transitions from other processes."""
        values = node_params("policy", POLICY_PARAMS, {"reload_poll_s": 0.5, **params}, required=("task",))
        if closed_control:
            values["remote_lifecycle"] = False
        args = ["--ros-args", *self._params(**values), *self._ns_args(ns)]
        proc = self._spawn(self.key("policy", ns), "protocad_ros.node.policy_node", args)
        self.wait_active(proc, "policy", ready_timeout, ns=ns)
        return proc

    def wait_checkpoint_loaded(self, proc: NodeProc, timeout: float, ns: str | None = None) -> bool:
        """Until the policy node holds a checkpoint: serving it (diagnostics' checkpoint_updates
        >= 0) or loaded and served from the next is_first (pending_checkpoint_updates >= 0), so
        that the first episode is not the random agent's it starts with while none has come."""
        fqn = self.node_fqn("policy", ns)

        def loaded() -> bool:
            d = self.graph.diagnostics(fqn) or {}
            return any(v.lstrip("-").isdigit() and int(v) >= 0
                       for v in (d.get("checkpoint_updates", "-1"), d.get("pending_checkpoint_updates", "-1")))

        return self.wait_until(proc, loaded, f"{fqn} to hold a checkpoint", timeout)

    def start_checkpoint_publisher(self, checkpoint: str | Path, *, topic: str = T.CHECKPOINT,
                                   ready_timeout: float = 60.0, signing_key: str | Path | None = None) -> NodeProc:
        """The learner side of checkpoints over ROS (trainer/nodes/checkpoint_publisher.py) on
        `checkpoint`, signing with `signing_key` (the run key's private half)."""
        node_ns = "/" + self.namespace.strip("/")
        announce = topic if topic.startswith("/") else f"{node_ns}/{topic}"
        wants = [(announce, "pub")]
        old = self.graph.snapshot("checkpoint_publisher", node_ns, wants)
        args = ["--ros-args", *self._params(checkpoint=str(checkpoint), topic=topic,
                                            signing_key=str(signing_key) if signing_key else None),
                *self._ns_args(None)]
        proc = self._spawn("checkpoint_publisher", "trainer.nodes.checkpoint_publisher", args)
        self.wait_endpoints(proc, "checkpoint_publisher", node_ns, wants, ready_timeout, old=old)
        return proc

    def start_random_actor(self, *, task: str, seed: int = 0, ready_timeout: float = 60.0,
                           ns: str | None = None) -> NodeProc:
        args = ["--ros-args", *self._params(task=task, seed=seed), *self._ns_args(ns)]
        node_ns = "/" + (ns or self.namespace).strip("/")
        wants = [(self.node_fqn(T.ACTION, ns), "pub"), (self.node_fqn(T.IMAGE, ns), "sub"),
                 (self.node_fqn(T.STEP_INFO, ns), "sub")]
        old = self.graph.snapshot("random_actor", node_ns, wants)
        proc = self._spawn(self.key("actor", ns), "trainer.nodes.random_actor", args)
        self.wait_endpoints(proc, "random_actor", node_ns, wants, ready_timeout, old=old)
        return proc

    def start_recorder(self, bag: str | Path, *, extra_topics: Iterable[str] = (T.DIAGNOSTICS,),
                       wait_topics: Iterable[str] = (), ready_timeout: float = 60.0,
                       log_name: str | None = None, namespaces: Sequence[str] | None = None) -> NodeProc:
        """One recorder for the robots in `namespaces` (default: this stack's namespace)."""
        # The bag library (mcap) only where a recorder starts: evaluate and compare import this
        # module at startup.
        from trainer.nodes.recorder_topics import default_topics

        topics = [t if t != T.CLOCK else T.clock_topic(ns)
                  for ns in (namespaces or [self.namespace]) for t in default_topics(ns)]
        topics += [t for t in extra_topics]
        args = ["-o", str(bag), "--namespace", self.namespace, "--flush-interval", "1.0",
                "--topics", *topics]   # bounded by the recorder's defaults (record_budget.contract_bounds)
        wants = recorder_endpoints(wait_topics)
        old = self.graph.snapshot("recorder", "/", wants)
        # A super client: it reads topic types from the graph before it subscribes to them.
        proc = self._spawn("recorder", "trainer.nodes.recorder", args, log_name, super_client=True)
        self.wait_endpoints(proc, "recorder", "/", wants, ready_timeout, old=old)
        return proc

    def wait_exit(self, proc: NodeProc, timeout: float, *, watch: Sequence[str] = ("policy", "actor", "recorder"),
                  stop=None) -> int:
        """Wait for `proc` to exit (code 0 expected); NodeFailed if it fails or a watched
        process dies meanwhile; returns -1 when `stop` (a console.StopFlag) is raised."""
        deadline = time.monotonic() + timeout
        while proc.alive():
            if stop is not None and stop.stop:
                return -1
            for name, other in list(self.procs.items()):
                if name.split("@")[0] not in watch and name != DISCOVERY_SERVER:
                    continue
                if other is not proc and not other.alive() and other.p.returncode not in (0, None):
                    raise NodeFailed(f"{name} died with code {other.p.returncode}; log "
                                     f"{other.log_path}:\n{other.tail()}")
            if time.monotonic() > deadline:
                raise NodeFailed(f"{proc.name} still running after {timeout:.0f}s; log {proc.log_path}:\n{proc.tail()}")
            time.sleep(0.2)
        if proc.p.returncode != 0:
            raise NodeFailed(f"{proc.name} exited with code {proc.p.returncode}; log {proc.log_path}:\n{proc.tail()}")
        return 0

    def stop(self, name: str, sig: int = signal.SIGINT, timeout: float = 20.0) -> int | None:
        proc = self.procs.get(name)
        return proc.stop(sig, timeout) if proc is not None else None

    def stop_all(self) -> dict[str, int | None]:
        """Bridges first (no new observations), then actors, the recorder (drains), the
        discovery server after every node."""
        self.close_graph()
        codes = {}
        for kind in ("bridge", "actor", "policy", "recorder"):
            for name in [n for n in self.procs if n.split("@")[0] == kind]:
                codes[name] = self.stop(name)
        for name in [n for n in self.procs if n not in codes and n != DISCOVERY_SERVER]:
            codes[name] = self.stop(name)
        if DISCOVERY_SERVER in self.procs:
            codes[DISCOVERY_SERVER] = self.stop(DISCOVERY_SERVER)
        return codes
