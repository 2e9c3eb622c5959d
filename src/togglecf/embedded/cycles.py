"""Cycles per sample of an exported C filter on a Cortex-M4F, estimated without the hardware.

The filter's sources are compiled with ``arm-none-eabi-gcc`` for the Cortex-M4F (``ARM_FLAGS``:
Thumb-2, single-precision FPU, hard-float ABI) and linked with newlib's libm into a bare-metal
image (``build_image``: no start-up code, no I/O; a small bench harness around the filter's API,
``bench_source``). An instruction-set emulator (unicorn, ARMv7 Thumb-2 with VFP: the instructions
the Cortex-M4F runs) executes one filter update per sample on real IMU samples
(``CycleCounter.call``); every executed basic block is disassembled once (capstone) and priced with
the instruction timings of the Cortex-M4 Technical Reference Manual (``CycleModel``).

What it is: an **estimate** of the core's cycles with zero wait states (code and data in memory
that answers in one cycle, e.g. SRAM or an STM32F4's flash behind its ART accelerator at hit),
no interrupts, no caches. What it is not: a cycle-accurate simulation. The instruction count is
exact for the compiled code; the cycles are a model: a taken branch costs ``1 + refill`` (the TRM's
P, 1-3), neighbouring single loads/stores pipeline (a run of N costs N + 1), divisions cost
``divide`` cycles (2-12 in the TRM: data-dependent), FPU register dependencies and the IT
instruction's folding are not modelled. ``cycles_low`` / ``cycles_high`` re-price the taken branches
with P = 1 and P = 3: the range the refill alone spans.

``measure_filter(out_dir, sources, gyr, acc, mag, fs)`` does it for one export directory: per
sample instructions and cycles (``Measurement``), the quaternion after every sample (to check
the emulated build against the host build), and the cycles of the init.
"""
from __future__ import annotations

import bisect
import re
import shutil
import tempfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from togglecf.core.extras import require
from togglecf.embedded.framework import CSourceSet
from togglecf.embedded.toolchain import ARM_FLAGS, ARM_GCC, arm_available, run_command

__all__ = ["CycleModel", "Measurement", "CycleCounter", "BlockCost", "missing_reason", "bench_source", "build_image",
           "instruction_cost", "block_cost", "measure_filter", "summarize", "CODE_BASE", "STACK_TOP",
           "LINKER_SCRIPT"]

#: where the image is loaded (code, constants, data and zero-initialised data, contiguous)
CODE_BASE = 0x08000000
#: the initial stack pointer (a separate 256 KiB region below it)
STACK_TOP = 0x20040000
_STACK_SIZE = 0x40000
#: the return address of a call: an unmapped-free page where the emulation stops
_RETURN = 0x00001000
_IMAGE_SPACE = 0x01000000

_CONDITIONS = ("eq", "ne", "cs", "hs", "cc", "lo", "mi", "pl", "vs", "vc", "hi", "ls", "ge", "lt", "gt", "le", "al")
_ALU = {"add", "adc", "sub", "sbc", "rsb", "and", "orr", "orn", "eor", "bic", "mov", "mvn", "movw", "movt", "cmp",
        "cmn", "tst", "teq", "lsl", "lsr", "asr", "ror", "rrx", "neg", "mul", "sxtb", "sxth", "uxtb", "uxth", "sxtab",
        "sxtah", "uxtab", "uxtah", "bfi", "bfc", "ubfx", "sbfx", "clz", "rbit", "rev", "rev16", "revsh", "addw", "subw",
        "adr", "nop", "sel", "usat", "ssat", "smull", "umull", "smlal", "umlal", "cpsid", "cpsie", "dmb", "dsb", "isb",
        "uadd8", "usub8", "qadd", "qsub", "smulbb", "smultt", "smlabb", "smmul", "smmla", "pld", "yield", "udf", "bkpt"}
_MAC = {"mla", "mls"}
_DIVIDE = {"sdiv", "udiv"}
_LOAD_STORE = {"ldr", "ldrb", "ldrh", "ldrsb", "ldrsh", "str", "strb", "strh", "ldrex", "strex", "ldrt", "strt"}
_DOUBLE = {"ldrd", "strd"}
_MULTIPLE = {"ldm", "ldmia", "ldmdb", "ldmfd", "stm", "stmia", "stmdb", "stmea", "push", "pop"}
_BRANCH = {"b", "bl", "bx", "blx", "cbz", "cbnz"}
_TABLE_BRANCH = {"tbb", "tbh"}
_FP1 = {"vadd", "vsub", "vmul", "vnmul", "vabs", "vneg", "vcmp", "vcmpe", "vcvt", "vcvtr", "vcvta", "vcvtb", "vcvtt",
        "vmov", "vmrs", "vmsr"}
