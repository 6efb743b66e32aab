"""Plant parameters of the IP02 cart: the handout's appendix as an immutable pytree.

    m y'' + c y' = gamma * u + F_effects(y, y'),      m = M + M_J,   c = B_eq + B_emf
    M_J   = eta_g Kg^2 Jm / r_mp^2
    B_emf = eta_g Kg^2 eta_m Kt Km / (Rm r_mp^2)       (0 with the motor unplugged)
    gamma = eta_g Kg eta_m Kt / (Rm r_mp)               (times gamma_scale)

This is the nominal model, the handout's equation (0.1): no amplifier limit, no friction. The
lab's 6 V limit is the Simulink saturation block, i.e. the controller's ``v_limit``. Effects
beyond the linear model (saturation, friction, delay, ...) are pieces in ``Plant.effects`` that
a file, an option or a fit adds; see :mod:`jaxcart.effects` and :func:`jaxcart.build_plant`
(the one plant builder; :func:`jaxcart.handout_plant` and :func:`jaxcart.tap_plant` call it).
The appendix's numbers are :mod:`hw.handout`'s, the one copy.

>>> p = Plant()
>>> round(float(p.m), 4), round(float(p.B_emf), 4), round(float(p.gamma), 4)
(1.0731, 7.7236, 1.7235)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields

import jax
import jax.numpy as jnp

from hw.handout import APPENDIX
from hw.handout import ENCODER_RESOLUTION as ENCODER_RESOLUTION
from hw.handout import TRACK_LENGTH as TRACK_LENGTH
from hw.handout import TRAVEL as TRAVEL
from jaxcart.effects import REGISTRY, STAGE_ORDER


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Plant:
    """The cart, its motor and gearbox, and the effects acting on it.

    M: cart plus added weight, Mc + Mw [kg]
    B_eq: equivalent viscous friction at the cart [kg/s] (N s/m)
    Rm: armature resistance [ohm]
    Kt: motor torque constant [N m/A]
    Km: back-EMF constant [V s/rad]
    Jm: rotor moment of inertia [kg m^2]
    Kg: gearbox ratio [-]
    r_mp: motor pinion radius [m]
    eta_g, eta_m: gearbox and motor efficiencies [-]
    gamma_scale: multiplier on the input gain gamma [-] (amplifier gain error, fitted)
    effects: nonlinear effects, each an :class:`jaxcart.effects.Effect`
    motor_connected: False for the tap test (no back-EMF, no drive) (static)
    """

    M: float = APPENDIX["M"]
    B_eq: float = APPENDIX["B_eq"]
    Rm: float = APPENDIX["Rm"]
    Kt: float = APPENDIX["Kt"]
    Km: float = APPENDIX["Km"]
    Jm: float = APPENDIX["Jm"]
    Kg: float = APPENDIX["Kg"]
    r_mp: float = APPENDIX["r_mp"]
    eta_g: float = APPENDIX["eta_g"]
    eta_m: float = APPENDIX["eta_m"]
    gamma_scale: float = APPENDIX["gamma_scale"]
    effects: tuple = ()
    motor_connected: bool = field(default=True, metadata={"static": True})

    def __post_init__(self):
        for name in ("M", "Rm", "Kg", "r_mp", "eta_g", "eta_m", "Jm", "B_eq", "gamma_scale"):
            value = getattr(self, name)
            if isinstance(value, float | int) and not value >= 0:
                raise ValueError(f"plant parameter {name} = {value!r}: it must be >= 0")
        if isinstance(self.M, float | int) and self.M == 0:
            raise ValueError("plant parameter M = 0 kg: the cart needs a positive mass")
        kinds = [type(e).name for e in self.effects]
        if len(kinds) != len(set(kinds)):
            raise ValueError(f"an effect is named twice in {kinds}; give each effect once")

    # Derived quantities of the handout (section 1.1).
    @property
    def M_J(self):
        """Rotor inertia reflected to the cart [kg]."""
        return self.eta_g * self.Kg**2 * self.Jm / self.r_mp**2

    @property
    def m(self):
        """Total moving mass M + M_J [kg]."""
        return self.M + self.M_J

    @property
    def B_emf(self):
        """Back-EMF damping [kg/s]; 0 when the motor is unplugged."""
        if not self.motor_connected:
            return 0.0 * self.Kt
        return self.eta_g * self.Kg**2 * self.eta_m * self.Kt * self.Km / (self.Rm * self.r_mp**2)

    @property
    def c(self):
        """Total viscous damping B_eq + B_emf [kg/s]."""
        return self.B_eq + self.B_emf

    @property
    def gamma(self):
        """Force per volt at the cart [N/V]."""
        return (
            self.gamma_scale * self.eta_g * self.Kg * self.eta_m * self.Kt / (self.Rm * self.r_mp)
        )

    # Parameters by name, across the plant and its effects (used by fitting and files).
    def param_names(self) -> tuple[str, ...]:
        own = tuple(f.name for f in fields(self) if f.name not in ("effects", "motor_connected"))
        return own + tuple(n for e in self.effects for n in e.param_names())

    def get(self, name: str):
        """Value of a named parameter of the plant or of one of its effects."""
        if name in _OWN:
            return getattr(self, name)
        for effect in self.effects:
            if name in effect.param_names():
                return getattr(effect, name)
        raise KeyError(f"unknown plant parameter {name!r}; known: {', '.join(self.param_names())}")

    def replace(self, **values) -> Plant:
        """A copy with named parameters changed (plant fields or effect parameters)."""
        own = {k: v for k, v in values.items() if k in _OWN}
        rest = {k: v for k, v in values.items() if k not in _OWN}
        effects = []
        for effect in self.effects:
            mine = {k: rest.pop(k) for k in list(rest) if k in effect.param_names()}
            effects.append(dataclasses.replace(effect, **mine) if mine else effect)
        if rest:
            raise KeyError(
                f"unknown plant parameter(s) {', '.join(rest)}; known: "
                f"{', '.join(self.param_names())}"
            )
        return dataclasses.replace(self, effects=tuple(effects), **own)

    def effect(self, kind):
        """The effect of the given class or registry name ("coulomb"), or None."""
        if isinstance(kind, str):
            kind = REGISTRY[kind]
        return next((e for e in self.effects if isinstance(e, kind)), None)

    def stage(self, name: str) -> tuple:
        """The effects acting at one stage ("voltage", "force", "sensor"), in loop order."""
        chosen = [e for e in self.effects if e.stage == name]
        return tuple(sorted(chosen, key=lambda e: e.order))

    @property
    def structure(self) -> tuple[str, ...]:
        """Names of the plant's effects in loop order ("nominal" when it has none)."""
        ordered = sorted(self.effects, key=lambda e: (STAGE_ORDER[e.stage], e.order))
        return tuple(type(e).name for e in ordered)


_OWN = frozenset(f.name for f in fields(Plant) if f.name not in ("effects", "motor_connected"))


def voltage_limit(plant: Plant, controller=None):
    """The effective voltage limit [V]: the smaller of the controller's software ``v_limit``
    and the amplifier's ``v_sat`` (inf when neither limits). Traced values pass through."""
    # The amplifier's limit is the effect that declares the parameter v_sat.
    limits = [e.v_sat for e in plant.effects if "v_sat" in e.param_names()]
    if controller is not None:
        limits.append(controller.v_limit)
    if not limits:
        return float("inf")
    if all(isinstance(x, int | float) for x in limits):
        return float(min(limits))
    out = limits[0]
    for x in limits[1:]:
        out = jnp.minimum(out, x)
    return out
