"""The VQF-class core filter (``togglecf.filters.vqf_core``) as a self-contained C99 source set.

``export_c_vqf(out_dir, fs, settings=None, use_mag=True)`` writes into ``out_dir``:

* ``tcf_vqf.h`` / ``tcf_vqf.c``: hand-written port of ``vqf_core_step`` (float32, no heap, no
  globals written, all state in one fixed-size ``tcf_vqf_t``; templates shipped in
  ``togglecf/embedded/``). The coefficients are derived *in C* by ``tcf_vqf_init`` from the
  physical settings and Ts (the formulas of ``vqf_core.core_coefficients``), so firmware can
  pick rate and settings at run time and the generated header holds only settings; in float32
  this loses nothing because the second-order low-passes use a well-conditioned "delta" form
  (see ``tcf_vqf.h``) whose two coefficients are small numbers with full relative precision;
* ``tcf_vqf_config.h``: generated: rate, mode and every setting as ``TCF_VQF_PARAMS_INIT``
  (a ``tcf_vqf_params_t`` initialiser);
* ``tcf_vqf_harness.c`` + ``Makefile``: the host program ``tcf_vqf_harness in.csv out.csv``
  (CSV format of ``tcf_harness.c``, optional ``dt`` column -> ``w,x,y,z``);
* ``vqf_report.json``: the returned report (files, settings, ``state_bytes`` = sizeof(tcf_vqf_t),
  object sizes for the host, rv32imc and Cortex-M4F, stack of the update call chain).

``build_vqf_harness(out_dir)`` compiles the harness with gcc; ``run_vqf_harness(exe, gyr, acc,
mag)`` runs it on arrays and returns the quaternions ``(N, 4)``.

Cortex-M4F sizes: ``arm_object_size`` / ``unit_chain_stack`` beside the RISC-V ones of
``togglecf.embedded.toolchain`` (``arm-none-eabi-gcc -mcpu=cortex-m4 -mfpu=fpv4-sp-d16
-mfloat-abi=hard -mthumb -Os``, Debian ``gcc-arm-none-eabi``); None when it is not installed.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np

from togglecf.core.io import atomic_write_json
from togglecf.embedded import framework
from togglecf.embedded.toolchain import (
    c_float,
    link_arm,
    link_riscv,
    run_csv_harness,
    template,
    unit_chain_stack,
)
from togglecf.filters.vqf_core import VQFCoreSettings

__all__ = ["export_c_vqf", "vqf_config_header", "build_vqf_harness", "run_vqf_harness", "VQF_TEMPLATES", "VQF_SOURCES",
           "C_VQF", "measure_vqf_state_bytes", "vqf_state_bytes", "DIAG_NAMES"]

VQF_TEMPLATES = ("tcf_vqf.h", "tcf_vqf.c", "tcf_math.h", "tcf_vqf_standalone.c", "tcf_vqf_harness.c", "tcf_csv.h")
#: the core's firmware sources: tcf_vqf.c (what the learned filter drives too) and the standalone API
#: (default parameters, bias and heading-offset getters)
VQF_SOURCES = ("tcf_vqf.c", "tcf_vqf_standalone.c")
#: the VQF core as C files (framework.CSourceSet)
C_VQF = framework.CSourceSet(
    what="the exported VQF core", exporter="export_c_vqf", api_header="tcf_vqf.h", state_type="tcf_vqf_t",
    sources=VQF_SOURCES, headers=("tcf_vqf.h", "tcf_math.h", "tcf_vqf_config.h"), templates=VQF_TEMPLATES,
    generated=("tcf_vqf_config.h",), harness="tcf_vqf_harness",
    firmware=framework.FirmwareCalls(
        setup="static const tcf_vqf_params_t p = TCF_VQF_PARAMS_INIT;\n  if (tcf_vqf_init(&tcf_f, &p) != 0) return 1;",
        update="tcf_vqf_update_dt(&tcf_f, g, a, m, tcf_in[9]);", quat="tcf_vqf_quat(&tcf_f, tcf_q);", inputs=10),
    note="tcf_vqf_config.h holds TCF_VQF_PARAMS_INIT. Never add -ffast-math (tcf_vqf.c refuses it: the bad-sample "
         "tests need NaN semantics).")
#: columns of ``tcf_vqf_harness --diag`` after w,x,y,z (= VQFCoreFilter.diagnostic_names)
DIAG_NAMES = ("rest", "mag_dist", "bias_x", "bias_y", "bias_z", "bias_sigma", "delta", "k_mag")
_BOOL_SETTINGS = {"motion_bias_est_enabled", "rest_bias_est_enabled", "mag_dist_rejection_enabled"}


# ------------------------------------------------------------------------------------------
# Export
# ------------------------------------------------------------------------------------------

def vqf_config_header(fs, settings: VQFCoreSettings, use_mag: bool) -> str:
    """``tcf_vqf_config.h``: rate ``fs`` [Hz], mode and every setting of ``settings`` as the
    ``tcf_vqf_params_t`` initialiser ``TCF_VQF_PARAMS_INIT``. ``fs=None``: no rate (``.fs`` 0, no
    ``TCF_VQF_FS``): the filter that embeds the core sets ``.fs`` at init."""
    rate = [] if fs is None else [f"    .fs = {c_float(fs)},"]
    lines = [*rate, f"    .use_mag = {1 if use_mag else 0},"]
    for f in fields(settings):
        v = getattr(settings, f.name)
        lines.append(f"    .{f.name} = {int(bool(v)) if f.name in _BOOL_SETTINGS else c_float(v)},")
    body = " \\\n".join(lines)
    comment = ["VQF core settings (togglecf.filters.vqf_core.VQFCoreSettings, VQF's units: deg/s, deg, s,",
               "m/s^2) and rate; tcf_vqf_init derives the per-sample coefficients from them.",
               f"mode: {'9D (acc + gyr + mag)' if use_mag else '6D (acc + gyr)'}"]
    rate_defines = ("/* no rate: .fs is set at init (tcf_vqft_init(&f, fs)) */" if fs is None else
                    f"""#define TCF_VQF_FS {c_float(fs)}          /* Hz: call tcf_vqf_update once per sample at this rate */
