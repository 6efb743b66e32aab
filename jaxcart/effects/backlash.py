"""Backlash: play between the pinion and the rack, taken up after each reversal of the drive.

The model (the same in both simulators). The rigid plant's one body splits in two, coupled only
when the gap is closed:

    motor side (rotor + pinion, reflected mass M_J [kg], position x_m [m]):
        M_J x_m'' = gamma v - B_emf x_m' - N
    cart (mass M [kg], position y [m]):
        M y'' = -B_eq y' + F(y, y', v) + N

with the play d = x_m - y in [-b/2, b/2] (b = ``backlash``, the total play in cart-equivalent
metres) and N [N] the contact force of the pinion on the rack:

- free (|d| < b/2): N = 0; the motor crosses the gap under its own linear dynamics and the cart
  moves under its own forces (viscous B_eq, friction, springs);
- contact on side s = sign(d) (|d| = b/2, d' = 0): the two move as the plant's one body of mass
  m = M + M_J and damping c = B_eq + B_emf, and N = gamma v - B_emf y' - M_J y'' (from the motor's
  equation); the contact holds while s N >= 0 and separates when s N would turn negative (the
  pinion cannot pull the rack). With friction stuck, N = gamma v.
- impact (|d| reaches b/2 with the motor closing): perfectly inelastic, momentum shared:
  y'+ = x_m'+ = (M y'- + M_J x_m'-) / m.

F, the cart's other forces, sees the cart's y and y' (a current limit acts on the cart's
velocity too: a known simplification). With b = 0 the motor never leaves the rack and the model
is the plant without backlash. The initial play is d = 0 (the pinion mid-gap, at rest): the first
drive must cross b/2 before the cart moves.

Exact form (:mod:`jaxcart.exact`): no smoothing; the three modes with their events (impact:
|d| = b/2; separation: N = 0; stick-slip of the cart's dry friction) located by bisection inside
RK4 sub-steps (Ts/5), the mode switches applied exactly.

Smooth form (:mod:`jaxcart.smooth_sim`): the same hybrid model stepped on sub-steps of Ts/substeps:
each sub-step first advances both bodies free (the motor in closed form, the cart with the
simulator's friction step); if that would close the gap (penetration p = s d - b/2 > 0) the
impact time t_c in the sub-step is located by interpolating p (secant, then one regula-falsi
step), both bodies are advanced free to t_c, the momentum is shared, and the joined body goes on
over the rest of the sub-step; a contact separates at the next sub-step whose free step opens
the gap. Like :mod:`jaxcart.effects.delay` it needs no smoothing width: the run is continuous in
b and differentiable with respect to it through the event times t_c and the reset d = s b/2
(an impact moving across a sub-step boundary is continuous: t_c = hs there equals t_c = 0 in the
next), and it converges to the exact form as the sub-steps shrink (the event times are exact to
O(hs^3)). A separation is taken up to one sub-step late, where N = 0: the joined and free
motions agree to first order there, so this costs O(hs^2) per separation.

Protocol extension (for :mod:`jaxcart.effects.base`): a force-stage effect may carry state and
own the motion between samples. It sets ``transmission = True`` and gives ``init_state`` /
``exact_init`` as any stateful effect; the smooth simulator then carries its state through the
loop and steps the sub-steps with the two-body step; the exact one with its two-body event
integrator. Plants without such an effect pay nothing (no state, the same one-body step).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from jaxcart.effects.base import Effect, Param, register


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Backlash(Effect):
    """Play between pinion and rack.

    backlash: total play b [m], in cart-equivalent metres (the motor side moves b between the
        two contacts)
    """

    backlash: float = 0.0

    name = "backlash"
    stage = "force"
    #: owns the motion between samples (a second body, the motor side, and its state)
    transmission = True
    summary = "backlash: play b between pinion and rack, crossed after each reversal"
    not_candidate = (
        "its two-body sub-step makes the batch's compile several times longer; fit it "
        "with jaxcart fit"
    )
    shows_in = ("sign_velocity",)
    params = (
        Param(
            "backlash",
            "m",
            0.0,
            5e-3,
            2e-4,
            None,
            "total play of pinion and rack",
            neutral=0.0,
        ),
    )

    def init_state(self, sample_time: float) -> tuple:
        """(d, d'): the play x_m - y [m] and its rate [m/s]; mid-gap at rest."""
        return (jnp.zeros(()), jnp.zeros(()))

    def exact_init(self, sample_time: float):
        """[d, d', mode]: play [m], its rate [m/s], contact side (+1, -1) or 0 when free."""
        return [0.0, 0.0, 0.0 if float(self.backlash) > 0.0 else 1.0]
