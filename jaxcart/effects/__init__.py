"""Effects beyond the handout's linear model, each with an exact and a smoothed form."""

from jaxcart.effects.base import Effect
from jaxcart.effects.coulomb import Coulomb
from jaxcart.effects.saturation import Saturation

__all__ = ["Effect", "Coulomb", "Saturation"]