#define TCF_VQF_DT {c_float(1.0 / fs)}    /* s, 1 / TCF_VQF_FS */""")
    return framework.config_header("tcf_vqf_config.h", "cvqf.export_c_vqf", comment, f"""
{rate_defines}
#define TCF_VQF_USE_MAG {1 if use_mag else 0}

/* static const tcf_vqf_params_t p = TCF_VQF_PARAMS_INIT; tcf_vqf_init(&f, &p); */
#define TCF_VQF_PARAMS_INIT {{ \\
{body} \\
}}""")


def vqf_state_bytes() -> int:
    """``TCF_VQF_STATE_BYTES`` of the shipped ``tcf_vqf.h``: the documented ``sizeof(tcf_vqf_t)``
    (``tcf_vqf.c`` checks the two agree at compile time), for the formulas of the filters that
    embed the core."""
    m = re.search(r"#define TCF_VQF_STATE_BYTES \(4 \* (\d+)\)", template("tcf_vqf.h"))
    if m is None:
        raise RuntimeError("tcf_vqf.h: no '#define TCF_VQF_STATE_BYTES (4 * N)'")
    return 4 * int(m.group(1))


def measure_vqf_state_bytes(out_dir) -> int:
    """``sizeof(tcf_vqf_t)`` with the host gcc (all members are 4 bytes: the same on rv32/ARM)."""
    return framework.probe_sizes(out_dir, "tcf_vqf.h", ["sizeof(tcf_vqf_t)"])[0]


def _sum_sizes(sizes) -> dict | None:
    """text/data/bss/total summed over objects (None if any is None: no cross compiler)."""
    if any(x is None for x in sizes):
        return None
    return {k: sum(x[k] for x in sizes) for k in sizes[0]}


