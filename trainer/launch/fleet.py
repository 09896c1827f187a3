"""`protocad-fleet`: one machine's share of a fleet, discovering through a Fast DDS
Discovery Server: M actor groups (a sim bridge and an actor each, in /protocad/robotK), and/or
one recorder for the fleet's namespaces, and/or the server itself.

    # machine A (server, recorder, the learner's checkpoints on /protocad/checkpoint, signed
    # with the run key it makes in runs/fleet/keys/: copy keys/checkpoint.pub to B and C)
    protocad-fleet --start-discovery-server 0.0.0.0:11811 --robots 4 --no-actors --run-dir runs/fleet \\
        --record runs/fleet/bags/session1 --publish-checkpoint runs/fleet/checkpoints/latest.pt
    # machines B and C: two actor groups each, robot0-1 and robot2-3, fed over ROS
    protocad-fleet --discovery-server A:11811 --robots 2 --first-robot 0 --task walker_walk \\
        --checkpoint policy/latest.pt --checkpoint-topic /protocad/checkpoint --trusted-key checkpoint.pub
    protocad-fleet --discovery-server A:11811 --robots 2 --first-robot 2 --task walker_walk \\
        --checkpoint policy/latest.pt --checkpoint-topic /protocad/checkpoint --trusted-key checkpoint.pub
    # A again: train on every robot's episodes
    protocad-train --logs runs/fleet/bags --namespace /protocad/robot0 /protocad/robot1 ...

Every machine uses the same ROS_DOMAIN_ID (--domain-id, default $ROS_DOMAIN_ID) and the same
server; robot names must not repeat across machines (--first-robot). The actor is a policy node
on --checkpoint (it waits for the file and reloads it whenever it changes: a shared file system;
or, with --checkpoint-topic, it receives every new version a checkpoint publisher announces,
which the learner's machine runs with --publish-checkpoint) or, without one, uniform random
actions. Checkpoints over ROS are signed by default: the publisher signs with the run key
(RUN_DIR/keys/checkpoint.key, mode 0600, made on first use, reused when --run-dir is given
again) and every policy node trusts only its public key (--trusted-key, default this run's
keys/checkpoint.pub); --allow-unsigned turns both off. Each bridge runs lock-step and waits for --min-subscribers readers (default 2: its actor and a recorder, on whichever
machine) before its first step, so the bag misses nothing: start the recorder first. Ctrl-C
stops every process (the recorder last, the server after it); with --episodes N the actor groups
end by themselves after N episodes per robot. Node logs in --log-dir.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from protocad_ros.checkpoint.signing import SigningError, next_seq
from protocad_ros.model.hyperparameters import DEFAULT_CLI_PRESET, PRESETS, VARIANTS
from sim_bridge.contract import topics as T
from trainer import cli_values, console
from trainer.launch import discovery, run_key
from trainer.launch.rosprocs import NodeFailed, RosStack, robot_namespaces
from trainer.launch.stack import checkpoint_mismatch
from trainer.settings import arg, build, settings_parser


@dataclass
class FleetSettings(discovery.DiscoverySettings):
    """protocad-fleet's options: this machine's share of the fleet (and how it discovers)."""

    robots: int = arg(1, type=cli_values.positive_int)
    """robots (actor groups / recorded namespaces) on this machine"""
    first_robot: int = arg(0, type=cli_values.non_negative_int)
    """number of the first robot: /protocad/robotFIRST ... (distinct per machine)"""
    no_actors: bool = False
    """start no actor group (e.g. only the recorder)"""
    record: str | None = arg(None, metavar="BAG")
    """also record the robots' topics into this bag"""
    task: str = "pendulum_swingup"
    """the actor groups' task"""
    variant: str | None = arg(None, choices=VARIANTS)
    """the learner's variant (default: the policy node's, protocad): the policy's random agent
    until a checkpoint arrives, and checkpoints of another variant are refused"""
    preset: str | None = arg(None, choices=PRESETS,
                             help=f"the learner's model preset (default: the policy node's, {DEFAULT_CLI_PRESET}): "
                                  "checkpoints of other layer sizes are refused while the random agent serves")
    checkpoint: str | None = None
    """the policy nodes' checkpoint (default: random actions); with --checkpoint-topic their own
    copy of what they receive"""
    checkpoint_topic: str | None = arg(None, metavar="TOPIC")
    """the policy nodes receive checkpoints over ROS from a checkpoint publisher announcing on
    TOPIC (e.g. /protocad/checkpoint, absolute so that every robot hears the one publisher),
    written to --checkpoint and served from the next episode"""
    wait_for_checkpoint: bool = False
    """with --checkpoint-topic: each bridge starts only once its policy serves a received
    checkpoint (no episode of the random agent it starts with)"""
    publish_checkpoint: str | None = arg(None, metavar="FILE")
    """also run the checkpoint publisher on the learner's FILE, announcing on --checkpoint-topic
    (default /protocad/checkpoint)"""
    exploration_noise: float = 0.0
    """policy nodes' exploration noise"""
    episodes: int = arg(0, type=cli_values.non_negative_int)
    """episodes per robot, then the groups end (0: until Ctrl-C)"""
    episode_length: int = arg(500, type=cli_values.positive_int)
    """agent steps per episode"""
    action_repeat: int = arg(2, type=cli_values.positive_int)
    """the bridges' action repeat"""
    min_subscribers: int = arg(2, type=cli_values.positive_int)
    """readers each bridge waits for before stepping (its actor + a recorder)"""
    seed: int = 0
    """seeds robot I's actor (SEED + FIRST + I) and bridge (1000 SEED + FIRST + I)"""
    domain_id: int | None = None
    """ROS_DOMAIN_ID, the same on every machine (default $ROS_DOMAIN_ID)"""
    run_dir: str | None = None
    """the fleet's directory: its run key (keys/checkpoint.key, made on first use, reused on the
    next run) and the node logs (default: the parent of --log-dir, else runs/fleet-STAMP)"""
    log_dir: str | None = None
    """node logs (default RUN_DIR/logs)"""
    trusted_key: str | None = arg(None, metavar="PUB")
    """public key file the policy nodes trust: only checkpoints it signed are served (default:
    this run's keys/checkpoint.pub; on an actor machine, the learner machine's copy)"""
    allow_unsigned: bool = False
    """no signatures: the publisher does not sign and the policy nodes serve unsigned checkpoints
    received over --checkpoint-topic (anyone on the domain can replace the model;
    msgs_docs/security.md)"""
    min_checkpoint_seq: int | None = arg(None, type=cli_values.non_negative_int, metavar="SEQ")
    """with --trusted-key: the policy nodes take no signed version below SEQ (their rollback floor
    from the first message, also on a brand-new robot). Default: with --publish-checkpoint, the
    time this fleet starts its publisher in ms (seq is the signer's clock: every version it signs
    is above, every one signed before is refused); else 0, none (on an actor machine give the
    publisher's current seq: its /diagnostics or FILE.sig)"""
    ready_timeout: float = 120.0
    """seconds each node may take to start"""
    open_control_plane: bool = False
    """let other processes reset episodes and change the nodes' lifecycle states (closed by
    default here: anyone on the fleet's network reaches the domain; reset_service:=false,
    remote_lifecycle:=false)"""


