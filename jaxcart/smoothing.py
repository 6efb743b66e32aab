"""Smooth stand-ins for sign() and clip(), with a width, so that gradients flow through them.

The forms are algebraic (a square root, no exp): cheap on a CPU, exact in the limit width -> 0,
and their error is largest at the corner (width/2 for the clip) and falls off as width^2 away
from it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import jax
import jax.numpy as jnp


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Smoothing:
    """Widths of the smoothed nonlinearities (array leaves: changing them never retraces).

    voltage: width of smoothed voltage corners (saturation, deadzone) [V]
    velocity: width of smoothed friction sign() around zero velocity [m/s]
    position: width of smoothed position corners (backlash, quantization) [m]
    """

    voltage: float = 0.05
    velocity: float = 2e-3
    position: float = 1e-5

    def scaled(self, factor) -> Smoothing:
        """All widths multiplied by ``factor`` (smoothing continuation, epsilon -> 0)."""
        return replace(
            self,
            voltage=self.voltage * factor,
            velocity=self.velocity * factor,
            position=self.position * factor,
        )


def smooth_relu(x, width):
    """max(x, 0) smoothed over ``width``: (x + sqrt(x^2 + width^2)) / 2."""
    return 0.5 * (x + jnp.sqrt(x * x + width * width))


def smooth_clip(x, limit, width):
    """clip(x, -limit, limit) with corners smoothed over ``width``; ``limit = inf`` is no clip.

    At ``width = 0`` this is the exact clip (its gradient is 0 outside the band).
    """
    if _is_zero(width):
        return jnp.clip(x, -limit, limit)
    finite = jnp.isfinite(limit)
    safe = jnp.where(finite, limit, 0.0)
    clipped = x - smooth_relu(x - safe, width) + smooth_relu(-x - safe, width)
    return jnp.where(finite, clipped, x)


def _is_zero(width) -> bool:
    """True for a width known to be 0 at trace time (then the exact form is used)."""
    try:
        return float(width) == 0.0
    except (TypeError, jax.errors.ConcretizationTypeError):
        return False


def smooth_sign(x, width):
    """sign(x) smoothed over ``width``: x / sqrt(x^2 + width^2); exact sign at width 0."""
    denom = x * x + width * width
    safe = jnp.where(denom > 0, denom, 1.0)
    return jnp.where(denom > 0, x * jax.lax.rsqrt(safe), 0.0)


def smooth_abs(x, width):
    """|x| smoothed over ``width``: x smooth_sign(x) = x^2 / sqrt(x^2 + width^2); exact at
    width 0, and within width of |x| everywhere."""
    return x * smooth_sign(x, width)


def continuation(shrink: float, stages: int) -> tuple[float, ...]:
    """The smoothing continuation schedule shared by fitting and tuning: width factors from 1
    down to ``shrink`` in ``stages`` geometric steps (``continuation(0.125, 4)`` is 1, 0.5,
    0.25, 0.125). Each stage starts from the previous stage's answer, so the optimizer follows
    the smoothed problem toward the exact one as the widths go to 0."""
    if not (0 < shrink <= 1 and stages >= 1):
        raise ValueError(f"continuation({shrink}, {stages}): need 0 < shrink <= 1, stages >= 1")
    if stages == 1:
        return (1.0,)
    return tuple(float(shrink ** (i / (stages - 1))) for i in range(stages))
