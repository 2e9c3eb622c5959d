"""The embedded export for microcontrollers: pruned models within a flash budget, as C.

Trains the pruned point for 32 KB of rv32imc -Os object code (the ESP32-C3) on the trials of
models/default and writes build/embedded/default/{models,array,tl2cgen,filter}/ plus
export_report.json: the best point of the pruning sweep in build/embedded/default/sweep when one
is there, else the default point (10 trees x depth 4, all features: the feature-v1 sweep's choice for
32 KB, ``togglecf.run.prune.DEFAULT_EXPORT_POINT``); minutes. Add ``--full-sweep`` to run (or
resume) the sweep first (~30 min on 2 cores; every point judged by the toggling filter's held-out
BROAD error, as the study). Train models/default first (`togglecf train`). Any option of
`togglecf export` can be appended, e.g. `--max-bytes 65536 --full-sweep`.

    python pipelines/export_embedded.py [--models models/default] [--out build/embedded/default] [--full-sweep] [...]
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