def export_c_vqf(out_dir, fs: float, settings: VQFCoreSettings | None = None, use_mag: bool = True, *,
                 sizes: bool = True) -> dict:
    """Write the C VQF core for rate ``fs`` [Hz] and ``settings`` (default: VQF's) into
    ``out_dir``; returns the report (also ``out_dir/vqf_report.json``): ``files``, ``fs``,
    ``use_mag``, ``settings``, ``state_bytes`` (sizeof(tcf_vqf_t), gcc) and, with ``sizes``,
    ``object_sizes`` {host, riscv, arm} of ``VQF_SOURCES`` together (text + data + bss summed over
    the two objects; -Os; None where a cross compiler is missing), ``stack`` {riscv, arm} of the
    ``tcf_vqf_update`` call chain (through both sources, compiled as one unit), and the linked
    program sizes ``linked_riscv`` (picolibc) / ``linked_arm`` (newlib-nano)."""
    if not (isinstance(fs, (int, float, np.floating)) and math.isfinite(fs) and fs > 0):
        raise ValueError(f"fs must be a positive sampling rate in Hz, got {fs!r}")
    fs = float(fs)
    settings = settings if settings is not None else VQFCoreSettings()
    if not isinstance(settings, VQFCoreSettings):
        raise TypeError(f"settings must be VQFCoreSettings, got {type(settings).__name__}")
    if not 1.0 / fs <= settings.max_dt:
        raise ValueError(f"1/fs = {1 / fs:g} s exceeds max_dt = {settings.max_dt:g} s: the gyro would never be "
                         "integrated")
    out_dir = Path(out_dir)
    files = framework.write_source_set(out_dir, C_VQF, {"tcf_vqf_config.h": vqf_config_header(fs, settings, use_mag)})
    report = {"out_dir": str(out_dir), "files": [str(p) for p in files], "fs": fs, "use_mag": bool(use_mag),
              "settings": asdict(settings), "coefficients": "derived in C by tcf_vqf_init (float32)",
              "state_bytes": measure_vqf_state_bytes(out_dir)}
    if sizes:
        srcs = [out_dir / f for f in VQF_SOURCES]
        per = framework.per_source_sizes(out_dir, C_VQF).values()
        report["object_sizes"] = {t: _sum_sizes([p[t] for p in per]) for t in ("host", "riscv", "arm")}
        report["stack"] = unit_chain_stack(srcs, [out_dir], "tcf_vqf_update")  # the chain crosses the two files
        main = framework.firmware_main(C_VQF, includes=("tcf_vqf_config.h",))
        report["linked_riscv"] = link_riscv(srcs, [out_dir], main)
        report["linked_arm"] = link_arm(srcs, [out_dir], main)
    atomic_write_json(out_dir / "vqf_report.json", report)
    return report


def build_vqf_harness(out_dir, exe=None, cflags=framework.HARNESS_CFLAGS) -> Path:
    """Compile ``tcf_vqf_harness`` from the sources in ``out_dir`` with the host gcc; returns the
    executable (default ``out_dir/tcf_vqf_harness``). Raises ``RuntimeError`` with gcc's output."""
    return framework.build_host_harness(out_dir, C_VQF, exe, cflags)


def run_vqf_harness(exe, gyr, acc, mag=None, *, dt=None, six_d: bool = False, no_mag: bool = False,
                    diagnostics: bool = False):
    """Run the compiled harness on ``(N, 3)`` arrays (``mag=None``: the filter gets ``mag =
    NULL``, which gives the 6D result; ``six_d``: run with ``use_mag = 0``; ``no_mag``: pass
    NULL although mag is given; ``dt``: scalar or ``(N,)`` time steps for
    ``tcf_vqf_update_dt``). Returns the quaternions ``(N, 4)`` float64, or with
    ``diagnostics`` ``(quat, dict)`` with ``DIAG_NAMES`` per sample and the filter's
    ``ns_per_sample`` (clock() around the update calls)."""
    flags = (["--6d"] if six_d else []) + (["--no-mag"] if no_mag else [])
    return run_csv_harness(exe, gyr, acc, mag, dt=dt, float32=True, flags=flags, diagnostics=diagnostics)


def report_json(report: dict) -> str:
    """The report as indented JSON (for printing)."""
    return json.dumps(report, indent=2, default=str)