_FP_MAC = {"vmla", "vmls", "vnmla", "vnmls", "vfma", "vfms", "vfnma", "vfnms"}
_FP_LONG = {"vdiv", "vsqrt"}
_FP_LOAD_STORE = {"vldr", "vstr"}
_FP_MULTIPLE = {"vldm", "vldmia", "vldmdb", "vstm", "vstmia", "vstmdb", "vpush", "vpop"}
_KNOWN = (_ALU | _MAC | _DIVIDE | _LOAD_STORE | _DOUBLE | _MULTIPLE | _BRANCH | _TABLE_BRANCH | _FP1 | _FP_MAC
          | _FP_LONG | _FP_LOAD_STORE | _FP_MULTIPLE)


@dataclass(frozen=True)
class CycleModel:
    """Cortex-M4 instruction timing (Technical Reference Manual, processor and FPU instruction tables),
    zero wait states. ``refill``: P, the cycles a taken branch adds to refill the pipeline (1-3 by the
    TRM, by the target's alignment and width); ``divide``: SDIV/UDIV (2-12, data-dependent);
    ``fp_long``: VDIV.F32 and VSQRT.F32 (14); ``fp_mac``: VMLA/VMLS/VNMLA/VNMLS/VFMA... (3);
    ``mac``: MLA/MLS (2); ``it``: the IT instruction (1; the core can fold it into the previous
    16-bit instruction for 0, not modelled)."""

    refill: int = 2
    divide: int = 12
    fp_long: int = 14
    fp_mac: int = 3
    mac: int = 2
    it: int = 1

    def describe(self) -> str:
        """The assumptions in one line (for a table's notes)."""
        return (f"zero wait states; taken branch 1 + P with P = {self.refill} (TRM: 1-3); ALU, MUL, VADD/VSUB/VMUL/"
                f"VMOV/VCVT/VCMP 1; MLA/MLS {self.mac}; LDR/STR 2, a run of N neighbouring single loads/stores "
                f"N + 1; LDRD/STRD 3; LDM/STM/PUSH/POP and VLDM/VSTM/VPUSH/VPOP 1 + N (words); VLDR/VSTR 2; "
                f"VMLA/VFMA family {self.fp_mac}; VDIV/VSQRT {self.fp_long}; SDIV/UDIV {self.divide} (TRM: 2-12); "
                f"IT {self.it}; TBB/TBH 2 + P; FPU register dependencies not modelled")


@dataclass(frozen=True)
class BlockCost:
    """A basic block as priced: ``instructions``; ``cycles`` with its last branch not taken;
    ``ends_in_branch``: the last instruction can branch (taken, it adds ``refill``: known from
    where the execution goes next); ``unknown``: mnemonics priced 1 cycle by default."""

    instructions: int
    cycles: int
    ends_in_branch: bool
    unknown: tuple = ()


@dataclass
class Measurement:
    """Per-sample counts of one filter: ``instructions`` and ``cycles`` (``(N,)`` int64, one update
    each), ``taken`` (the taken branches per sample, for re-pricing the refill), ``quat`` ``(N, 4)``
    after each sample, ``init_instructions`` / ``init_cycles`` of the init call, ``unknown``: the
    mnemonics the model did not know (priced 1 cycle), ``model``: the ``CycleModel``."""

    instructions: np.ndarray
    cycles: np.ndarray
    taken: np.ndarray
    quat: np.ndarray
    init_instructions: int
    init_cycles: int
    model: CycleModel
    unknown: set = field(default_factory=set)
    #: cycles of the per-sample updates by the function they ran in (the symbol at or below each basic
    #: block: a function the compiler inlined counts as its caller's; libm's functions as themselves)
    per_function: dict = field(default_factory=dict)


def missing_reason() -> str | None:
    """Why the cycle estimate cannot run here (no ``arm-none-eabi-gcc``, no unicorn/capstone), or None."""
    if not arm_available():
        return f"{ARM_GCC} not found (apt-get install gcc-arm-none-eabi)"
    for module in ("unicorn", "capstone"):
        try:
            require(module, "embedded", "the Cortex-M4F cycle estimate")
        except ImportError as exc:
            return str(exc)
    return None


