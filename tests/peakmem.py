"""Peak memory and CPU time of one ``onlinecal`` command in a fresh process (the memory tests of issue 16.5)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# VmHWM: the peak of the command's own process (ru_maxrss would carry the parent's peak across fork + exec)
_CLI = """
import runpy, sys, time
c0 = time.process_time()
sys.argv = ["onlinecal", *sys.argv[1:]]
try:
    runpy.run_module("onlinecal", run_name="__main__")
except SystemExit as e:
    code = e.code
hwm = [int(x.split()[1]) for x in open("/proc/self/status") if x.startswith("VmHWM:")][0]
print("PEAK", hwm, time.process_time() - c0, code, file=sys.stderr)
"""


def peak(args: list[str]) -> tuple[int, float]:
    """(peak RSS in kB, CPU seconds) of ``onlinecal *args``; the command must end with a result (exit 0/4/5)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    r = subprocess.run([sys.executable, "-c", _CLI, *args], capture_output=True, text=True, env=env)
    line = [x for x in r.stderr.splitlines() if x.startswith("PEAK ")]
    assert line, r.stderr[-2000:]
    kb, cpu, code = line[-1].split()[1:]
    assert code in ("0", "4", "5"), r.stderr[-2000:]  # a result (healthy, degraded or failed), not an error
    return int(kb), float(cpu)
