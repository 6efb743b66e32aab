"""Amplifier saturation: the motor sees clip(u, -v_sat, v_sat) (docs/design.md, "Effects")."""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Held, Param, register
from jaxcart.smoothing import smooth_clip


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Saturation(Effect):
    """Voltage limit of the power amplifier (not the software's ``v_limit``).

    v_sat: largest voltage magnitude the amplifier delivers [V]
    """

    v_sat: float = 6.0

    name = "saturation"
    stage = "voltage"
    order = 60
    summary = "amplifier voltage limit: v = clip(u, -v_sat, v_sat)"
    limits = "command"
    shows_in = ("command",)
    params = (
        Param(
            "v_sat",
            "V",
            1e-3,
            math.inf,
            6.0,
            "voltage",
            "amplifier voltage limit",
            role="drive",
            plausible=(0.5, 30.0),
            neutral=math.inf,
            min_size=0.1,
        ),
    )

    def smooth(self, state, held: Held, smoothing, sample_time):
        f = lambda v: smooth_clip(v, self.v_sat, smoothing.voltage)  # noqa: E731
        return Held(f(held.early), f(held.late), held.split), state

    def exact(self, state, held: Held, sample_time):
        top = self.v_sat
        early, late = held.early, held.late
        return Held(min(max(early, -top), top), min(max(late, -top), top), held.split), state
