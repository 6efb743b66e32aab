"""A dead band that differs by direction: commands within [-(deadzone - deadzone_asym),
deadzone + deadzone_asym] move nothing, so it is deadzone+ = deadzone + deadzone_asym wide
pushing right and deadzone- = deadzone - deadzone_asym pushing left (worn motor brushes). The
symmetric part is the deadzone's own half-width (:mod:`.deadzone`, which this effect stands on);
its parameter is the asymmetry, the band's centre [V] (docs/design.md, "Effects").

Both forms: the command shifted by -deadzone_asym just before the symmetric dead band, which
gives the sided band exactly: dz(u - a) is 0 for u in [a - dz, a + dz] = [-dz-, dz+], u - dz+
above it and u + dz- below it (tests/test_effects_reference.py, to 1e-12 m). The smooth form is
the deadzone's smoothed clip of the shifted command; the shift itself has no corner.

Alone, without the dead band, the shift would be a voltage offset of -deadzone_asym
(:mod:`.voltage_offset`): this effect only means a sided band beside ``deadzone``, and the
diagnosis frees the two together, with |deadzone_asym| <= deadzone.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Held, Param, register, within


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class DeadzoneAsymmetry(Effect):
    """Direction-dependent dead band of the drive.

    deadzone_asym: the band's centre [V]: deadzone+ = deadzone + deadzone_asym (pushing right),
        deadzone- = deadzone - deadzone_asym (pushing left)
    """

    deadzone_asym: float = 0.0

    name = "deadzone_asymmetry"
    stage = "voltage"
    order = 39  # just before the dead band (40) it shifts
    summary = "dead band by direction: commands in [-(dz - a), dz + a] move nothing"
    requires = ("deadzone",)
    # Pushed one way only, the shifted band is that side's edge: the deadzone's.
    needs = ("drive_both_ways",)
    shows_in = ("command", "sign_velocity")
    params = (
        Param(
            "deadzone_asym",
            "V",
            -5.0,
            5.0,
            0.05,
            None,
            "centre of the dead band (half the difference, right minus left)",
            role="drive",
            plausible=(-1.0, 1.0),
            neutral=0.0,
            min_size=0.03,
        ),
    )

    @classmethod
    def consistent(cls, values: dict) -> dict:
        """Neither side of the band narrower than 0: |deadzone_asym| <= deadzone."""
        return within(values, "deadzone_asym", "deadzone")

    def smooth(self, state, held: Held, smoothing, sample_time):
        return held.shifted(-self.deadzone_asym), state

    def exact(self, state, held: Held, sample_time):
        return held.shifted(-self.deadzone_asym), state
