"""Coulomb friction that differs by direction: the kinetic level is f_c + f_c_asym sliding right
(+y) and f_c - f_c_asym sliding left. The symmetric part is Coulomb's f_c (:mod:`.coulomb`, which
this effect stands on); its own parameter is the asymmetry, so f_c_asym = 0 is plain Coulomb
friction and the diagnosis tests the asymmetry itself (docs/design.md, "Effects").

Exact form: the simulators' one dry-friction law with a level per direction; sliding, the
friction is -(f_c + f_c_asym) right and +(f_c - f_c_asym) left, and a cart at rest breaks away
right only where the applied force exceeds max(f_s, f_c + f_c_asym), left only where it is below
-max(f_s, f_c - f_c_asym). The levels are constant within a slip phase, so the exact simulator
keeps its closed form. Smooth form: the magnitude f_c + f_c_asym s with s = y'/sqrt(y'^2 + w^2),
the smoothed sign, so F = -(f_c s + f_c_asym s^2).

In this model it is exactly Coulomb friction f_c plus the constant force -f_c_asym [N] (a track
tilted down to the left, :mod:`.tilt`): sliding the forces are equal, and at rest the Karnopp
band [-(f_c - f_c_asym), f_c + f_c_asym] is [-f_c, f_c] shifted by that force
(tests/test_effects_reference.py, to 1e-12 m). No recording tells them apart (a tap neither:
the tilt pulls there too); the diagnosis names this one effect rather than Coulomb friction and
a tilt. With stiction they differ: the static level f_s is the same both ways here.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Param, register, within


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class CoulombAsymmetry(Effect):
    """Direction-dependent Coulomb friction.

    f_c_asym: half the difference of the kinetic levels, right minus left [N]: f_c+ = f_c +
        f_c_asym sliding right, f_c- = f_c - f_c_asym sliding left
    """

    f_c_asym: float = 0.0

    name = "coulomb_asymmetry"
    stage = "force"
    dry_friction = True
    sided = True
    summary = "Coulomb friction by direction: f_c + f_c_asym sliding right, f_c - f_c_asym left"
    requires = ("coulomb",)
    # Sliding one way only, the asymmetry is that way's level: f_c's.
    needs = ("both_ways",)
    shows_in = ("sign_velocity", "position")
    params = (
        Param(
            "f_c_asym",
            "N",
            -20.0,
            20.0,
            0.05,
            "velocity",
            "half the difference of the kinetic levels, right minus left",
            plausible=(-2.0, 2.0),
            neutral=0.0,
            min_size=0.02,
        ),
    )

    @classmethod
    def consistent(cls, values: dict) -> dict:
        """Neither direction's level below 0: |f_c_asym| <= f_c."""
        return within(values, "f_c_asym", "f_c")

    def kinetic(self, y, xp):
        return 0.0 * y  # nothing both ways: it only splits the level

    def kinetic_sides(self, y, xp):
        return self.f_c_asym + 0.0 * y, -self.f_c_asym + 0.0 * y
