"""Precision is chosen from the hardware, never silently: 'auto' picks bfloat16 only with bf16
arithmetic, an explicit choice is honoured, and the benchmark times what was asked."""
from __future__ import annotations

import subprocess
import sys

import pytest

from helpers import ROOT
from protocad_ros.model import precision as P


@pytest.mark.parametrize("flags, expected", [
    (set(), "float32"),                                  # AVX2-only: bf16 is emulated, ~85x slower
    ({"avx2", "avx512f"}, "float32"),                    # AVX512 without the BF16 extension
    ({"avx2", "avx512f", "avx512_bf16"}, "bfloat16"),
    ({"amx_bf16"}, "bfloat16"),
])
def test_auto_picks_bfloat16_only_with_bf16_arithmetic(monkeypatch, flags, expected):
    monkeypatch.setattr(P, "cpu_flags", lambda: set(flags))
    choice = P.resolve_precision("auto", "cpu")
    assert choice.precision == expected
    assert "chosen automatically" in choice.describe() and "CPU capability" in choice.describe()


def test_explicit_precision_is_honoured_and_unknown_is_refused(monkeypatch):
    monkeypatch.setattr(P, "cpu_flags", lambda: set())
    assert P.resolve_precision("bfloat16", "cpu").precision == "bfloat16"
    assert "as requested" in P.resolve_precision("float32", "cpu").describe()
    with pytest.raises(ValueError, match="precision must be one of"):
        P.resolve_precision("fp16", "cpu")


def bench_rows(*args: str) -> list[str]:
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_train.py"), "--list", *args],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.split("\n")[:-1]


@pytest.mark.process
def test_bench_train_float32_runs_float32_only_including_the_dreamerv3_rows():
    rows = bench_rows("--dreamerv3-sizes", "--precision", "float32")
    assert rows and all(r.endswith(" float32") for r in rows)
    assert "dreamerv3-sizes/dreamer float32" in rows
    assert bench_rows("--only-dreamerv3", "--precision", "float32") == ["dreamerv3-sizes/dreamer float32"]
