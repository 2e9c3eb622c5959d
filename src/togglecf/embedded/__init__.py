"""Embedded export: the C toolchain and size measurements, trees as C (TL2cgen and compact
arrays), and the whole toggling filter in C99 (the ``.c``/``.h`` templates ship beside)."""
from togglecf.embedded.cfilter import build_harness, export_c_filter, run_harness
from togglecf.embedded.forest_export import export_array_c, export_tl2cgen, forest_to_c
from togglecf.embedded.toolchain import RISCV_GCC, link_riscv, measure_sizes, stack_usage

__all__ = ["build_harness", "export_c_filter", "run_harness", "export_array_c", "export_tl2cgen", "forest_to_c",
           "RISCV_GCC", "link_riscv", "measure_sizes", "stack_usage"]