def _mnemonic(raw: str) -> str:
    """A capstone mnemonic without width qualifier, data type, condition code or flag-setting ``s``
    (``"vmla.f32"`` -> ``"vmla"``, ``"bls"`` -> ``"b"``, ``"movs"`` -> ``"mov"``, ``"addeq.w"`` -> ``"add"``)."""
    m = raw.lower().split(".")[0]
    if re.fullmatch(r"it[te]{0,3}", m):
        return "it"
    if m in _KNOWN:
        return m
    for cand in (m[:-2] if m[-2:] in _CONDITIONS else None, m[:-1] if m.endswith("s") else None):
        if cand in _KNOWN:
            return cand
    if m[-2:] in _CONDITIONS and m[:-2].endswith("s") and m[:-3] in _KNOWN:
        return m[:-3]
    return m


def _register_words(op_str: str) -> int:
    """Words moved by a register list ``{r4, r5, lr}`` / ``{d8, d9}`` / ``{s16-s19}`` (a d register is 2)."""
    inside = op_str[op_str.find("{") + 1:op_str.find("}")]
    words = 0
    for item in (s.strip() for s in inside.split(",") if s.strip()):
        size = 2 if item.startswith("d") else 1
        if "-" in item:
            lo, hi = (int(re.sub(r"\D", "", x)) for x in item.split("-"))
            words += size * (hi - lo + 1)
        else:
            words += size
    return words


def instruction_cost(mnemonic: str, op_str: str, model: CycleModel, after_load_store: bool = False) -> tuple:
    """``(cycles, kind)`` of one instruction with its branch (if any) not taken; ``kind``: ``"branch"``
    (can add ``model.refill`` when taken), ``"load_store"`` (a single load/store: the next one
    pipelines), ``"unknown"`` (a mnemonic the model does not price: 1) or ``""``."""
    m = _mnemonic(mnemonic)
    writes_pc = bool(re.match(r"\s*pc\b", op_str)) or ("{" in op_str and "pc" in op_str[op_str.find("{"):])
    if m == "it":
        return model.it, ""
    if m in _ALU:
        return 1, "branch" if writes_pc else ""
    if m in _MAC:
        return model.mac, ""
    if m in _DIVIDE:
        return model.divide, ""
    if m in _LOAD_STORE:
        if writes_pc:
            return 2, "branch"
        return (1 if after_load_store else 2), "load_store"
    if m in _DOUBLE:
        return 3, ""
    if m in _MULTIPLE:
        return 1 + _register_words(op_str), "branch" if writes_pc else ""
    if m in _BRANCH:
        return 1, "branch"
    if m in _TABLE_BRANCH:
        return 2, "branch"
    if m in _FP1:
        two_core = m == "vmov" and op_str.count(",") == 2 and re.search(r"\bd\d+\b", op_str)
        return (2 if two_core else 1), ""
    if m in _FP_MAC:
        return model.fp_mac, ""
    if m in _FP_LONG:
        return model.fp_long, ""
    if m in _FP_LOAD_STORE:
        return (3 if re.match(r"\s*d\d+", op_str) else 2), ""
    if m in _FP_MULTIPLE:
        return 1 + _register_words(op_str), ""
    return 1, "unknown"


def block_cost(instructions, model: CycleModel) -> BlockCost:
    """Price a basic block: ``instructions``, ``(mnemonic, op_str)`` pairs in execution order."""
    cycles, kind, unknown = 0, "", []
    for mnemonic, op_str in instructions:
        c, kind = instruction_cost(mnemonic, op_str, model, after_load_store=kind == "load_store")
        cycles += c
        if kind == "unknown":
            unknown.append(mnemonic)
    return BlockCost(len(instructions), cycles, kind == "branch", tuple(unknown))


def _tool(name: str) -> str:
    """``arm-none-eabi-<name>`` (binutils of the cross compiler)."""
    path = shutil.which(f"arm-none-eabi-{name}")
    if path is None:
        raise RuntimeError(f"arm-none-eabi-{name} not found (apt-get install binutils-arm-none-eabi)")
    return path


