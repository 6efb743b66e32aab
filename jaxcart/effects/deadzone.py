"""Amplifier deadzone: commands within +/- deadzone give 0 V, larger ones lose it
(v = u - clip(u, -deadzone, deadzone)); docs/design.md, "Effects"."""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Held, Param, register
from jaxcart.smoothing import smooth_clip


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Deadzone(Effect):
    """Deadzone of the amplifier's input.

    deadzone: half-width of the band of commands that move nothing [V]
    """

    deadzone: float = 0.0

    name = "deadzone"
    stage = "voltage"
    order = 40
    summary = "amplifier deadzone: v = u - clip(u, -deadzone, deadzone)"
    shows_in = ("command", "sign_velocity")
    params = (
        Param(
            "deadzone",
            "V",
            0.0,
            5.0,
            0.3,
            "voltage",
            "half-width of the dead band",
            role="drive",
            plausible=(0.0, 2.0),
            neutral=0.0,
            min_size=0.05,
        ),
    )

    def smooth(self, state, held: Held, smoothing, sample_time):
        f = lambda v: v - smooth_clip(v, self.deadzone, smoothing.voltage)  # noqa: E731
        return Held(f(held.early), f(held.late), held.split), state

    def exact(self, state, held: Held, sample_time):
        w = self.deadzone
        early, late = held.early, held.late
        return (
            Held(early - min(max(early, -w), w), late - min(max(late, -w), w), held.split),
            state,
        )
