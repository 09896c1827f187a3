"""Agent checkpoints: the file format, its limits and its signatures.

  files.py       no torch: the format's names, CheckpointError, where a checkpoint is, its one
                 bounded read, what makes two configs different networks
  limits.py      no torch: what a file from a stranger must keep before torch expands it
  signing.py     no torch: Ed25519 signatures of checkpoints (the commands that make keys
                 and sign files by hand: trainer/launch/run_key.py)
  agent_file.py  torch: save, read, load and restore agents and policy files

Node-side and command-line code imports the torch-free modules at its top (a node's --help, its
parameter and signature checks and a checkpoint's receipt run before any model loads) and
agent_file.py where a model is built. Nothing is re-exported here: import the module.

May import: protocad_ros.atomic, protocad_ros.model
"""
