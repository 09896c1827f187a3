"""Precision is chosen from the hardware, never silently: 'auto' and a config's 'bfloat16' are
bfloat16 only with bf16 arithmetic, a command line's choice is honoured, and the benchmark times
what was asked."""
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


def test_a_config_asks_and_only_a_command_line_forces_emulated_bfloat16(monkeypatch):
    monkeypatch.setattr(P, "cpu_flags", lambda: {"avx2"})
    asked = P.resolve_precision("bfloat16", "cpu")            # a config's value: a request
    assert (asked.precision, asked.emulated) == ("float32", True)
    assert asked.describe().startswith("precision float32: the config asks for bfloat16")
    forced = P.resolve_precision("bfloat16", "cpu", explicit=True)   # --precision bfloat16
    assert forced.precision == "bfloat16" and forced.describe().startswith("warning: ")
    assert "as --precision asked" in P.resolve_precision("float32", "cpu", explicit=True).describe()
    monkeypatch.setattr(P, "cpu_flags", lambda: {"avx2", "amx_bf16"})
    assert P.resolve_precision("bfloat16", "cpu").precision == "bfloat16"
    assert "as the config asks" in P.resolve_precision("bfloat16", "cpu").describe()
    with pytest.raises(ValueError, match="precision must be one of"):
        P.resolve_precision("fp16", "cpu")


def test_the_environment_override_hides_the_bf16_flags(monkeypatch):
    """$PROTOCAD_CPU_NO_BF16 (tests, diagnostics; inherited by child processes) makes any CPU
    choose as an AVX2-only one would."""
    monkeypatch.setenv(P.NO_BF16_ENV, "1")
    assert not P.cpu_flags() & P.BF16_FLAGS
    assert P.resolve_precision("auto", "cpu").precision == "float32"
    assert f"hidden by ${P.NO_BF16_ENV}" in P.cpu_capability()
    monkeypatch.setenv(P.NO_BF16_ENV, "0")
    assert "hidden" not in P.cpu_capability()


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
