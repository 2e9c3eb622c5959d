"""The C toolchain: host gcc, the RISC-V cross compiler (rv32imc, ESP32-C3 class), object sizes,
stack usage and linked program sizes, and C float literals that round-trip float32."""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
from importlib import resources
from pathlib import Path

import numpy as np

__all__ = ["RISCV_GCC", "RISCV_FLAGS", "ARM_GCC", "ARM_SIZE", "ARM_FLAGS", "arm_available", "arm_object_size",
           "call_chain_stack", "unit_chain_stack", "template", "need_gcc", "run_host_program", "run_harness_command", "write_imu_csv", "native_stderr_silenced", "run_command", "gcc_shared", "c_float",
           "riscv_flags", "object_size", "measure_sizes", "stack_usage", "link_riscv", "link_arm", "reachable_code_size",
           "run_prediction_harness", "run_csv_harness"]

RISCV_GCC = "riscv64-unknown-elf-gcc"


RISCV_FLAGS = ("-march=rv32imc", "-mabi=ilp32")

ARM_GCC = "arm-none-eabi-gcc"
ARM_SIZE = "arm-none-eabi-size"
#: Cortex-M4F: single-precision FPU, hard-float ABI, Thumb-2
ARM_FLAGS = ("-mcpu=cortex-m4", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard", "-mthumb")


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


def link_arm(c_files, include_dirs, main_source: str) -> dict | None:
    """Size of a linked Cortex-M4F newlib-nano program (``main_source`` + ``c_files``; -Os, unused
    sections dropped): the code, libm float routines and C start-up. None without the toolchain
    or its newlib (the object sizes still stand)."""
    if not arm_available():
        return None
    size_tool = ARM_SIZE if shutil.which(ARM_SIZE) else "size"
    with tempfile.TemporaryDirectory() as tmp:
        main = Path(tmp) / "main.c"
        main.write_text(main_source)
        elf = Path(tmp) / "fw.elf"
        try:
            run_command([ARM_GCC, *ARM_FLAGS, "-Os", "-ffunction-sections", "-fdata-sections", "-Wl,--gc-sections",
                         "--specs=nano.specs", "--specs=nosys.specs", *[f"-I{d}" for d in include_dirs], main,
                         *c_files, "-o", elf, "-lm"])
        except RuntimeError:
            return None
        line = run_command([size_tool, elf]).splitlines()[1].split()
    text, data, bss = (int(v) for v in line[:3])
    return {"text": text, "data": data, "bss": bss, "flash": text + data}


def reachable_code_size(compiler, flags, size_tool, c_files, include_dirs, roots) -> dict:
    """``{text, data, bss, total}`` of the part of ``c_files`` a firmware link keeps when it calls
    only the functions ``roots``: each file compiled ``-Os -ffunction-sections -fdata-sections``,
    then partially linked (``-r``) with ``--gc-sections`` from those roots. Only the code and
    constants of ``c_files`` count: what they call outside (libm, soft-float, libc) stays
    undefined, as in ``object_size``; unlike there, functions nothing reachable calls (unused
    API) are dropped."""
    link_flags = [f for f in flags if not f.startswith("--specs=")]
    with tempfile.TemporaryDirectory() as tmp:
        objs = []
        for i, f in enumerate(map(Path, c_files)):
            obj = Path(tmp) / f"{i}_{f.stem}.o"
            run_command([compiler, *flags, "-Os", "-ffunction-sections", "-fdata-sections", "-c", f, "-o", obj,
                         *[f"-I{d}" for d in [*include_dirs, f.parent]]])
            objs.append(obj)
        out = Path(tmp) / "kept.o"
        run_command([compiler, *link_flags, "-nostdlib", "-r", "-Wl,--gc-sections", f"-Wl,--entry={roots[0]}",
                     *(f"-Wl,--undefined={r}" for r in roots[1:]), *objs, "-o", out])
        line = run_command([size_tool, out]).splitlines()[1].split()
    text, data, bss = (int(v) for v in line[:3])
    return {"text": text, "data": data, "bss": bss, "total": text + data + bss}


def arm_available() -> bool:
    return shutil.which(ARM_GCC) is not None


def arm_object_size(c_file, include_dirs=()) -> dict | None:
    """``{text, data, bss, total}`` of ``c_file`` compiled for a Cortex-M4F with ``-Os``
    (``arm-none-eabi-gcc`` + ``ARM_FLAGS``), or None without the cross compiler."""
    if not arm_available():
        return None
    size_tool = ARM_SIZE if shutil.which(ARM_SIZE) else "size"
    return object_size(ARM_GCC, list(ARM_FLAGS), size_tool, Path(c_file),
                       [*map(Path, include_dirs), Path(c_file).parent])


def call_chain_stack(compiler, flags, c_file, include_dirs, root: str) -> dict:
    """Stack of ``root`` in ``c_file`` (``-Os -fstack-usage -fcallgraph-info=su``): ``{"frame":
    root's own frame, "chain": the deepest chain of frames through the file's functions
    (bytes), "path": its function names, "external": callees outside the file (libm: not
    counted)}``. gcc's static figures; exact for functions without dynamic stack."""
    with tempfile.TemporaryDirectory() as tmp:
        obj = Path(tmp) / "s.o"
        run_command([compiler, *flags, "-Os", "-fstack-usage", "-fcallgraph-info=su", "-c", c_file, "-o", obj,
                     *[f"-I{d}" for d in include_dirs]])
        text = (Path(tmp) / "s.ci").read_text()
    frames, edges = {}, {}
    for m in re.finditer(r'node:\s*\{\s*title:\s*"([^"]+)"\s*label:\s*"([^"]*)"', text):
        name, label = m.group(1), m.group(2)
        su = re.search(r"(\d+) bytes \((static|dynamic|dynamic,bounded)\)", label)
        frames[name] = int(su.group(1)) if su else None
    for m in re.finditer(r'edge:\s*\{\s*sourcename:\s*"([^"]+)"\s*targetname:\s*"([^"]+)"', text):
        edges.setdefault(m.group(1), []).append(m.group(2))
    if frames.get(root) is None:
        raise RuntimeError(f"{c_file}: no stack-usage entry for {root}")

    def deepest(fn, seen):
        own = frames.get(fn)
        if own is None:
            return 0, []
        best, path = 0, []
        for callee in edges.get(fn, ()):
            if callee not in seen:
                b, p = deepest(callee, seen | {callee})
                if b > best:
                    best, path = b, p
        return own + best, [fn, *path]

    chain, path = deepest(root, {root})
    external = sorted({c for fn in frames if frames[fn] is not None for c in edges.get(fn, ())
                       if frames.get(c) is None})
    return {"frame": frames[root], "chain": chain, "path": path, "external": external}


def unit_chain_stack(c_files, include_dirs, root: str) -> dict:
    """``call_chain_stack`` of ``root`` over ``c_files`` compiled as one translation unit (a chain
    may cross the files): ``{"riscv": ..., "arm": ...}``, None for a missing cross compiler. gcc
    names static functions "<file>:<name>" there; the path keeps the name."""
    with tempfile.TemporaryDirectory() as tmp:
        unit = Path(tmp) / "unit.c"
        unit.write_text("".join(f'#include "{Path(f).resolve()}"\n' for f in c_files), encoding="utf-8")
        rv = riscv_flags()
        out = {"riscv": None if rv is None else call_chain_stack(RISCV_GCC, rv, unit, include_dirs, root),
               "arm": call_chain_stack(ARM_GCC, list(ARM_FLAGS), unit, include_dirs, root) if arm_available()
               else None}
    for v in out.values():
        if v is not None:
            v["path"] = [name.rsplit(":", 1)[-1] for name in v["path"]]
    return out


def template(name: str) -> str:
    """A C template shipped in the package (``togglecf/embedded/<name>``)."""
    return resources.files("togglecf").joinpath("embedded", name).read_text()


def need_gcc(what: str) -> str:
    """Path of the host gcc, or a clear error naming what needs it."""
    gcc = shutil.which("gcc")
    if gcc is None:
        raise RuntimeError(f"gcc not found on PATH: {what} needs a host C compiler (apt-get install gcc)")
    return gcc


def run_harness_command(exe, cmd):
    """Run a compiled host harness; a failure raises with its stderr."""
    res = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"{exe} failed ({res.returncode}): {res.stderr.strip()}")
    return res


