"""The Cortex-M4F cycle estimate (``togglecf.embedded.cycles``, ``pipelines/bench_cycles.py``): the
counter on a function whose instructions and cycles are known by hand, the emulated filter against
its host build, and the benchmark's quick mode. Skips with the reason without ``arm-none-eabi-gcc``
or the ``embedded`` extra (unicorn, capstone)."""
import csv
import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from togglecf.core import quaternion as quat
from togglecf.embedded import cvqf, cycles
from togglecf.embedded.toolchain import ARM_FLAGS, ARM_GCC

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"
REASON = cycles.missing_reason()
needs_emulator = pytest.mark.skipif(REASON is not None, reason=f"cycle estimate unavailable: {REASON}")

#: 38 instructions: movs; 10 x (adds, cmp, bne) with 9 taken; vmov, vsqrt, 3 ldr, push, pop {pc}.
#: Cycles at P = 2: 1 + 10 x 3 + 9 x 2 (taken bne) + 1 + 14 + (2 + 1 + 1) (pipelined ldr) + 4 + (4 + 2) = 78
KNOWN_ASM = """
  .syntax unified
  .thumb
  .text
  .global tcf_bench_init
  .thumb_func
tcf_bench_init:
  movs r0, #0
  bx lr
  .global tcf_known
  .thumb_func
tcf_known:
  movs r0, #0
1:
  adds r0, #1
  cmp r0, #10
  bne 1b
  vmov s0, r0
  vsqrt.f32 s1, s0
  ldr r1, [sp, #-4]
  ldr r2, [sp, #-8]
  ldr r3, [sp, #-12]
  push {r4, r5, lr}
  pop {r4, r5, pc}
"""


@pytest.mark.parametrize("mnemonic, op_str, cycles_, kind", [
    ("adds", "r0, #1", 1, ""), ("bls", "#0x10", 1, "branch"), ("movs", "r0, #0", 1, ""),
    ("vmla.f32", "s0, s1, s2", 3, ""), ("vdiv.f32", "s0, s1, s2", 14, ""), ("vsqrt.f32", "s0, s1", 14, ""),
    ("ldr.w", "r0, [r1, #4]", 2, "load_store"), ("push", "{r4, r5, r6, lr}", 5, ""), ("pop", "{r4, pc}", 3, "branch"),
    ("vpush", "{d8, d9}", 5, ""), ("vldr", "s0, [r0]", 2, ""), ("vmov", "r0, r1, d0", 2, ""), ("itte", "eq", 1, ""),
    ("sdiv", "r0, r1, r2", 12, ""), ("addeq.w", "r0, r0, #1", 1, ""), ("cbz", "r0, #0x20", 1, "branch"),
    ("frobnicate", "r0", 1, "unknown")])
def test_instruction_cost(mnemonic, op_str, cycles_, kind):
    assert cycles.instruction_cost(mnemonic, op_str, cycles.CycleModel()) == (cycles_, kind)


def test_neighbouring_loads_pipeline():
    block = [("ldr", "r0, [r1]"), ("ldr", "r2, [r1, #4]"), ("str", "r2, [r3]"), ("adds", "r0, #1"), ("ldr", "r0, [r1]")]
    cost = cycles.block_cost(block, cycles.CycleModel())
    assert (cost.instructions, cost.cycles, cost.ends_in_branch) == (5, 2 + 1 + 1 + 1 + 2, False)


def _linked(tmp_path, asm: str):
    """The bare-metal image of the assembly ``asm`` (linked at ``cycles.CODE_BASE``)."""
    src, script, elf = tmp_path / "k.s", tmp_path / "k.ld", tmp_path / "k.elf"
    src.write_text(asm)
    script.write_text(cycles.LINKER_SCRIPT)
    subprocess.run([ARM_GCC, *ARM_FLAGS, "-nostartfiles", "-nostdlib", "-T", str(script), str(src), "-o", str(elf)],
                   check=True, capture_output=True)
    return elf


@needs_emulator
def test_counter_on_a_known_function(tmp_path):
    elf = _linked(tmp_path, KNOWN_ASM)
    counter = cycles.CycleCounter(elf)
    assert counter.call("tcf_known") == (38, 78, 10)
    assert counter.result == 10 and not counter.unknown
    assert counter.call("tcf_known") == (38, 78, 10)  # the counts start over with each call
    assert cycles.CycleCounter(elf, cycles.CycleModel(refill=1)).call("tcf_known") == (38, 68, 10)


