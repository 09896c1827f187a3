"""Which float precision to train in, decided from what the machine can do (no ROS, no guessing).

bfloat16 autocast is several times faster than float32 where the hardware has bf16 arithmetic
(CUDA GPUs from Ampere on; x86 CPUs with AVX512-BF16 or AMX) and dramatically slower where
it is emulated: on an AVX2-only CPU a 1024x1024 bf16 matmul ran at 0.8 GFLOP/s against 71 in
float32. So 'auto' never picks bfloat16 without the hardware, and every caller prints the
choice with `describe()`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

PRECISIONS = ("auto", "float32", "bfloat16")


def cpu_flags() -> set[str]:
    """The CPU feature flags of /proc/cpuinfo (empty where there is none)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def cpu_capability() -> str:
    """torch's dispatch level (e.g. 'AVX2', 'AVX512') plus the bf16 flags the CPU has."""
    import torch

    level = torch.backends.cpu.get_cpu_capability()
    bf16 = sorted(cpu_flags() & {"avx512_bf16", "amx_bf16"})
    return f"{level}" + (f" ({', '.join(bf16)})" if bf16 else " (no bf16 arithmetic)")


def bf16_is_fast(device: str) -> bool:
    """True where bfloat16 matmuls run in hardware on `device` ('cpu', 'cuda', 'cuda:N')."""
    import torch

    if device.startswith("cuda"):
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    return bool(cpu_flags() & {"avx512_bf16", "amx_bf16"})


@dataclass(frozen=True)
class PrecisionChoice:
    precision: str      # 'float32' | 'bfloat16'
    requested: str      # what the user asked for ('auto' included)
    device: str
    capability: str

    def describe(self) -> str:
        how = "chosen automatically" if self.requested == "auto" else "as requested"
        return f"precision {self.precision} ({how}; {self.device}, CPU capability {self.capability})"


def resolve_precision(requested: str, device: str) -> PrecisionChoice:
    """'auto' -> bfloat16 where `bf16_is_fast(device)`, else float32; an explicit value is
    honoured as given (a slow choice is the user's to make, and describe() shows it)."""
    if requested not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {requested!r}")
    chosen = requested
    if requested == "auto":
        chosen = "bfloat16" if bf16_is_fast(device) else "float32"
    return PrecisionChoice(chosen, requested, device, cpu_capability())