LINKER_SCRIPT = f"""ENTRY(tcf_bench_init)
SECTIONS {{
  . = {CODE_BASE:#x};
  .text : {{ *(.text .text.*) *(.rodata .rodata.*) }}
  .ARM.exidx : {{ *(.ARM.exidx*) }}
  .init_array : {{ *(.init_array*) }}
  .data : {{ *(.data .data.*) }}
  .bss : {{ *(.bss .bss.*) *(COMMON) }}
  end = .; _end = .;
}}
"""


def bench_source(sources: CSourceSet, includes=()) -> str:
    """The bench harness of an export (C): the state, the inputs ``tcf_in`` (gyr, acc, mag, then Δt
    for an API that takes it), ``tcf_mag_on`` (0: mag = NULL), and three functions the counter
    calls: ``tcf_bench_init`` (the setup, 0 on success), ``tcf_bench_step`` (one update: the
    measured call) and ``tcf_bench_quat`` (the orientation into ``tcf_q``, not measured)."""
    calls = sources.firmware
    head = "".join(f'#include "{h}"\n' for h in (sources.api_header, *includes))
    return f"""{head}float tcf_in[{max(calls.inputs, 10)}];
float tcf_q[4];
int tcf_mag_on = 1;
static {sources.state_type} tcf_f;
int tcf_bench_init(void) {{
  {calls.setup}
  return 0;
}}
void tcf_bench_step(void) {{
  const float *g = tcf_in, *a = tcf_in + 3, *m = tcf_mag_on ? tcf_in + 6 : (const float *)0;
  {calls.update}
}}
void tcf_bench_quat(void) {{
  {calls.quat}
}}
"""


def build_image(out_dir, sources: CSourceSet, elf, opt: str = "-O2", includes=()) -> Path:
    """Compile the export in ``out_dir`` (its ``sources.sources``) and ``bench_source`` for the
    Cortex-M4F (``ARM_FLAGS``, ``opt``) and link them with newlib-nano's libm into the bare-metal
    image ``elf`` (no start-up code: the counter loads the sections itself; unused sections
    dropped). Returns ``elf``."""
    out_dir, elf = Path(out_dir), Path(elf)
    with tempfile.TemporaryDirectory() as tmp:
        main, script = Path(tmp) / "tcf_bench.c", Path(tmp) / "bench.ld"
        main.write_text(bench_source(sources, includes))
        script.write_text(LINKER_SCRIPT)
        run_command([ARM_GCC, *ARM_FLAGS, opt, "-std=c99", "-ffunction-sections", "-fdata-sections", "-nostartfiles",
                     "-T", script, "-Wl,--gc-sections", "-Wl,--undefined=tcf_bench_step",
                     "-Wl,--undefined=tcf_bench_quat", "--specs=nano.specs", "--specs=nosys.specs", f"-I{out_dir}",
                     main, *(out_dir / f for f in sources.sources), "-o", elf, "-lm"])
    return elf


