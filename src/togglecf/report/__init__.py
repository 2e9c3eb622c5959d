"""Tables and figures only: the study report and orientation plots."""
from togglecf.report.study_report import group_table, write_report

__all__ = ["group_table", "write_report"]
