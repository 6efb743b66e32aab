"""A cable spring: the cart's cable pulls it toward a rest position, F = -k_s (y - y_rest)
(docs/design.md, "Effects")."""

from __future__ import annotations

from dataclasses import dataclass

import jax

from jaxcart.effects.base import Effect, Param, register


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Spring(Effect):
    """Linear spring force along the track.

    k_s: stiffness [N/m]; y_rest: position where the spring is relaxed [m]
    """

    k_s: float = 0.0
    y_rest: float = 0.0

    name = "spring"
    stage = "force"
    summary = "cable spring: F = -k_s (y - y_rest)"
    shows_in = ("position",)
    params = (
        Param(
            "k_s",
            "N/m",
            0.0,
            1e4,
            5.0,
            None,
            "spring stiffness",
            plausible=(0.0, 200.0),
            neutral=0.0,
            min_size=0.1,
        ),
        Param(
            "y_rest",
            "m",
            -1.0,
            1.0,
            0.0,
            None,
            "rest position of the spring",
            plausible=(-0.5, 0.5),
        ),
    )

    def smooth_force(self, y, yd, v, smoothing, plant):
        return -self.k_s * (y - self.y_rest)

    def exact_force(self, y, yd, v, plant):
        return -self.k_s * (y - self.y_rest)

    def exact_force_for(self, drive):
        k_s, y_rest = self.k_s, self.y_rest
        return lambda y, yd, v: -k_s * (y - y_rest)

    def exact_affine(self, drive):
        return -self.k_s, 0.0, self.k_s * self.y_rest
