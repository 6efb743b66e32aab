"""A tilted track: gravity's component along the track is a constant force f_tilt on the cart
[N] (f_tilt = M g sin(theta): 0.5 N is a 3.1 degree tilt under the 0.94 kg cart; positive along
+y), F = f_tilt whether the motor is connected or not (docs/design.md, "Effects").

Exact form: the constant force, which keeps every closed form of the exact simulator (a force
piecewise linear in the velocity, one piece; affine in (y, y') beside a spring). Smooth form: the
same.

Under P or PD control without integral action the loop holds it with a steady error: the cart
settles past the reference by f_tilt / (kp gamma) [m]. In a driven run it is nearly the same
physics as a voltage offset of the amplifier (:mod:`.voltage_offset`, b = f_tilt / gamma): in
closed loop, under the software limit too, the two give the same motion; they differ where the
amplifier's own saturation clips the offset voltage, and in a tap with the motor unplugged,
where only the tilt acts. With Coulomb friction f_c >= |f_tilt| it is exactly Coulomb friction
that differs by direction (:mod:`.coulomb_asymmetry`, f_c_asym = -f_tilt), which the diagnosis
names instead (one effect rather than two).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from jaxcart.effects.base import Effect, Param, register


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Tilt(Effect):
    """A constant force along the track.

    f_tilt: the force along +y [N] (gravity on a tilted track: M g sin(theta))
    """

    f_tilt: float = 0.0

    name = "tilt"
    stage = "force"
    summary = "tilted track: a constant force f_tilt along +y"
    shows_in = ("position", "command")
    # In a driven run it is a drive offset (voltage_offset); a tap, where only the tilt pulls,
    # tells them apart.
    needs = ("tap",)
    params = (
        Param(
            "f_tilt",
            "N",
            -20.0,
            20.0,
            0.1,
            None,
            "constant force along +y (gravity on a tilted track)",
            plausible=(-2.0, 2.0),
            neutral=0.0,
            min_size=0.02,
        ),
    )

    def smooth_force(self, y, yd, v, smoothing, plant):
        return self.f_tilt * jnp.ones_like(y)

    def exact_force(self, y, yd, v, plant):
        return self.f_tilt

    def exact_force_for(self, drive):
        f_tilt = self.f_tilt
        return lambda y, yd, v: f_tilt

    def exact_affine(self, drive):
        return 0.0, 0.0, self.f_tilt

    def exact_velocity_pieces(self, drive, v):
        return (), ((self.f_tilt, 0.0),)
