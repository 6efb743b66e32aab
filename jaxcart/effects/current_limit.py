"""Amplifier current limit: the motor current, not the voltage, saturates.

The armature current is i = (v - K_b y') / Rm with K_b = B_emf / gamma [V s/m] (back-EMF), and
the drive force is gamma Rm i. The linear model's gamma v - B_emf y' is that force unlimited; a
limit |i| <= i_max replaces it with gamma Rm clip(i, -i_max, i_max), so this effect adds
    F = gamma (clip(u, -Rm i_max, Rm i_max) - u),   u = v - K_b y'.
At rest it acts like a voltage limit Rm i_max; at speed the back-EMF lowers the current and the
two differ (docs/design.md, "Effects").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Param, register
from jaxcart.smoothing import smooth_clip


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class CurrentLimit(Effect):
    """Current limit of the amplifier.

    i_max: largest armature current magnitude [A]
    """

    i_max: float = math.inf

    name = "current_limit"
    stage = "force"
    summary = "amplifier current limit: |i| <= i_max (the force saturates, not the voltage)"
    limits = "current"
    shows_in = ("command",)
    params = (
        Param(
            "i_max",
            "A",
            1e-3,
            math.inf,
            1.5,
            "voltage",
            "armature current limit",
            role="drive",
            plausible=(0.05, 20.0),
            neutral=math.inf,
            # A clip of the armature current under 0.15 A is what an amplifier's bandwidth
            # takes off the first sample's current spike (6 V draws 2.3 A at rest): on the
            # independent generator a 0.1 ms amplifier lag fits as a 2.22 A limit, 0.09 A
            # below that spike; the suite's true limits clip 0.3-1.1 A.
            min_size=0.15,
        ),
    )

    def smooth_force(self, y, yd, v, smoothing, plant):
        gamma = plant.gamma
        u = v - plant.B_emf / gamma * yd
        limit = self.i_max * plant.Rm
        return gamma * (smooth_clip(u, limit, smoothing.voltage) - u)

    def exact_force(self, y, yd, v, plant):
        gamma = plant.gamma  # plain floats here (jaxcart.exact)
        u = v - plant.B_emf / gamma * yd
        limit = self.i_max * plant.Rm
        return gamma * (min(max(u, -limit), limit) - u)

    def exact_force_for(self, drive):
        gamma = drive.gamma
        k_b, limit = drive.B_emf / gamma, self.i_max * drive.Rm

        def force(y, yd, v):
            u = v - k_b * yd
            return gamma * (min(max(u, -limit), limit) - u)

        return force

    def exact_velocity_pieces(self, drive, v):
        """The force at the held voltage v [V] as pieces linear in y' (see
        :class:`jaxcart.effects.base.Effect`): the current limits where u = v - K_b y' reaches
        +-Rm i_max, i.e. at y' = (v -+ Rm i_max) / K_b; between them no force."""
        gamma = drive.gamma
        k_b, limit = drive.B_emf / gamma, self.i_max * drive.Rm
        if not math.isfinite(limit):
            return (), ((0.0, 0.0),)
        clipped = gamma * (min(max(v, -limit), limit) - v)
        if k_b == 0.0:  # no back-EMF: u is v whatever the speed
            return (), ((clipped, 0.0),)
        # Below the low break u > limit: F = gamma (limit - v) + B_emf y'; above the high one
        # u < -limit: F = gamma (-limit - v) + B_emf y'.
        low, high = (v - limit) / k_b, (v + limit) / k_b
        b_emf = gamma * k_b
        return (low, high), (
            (gamma * (limit - v), b_emf),
            (0.0, 0.0),
            (-gamma * (limit + v), b_emf),
        )
