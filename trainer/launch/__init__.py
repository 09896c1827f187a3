"""Starting and watching nodes as processes: the collect-train-reload loop, stacks and fleets,
the Discovery Server, the graph view launchers wait on.

May import: ROS, protocad_ros, sim_bridge.contract, sim_bridge.bridge, sim_bridge.nodekit (sender_gid, the Param tables), trainer.runs, trainer.run_input, trainer.run_config, trainer.torch_setup, trainer.metrics_log, trainer.cli_values, trainer.console, trainer.settings, trainer.data, trainer.learn, trainer.viz, trainer.nodes
"""
