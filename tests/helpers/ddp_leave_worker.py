"""Run by tests/trainer/learn/test_distributed.py under torchrun: a command body that prints a
line without flushing it and returns the exit code given on the command line."""
from __future__ import annotations

import sys

from trainer.learn import distributed


def main(code: int) -> int:
    def body(ctx: distributed.DistContext, _device: str) -> int:
        print(f"rank {ctx.rank} of {ctx.world_size} finished")   # stdout is a pipe: block-buffered
        return code

    return distributed.run_entry_point(1, "cpu", body)


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1])))
