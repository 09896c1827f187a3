"""Logs, learning and running the loop (ROS package `trainer`).

  bag/       rosbag2-layout MCAP writing and reading, ROS 2 message (de)serialisation (no ROS)
  data/      the dataset over bags: the store, the batch sampler, what it reads and reports
  learn/     training (one process or data-parallel) and evaluation on contexts
  research/  the ROS-free online runs (Algorithm 1), grids of them and their statistics
  viz/       rerun recordings: training metrics and the latent-context views
  nodes/     the recorder, the random actor and the checkpoint publisher (ROS nodes)
  launch/    starting the nodes: the collect-train-reload loop, stacks, fleets, discovery
  ros2cli/   the `ros2` front-end for environments without ros2cli
  (here)     runs.py: run directories, metrics files, CLI helpers every command uses;
             settings.py: typed run settings and the command lines generated from them;
             provenance.py: the commit a run trains with (stdlib only: setup.py loads it)

May import: protocad_ros.atomic, protocad_ros.checkpoint.files (its file names), protocad_ros.model, sim_bridge.contract
"""
