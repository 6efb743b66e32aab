"""Stiction: a static (breakaway) friction level f_s above the kinetic one.

Exact form: Karnopp; a cart at rest stays at rest while |net applied force| <= f_s, then slides
against the kinetic level (Coulomb's f_c, 0 without it). Smooth form: the friction magnitude
rises from the kinetic level K to f_s near zero velocity,
    F = -(K + max(f_s - K, 0) exp(-(y'/v_s)^2)) y'/sqrt(y'^2 + w^2),   v_s = sqrt(w c),
c = 0.01 m/s, so the breakaway is differentiable; as the velocity width w -> 0, v_s -> 0 and
v_s/w -> inf, so the peak tends to f_s: the smooth form converges to Karnopp, at the rate
sqrt(w) (measured: 60x less error over a 1000x narrower width; docs/design.md, "Effects").
"""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Param, register

#: The Stribeck velocity is sqrt(w STRIBECK_SCALE) for a velocity width w [m/s].
STRIBECK_SCALE = 1e-2


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Stiction(Effect):
    """Static friction above kinetic.

    f_s: static (breakaway) friction level [N]
    """

    f_s: float = 0.0

    name = "stiction"
    stage = "force"
    dry_friction = True
    summary = "stiction: breakaway needs |F| > f_s (static above kinetic)"
    requires = ("coulomb",)
    shows_in = ("sign_velocity",)
    params = (
        Param(
            "f_s",
            "N",
            0.0,
            20.0,
            0.5,
            "velocity",
            "static friction level",
            plausible=(0.0, 5.0),
            neutral=0.0,
            min_size=0.03,
            starts_at="held",
        ),
    )

    @classmethod
    def consistent(cls, values: dict) -> dict:
        """Static friction is never below the kinetic level it breaks away from."""
        if "f_s" in values and "f_c" in values:
            values = {**values, "f_s": max(values["f_s"], values["f_c"])}
        return values

    @classmethod
    def strengths(cls, values: dict, peaks: dict):
        """Stiction is there when static friction exceeds the kinetic level: f_s - f_c > 0."""
        excess = values["f_s"] - values["f_c"]
        yield cls.name, excess, {"f_s": 1.0, "f_c": -1.0}, f"f_s - f_c = {excess:.3g} N", "0 N"

    def static(self):
        return self.f_s
