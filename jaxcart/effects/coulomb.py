"""Coulomb (dry) friction: a force f_c opposing motion; a stuck cart stays stuck while the net
applied force is within +/- f_c (Karnopp). Static friction equal to kinetic here; stiction
(static above kinetic) is its own effect."""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect
from jaxcart.smoothing import smooth_sign


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Coulomb(Effect):
    """Coulomb friction.

    f_c: kinetic (and static) friction force [N]
    """

    f_c: float = 0.0

    stage = "force"
    param_names = ("f_c",)

    def smooth_force(self, y, ydot, smoothing):
        return -self.f_c * smooth_sign(ydot, smoothing.velocity)

    def friction_levels(self):
        """(kinetic, static) friction force [N] for the exact stick-slip simulator."""
        return float(self.f_c), float(self.f_c)
