"""Voltage saturation of the power amplifier: v_applied = clip(u, -v_sat, v_sat)."""

from __future__ import annotations

from dataclasses import dataclass

import jax
import numpy as np

from jaxcart.effects.base import Effect
from jaxcart.smoothing import smooth_clip


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Saturation(Effect):
    """Amplifier saturation.

    v_sat: largest voltage magnitude the amplifier delivers [V] (the lab's +/-6 V)
    """

    v_sat: float = 6.0

    stage = "voltage"
    param_names = ("v_sat",)

    def smooth(self, v, smoothing):
        return smooth_clip(v, self.v_sat, smoothing.voltage)

    def exact(self, v):
        return np.clip(v, -self.v_sat, self.v_sat)
