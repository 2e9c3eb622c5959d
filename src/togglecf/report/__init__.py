"""Tables and figures only: the study report, orientation plots, result tables for the docs, and the
one palette every figure uses (``report.style``)."""
from togglecf.report.study_report import group_table, write_report
from togglecf.report.style import FILTER_STYLE, style
from togglecf.report.tables import write_table

__all__ = ["group_table", "write_report", "FILTER_STYLE", "style", "write_table"]