class CycleCounter:
    """A bare-metal Cortex-M4F image (``build_image``, or any ELF linked at ``CODE_BASE``) loaded into
    the emulator: ``call(symbol)`` runs a function to its return and counts what it executed;
    ``write_floats`` / ``read_floats`` / ``write_int`` set and read its globals."""

    def __init__(self, elf, model: CycleModel | None = None):
        uc = require("unicorn", "embedded", "the Cortex-M4F cycle estimate")
        arm = require("unicorn.arm_const", "embedded", "the Cortex-M4F cycle estimate")
        cs = require("capstone", "embedded", "the Cortex-M4F cycle estimate")
        self.model = model or CycleModel()
        table = self._symbols(Path(elf))
        self.symbols = {name: address for name, (address, _) in table.items()}
        # code symbols by address, to attribute each block's cycles to its function (per_function)
        code = sorted((address & ~1, name) for name, (address, kind) in table.items() if kind in "tTW")
        self._code_starts, self._code_names = [a for a, _ in code], [n for _, n in code]
        self._block_function: dict = {}
        self.per_function: Counter = Counter()
        self._last_function = "?"  # of the last block run (the final return's refill is its)
        with tempfile.TemporaryDirectory() as tmp:
            flat = Path(tmp) / "image.bin"
            run_command([_tool("objcopy"), "-O", "binary", elf, flat])
            image = flat.read_bytes()
        if len(image) > _IMAGE_SPACE // 2:
            raise ValueError(f"{elf}: image of {len(image)} bytes does not fit the emulated memory")
        self._arm = arm
        self.mu = uc.Uc(uc.UC_ARCH_ARM, uc.UC_MODE_THUMB)
        self.mu.mem_map(CODE_BASE, _IMAGE_SPACE)
        self.mu.mem_write(CODE_BASE, image)
        self.mu.mem_map(STACK_TOP - _STACK_SIZE, _STACK_SIZE)
        self.mu.mem_map(_RETURN, 0x1000)
        # the FPU on (coprocessor access for CP10/CP11, FPEXC.EN): the core starts with it off
        self.mu.reg_write(arm.UC_ARM_REG_C1_C0_2, self.mu.reg_read(arm.UC_ARM_REG_C1_C0_2) | (0xF << 20))
        self.mu.reg_write(arm.UC_ARM_REG_FPEXC, 0x40000000)
        self._md = cs.Cs(cs.CS_ARCH_ARM, cs.CS_MODE_THUMB | cs.CS_MODE_MCLASS)
        self._blocks: dict = {}
        self.unknown: set = set()
        self._counts = [0, 0, 0]  # instructions, cycles, taken branches of the current call
        self._branch_end = None  # where the previous block falls through to, when it ended in a branch
        self.mu.hook_add(uc.UC_HOOK_BLOCK, self._on_block)

    @staticmethod
    def _symbols(elf: Path) -> dict:
        """name -> (address, ``nm`` type letter) of the ELF's symbols."""
        out = {}
        for line in run_command([_tool("nm"), elf]).splitlines():
            parts = line.split()
            if len(parts) == 3:
                out[parts[2]] = (int(parts[0], 16), parts[1])
        return out

    def _function_of(self, address: int) -> str:
        i = bisect.bisect_right(self._code_starts, address) - 1
        return self._code_names[i] if i >= 0 else "?"

    def address(self, name: str) -> int:
        """The address of the global ``name`` (a function's without the Thumb bit)."""
        if name not in self.symbols:
            raise KeyError(f"no symbol {name!r} in the image")
        return self.symbols[name] & ~1

    def _price(self, address: int, size: int) -> BlockCost:
        code = bytes(self.mu.mem_read(address, size))
        insns = [(i.mnemonic, i.op_str) for i in self._md.disasm(code, address)]
        decoded = sum(i.size for i in self._md.disasm(code, address))
        cost = block_cost(insns, self.model)
        if decoded != size:
            cost = BlockCost(cost.instructions, cost.cycles, cost.ends_in_branch,
                             cost.unknown + (f"undecoded bytes at {address + decoded:#x}",))
        self.unknown.update(cost.unknown)
        self._blocks[(address, size)] = cost
        return cost

    def _on_block(self, _uc, address, size, _data):
        if address == _RETURN:
            return
        cost = self._blocks.get((address, size)) or self._price(address, size)
        counts = self._counts
        cycles = cost.cycles
        if self._branch_end is not None and address != self._branch_end:
            cycles += self.model.refill  # the branch into this block was taken
            counts[2] += 1
        counts[0] += cost.instructions
        counts[1] += cycles
        name = self._block_function.get(address)
        if name is None:
            name = self._block_function[address] = self._function_of(address)
        self.per_function[name] += cycles
        self._last_function = name
        self._branch_end = address + size if cost.ends_in_branch else None

    def call(self, name: str, max_instructions: int = 0) -> tuple:
        """Run the function ``name`` (no arguments) to its return: ``(instructions, cycles, taken
        branches)`` executed (the call's own return included: its caller's ``bl`` is not).
        ``max_instructions``: stop after that many (0: no limit), e.g. to catch an endless loop."""
        arm = self._arm
        self._counts = [0, 0, 0]
        self._branch_end = None
        self.mu.reg_write(arm.UC_ARM_REG_SP, STACK_TOP)
        self.mu.reg_write(arm.UC_ARM_REG_LR, _RETURN | 1)
        self.mu.emu_start(self.address(name) | 1, _RETURN, count=max_instructions)
        if self.mu.reg_read(arm.UC_ARM_REG_PC) & ~1 != _RETURN:
            raise RuntimeError(f"{name} did not return within {max_instructions} instructions")
        if self._branch_end is not None:  # the return itself: a taken branch
            self._counts[1] += self.model.refill
            self._counts[2] += 1
            self.per_function[self._last_function] += self.model.refill
        r0 = self.mu.reg_read(arm.UC_ARM_REG_R0)
        self.result = r0 - (1 << 32) if r0 >= 1 << 31 else r0
        return tuple(self._counts)

    def write_floats(self, name: str, values) -> None:
        """Store ``values`` as float32 at the global ``name``."""
        self.mu.mem_write(self.address(name), np.asarray(values, "<f4").tobytes())

    def read_floats(self, name: str, n: int) -> np.ndarray:
        """``n`` float32 at the global ``name``."""
        return np.frombuffer(bytes(self.mu.mem_read(self.address(name), 4 * n)), "<f4").copy()

    def write_int(self, name: str, value: int) -> None:
        """Store a 32-bit int at the global ``name``."""
        self.mu.mem_write(self.address(name), int(value).to_bytes(4, "little", signed=True))


