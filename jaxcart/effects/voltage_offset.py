"""A voltage offset of the amplifier: the motor sees the command plus a constant bias,
v = u + v_offset [V] (an offset of the amplifier's input stage or of the DAC), after any dead
band and before the amplifier's own saturation (docs/design.md, "Effects").

Exact and smooth forms: the same sum (no corner, no width).

In a driven run it is nearly the same physics as a tilted track (:mod:`.tilt`): gamma v_offset
is a constant force, and the software's limit (the PID's v_limit, before the amplifier) clips
the command, not the offset, so in closed loop the two give the same motion. They differ only
where the amplifier's saturation (v_sat, after the offset) clips u + v_offset, and in a tap with
the motor unplugged, where the offset does nothing and a tilt still pulls; a diagnosis of
closed-loop runs alone names the two as equivalent.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Held, Param, register


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class VoltageOffset(Effect):
    """Constant voltage bias of the drive.

    v_offset: the voltage added to every command [V]
    """

    v_offset: float = 0.0

    name = "voltage_offset"
    stage = "voltage"
    order = 50  # after the dead band (40), before the amplifier's saturation (60)
    summary = "amplifier offset: v = u + v_offset"
    shows_in = ("command", "position")
    params = (
        Param(
            "v_offset",
            "V",
            -10.0,
            10.0,
            0.05,
            None,
            "voltage added to every command",
            role="drive",
            plausible=(-2.0, 2.0),
            neutral=0.0,
            min_size=0.02,
        ),
    )

    def smooth(self, state, held: Held, smoothing, sample_time):
        return held.shifted(self.v_offset), state

    def exact(self, state, held: Held, sample_time):
        return held.shifted(self.v_offset), state
