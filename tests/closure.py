"""The shared out-of-fit gyro check (``../shared/tools/gyro_closure.py``: integrated gyro against the accel + mag
attitude at both ends of a hand-held log), run as the tool itself, and the MARG set it is run on."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
MARG = SHARED / "data" / "marg-set1"
CLOSURE = SHARED / "tools" / "gyro_closure.py"


def closure(cal: Path, logs: list[Path]) -> list[float]:
    """The tool's closure error (deg) of each log in ``logs`` for the calibration JSON ``cal``."""
    p = subprocess.run([sys.executable, str(CLOSURE), str(cal), *map(str, logs)], capture_output=True, text=True,
                       timeout=600, check=True)
    return [float(line.rsplit("closure error", 1)[1].split()[0]) for line in p.stdout.splitlines()]
