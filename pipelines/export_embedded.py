"""The embedded export for microcontrollers: pruned models within a flash budget, as C.

Runs (or resumes) the pruning sweep of models/default in build/embedded/default/sweep (every
point judged by the toggling filter's held-out BROAD error, as the study), picks the most
accurate point whose trees fit in 32 KB of rv32imc -Os object code (the ESP32-C3), trains it
on the same trials, and writes build/embedded/default/{models,array,tl2cgen,filter}/ plus
export_report.json. Train models/default first (`togglecf train`). Any option of
`togglecf export` can be appended, e.g. `--max-bytes 65536`.

    python pipelines/export_embedded.py [--models models/default] [--out build/embedded/default] [...]
"""
import sys

from togglecf.cli.main import main

DEFAULTS = {"--models": "models/default", "--out": "build/embedded/default", "--max-bytes": "32768",
            "--format": "both"}

if __name__ == "__main__":
    args = sys.argv[1:]
    for flag, value in DEFAULTS.items():
        if flag not in args:
            args += [flag, value]
    sys.exit(main(["export", *args]))
