"""The effects library: physics beyond the handout's linear model, one module each, each with a
smooth (JAX) and an exact (numpy) form; see :mod:`jaxcart.effects.base` for the protocol.

Registering an effect is the import line below (the module's ``@register`` does the rest).
"""

from jaxcart.effects.backlash import Backlash
from jaxcart.effects.base import (
    REGISTRY,
    STAGE_ORDER,
    STAGES,
    Effect,
    Held,
    Param,
    effect_of_param,
    register,
)
from jaxcart.effects.coulomb import Coulomb
from jaxcart.effects.coulomb_asymmetry import CoulombAsymmetry
from jaxcart.effects.current_limit import CurrentLimit
from jaxcart.effects.deadzone import Deadzone
from jaxcart.effects.deadzone_asymmetry import DeadzoneAsymmetry
from jaxcart.effects.delay import Delay
from jaxcart.effects.friction_curve import FrictionCurve
from jaxcart.effects.quantization import Quantization
from jaxcart.effects.saturation import Saturation
from jaxcart.effects.spring import Spring
from jaxcart.effects.stiction import Stiction
from jaxcart.effects.stribeck import Stribeck
from jaxcart.effects.tilt import Tilt
from jaxcart.effects.track_friction import TrackFriction
from jaxcart.effects.viscous_asymmetry import ViscousAsymmetry
from jaxcart.effects.voltage_offset import VoltageOffset

__all__ = [
    "REGISTRY",
    "STAGE_ORDER",
    "STAGES",
    "Effect",
    "Held",
    "Param",
    "effect_of_param",
    "register",
    "Backlash",
    "Coulomb",
    "CoulombAsymmetry",
    "CurrentLimit",
    "Deadzone",
    "DeadzoneAsymmetry",
    "Delay",
    "FrictionCurve",
    "Quantization",
    "Saturation",
    "Spring",
    "Stiction",
    "Stribeck",
    "Tilt",
    "TrackFriction",
    "ViscousAsymmetry",
    "VoltageOffset",
]