def build_parser() -> argparse.ArgumentParser:
    return settings_parser("protocad-fleet", __doc__.split("\n\n")[0], [(None, FleetSettings)],
                           epilog=__doc__.split("\n\n", 1)[1])


def run(a: FleetSettings) -> int:
    mismatch = checkpoint_mismatch({"bridge": {"task": a.task}, "policy": {"checkpoint": a.checkpoint}})
    if mismatch:   # before any node: its policies would refuse every bridge
        print(f"protocad-fleet: error: {mismatch.replace('bridge.task', '--task')}", file=sys.stderr)
        return 2
    namespaces = robot_namespaces(T.DEFAULT_NAMESPACE, a.robots, first=a.first_robot)
    run_dir = Path(a.run_dir or (Path(a.log_dir).parent if a.log_dir else time.strftime("runs/fleet-%Y%m%d-%H%M%S")))
    log_dir = Path(a.log_dir or run_dir / "logs")
    try:
        signing_key, trusted = fleet_keys(a, run_dir)
    except (SigningError, OSError) as exc:
        print(f"protocad-fleet: error: {exc}", file=sys.stderr)
        return 2
    server, start_server = discovery.from_args(a)
    stack = RosStack(log_dir, domain_id=a.domain_id, discovery_server=server, start_discovery_server=start_server,
                     ready_timeout=a.ready_timeout)
    print(f"[fleet] ROS_DOMAIN_ID={stack.domain_id}; {stack.describe_discovery()}; robots "
          f"{', '.join(namespaces)}; logs in {log_dir}", flush=True)
    bridges = []
    with console.StopFlag() as stop:
        try:
            if a.record:
                stack.start_recorder(a.record, namespaces=namespaces, ready_timeout=a.ready_timeout)
                print(f"[fleet] recording {len(namespaces)} robot(s) into {a.record}", flush=True)
            min_seq = a.min_checkpoint_seq or 0
            if a.publish_checkpoint:
                if a.min_checkpoint_seq is None and trusted is not None:
                    min_seq = next_seq()   # before the publisher starts: each version it signs is above
                topic = a.checkpoint_topic or "/" + T.DEFAULT_NAMESPACE.strip("/") + "/" + T.CHECKPOINT
                stack.start_checkpoint_publisher(a.publish_checkpoint, topic=topic, ready_timeout=a.ready_timeout,
                                                 signing_key=signing_key.private if signing_key else None)
                print(f"[fleet] publishing {a.publish_checkpoint} on {topic}"
                      + (f", signed: {run_key.describe(signing_key)}" if signing_key else ", UNSIGNED (--allow-unsigned)"),
                      flush=True)
            for i, ns in enumerate([] if a.no_actors else namespaces):
                seed = a.seed + a.first_robot + i
                if a.checkpoint:
                    policy = stack.start_policy(
                        checkpoint=a.checkpoint, task=a.task, wait_for_checkpoint=True, reload_poll_s=1.0,
                        mode="sample", exploration_noise=a.exploration_noise, seed=seed,
                        variant=a.variant, preset=a.preset,
                        ready_timeout=a.ready_timeout, ns=ns, checkpoint_topic=a.checkpoint_topic,
                        closed_control=not a.open_control_plane, trusted_keys=trusted,
                        allow_unsigned=a.allow_unsigned, min_checkpoint_seq=min_seq if trusted else 0)
                    if a.wait_for_checkpoint:
                        stack.wait_checkpoint_loaded(policy, a.ready_timeout, ns=ns)
                else:
                    stack.start_random_actor(task=a.task, seed=seed, ready_timeout=a.ready_timeout, ns=ns)
                bridges.append(stack.start_bridge(task=a.task, seed=1000 * a.seed + a.first_robot + i,
                                                  max_episodes=a.episodes, episode_length=a.episode_length,
                                                  action_repeat=a.action_repeat, min_subscribers=a.min_subscribers,
                                                  ns=ns, closed_control=not a.open_control_plane))
            print(f"[fleet] running {len(bridges)} actor group(s)" + (f", {a.episodes} episode(s) each" if
                  a.episodes and bridges else "") + ": Ctrl-C stops every node", flush=True)
            while not stop.stop:
                if bridges and all(b.p.poll() == 0 for b in bridges):
                    print("[fleet] every bridge finished", flush=True)
                    break
                dead = [n for n, p in stack.procs.items() if not p.alive() and p.p.returncode != 0]
                if dead:
                    raise NodeFailed(", ".join(f"{n} exited with code {stack.procs[n].p.returncode}; log "
                                               f"{stack.procs[n].log_path}" for n in dead))
                time.sleep(0.2)
        except NodeFailed as exc:
            print(f"[fleet] {exc}", file=sys.stderr, flush=True)
            failed = True
        else:
            failed = False
        finally:
            codes = stack.stop_all()
    if stack.forged_note():
        print(f"[fleet] {stack.forged_note()}", file=sys.stderr, flush=True)
    print("[fleet] exit codes: " + ", ".join(f"{n} {c}" for n, c in codes.items()), flush=True)
    return 1 if failed else 0


