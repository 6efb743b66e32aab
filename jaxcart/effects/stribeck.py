"""Stribeck friction: sliding, the friction falls from its breakaway (static) level to the
kinetic (Coulomb) level as the speed grows,

    F = -sign(y') (f_c + (f_s - f_c) exp(-(y'/v_stribeck)^2))                 [N]

with Coulomb's f_c (:mod:`.coulomb`), stiction's f_s (:mod:`.stiction`) and the Stribeck speed
v_stribeck [m/s]; at rest the Karnopp law of stiction holds (the cart breaks away only where the
applied force exceeds f_s). This effect stands on both and adds one parameter, the speed; the
three are nested: as v_stribeck -> 0 it is stiction (the jump from f_s to f_c at breakaway), with
f_s = f_c it is Coulomb friction whatever the speed. So the diagnosis can prefer the simpler
named effect: Stribeck is named only where its speed is significant and at least
``min_size`` (1 mm/s), and stiction only where f_s - f_c is (docs/design.md, "Effects").

Exact form: the combined dry-friction law with the level K + max(f_s - K, 0) exp(-(q/v_s)^2) at
speed q in each slip phase; it varies with the speed, so the exact simulator integrates that
phase by RK4 (Ts/5 sub-steps, the direction fixed, stops located by bisection). Smooth form:
stiction's bump over the speed sqrt(v_stribeck^2 + w c) (w the velocity width, c = 0.01 m/s),
which tends to v_stribeck as w -> 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Param, register


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Stribeck(Effect):
    """The Stribeck speed of the static-to-kinetic fall.

    v_stribeck: speed over which the friction falls from f_s to f_c [m/s] (0: at once)
    """

    v_stribeck: float = 0.0

    name = "stribeck"
    stage = "force"
    dry_friction = True
    summary = "Stribeck friction: f_c + (f_s - f_c) exp(-(y'/v_stribeck)^2) sliding"
    requires = ("coulomb", "stiction")
    shows_in = ("sign_velocity",)
    params = (
        Param(
            "v_stribeck",
            "m/s",
            0.0,
            1.0,
            0.01,
            "velocity",
            "Stribeck speed of the fall from static to kinetic friction",
            plausible=(1e-4, 0.2),
            neutral=0.0,
            min_size=1e-3,
        ),
    )

    def kinetic(self, y, xp):
        return 0.0 * y  # no level of its own: it shapes the fall from f_s to f_c

    def stribeck(self):
        return self.v_stribeck
