"""The C toolchain: host gcc, the RISC-V cross compiler (rv32imc, ESP32-C3 class), object sizes,
stack usage and linked program sizes, and C float literals that round-trip float32."""
from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["RISCV_GCC", "RISCV_FLAGS", "native_stderr_silenced", "run_command", "gcc_shared", "c_float",
           "riscv_flags", "object_size", "measure_sizes", "stack_usage", "link_riscv"]

RISCV_GCC = "riscv64-unknown-elf-gcc"


RISCV_FLAGS = ("-march=rv32imc", "-mabi=ilp32")


@contextlib.contextmanager
def native_stderr_silenced():
    """Discard what C/C++ code writes to file descriptors 1 and 2 inside the block (Treelite's
    and TL2cgen's log lines, which Python's ``sys.stdout``/``sys.stderr`` cannot catch)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            yield
    finally:
        for fd, old in zip((1, 2), saved):
            os.dup2(old, fd)
            os.close(old)


def run_command(cmd, cwd=None):
    res = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"command failed ({res.returncode}): {' '.join(map(str, cmd))}\n{res.stderr[-4000:]}")
    return res.stdout


def gcc_shared(sources, lib, include_dirs=(), opt="-O1", defines=()):
    """Compile C ``sources`` into a shared library ``lib`` (host gcc)."""
    cmd = ["gcc", opt, "-std=c99", "-shared", "-fPIC", *[f"-D{d}" for d in defines], "-o", lib, *sources,
           *[f"-I{d}" for d in include_dirs], "-lm"]
    run_command(cmd)
    return Path(lib)


def c_float(v) -> str:
    """A float32 as a C literal that round-trips exactly."""
    v = np.float32(v)
    if not np.isfinite(v):
        raise ValueError(f"non-finite value {v} cannot be exported")
    text = f"{float(v):.9g}"
    if not any(ch in text for ch in ".en"):  # "0" / "-10": C needs a float literal before the f suffix
        text += ".0"
    return text + "f"


def riscv_flags():
    """Flags for the RISC-V cross compiler, or None when it is not installed."""
    if shutil.which(RISCV_GCC) is None:
        return None
    flags = list(RISCV_FLAGS)
    with tempfile.TemporaryDirectory() as tmp:
        probe = Path(tmp) / "p.c"
        probe.write_text("#include <stdio.h>\n#include <math.h>\nint f(void){return 0;}\n")
        for extra in (["--specs=picolibc.specs"], []):
            if subprocess.run([RISCV_GCC, *flags, *extra, "-Os", "-c", str(probe), "-o", str(Path(tmp) / "p.o")],
                              capture_output=True).returncode == 0:
                return flags + extra
    return flags  # compiler without a C library: files including stdio.h will fail


def object_size(compiler, flags, size_tool, c_file, include_dirs):
    with tempfile.TemporaryDirectory() as tmp:
        obj = Path(tmp) / "x.o"
        run_command([compiler, *flags, "-Os", "-c", c_file, "-o", obj, *[f"-I{d}" for d in include_dirs]])
        line = run_command([size_tool, obj]).splitlines()[1].split()
    text, data, bss = (int(v) for v in line[:3])
    return {"text": text, "data": data, "bss": bss, "total": text + data + bss}


def measure_sizes(c_files, include_dirs=None, riscv: bool = True) -> dict:
    """``{file: {"host": {text, data, bss, total}, "riscv": {...} or None}}`` of ``gcc -Os -c``
    objects (host gcc + ``size``; RISC-V rv32imc/ilp32 when the cross compiler is installed).
    Constant arrays land in ``text`` (``.rodata`` is counted there by ``size``)."""
    rv = riscv_flags() if riscv else None
    rv_size = "riscv64-unknown-elf-size" if shutil.which("riscv64-unknown-elf-size") else "size"
    out = {}
    for f in map(Path, c_files):
        inc = list(include_dirs or []) + [f.parent]
        out[str(f)] = {"host": object_size("gcc", [], "size", f, inc),
                       "riscv": None if rv is None else object_size(RISCV_GCC, rv, rv_size, f, inc)}
    return out


def stack_usage(c_file, include_dirs, function: str) -> int | None:
    """Stack bytes of ``function`` in ``c_file`` compiled for rv32imc with ``-Os -fstack-usage``
    (gcc's static figure: exact for functions without dynamic stack), or None without the
    cross compiler."""
    flags = riscv_flags()
    if flags is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        obj = Path(tmp) / "s.o"
        run_command([RISCV_GCC, *flags, "-Os", "-fstack-usage", "-c", c_file, "-o", obj, *[f"-I{d}" for d in include_dirs]])
        for line in (Path(tmp) / "s.su").read_text().splitlines():
            where, nbytes, _kind = line.rsplit("\t", 2) if "\t" in line else (line, "0", "")
            if where.endswith(f":{function}"):
                return int(nbytes)
    raise RuntimeError(f"{c_file}: no stack-usage entry for {function}")


def link_riscv(c_files, include_dirs, main_source: str, defines=()) -> dict | None:
    """Size of a linked rv32imc picolibc program (``main_source`` + ``c_files``; -Os, unused
    sections dropped): models, walker, soft-float and libm routines, C runtime start-up (an
    empty program is ~0.5 KiB text + 2 KiB stack). None without the cross compiler/picolibc."""
    flags = riscv_flags()
    if flags is None or "--specs=picolibc.specs" not in flags:
        return None
    rv_size = "riscv64-unknown-elf-size" if shutil.which("riscv64-unknown-elf-size") else "size"
    with tempfile.TemporaryDirectory() as tmp:
        main = Path(tmp) / "tcf_main.c"
        main.write_text(main_source)
        elf = Path(tmp) / "fw.elf"
        run_command([RISCV_GCC, *flags, "-Os", "-ffunction-sections", "-fdata-sections", "-Wl,--gc-sections",
              "-Wl,--defsym=__flash_size=0x1000000", "-Wl,--defsym=__ram_size=0x100000",
              *[f"-D{d}" for d in defines], *[f"-I{d}" for d in include_dirs], main, *c_files, "-o", elf, "-lm"])
        line = run_command([rv_size, elf]).splitlines()[1].split()
    text, data, bss = (int(v) for v in line[:3])
    return {"text": text, "data": data, "bss": bss, "flash": text + data}
