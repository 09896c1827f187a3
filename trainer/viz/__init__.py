"""rerun recordings: training metrics on the update timeline and the latent-context views
(embeddings, prototypes, assignments, reconstructions) of a checkpoint. No ROS.

May import: protocad_ros, sim_bridge.contract, sim_bridge.sim, trainer.runs, trainer.settings, trainer.data
"""
