"""``togglecf import``: a CSV/NumPy log (and a mocap reference) into BROAD's layout
(``togglecf.data.importer``). The parser is ``cli.parsers.add_import_parser``; this module is
imported when the command runs."""
from __future__ import annotations

from togglecf.core.extras import check_extra
from togglecf.data.importer import REFERENCE_WHAT, ImportSettings, import_recording, summary_text

__all__ = ["cmd_import"]


def cmd_import(args):
    if args.reference:  # refuse at once, before a file is read
        check_extra("import", what=REFERENCE_WHAT)
    settings = ImportSettings(units=args.units, time_unit=args.time_unit, frame=args.frame, quat_order=args.quat_order,
                              calibrate_mag=args.calibrate_mag, thorough=args.thorough)
    if args.calibrate_mag and not args.reference:
        raise ValueError("--calibrate-mag needs --reference (the calibration runs with the alignment)")
    result = import_recording(args.imu, args.out, args.reference, name=args.name, groups=args.group or ("imported",),
                              settings=settings, plot=args.plot)
    print(summary_text(result.report))
    for path in result.files:
        print(f"wrote {path}")
    if result.report.get("reference_from", "").startswith("none"):
        print("no reference: the trial can be filtered (togglecf stream, the Python API) but not scored")
    else:
        print(f"evaluate it: togglecf evaluate --data {result.path.parent} --trials {result.trial.name}")
    return 0