def fleet_keys(a: FleetSettings, run_dir: Path) -> tuple[run_key.RunKey | None, Path | None]:
    """(the run key the publisher signs with, the public key the policy nodes trust): signed by
    default wherever checkpoints travel over ROS; (None, None) with --allow-unsigned. A policy
    node that receives checkpoints needs a key to trust: SigningError names the fix."""
    if a.allow_unsigned:
        return None, Path(a.trusted_key) if a.trusted_key else None
    key = run_key.run_key(run_dir) if a.publish_checkpoint else None
    trusted = Path(a.trusted_key) if a.trusted_key else key.public if key else None
    if trusted is None and run_key.key_paths(run_dir)[1].is_file():
        trusted = run_key.key_paths(run_dir)[1]
    receives = a.checkpoint_topic and a.checkpoint and not a.no_actors
    if receives and trusted is None:
        raise SigningError("--checkpoint-topic needs the public key of the machine that publishes the "
                           "checkpoints: --trusted-key FILE.pub (its RUN_DIR/keys/checkpoint.pub), or "
                           "--allow-unsigned")
    if trusted is not None and not trusted.is_file():
        raise SigningError(f"--trusted-key {trusted}: no such file")
    # A shared checkpoint file without the topic: signatures only when a key is named for it.
    return key, trusted if receives or a.trusted_key else None


def main(argv: Sequence[str] | None = None) -> int:
    a = build(FleetSettings, vars(build_parser().parse_args(argv)))
    if (a.checkpoint_topic or a.wait_for_checkpoint) and not a.checkpoint and not a.no_actors:
        print("protocad-fleet: error: --checkpoint-topic / --wait-for-checkpoint need --checkpoint (the policy "
              "nodes' own copy of what they receive)", file=sys.stderr)
        return 2
    if a.no_actors and not a.record and not a.start_discovery_server and not a.publish_checkpoint:
        print("protocad-fleet: error: --no-actors without --record or --start-discovery-server "
              "starts nothing", file=sys.stderr)
        return 2
    if a.domain_id is None:
        if not os.environ.get("ROS_DOMAIN_ID", "").isdigit():
            print("protocad-fleet: error: give --domain-id (the same on every machine of the fleet) "
                  "or set ROS_DOMAIN_ID", file=sys.stderr)
            return 2
        a = dataclasses.replace(a, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    try:
        return run(a)
    except (NodeFailed, FileNotFoundError) as exc:   # e.g. the discovery server did not start
        print(f"protocad-fleet: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
