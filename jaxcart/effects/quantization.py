"""Encoder quantization: the controller reads a whole number of counts, y_meas = q floor(y / q).

Smooth form: floor(x) = x - frac(x), with the sawtooth frac(x) - 1/2 = -sum_n sin(2 pi n x)/(pi n)
summed in closed form with a damping r = exp(-2 pi w / q) (w the position width [m]):
    floor_w(x) = x - 1/2 + atan2(r sin(2 pi x), 1 - r cos(2 pi x)) / pi,
exact as w -> 0 (r -> 1) away from the count edges (docs/design.md, "Effects").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from jaxcart.effects.base import Effect, Param, register


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Quantization(Effect):
    """Encoder count size.

    quantization: distance per encoder count [m] (the IP02: 2.275e-5 m)
    """

    quantization: float = 2.275e-5

    name = "quantization"
    stage = "sensor"
    summary = "encoder quantization: the controller reads q floor(y / q)"
    not_candidate = "the encoder's count, read from each recording"
    params = (
        Param("quantization", "m", 1e-9, 1e-2, 2.275e-5, "position", "count size", role="sensor"),
    )

    def smooth_measure(self, state, y, smoothing):
        q = self.quantization
        x = y / q
        r = jnp.exp(-2 * jnp.pi * smoothing.position / q)
        theta = 2 * jnp.pi * x
        saw = jnp.arctan2(r * jnp.sin(theta), 1 - r * jnp.cos(theta)) / jnp.pi
        return q * (x - 0.5 + saw), state

    def exact_measure(self, state, y):
        q = float(self.quantization)
        return q * math.floor(y / q), state
