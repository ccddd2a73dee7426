"""Augmented-state UKF for online calibration (attitude on the manifold + the paper's 36 terms + dip).

The filter itself (:class:`OnlineCalibrator`, with numba's kernels and scipy) and the live run are loaded on
first use (PEP 562): a command that only needs a part of this package — the batch reading its config, the
Earth rate or the observability words — starts without them (~0.6 s of every such command's start).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .config import UKFConfig
from .replay import OnlineResult, replay, write_trace

if TYPE_CHECKING:
    from .filter import OnlineCalibrator
    from .live_run import run_live

__all__ = ["OnlineCalibrator", "OnlineResult", "UKFConfig", "replay", "run_live", "write_trace"]

_LAZY = {"OnlineCalibrator": "filter", "run_live": "live_run"}


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{mod}", __name__), name)
    globals()[name] = value
    return value
