"""Friction that varies along the track: a kinetic level f(y) [N], a smooth map of position
through a few knots (a worn or dirty stretch, a tight bearing).

    f(y) = sum_i c_i phi_i(y) / sum_i phi_i(y),   phi_i = exp(-((y - k_i) / h)^2 / 2)

with knots k_i evenly spaced over +/- 0.4 m (the cart's travel), h their spacing: a normalized
radial basis whose weights c interpolate the levels a_i given at the knots (f(k_i) = a_i; c = W^-1
a, W_ij = phi_j(k_i) / sum_l phi_l(k_i)). So a level is the friction at its knot (a fit's values
and standard errors are friction where the cart was), equal levels give a constant one, and
between the knots f may pass a little beyond its neighbours (0.02 N over levels rising 0.4 N
over two spacings). It adds to Coulomb's f_c, the sum held at 0 or above (docs/design.md,
"Effects").
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import jax
import numpy as np

from jaxcart.effects.base import Effect, Param, register

#: The knots span the travel of the cart [m].
SPAN = 0.4


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class TrackFriction(Effect):
    """Position-dependent kinetic friction.

    f_track: friction levels at the knots [N], a vector of 2 or more values; knots evenly spaced
        over [-0.4, 0.4] m
    """

    f_track: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)

    name = "track_friction"
    stage = "force"
    dry_friction = True
    position_dependent = True
    summary = "friction along the track: a smooth map f(y) through knots over +/-0.4 m"
    not_candidate = (
        "the diagnosis's batch does not fit a vector yet (5 knots and B_eq are 6 slots of its "
        "5): jaxcart diagnose --curve reads it as the last candidate where the recordings "
        "cover 0.4 m of the track; fit it with jaxcart fit --params B_eq,f_track"
    )
    # Two knot spacings: three knots within reach, so that a level that varies shows.
    covers = 0.4
    shows_in = ("position",)
    params = (
        Param(
            "f_track",
            "N",
            0.0,
            20.0,
            0.3,
            "velocity",
            "friction at the knots",
            size=5,
            plausible=(0.0, 5.0),
            neutral=0.0,
        ),
    )

    def kinetic(self, y, xp):
        if xp is math:
            return self.exact_kinetic_sides()(y)[0]
        a = xp.asarray(self.f_track)
        n = a.shape[-1]
        c = xp.asarray(_interpolation(n)) @ a
        knots = np.linspace(-SPAN, SPAN, n)
        z = (y - knots) / (2 * SPAN / (n - 1))  # y is a scalar here (each simulator steps one run)
        w = xp.exp(-0.5 * z * z)
        return xp.sum(c * w) / xp.sum(w)

    def exact_kinetic_sides(self):
        """The exact simulator's levels, on plain floats, the basis bound once per run."""
        weights, offsets, inv_h = _exact_form(tuple(float(v) for v in self.f_track))
        pairs, exp = tuple(zip(weights, offsets, strict=True)), math.exp

        def sides(y):
            u = y * inv_h
            num = den = 0.0
            for c, o in pairs:
                z = u + o  # (y - k_i) / h
                w = exp(-0.5 * z * z)
                num += c * w
                den += w
            level = num / den
            return level, level

        return sides


@functools.cache
def _interpolation(n: int) -> np.ndarray:
    """W^-1 of n knots: the basis weights c = W^-1 a that put f through the levels a."""
    knots = np.linspace(-SPAN, SPAN, n)
    phi = np.exp(-0.5 * ((knots[:, None] - knots[None, :]) / (2 * SPAN / (n - 1))) ** 2)
    return np.linalg.inv(phi / phi.sum(axis=1, keepdims=True))


@functools.lru_cache(maxsize=256)
def _exact_form(levels: tuple) -> tuple:
    """(the basis weights of ``levels``, -k_i / h, 1 / h [1/m]) as plain floats, once per
    levels (a fit's exact runs share them)."""
    n = len(levels)
    h = 2 * SPAN / (n - 1)
    weights = _interpolation(n) @ np.asarray(levels, dtype=float)
    return (
        tuple(float(c) for c in weights),
        tuple(float(-k / h) for k in np.linspace(-SPAN, SPAN, n)),
        1.0 / h,
    )
