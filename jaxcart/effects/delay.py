"""Transport delay of the drive: the voltage commanded at t_k reaches the motor at t_k + delay.

Any fraction of a sample: with delay = n Ts + s (0 <= s < Ts), over [t_k, t_k + s) the motor sees
u_{k-n-1} and over [t_k + s, t_k+1) it sees u_{k-n}, so the held voltage's edge moves inside the
sample. The state is the line of past commands (zeros before the run starts). Both forms are the
same piecewise-constant voltage (no smoothing is needed); the smooth form is differentiable with
respect to the delay through the edge's position s (docs/design.md, "Effects").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp

from jaxcart.effects.base import Effect, Held, Param, register


@register
@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Delay(Effect):
    """Input (transport) delay.

    delay: time from the command to the motor [s]
    max_delay: longest delay the line holds [s] (static: sets the state's length)
    """

    delay: float = 0.0
    max_delay: float = field(default=0.025, metadata={"static": True})

    name = "delay"
    stage = "voltage"
    order = 10  # first: it sees the plain zero-order hold
    splits_sample = True
    summary = "transport delay: the command acts `delay` seconds late"
    shows_in = ("acceleration",)
    params = (
        Param(
            "delay",
            "s",
            0.0,
            0.05,
            0.002,
            None,
            "input delay",
            role="drive",
            plausible=(0.0, 0.024),
            neutral=0.0,
            min_size=5e-4,
        ),
    )

    def _length(self, sample_time: float) -> int:
        return int(math.ceil(self.max_delay / sample_time)) + 2

    def check(self, sample_time: float) -> None:
        try:
            d = float(self.delay)
        except (TypeError, jax.errors.ConcretizationTypeError):
            return
        if d > self.max_delay + 1e-15:
            raise ValueError(
                f"delay = {d} s is longer than the line's max_delay = {self.max_delay} s; "
                "build the Delay with a larger max_delay"
            )

    def init_state(self, sample_time: float) -> tuple:
        return (jnp.zeros(self._length(sample_time) - 1),)

    def exact_init(self, sample_time: float):
        return [0.0] * (self._length(sample_time) - 1)

    def smooth(self, state, held: Held, smoothing, sample_time):
        (past,) = state
        ts = sample_time
        line = jnp.concatenate([jnp.reshape(held.late, (1,)), past.astype(held.late.dtype)])
        d = jnp.clip(self.delay, 0.0, self.max_delay)
        n = jax.lax.stop_gradient(jnp.floor(d / ts)).astype(jnp.int32)
        split = d - n * ts
        early = jax.lax.dynamic_index_in_dim(line, n + 1, keepdims=False)
        late = jax.lax.dynamic_index_in_dim(line, n, keepdims=False)
        return Held(early, late, split), (line[:-1],)

    def exact(self, state, held: Held, sample_time):
        ts = sample_time
        line = [held.late, *state]
        d = min(max(float(self.delay), 0.0), self.max_delay)
        n = int(math.floor(d / ts))
        split = d - n * ts
        if split >= ts:  # rounding at a whole number of samples
            n, split = n + 1, 0.0
        return Held(line[n + 1], line[n], split), line[:-1]
