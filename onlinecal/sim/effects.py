"""The effects library: what real sensors do that the paper's model lacks (contract vocabulary).

This version knows the names but does not yet synthesise them; asking for one is an error rather
than a session silently simulated without it.
"""

from __future__ import annotations

EFFECTS = ("temperature_bias", "bias_drift", "g_sensitivity", "time_offset", "saturation",
           "scale_nonlinearity", "lever_arm", "axis_sign")


class EffectError(ValueError):
    """An effect spec that cannot be honoured."""


def parse_effect(spec: str) -> object:
    """Parse ``NAME`` or ``NAME:key=value,...``. Raises EffectError (none is implemented yet)."""
    name = spec.split(":", 1)[0].strip()
    if name not in EFFECTS:
        raise EffectError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    raise EffectError(f"effect {name!r} is not implemented in this version; no session was written")
