"""Model-discrepancy discovery (``onlinecal diagnose``): what the paper's sensor model gets wrong on measured
data, the named cause, the extended model and its held-out gain. Entry point :func:`diagnose`."""

from .core import diagnose
from .result import SCHEMA, Diagnosis, Finding

__all__ = ["SCHEMA", "Diagnosis", "Finding", "diagnose"]
