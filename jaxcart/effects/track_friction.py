"""Friction that varies along the track: a kinetic level f(y) [N], a smooth map of position
through a few knots (a worn or dirty stretch, a tight bearing).

    f(y) = sum_i a_i phi_i(y) / sum_i phi_i(y),   phi_i = exp(-((y - k_i) / h)^2 / 2)

with knots k_i evenly spaced over +/- 0.4 m (the cart's travel), h their spacing: a normalized
radial basis, so equal values a_i give a constant level and f stays within [min a, max a]. It adds
to Coulomb's f_c (docs/design.md, "Effects").
"""

from __future__ import annotations

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
        "a candidate only where the recordings cover 0.4 m of the track, and the diagnosis's "
        "batch does not fit a vector yet (5 knots and B_eq are 6 slots of its 5); fit it with "
        "jaxcart fit --params B_eq,f_track"
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
        if xp is math:  # the exact simulator: plain floats, called ~10^5 times a run
            n = len(self.f_track)
            h = 2 * SPAN / (n - 1)
            w = [math.exp(-0.5 * ((y + SPAN - i * h) / h) ** 2) for i in range(n)]
            return sum(a * wi for a, wi in zip(self.f_track, w, strict=True)) / sum(w)
        a = xp.asarray(self.f_track)
        n = a.shape[-1]
        knots = np.linspace(-SPAN, SPAN, n)
        h = 2 * SPAN / (n - 1)
        z = (y - knots) / h  # y is a scalar here (each simulator steps one run)
        w = xp.exp(-0.5 * z * z)
        return xp.sum(a * w) / xp.sum(w)
