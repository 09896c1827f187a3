"""Which float precision to train and act in, decided on the machine that runs (no ROS, no guessing).

bfloat16 autocast is several times faster than float32 where the hardware has bf16 arithmetic
(CUDA GPUs from Ampere on; x86 CPUs with AVX512-BF16 or AMX) and dramatically slower where
it is emulated: on an AVX2-only CPU a 1024x1024 bf16 matmul ran at 0.8 GFLOP/s against 71 in
float32. So a config's `train.precision` is a request ('auto', 'float32' or 'bfloat16'), and
every process that builds an agent resolves it on its own device (`resolve_precision`):

- 'auto' is bfloat16 where the device has bf16 arithmetic, else float32;
- 'bfloat16' from a config (a run's config.yaml, a shipped policy's, a preset's) is a request:
  float32 where bf16 would be emulated, said in one line. A config carried from a bf16 machine
  (older configs recorded the precision resolved there) so never makes another machine crawl;
- only `--precision bfloat16` on a command line is an explicit choice: kept, with a warning.

PROTOCAD_CPU_NO_BF16=1 (a test and diagnostic override, read by `cpu_flags`) makes this process
and the processes it starts treat the CPU as one without bf16 arithmetic: what an AVX2-only
machine would choose, shown on any machine.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

PRECISIONS = ("auto", "float32", "bfloat16")
BF16_FLAGS = frozenset({"avx512_bf16", "amx_bf16"})
#: Environment variable: a non-empty value other than 0 hides the CPU's bf16 flags (tests, diagnostics).
NO_BF16_ENV = "PROTOCAD_CPU_NO_BF16"


def cpu_flags() -> set[str]:
    """The CPU feature flags of /proc/cpuinfo (empty where there is none), without the bf16
    ones when $PROTOCAD_CPU_NO_BF16 is set."""
    flags: set[str] = set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    except OSError:
        pass
    if os.environ.get(NO_BF16_ENV, "0") not in ("", "0"):
        flags -= BF16_FLAGS
    return flags


def cpu_capability() -> str:
    """torch's dispatch level (e.g. 'AVX2', 'AVX512') plus the bf16 flags the CPU has."""
    import torch

    level = torch.backends.cpu.get_cpu_capability()
    bf16 = sorted(cpu_flags() & BF16_FLAGS)
    hidden = f", hidden by ${NO_BF16_ENV}" if os.environ.get(NO_BF16_ENV, "0") not in ("", "0") else ""
    return f"{level}" + (f" ({', '.join(bf16)})" if bf16 else f" (no bf16 arithmetic{hidden})")


def bf16_is_fast(device: str) -> bool:
    """True where bfloat16 matmuls run in hardware on `device` ('cpu', 'cuda', 'cuda:N')."""
    import torch

    if device.startswith("cuda"):
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    return bool(cpu_flags() & BF16_FLAGS)


@dataclass(frozen=True)
class PrecisionChoice:
    precision: str      # 'float32' | 'bfloat16': what runs
    requested: str      # what was asked for ('auto' included)
    device: str
    capability: str
    explicit: bool = False   # asked on a command line (kept even where slow)
    emulated: bool = False   # bfloat16 was asked for and this device has no bf16 arithmetic

    def describe(self) -> str:
        """One line: what runs, why, and on what."""
        where = f"{self.device}, CPU capability {self.capability}"
        if self.emulated and self.precision == "bfloat16":
            return (f"warning: precision bfloat16 as --precision asked, but {self.device} emulates it "
                    f"(many times slower than float32; {where})")
        if self.emulated:
            return (f"precision float32: the config asks for bfloat16, which {self.device} would emulate "
                    f"(many times slower); --precision bfloat16 forces it ({where})")
        how = ("chosen automatically" if self.requested == "auto"
               else "as --precision asked" if self.explicit else "as the config asks")
        return f"precision {self.precision} ({how}; {where})"

    def ran_here(self) -> str:
        """What ran here, for config.yaml's train.precision line (Config.save(ran=...)): the
        value stays the request, resolved again wherever the file is used."""
        return f"ran in {self.precision} here ({self.device}, CPU capability {self.capability})"

    def to_dict(self) -> dict[str, Any]:
        """For run.json: what ran, what was asked, and the machine's capability."""
        return asdict(self)


def resolve_precision(requested: str, device: str, explicit: bool = False) -> PrecisionChoice:
    """'auto' -> bfloat16 where `bf16_is_fast(device)`, else float32; 'bfloat16' -> float32
    where it is emulated unless `explicit` (a command line's --precision), which keeps it;
    'float32' -> float32."""
    if requested not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {requested!r}")
    fast = bf16_is_fast(device)
    chosen = requested
    if requested == "auto" or (requested == "bfloat16" and not explicit):
        chosen = "bfloat16" if fast else "float32"
    emulated = requested == "bfloat16" and not fast
    return PrecisionChoice(chosen, requested, device, cpu_capability(), explicit, emulated)
