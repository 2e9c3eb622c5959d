"""BROAD's error metrics (``../shared/docs/broad-metrics.md``): total, heading, inclination RMSE in
degrees over the ``movement`` samples, group means and the TAGP."""
from togglecf.metrics.broad import (
                                    METRICS,
                                    ErrorReference,
                                    TagpResult,
                                    error_angles_rad,
                                    error_quaternion,
                                    group_means,
                                    remove_heading_offset,
                                    rmse_deg,
                                    tagp,
                                    trial_errors,
)

__all__ = ["METRICS", "ErrorReference", "TagpResult", "error_angles_rad", "error_quaternion", "group_means",
           "remove_heading_offset", "rmse_deg", "tagp", "trial_errors"]