def measure_filter(out_dir, sources: CSourceSet, gyr, acc, mag, fs: float, *, opt: str = "-O2", includes=(),
                   model: CycleModel | None = None) -> Measurement:
    """Count one update per sample of the export in ``out_dir`` (``sources``: its ``CSourceSet``;
    ``includes``: extra headers its setup needs) on the samples ``gyr`` [rad/s], ``acc`` [m/s²],
    ``mag`` [µT] (``(N, 3)``; ``mag=None``: the filter gets NULL) at ``fs`` [Hz] (Δt = 1/fs for an
    API that takes it), compiled with ``opt``. The inputs are rounded to float32 (what the filter
    gets on a microcontroller)."""
    with tempfile.TemporaryDirectory() as tmp:
        elf = build_image(out_dir, sources, Path(tmp) / "bench.elf", opt, includes)
        counter = CycleCounter(elf, model)
    init = counter.call("tcf_bench_init")
    if counter.result != 0:
        raise RuntimeError(f"{sources.what}: the init returned {counter.result} in the emulator")
    per_function = Counter()  # the updates' cycles only (not the init's nor the quaternion reads')
    n = len(gyr)
    inputs = np.zeros((n, 10), np.float32)
    inputs[:, 0:3], inputs[:, 3:6] = gyr, acc
    if mag is not None:
        inputs[:, 6:9] = mag
    inputs[:, 9] = 1.0 / fs
    counter.write_int("tcf_mag_on", mag is not None)
    counts = np.zeros((n, 3), np.int64)
    quat = np.zeros((n, 4))
    for i in range(n):
        counter.write_floats("tcf_in", inputs[i])
        counter.per_function.clear()
        counts[i] = counter.call("tcf_bench_step")
        per_function.update(counter.per_function)
        counter.call("tcf_bench_quat")
        quat[i] = counter.read_floats("tcf_q", 4)
    return Measurement(instructions=counts[:, 0], cycles=counts[:, 1], taken=counts[:, 2], quat=quat,
                       init_instructions=int(init[0]), init_cycles=int(init[1]), model=counter.model,
                       unknown=set(counter.unknown), per_function=dict(per_function))


def summarize(m: Measurement, clock_hz: float, rates=(285.7, 100.0)) -> dict:
    """Per-sample figures of ``m``: ``instructions_mean`` / ``_max``, ``cycles_mean`` / ``_max``
    (the model's P), ``cycles_low_mean`` / ``cycles_high_mean`` / ``cycles_low_max`` / ``cycles_high_max``
    (taken branches re-priced with P = 1 and P = 3), ``us_mean`` / ``us_max`` [µs] at ``clock_hz``
    [Hz], and for each rate in ``rates`` [Hz] ``load_<rate>_mean`` / ``_max``: the share of its
    sample period the update takes (1.0 = all of it), at ``clock_hz``."""
    cyc = m.cycles.astype(float)
    low = cyc - m.taken * (m.model.refill - 1)
    high = cyc + m.taken * (3 - m.model.refill)
    out = {"samples": int(len(cyc)), "instructions_mean": float(m.instructions.mean()),
           "instructions_max": int(m.instructions.max()), "cycles_mean": float(cyc.mean()),
           "cycles_max": int(cyc.max()),
           "cycles_low_mean": float(low.mean()), "cycles_high_mean": float(high.mean()),
           "cycles_low_max": int(low.max()), "cycles_high_max": int(high.max()),
           "us_mean": 1e6 * float(cyc.mean()) / clock_hz, "us_max": 1e6 * float(cyc.max()) / clock_hz,
           "init_cycles": m.init_cycles}
    for rate in rates:
        period = clock_hz / rate  # cycles per sample period
        out[f"load_{rate:g}_mean"] = float(cyc.mean()) / period
        out[f"load_{rate:g}_max"] = float(cyc.max()) / period
    return out
