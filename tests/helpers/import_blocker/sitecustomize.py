"""Makes the top-level modules named in $PROTOCAD_BLOCK_IMPORTS (comma-separated) fail to import,
as on a machine that lacks them (the GPU machine has no ROS; a robot has no simulator).

Tests put this directory first on PYTHONPATH of a child process; Python imports
`sitecustomize` at start-up, before any project code.
"""
import os
import sys

_BLOCKED = {m.strip() for m in os.environ.get("PROTOCAD_BLOCK_IMPORTS", "").split(",") if m.strip()}


class _Blocker:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in _BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r} (blocked by the test's import blocker)",
                                      name=name)
        return None


if _BLOCKED:
    sys.meta_path.insert(0, _Blocker())
