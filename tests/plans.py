"""The one-channel plan the rig tests run: a [rig] section of the test's choosing, one rail position at
the simulated rig's advised scale, the given apertures."""

from __future__ import annotations

from psfd.drivers.sim import SimRig

PLAN = """[rig]
{rig}

[target]
kind = "bernoulli"

[capture]
apertures = [{apertures}]
x = [{x}]
channels = ["g1"]
"""


def one_channel_plan(rig: str, apertures: str = "8") -> str:
    """Plan text with ``rig`` as the body of its [rig] section."""
    return PLAN.format(rig=rig, apertures=apertures, x=SimRig().distance_for_scale())
