"""The trainer's ROS 2 nodes: the recorder (MCAP bags), the random actor and the checkpoint
publisher.

May import: ROS, protocad_ros, sim_bridge.contract, sim_bridge.nodekit, trainer.runs, trainer.run_config, trainer.torch_setup, trainer.metrics_log, trainer.cli_values, trainer.console, trainer.settings, trainer.bag, trainer.data
"""
