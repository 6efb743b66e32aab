"""Friction as a curve of the speed, in each direction: how the sliding friction departs from
its slow level (Coulomb's f_c, :mod:`.coulomb`, and its asymmetry) as the cart speeds up, read
from the data where no named law (Stribeck's fall, viscous friction by direction, ...) has its
shape:

    F = -d_right(y')   sliding right (y' > 0),    F = +d_left(-y')   sliding left      [N]

each d a table over the speed knots q_1 < ... < q_n, geometric from 20 mm/s to 0.32 m/s (4x
apart for 3 entries: 20, 80, 320 mm/s), linear between them, 0 up to the anchor q_0 = 5 mm/s
and held beyond q_n (where the plant's viscous B_eq y' grows on). A negative entry is friction
that falls with speed, a positive one friction that grows faster than B_eq says. Below 5 mm/s
the curve is 0: how friction behaves at the very start of motion (a breakaway above the
kinetic level, Stribeck's fall) is the named effects' (stiction, :mod:`.stribeck`), and a
table reaching down to rest would let a fit trade a steep slope there against the cart's few
samples that slow (a fit of one step put 1.8 N at 5 mm/s for a truth of 0.35 N). Nothing
holds f_c + d >= 0 here; a curve whose friction would push the cart is never named by the
diagnosis (:func:`tuning.estimation.diagnose.friction_curve.below_zero`).

Exact form: piecewise linear in the velocity alone, breaks at +-q_0 .. +-q_n, so the exact
simulator solves it in closed form between events (``exact_velocity_pieces``). Smooth form: the
same tables at the smoothed speed |y'| (``smooth_abs``) and direction (``smooth_sign``) over the
velocity width. Continuous, and 0 near rest, so the Karnopp law of Coulomb friction at rest is
untouched (docs/design.md, "Effects").
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart.effects.base import Effect, Param, register
from jaxcart.smoothing import smooth_abs, smooth_sign

#: The anchor below which the curve is 0, and the fastest knot [m/s].
ANCHOR, FASTEST = 0.005, 0.32
#: Entries of each table.
KNOTS = 3


def knots(n: int) -> tuple[float, ...]:
    """The speeds [m/s] of a table of ``n`` entries: geometric from ANCHOR (excluded) to
    FASTEST."""
    ratio = (FASTEST / ANCHOR) ** (1.0 / n)
    return tuple(ANCHOR * ratio**k for k in range(1, n + 1))


def _nodes(levels) -> tuple[tuple, tuple]:
    """(speeds [m/s], values [N]) of the whole curve: 0 at rest and at the anchor, then the
    table."""
    return (0.0, ANCHOR, *knots(len(levels))), (0.0, 0.0, *(float(v) for v in levels))


def _table(levels, q: float) -> float:
    """The curve of table ``levels`` at speed q >= 0 [m/s] (plain floats)."""
    xs, ys = _nodes(levels)
    if q >= xs[-1]:
        return ys[-1]
    k = bisect.bisect_right(xs, q)
    return ys[k - 1] + (ys[k] - ys[k - 1]) * (q - xs[k - 1]) / (xs[k] - xs[k - 1])


def _force(right, left, yd: float) -> float:
    """The exact force [N] at velocity yd [m/s] of the tables ``right`` and ``left``."""
    if yd > 0.0:
        return -_table(right, yd)
    return _table(left, -yd) if yd < 0.0 else 0.0


def _pieces(levels, side: float):
    """(breaks, (f0, k) pieces) of -side d(side y') for side y' >= 0, breaks ascending in y'."""
    xs, ys = _nodes(levels)
    pieces = []
    for k in range(len(xs) - 1):
        slope = (ys[k + 1] - ys[k]) / (xs[k + 1] - xs[k])
        # d(q) = ys[k] + slope (q - xs[k]) with q = side y'; the force is -side d.
        pieces.append((-side * (ys[k] - slope * xs[k]), -slope))
    pieces.append((-side * ys[-1], 0.0))
    breaks = [side * x for x in xs[1:]]
    return (breaks, pieces) if side > 0 else (breaks[::-1], pieces[::-1])


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class FrictionCurve(Effect):
    """Speed-dependent sliding friction, a table in each direction.

    f_curve_right, f_curve_left: the friction's departure from its slow level [N] sliding
        right (+y) and left, at the speeds :func:`knots` (3 entries: 20, 80, 320 mm/s)
    """

    f_curve_right: tuple = (0.0,) * KNOTS
    f_curve_left: tuple = (0.0,) * KNOTS

    name = "friction_curve"
    stage = "force"
    summary = (
        "friction as a curve of the speed, each direction: f_c + d(|y'|), a table over 20-320 mm/s"
    )
    requires = ("coulomb",)
    shows_in = ("sign_velocity",)
    not_candidate = (
        "the diagnosis's batch does not fit a vector yet; fit it with jaxcart fit "
        "--params B_eq,f_c,f_curve_right,f_curve_left"
    )
    params = tuple(
        Param(
            f"f_curve_{side}",
            "N",
            -20.0,
            20.0,
            0.0,
            "velocity",
            f"the sliding friction's departure from its slow level at 20, 80, 320 mm/s, "
            f"sliding {side}",
            size=KNOTS,
            plausible=(-2.0, 2.0),
            neutral=0.0,
        )
        for side in ("right", "left")
    )

    def smooth_force(self, y, yd, v, smoothing, plant):
        q = smooth_abs(yd, smoothing.velocity)
        s = smooth_sign(yd, smoothing.velocity)
        right = self._smooth_table(self.f_curve_right, q)
        left = self._smooth_table(self.f_curve_left, q)
        return -s * (0.5 * (1 + s) * right + 0.5 * (1 - s) * left)

    def exact_force(self, y, yd, v, plant):
        return _force(self.f_curve_right, self.f_curve_left, yd)

    def exact_force_for(self, drive):
        right, left = self._levels()
        return lambda y, yd, v: _force(right, left, yd)

    def exact_velocity_pieces(self, drive, v):
        """Breaks at -q_n .. -q_0, q_0 .. q_n: the tables' linear pieces, constant beyond."""
        right, left = self._levels()
        b_left, p_left = _pieces(left, -1.0)
        b_right, p_right = _pieces(right, 1.0)
        # The left side's last piece (-q_0, 0) and the right side's first (0, q_0) are one: 0.
        return (*b_left, *b_right), (*p_left[:-1], *p_right)

    def _levels(self):
        return tuple(float(x) for x in self.f_curve_right), tuple(
            float(x) for x in self.f_curve_left
        )

    @staticmethod
    def _smooth_table(levels, q):
        levels = jnp.asarray(levels)
        xs = np.array((0.0, ANCHOR, *knots(levels.shape[-1])))
        return jnp.interp(q, xs, jnp.concatenate([jnp.zeros(2, levels.dtype), levels]))
