"""Plant parameters of the IP02 cart: the handout's appendix as an immutable pytree.

    m y'' + c y' = gamma * u + F_effects(y, y'),      m = M + M_J,   c = B_eq + B_emf
    M_J   = eta_g Kg^2 Jm / r_mp^2
    B_emf = eta_g Kg^2 eta_m Kt Km / (Rm r_mp^2)       (0 with the motor unplugged)
    gamma = eta_g Kg eta_m Kt / (Rm r_mp)               (times gamma_scale)

Effects beyond this linear model (saturation, Coulomb friction, ...) are pieces in
``Plant.effects``; see :mod:`jaxcart.effects`.

>>> p = Plant()
>>> round(float(p.m), 4), round(float(p.B_emf), 4), round(float(p.gamma), 4)
(1.0731, 7.7236, 1.7235)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields

import jax

from jaxcart.effects import Coulomb, Saturation

#: Encoder resolution of the IP02 [m/count] (the handout's appendix).
ENCODER_RESOLUTION = 2.275e-5
#: Length of the track [m] and usable travel of the cart [m].
TRACK_LENGTH = 0.990
TRAVEL = 0.814


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

    M: float = 0.94
    B_eq: float = 5.4
    Rm: float = 2.6
    Kt: float = 0.00767
    Km: float = 0.00767
    Jm: float = 3.9e-7
    Kg: float = 3.71
    r_mp: float = 6.35e-3
    eta_g: float = 1.0
    eta_m: float = 1.0
    gamma_scale: float = 1.0
    effects: tuple = (Saturation(),)
    motor_connected: bool = field(default=True, metadata={"static": True})

    def __post_init__(self):
        for name in ("M", "Rm", "Kg", "r_mp", "eta_g", "eta_m", "Jm", "B_eq", "gamma_scale"):
            value = getattr(self, name)
            if isinstance(value, float | int) and not value >= 0:
                raise ValueError(f"plant parameter {name} = {value!r}: it must be >= 0")
        if isinstance(self.M, float | int) and self.M == 0:
            raise ValueError("plant parameter M = 0 kg: the cart needs a positive mass")
        names = [n for e in self.effects for n in e.param_names]
        if len(names) != len(set(names)):
            raise ValueError(f"two effects share a parameter name: {names}")

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
        return own + tuple(n for e in self.effects for n in e.param_names)

    def get(self, name: str):
        """Value of a named parameter of the plant or of one of its effects."""
        if name in _OWN:
            return getattr(self, name)
        for effect in self.effects:
            if name in effect.param_names:
                return getattr(effect, name)
        raise KeyError(f"unknown plant parameter {name!r}; known: {', '.join(self.param_names())}")

    def replace(self, **values) -> Plant:
        """A copy with named parameters changed (plant fields or effect parameters)."""
        own = {k: v for k, v in values.items() if k in _OWN}
        rest = {k: v for k, v in values.items() if k not in _OWN}
        effects = []
        for effect in self.effects:
            mine = {k: rest.pop(k) for k in list(rest) if k in effect.param_names}
            effects.append(dataclasses.replace(effect, **mine) if mine else effect)
        if rest:
            raise KeyError(
                f"unknown plant parameter(s) {', '.join(rest)}; known: "
                f"{', '.join(self.param_names())}"
            )
        return dataclasses.replace(self, effects=tuple(effects), **own)

    def effect(self, kind: type):
        """The first effect of the given class, or None."""
        return next((e for e in self.effects if isinstance(e, kind)), None)


_OWN = frozenset(f.name for f in fields(Plant) if f.name not in ("effects", "motor_connected"))


def handout_plant(*, f_c: float = 0.0, v_sat: float = 6.0, **overrides) -> Plant:
    """The handout's model: appendix values, B_eq = 5.4 kg/s, 6 V saturation, and Coulomb
    friction f_c [N] when it is positive."""
    effects = [Saturation(v_sat=v_sat)]
    if f_c:
        effects.append(Coulomb(f_c=f_c))
    return Plant(effects=tuple(effects), **overrides)


def tap_plant(**overrides) -> Plant:
    """The tap test: motor unplugged (B_emf = 0, no drive), no saturation in play."""
    effects = overrides.pop("effects", ())
    return Plant(motor_connected=False, effects=tuple(effects), **overrides)