CALLING_ASM = """
  .syntax unified
  .thumb
  .text
  .global tcf_outer
  .thumb_func
tcf_outer:
  push {r4, lr}
  movs r4, #3
  bl tcf_inner
  adds r0, r4
  pop {r4, pc}
  .global tcf_inner
  .thumb_func
tcf_inner:
  movs r0, #1
  adds r0, #1
  bx lr
"""


@needs_emulator
def test_counter_attributes_cycles_to_functions(tmp_path):
    """``per_function``: every cycle of a call goes to the function whose code ran it, the final return
    included: the sum is the call's count, and the callee gets what a call of it alone counts (the ``bl``
    into it, priced with its refill, is the caller's instruction)."""
    counter = cycles.CycleCounter(_linked(tmp_path, CALLING_ASM))
    _, alone, _ = counter.call("tcf_inner")
    counter.per_function.clear()
    _, total, _ = counter.call("tcf_outer")
    assert counter.result == 5
    assert set(counter.per_function) == {"tcf_outer", "tcf_inner"}
    assert sum(counter.per_function.values()) == total
    assert counter.per_function["tcf_inner"] == alone


@needs_emulator
def test_emulated_vqf_core_matches_its_host_build(tmp_path, rng):
    n, fs = 60, 285.7
    g = 0.3 * rng.standard_normal((n, 3))
    a = np.array([0.0, 0.0, 9.81]) + 0.2 * rng.standard_normal((n, 3))
    m = np.array([20.0, 0.0, -40.0]) + rng.standard_normal((n, 3))
    cvqf.export_c_vqf(tmp_path, fs, use_mag=True, sizes=False)
    meas = cycles.measure_filter(tmp_path, cvqf.C_VQF, g, a, m, fs, includes=("tcf_vqf_config.h",))
    ref = cvqf.run_vqf_harness(cvqf.build_vqf_harness(tmp_path), g, a, m, dt=1.0 / fs)
    assert np.degrees(np.nanmax(quat.angle_between(meas.quat, ref))) < 1e-3
    assert not meas.unknown
    assert meas.instructions.shape == (n,) and (meas.instructions > 100).all()
    assert (meas.cycles >= meas.instructions).all() and meas.init_cycles > 0
    s = cycles.summarize(meas, 168e6)
    assert s["cycles_low_mean"] <= s["cycles_mean"] <= s["cycles_high_mean"]
    assert s["load_100_mean"] == pytest.approx(s["cycles_mean"] / 1.68e6)
    assert sum(meas.per_function.values()) == meas.cycles.sum()
    assert any(name.startswith("tcf_vqf_update") for name in meas.per_function)


@needs_emulator
def test_bench_quick_mode_writes_the_table(tmp_path, mini_index):
    sys.path.insert(0, str(PIPELINES))
    try:
        bench = importlib.import_module("bench_cycles")
    finally:
        sys.path.remove(str(PIPELINES))
    res = bench.main(["--quick", "--samples", "40", "--out", str(tmp_path / "c")])
    with open(tmp_path / "c.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    fs_low = mini_index.load(mini_index.select(bench.QUICK_TRIAL)[0]).fs / bench.LOW_RATE_FACTOR
    assert list(rows[0]) == bench.table_columns(fs_low) and len(rows) == 3
    # the same samples every 3 averaged, run by an export at that rate: the VQF core's work a sample does not
    # depend on the rate (no window), so its mean cycles there agree to a few percent (measured 0.07 % on these
    # 40 samples)
    cycles_low = bench.low_rate_columns(fs_low)[0]
    assert float(rows[0][cycles_low]) == pytest.approx(float(rows[0]["cycles_mean"]), rel=0.05)
    assert float(rows[0]["ratio_to_vqf"]) == 1.0 and all(float(r["max_angle_deg"]) < 1e-3 for r in rows)
    text = (tmp_path / "c.md").read_text()
    assert "estimate" in text and "zero wait states" in text and "quick mode" in text.lower()
    assert res["paths"]["md"] == tmp_path / "c.md"
