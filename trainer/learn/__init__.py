"""Learning from the data: the trainer (one process or data-parallel over torch.distributed) and
evaluation of checkpoints on train or test contexts. No ROS.

May import: protocad_ros, sim_bridge.contract, sim_bridge.sim, trainer.runs, trainer.run_input, trainer.run_config, trainer.torch_setup, trainer.metrics_log, trainer.cli_values, trainer.console, trainer.settings, trainer.data, trainer.viz
"""
