"""``benchmarks/bench_ukf.py --parts``: the table of where a block's time goes names functions by their module
and attribute; a rename in the package left it raising AttributeError (found in session 21: the fast path's
``interp_weights`` had become ``interp_weights_floats``). Every part must name something that exists, and the
table must time the compiled call where a replay makes it."""

from __future__ import annotations

import importlib
import re

import pytest

from onlinecal.sim import simulate
from onlinecal.ukf import kernels
from tests.benchload import benchmark


def test_every_timed_part_names_an_existing_function() -> None:
    bench = benchmark("bench_ukf")
    for where, attr, label in bench._PARTS:
        mod_name, _, cls = where.partition(":")
        obj = importlib.import_module(mod_name)
        obj = getattr(obj, cls) if cls else obj
        assert callable(getattr(obj, attr, None)), (where, attr, label)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="the parts table times the compiled fast path")
def test_the_parts_table_times_the_motion_kernel_and_adds_up(capsys: pytest.CaptureFixture[str]) -> None:
    bench = benchmark("bench_ukf")
    bench.block_parts(simulate("flight", 3, duration=30.0, imu_rate=200.0).data)
    out = capsys.readouterr().out
    total = float(re.search(r"total ([\d.]+) µs per IMU sample", out).group(1))  # type: ignore[union-attr]
    rows = {m.group(1): float(m.group(2)) for m in re.finditer(r"^ +(\S.*?)\s+([\d.]+) µs/sample", out, re.M)}
    assert rows["motion_kernel (compiled: Q, predict, coverage, update, fold)"] > 0.0, out
    # the top-level parts (two-space indent, not the nested four) are disjoint: their sum is within the total
    top = [float(m.group(1)) for m in re.finditer(r"^  (?! )\S.*?\s+([\d.]+) µs/sample", out, re.M)]
    assert 0.0 < sum(top) <= total * 1.001, (sum(top), total, out)
