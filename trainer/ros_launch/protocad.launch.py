"""`ros2 launch trainer protocad.launch.py`: the sim bridge, the policy node and the recorder,
for users with a full ROS 2 install (launch, launch_ros). The same three nodes and parameters
as `protocad-stack` (trainer/launch/stack.py), which needs no launch system and also waits for each
node's state; here the bridge's own wait does the ordering: it steps only once
`min_subscribers` (the policy and the recorder) read its observations, so the bag still holds
every step from stamp 0.

    ros2 launch trainer protocad.launch.py task:=walker_walk split:=test \\
        checkpoint:=runs/X/checkpoints/latest.pt output:=runs/X/bags/session1
    ros2 launch trainer protocad.launch.py record:=false max_episodes:=5

Arguments: task, split, checkpoint ('' = a random agent), output (the bag directory), record,
max_episodes (0 = until shut down), namespace.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

ARGUMENTS = {
    "task": ("pendulum_swingup", "context-randomized DMC task of the bridge (and a random agent)"),
    "split": ("train", "context split the bridge draws from: train or test"),
    "checkpoint": ("", "the policy's checkpoint file; empty: a random agent"),
    "output": ("protocad_bag", "bag directory the recorder writes"),
    "record": ("true", "start the recorder"),
    "max_episodes": ("0", "the bridge stops after this many episodes (0: never)"),
    "namespace": ("/protocad", "namespace of the bridge and the policy"),
}


def generate_launch_description() -> LaunchDescription:
    arg = LaunchConfiguration
    record = arg("record")
    # the bridge waits for the policy, and for the recorder when there is one
    readers = PythonExpression(["2 if '", record, "'.lower() == 'true' else 1"])
    return LaunchDescription([
        *(DeclareLaunchArgument(name, default_value=default, description=text)
          for name, (default, text) in ARGUMENTS.items()),
        Node(package="trainer", executable="record", name="recorder", output="screen",
             arguments=["--output", arg("output"), "--namespace", arg("namespace")],
             condition=IfCondition(record)),
        Node(package="protocad_ros", executable="policy", namespace=arg("namespace"), output="screen",
             parameters=[{"checkpoint": arg("checkpoint"), "task": arg("task")}]),
        Node(package="sim_bridge", executable="node", namespace=arg("namespace"), output="screen",
             parameters=[{"task": arg("task"), "split": arg("split"),
                          "max_episodes": arg("max_episodes"), "min_subscribers": readers}]),
    ])
