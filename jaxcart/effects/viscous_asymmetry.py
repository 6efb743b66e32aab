"""Viscous friction that differs by direction: the cart's viscous coefficient is
B_eq + B_asym sliding right (+y) and B_eq - B_asym sliding left. The symmetric part stays the
plant's B_eq; this effect's parameter is the asymmetry, so it adds

    F = -B_asym |y'|                                                         [N]

(sliding right -B_asym y', left +B_asym y'), a force that always points to -y for B_asym > 0
and grows with the speed (docs/design.md, "Effects"). B_eq's meaning is unchanged: the mean of
the two directions' coefficients, as a tap in each direction would measure them.

Exact form: the force is piecewise linear in the velocity, one break at y' = 0, so the exact
simulator solves it in closed form between events (beside constant-level friction; by RK4
beside a spring). Smooth form: -B_asym y' s with s = y'/sqrt(y'^2 + w^2), the smoothed sign over
the velocity width w.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Param, register, within
from jaxcart.smoothing import smooth_abs


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class ViscousAsymmetry(Effect):
    """Direction-dependent viscous friction.

    B_asym: half the difference of the viscous coefficients, right minus left [kg/s]:
        B_eq + B_asym sliding right, B_eq - B_asym sliding left
    """

    B_asym: float = 0.0

    name = "viscous_asymmetry"
    stage = "force"
    summary = "viscous friction by direction: B_eq + B_asym sliding right, B_eq - B_asym left"
    shows_in = ("sign_velocity",)
    # Sliding one way only, the asymmetry is that way's coefficient: B_eq's.
    needs = ("both_ways",)
    params = (
        Param(
            "B_asym",
            "kg/s",
            -200.0,
            200.0,
            0.3,
            "velocity",
            "half the difference of the viscous coefficients, right minus left",
            plausible=(-10.0, 10.0),
            neutral=0.0,
            min_size=0.05,
        ),
    )

    @classmethod
    def consistent(cls, values: dict) -> dict:
        """Neither direction's coefficient below 0: |B_asym| <= B_eq."""
        return within(values, "B_asym", "B_eq")

    def smooth_force(self, y, yd, v, smoothing, plant):
        return -self.B_asym * smooth_abs(yd, smoothing.velocity)

    def exact_force(self, y, yd, v, plant):
        return -self.B_asym * abs(yd)

    def exact_force_for(self, drive):
        b = self.B_asym
        return lambda y, yd, v: -b * abs(yd)

    def exact_velocity_pieces(self, drive, v):
        """One break at y' = 0: F = B_asym y' below it, -B_asym y' above."""
        return (0.0,), ((0.0, self.B_asym), (0.0, -self.B_asym))