def run_csv_harness(exe, gyr, acc, mag=None, *, dt=None, float32: bool = False, flags=(), predictions=None,
                    diagnostics: bool = False):
    """Run a compiled host harness of this package (``tcf_*_harness in.csv out.csv``, the CSV of
    ``write_imu_csv``) on ``(N, 3)`` arrays. ``mag=None``: a 6-column CSV (the filter gets ``mag =
    NULL``); ``dt``: a time-step column; ``float32``: inputs rounded to float32 first; ``flags``:
    the harness's own options; ``predictions (N, S + 6)``: ``--pred`` (drive the filter step with
    these instead of the trees). Returns the quaternions ``(N, 4)`` float64, or with
    ``diagnostics`` (``--diag --time``) ``(quat, dict)``: every other output column per sample and
    ``ns_per_sample`` (the harness's clock() timing of the update calls; NaN if not printed)."""
    import pandas as pd  # optional heavy dependency, only for reading the harness's CSV

    with tempfile.TemporaryDirectory() as tmp:
        fin, fout = Path(tmp) / "in.csv", Path(tmp) / "out.csv"
        n = write_imu_csv(fin, gyr, acc, mag, dt, float32=float32)
        extra = []
        if predictions is not None:
            P = np.asarray(predictions, np.float64)
            if P.ndim != 2 or P.shape[0] != n:
                raise ValueError(f"predictions: expected shape ({n}, S + 6), got {P.shape}")
            fpred = Path(tmp) / "pred.csv"
            np.savetxt(fpred, P, fmt="%.17g", delimiter=",", header=",".join(f"p{j}" for j in range(P.shape[1])),
                       comments="")
            extra = ["--pred", str(fpred)]
        cmd = [str(exe), *(["--diag", "--time"] if diagnostics else []), *flags, *extra, str(fin), str(fout)]
        res = run_harness_command(exe, cmd)
        df = pd.read_csv(fout)
    quat = df[["w", "x", "y", "z"]].to_numpy(np.float64)
    if quat.shape != (n, 4):
        raise RuntimeError(f"{exe} wrote {quat.shape[0]} rows for {n} samples")
    if not diagnostics:
        return quat
    diag = {c: df[c].to_numpy(np.float64) for c in df.columns if c not in ("w", "x", "y", "z")}
    m = re.search(r"([0-9.]+) ns/sample", res.stderr)
    diag["ns_per_sample"] = float(m.group(1)) if m else float("nan")
    return quat, diag


