"""Coulomb (dry) friction: a force f_c opposing motion; a stuck cart stays stuck while the net
applied force is within the static level (Karnopp), which is f_c unless stiction sets it higher
(docs/design.md, "Effects")."""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Param, register


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Coulomb(Effect):
    """Coulomb friction.

    f_c: kinetic friction force [N] (also the static level when there is no stiction)
    """

    f_c: float = 0.0

    name = "coulomb"
    stage = "force"
    dry_friction = True
    summary = "Coulomb friction: -f_c sign(y')"
    shows_in = ("sign_velocity",)
    params = (
        Param(
            "f_c",
            "N",
            0.0,
            20.0,
            0.3,
            "velocity",
            "kinetic friction force",
            plausible=(0.0, 5.0),
            neutral=0.0,
            min_size=0.02,
        ),
    )

    def kinetic(self, y, xp):
        return self.f_c + 0.0 * y
