"""Augmented-state UKF for online calibration (attitude on the manifold + the paper's 36 terms + dip)."""

from .filter import OnlineCalibrator, UKFConfig
from .live_run import run_live as run_live  # the live run (onlinecal run)
from .replay import OnlineResult, replay, write_trace

__all__ = ["OnlineCalibrator", "OnlineResult", "UKFConfig", "replay", "write_trace"]
