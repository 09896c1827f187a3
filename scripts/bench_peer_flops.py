#!/usr/bin/env python3
"""FLOPs of one NM512/dreamerv3-torch training update, counted as `bench_train.py --flops`
counts ours: torch's FlopCounterMode (matmul + convolution, forward and backward) around the
peer's first `Dreamer._train` call on a synthetic batch of its dmc_vision shapes.

Run it with the peer's Python, in the directory msgs_docs/benchmarks.md ("The peer") describes
(the peer's sources in PEER/dreamerv3-torch and its bench_update.py in PEER); nothing of the
peer is part of this project, it is imported from there at run time:

    PEER/venv/bin/python scripts/bench_peer_flops.py --peer PEER
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from torch.utils.flop_counter import FlopCounterMode


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--peer", type=Path, required=True,
                    help="directory with bench_update.py and dreamerv3-torch/ (see msgs_docs/benchmarks.md)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--depth", type=int, default=3, help="module nesting shown in the breakdown")
    a = ap.parse_args()
    peer = a.peer.resolve()
    if not (peer / "bench_update.py").is_file() or not (peer / "dreamerv3-torch" / "dreamer.py").is_file():
        ap.error(f"{peer} has no bench_update.py and dreamerv3-torch/dreamer.py (see msgs_docs/benchmarks.md, 'The peer')")
    sys.path[:0] = [str(peer / "dreamerv3-torch"), str(peer)]
    gl = os.environ.get("MUJOCO_GL", "egl")
    import dreamer  # the peer's; it sets MUJOCO_GL=osmesa on import
    os.environ["MUJOCO_GL"] = gl
    train, calls = dreamer.Dreamer._train, [0]

    def counted(self, data):
        calls[0] += 1
        if calls[0] > 1:
            return train(self, data)
        fc = FlopCounterMode(display=False)
        with fc:
            out = train(self, data)
        print(f"dreamerv3-torch: FLOPs per update {fc.get_total_flops() / 1e9:.1f} G")
        for module, ops in sorted(fc.get_flop_counts().items()):
            if module != "Global" and module.count(".") < a.depth:
                print(f"  {module:45s} {sum(ops.values()) / 1e9:8.1f} G")
        return out

    dreamer.Dreamer._train = counted
    import bench_update

    sys.argv = [sys.argv[0], "--data", "synthetic", "--updates", "0", "--warmup", "1",
                "--threads", str(a.threads), "--logdir", str(peer / "bench_logdir")]
    bench_update.main()
    return 0


if __name__ == "__main__":
    sys.exit(main())