def run_prediction_harness(exe, gyr, acc, mag=None, *, diagnostics: bool = False, no_mag: bool = False,
                           predictions=None, fs=None, dt=None):
    """``run_csv_harness`` for a learned filter's harness (``tcf_harness``,
    ``tcf_vqf_toggling_harness``: the same command line); ``no_mag``: NULL although mag is given;
    ``fs`` [Hz]: ``--fs`` (the rate of a harness that takes one at init); ``dt`` [s]: the time-step
    column (scalar or ``(N,)``)."""
    flags = (["--no-mag"] if no_mag else []) + ([] if fs is None else ["--fs", repr(float(fs))])
    return run_csv_harness(exe, gyr, acc, mag, dt=dt, flags=flags, predictions=predictions, diagnostics=diagnostics)


def write_imu_csv(path, gyr, acc, mag=None, dt=None, float32: bool = False) -> int:
    """The C harnesses' input CSV: a header, then gyr, acc[, mag][, dt] per row; returns N.
    ``float32``: values rounded to float32 first (what a float32 filter gets; ``%.9g`` then
    round-trips exactly), else exact float64 digits."""
    cols = [np.asarray(gyr, np.float64), np.asarray(acc, np.float64)]
    names = ["gyr_x", "gyr_y", "gyr_z", "acc_x", "acc_y", "acc_z"]
    if mag is not None:
        cols.append(np.asarray(mag, np.float64))
        names += ["mag_x", "mag_y", "mag_z"]
    n = cols[0].shape[0]
    for c in cols:
        if c.shape != (n, 3):
            raise ValueError(f"gyr, acc, mag must be (N, 3) with the same N, got {[x.shape for x in cols]}")
    if dt is not None:
        dt = np.asarray(dt, np.float64)
        dt = np.full(n, float(dt)) if dt.ndim == 0 else dt
        if dt.shape != (n,):
            raise ValueError(f"dt: expected a scalar or shape ({n},), got {dt.shape}")
        cols.append(dt[:, None])
        names.append("dt")
    data = np.hstack(cols)
    if float32:
        np.savetxt(path, data.astype(np.float32), fmt="%.9g", delimiter=",", header=",".join(names), comments="")
    else:
        np.savetxt(path, data, fmt="%.17g", delimiter=",", header=",".join(names), comments="")
    return n


def run_host_program(source: str, include_dirs, what: str) -> str:
    """Compile the C program ``source`` with the host gcc against ``include_dirs``, run it and return
    what it prints (probes such as ``sizeof`` of an exported state); errors name ``what``."""
    gcc = need_gcc(what)
    with tempfile.TemporaryDirectory() as tmp:
        src, exe = Path(tmp) / "probe.c", Path(tmp) / "probe"
        src.write_text(source)
        res = subprocess.run([gcc, "-std=c99", "-o", str(exe), str(src), *[f"-I{d}" for d in include_dirs]],
                             capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"{what}: compiling the probe against {', '.join(map(str, include_dirs))} failed:\n"
                               f"{res.stderr}")
        return run_command([exe])
