"""The world-model study (issue 51): ProtoCAD's context module on fixed logs, world models only,
against Dreamer and a world model given the true context. `protocad-study` (cli.py) records the
dataset (dataset.py), trains and evaluates every arm x seed (grid.py) and reports them (report.py).

May import: protocad_ros, sim_bridge.contract, sim_bridge.sim, trainer.settings, trainer.runs, trainer.run_input, trainer.torch_setup, trainer.data, trainer.learn, trainer.research (the probes' window features and fits)
"""
