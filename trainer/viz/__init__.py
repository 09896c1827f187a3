"""rerun recordings: training metrics on the update timeline and the latent-context views
(embeddings, prototypes, assignments, reconstructions) of a checkpoint. No ROS.

May import: protocad_ros, sim_bridge.contract, sim_bridge.sim, trainer.runs, trainer.run_config, trainer.torch_setup, trainer.metrics_log, trainer.cli_values, trainer.console, trainer.settings, trainer.data
"""
