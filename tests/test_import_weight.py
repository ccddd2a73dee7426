"""What a command's start loads (session 14): the package ``onlinecal.ukf`` loads the filter — numba and
scipy.special with it — on first use, and nothing imports scipy.signal (~1 s) before the one function that
needs it. Each case runs in a fresh interpreter and reads ``sys.modules``."""

from __future__ import annotations

import subprocess
import sys

import pytest

_PROBE = """
import sys
{code}
print(" ".join(m for m in ("numba", "scipy.signal", "scipy.special", "onlinecal.ukf.filter") if m in sys.modules))
"""


def _loaded(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", _PROBE.format(code=code)], capture_output=True, text=True,
                         check=True, timeout=120)
    return set(out.stdout.split())


@pytest.mark.parametrize("code", [
    "import onlinecal.ukf",
    "from onlinecal.ukf import UKFConfig, replay",
    "from onlinecal.ukf.vehicle import observability_text",
    "from onlinecal.place import earth_rate_config; earth_rate_config(47.4, None, [])",
    "import onlinecal.cli, onlinecal.batch, onlinecal.health, onlinecal.report",
])
def test_the_light_parts_load_neither_the_filter_nor_scipy_signal(code: str) -> None:
    assert _loaded(code) == set()


def test_the_filter_loads_on_first_use_and_still_without_scipy_signal() -> None:
    got = _loaded("import onlinecal.ukf as u; u.OnlineCalibrator; import onlinecal.extensions, onlinecal.calfile, "
                  "onlinecal.apply_ext, onlinecal.export")
    assert {"numba", "onlinecal.ukf.filter"} <= got and "scipy.signal" not in got
