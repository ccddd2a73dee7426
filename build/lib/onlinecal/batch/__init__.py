"""The paper's offline calibration pipeline (Zhang, Höflinger & Reindl 2014, Sec. III)."""

from .pipeline import BatchResult, run_batch

__all__ = ["BatchResult", "run_batch"]
