"""The true cart of the independent generator: every parameter of its physics, in SI units.

Names follow jaxcart's where the physics is the same (``B_eq``, ``M``, ``gamma_scale``, ``f_c``,
``f_s``, ``v_sat``, ``i_max``, ``delay``, ``deadzone``, ``k_s``, ``y_rest``), and are its own
for what the library lacks (friction by direction, the Stribeck speed, the Karnopp band, a
tilted track, a drive offset, a dead band by direction, an amplifier lag, friction read from a
table along the track). The physics itself is in :mod:`tuning.verification.physics`.

>>> cart = TrueCart.from_values({"B_eq": 4.6, "f_c": 0.4, "v_sat": 5.0})
>>> cart.kinetic(+1), round(cart.m, 4), round(cart.gamma, 4)
(0.4, 1.0731, 1.7235)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

from hw.handout import APPENDIX

#: jaxcart's ``f_track`` knots lie evenly over +/- this [m] (jaxcart.effects.track_friction);
#: a truth given as ``f_track`` puts its table's points there.
TRACK_SPAN = 0.4
#: jaxcart's asymmetry parameters (half the difference between the two directions' levels):
#: NAME_asym translates to this cart's NAME_pos and NAME_neg about its level NAME (B: B_eq).
ASYMMETRIES = ("f_c_asym", "B_asym", "deadzone_asym")


@dataclass(frozen=True)
class TrueCart:
    """The independent generator's cart. Positions are in the track's frame, in which a run
    starts at 0 (the encoder reads 0 there, up to its phase).

    Mechanics:
      M: cart plus weight [kg]; Jm, Kg, r_mp, eta_g: the rotor's inertia [kg m^2], gear ratio
        [-], pinion radius [m] and gearbox efficiency [-] (the rotor's inertia seen at the cart
        is eta_g Kg^2 Jm / r_mp^2 [kg], geared to the cart also with the motor unplugged)
      B_eq: viscous friction [kg/s]; B_pos, B_neg: moving towards +y / -y [kg/s] (None: B_eq)
      f_c: kinetic (Coulomb) friction [N]; f_c_pos, f_c_neg: moving towards +y / -y [N]
        (None: f_c)
      f_s: static (breakaway) level [N] (None: the kinetic level); a cart at rest breaks away
        when the force on it exceeds max(f_s, kinetic level)
      v_stribeck: Stribeck speed [m/s]: sliding friction is K + (S - K) exp(-(v / v_stribeck)^2)
        from the breakaway level S down to the kinetic K; 0 drops to K at once (the lurch)
      v_band: Karnopp's zero-velocity band [m/s]: below it the cart counts as at rest
      rise_pos, rise_neg, v_rise: sliding friction that rises with the speed to a plateau, by
        rise_pos (moving towards +y) or rise_neg [N] times 1 - exp(-|y'| / v_rise) [m/s] (a
        shape none of jaxcart's named effects has; 0: none)
      track_y, track_f: friction along the track, a table: kinetic friction track_f [N] added at
        positions track_y [m] (increasing), linear between points, held beyond the ends
      f_tilt: a constant force towards +y [N] (a tilted track: M g sin(angle))
      k_s, y_rest: cable spring [N/m] and its rest position [m]: force -k_s (y - y_rest)
    Drive (command u [V] -> amplifier -> motor):
      motor_connected: False for a tap (no drive, no back-EMF)
      delay: transport delay of the command [s]
      v_offset: offset added to the command [V]
      deadzone: dead band of the amplifier [V]; deadzone_pos, deadzone_neg: for positive /
        negative voltages [V] (None: deadzone)
      lag: first-order lag of the amplifier output [s] (0: none)
      v_sat: amplifier output saturation [V]
      gamma_scale: drive gain [-]: the motor sees gamma_scale times the amplifier's output
        (so the force per volt is gamma_scale gamma; the back-EMF damping is unchanged)
      i_max: armature current limit [A]: i = (V - back-EMF) / Rm clipped to +/- i_max
      Rm, Kt, Km, eta_m: armature resistance [ohm], torque constant [N m/A], back-EMF constant
        [V s/rad], motor efficiency [-]
    """

    M: float = APPENDIX["M"]
    B_eq: float = APPENDIX["B_eq"]
    B_pos: float | None = None
    B_neg: float | None = None
    f_c: float = 0.0
    f_c_pos: float | None = None
    f_c_neg: float | None = None
    f_s: float | None = None
    v_stribeck: float = 0.0
    v_band: float = 1e-4
    rise_pos: float = 0.0
    rise_neg: float = 0.0
    v_rise: float = 0.01
    track_y: tuple = ()
    track_f: tuple = ()
    f_tilt: float = 0.0
    k_s: float = 0.0
    y_rest: float = 0.0
    motor_connected: bool = True
    delay: float = 0.0
    v_offset: float = 0.0
    deadzone: float = 0.0
    deadzone_pos: float | None = None
    deadzone_neg: float | None = None
    lag: float = 0.0
    v_sat: float = math.inf
    gamma_scale: float = APPENDIX["gamma_scale"]
    i_max: float = math.inf
    Rm: float = APPENDIX["Rm"]
    Kt: float = APPENDIX["Kt"]
    Km: float = APPENDIX["Km"]
    Jm: float = APPENDIX["Jm"]
    Kg: float = APPENDIX["Kg"]
    r_mp: float = APPENDIX["r_mp"]
    eta_g: float = APPENDIX["eta_g"]
    eta_m: float = APPENDIX["eta_m"]

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float | int) and not isinstance(value, bool):
                if math.isnan(value) or (value < 0 and f.name not in ("f_tilt", "y_rest")):
                    raise ValueError(f"TrueCart.{f.name} = {value!r}: give a number >= 0")
        if len(self.track_y) != len(self.track_f):
            raise ValueError("TrueCart: track_y and track_f must have one value each")
        if any(b <= a for a, b in zip(self.track_y, self.track_y[1:], strict=False)):
            raise ValueError("TrueCart.track_y must increase")
        for name in ("M", "Rm", "Kg", "r_mp", "v_band", "v_rise"):
            if not getattr(self, name) > 0:
                raise ValueError(f"TrueCart.{name} must be positive")

    @classmethod
    def from_values(cls, values: dict, **more) -> TrueCart:
        """A cart from ``{name: value}`` in the names above, plus jaxcart's ``f_track`` (a list
        of kinetic friction levels [N] at points evenly over +/- TRACK_SPAN m) and its
        asymmetries (``f_c_asym``, ``B_asym``, ``deadzone_asym``: half the difference between
        the two directions' levels, +y / positive commands the larger)."""
        values = {**values, **more}
        for asym in ASYMMETRIES:
            if asym in values:
                prefix = asym.removesuffix("_asym")
                level_name = "B_eq" if prefix == "B" else prefix
                a = float(values.pop(asym))
                level = float(values.get(level_name, getattr(cls, level_name)))
                values[f"{prefix}_pos"], values[f"{prefix}_neg"] = level + a, level - a
        if "f_track" in values:
            levels = tuple(float(x) for x in values.pop("f_track"))
            span = TRACK_SPAN
            step = 2 * span / (len(levels) - 1) if len(levels) > 1 else 0.0
            values["track_y"] = tuple(-span + i * step for i in range(len(levels)))
            values["track_f"] = levels
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            names = ", ".join(sorted(known))
            raise ValueError(f"TrueCart: no parameter {', '.join(unknown)}; the names: {names}")
        return cls(**values)

    def replace(self, **changes) -> TrueCart:
        return replace(self, **changes)

    @property
    def m(self) -> float:
        """Moving mass M + eta_g Kg^2 Jm / r_mp^2 [kg]."""
        return self.M + self.eta_g * self.Kg**2 * self.Jm / self.r_mp**2

    @property
    def force_per_amp(self) -> float:
        """Force on the cart per armature ampere eta_g Kg eta_m Kt / r_mp [N/A]."""
        return self.eta_g * self.Kg * self.eta_m * self.Kt / self.r_mp

    @property
    def emf_per_speed(self) -> float:
        """Back-EMF per cart speed Km Kg / r_mp [V s/m]."""
        return self.Km * self.Kg / self.r_mp

    @property
    def gamma(self) -> float:
        """Force per volt at rest gamma_scale force_per_amp / Rm [N/V] (0 unplugged)."""
        if not self.motor_connected:
            return 0.0
        return self.gamma_scale * self.force_per_amp / self.Rm

    def kinetic(self, direction: int, y: float = 0.0) -> float:
        """Kinetic friction level moving in ``direction`` (+1 / -1) at position y [N]."""
        level = self.f_c_pos if direction > 0 else self.f_c_neg
        return (self.f_c if level is None else level) + self.track(y)

    def rise(self, direction: int, speed: float) -> float:
        """The sliding friction's rise with the speed [N] moving in ``direction`` at ``speed``
        = |y'| [m/s]."""
        top = self.rise_pos if direction > 0 else self.rise_neg
        return top * (1.0 - math.exp(-speed / self.v_rise)) if top else 0.0

    def static(self, direction: int, y: float = 0.0) -> float:
        """Breakaway level towards ``direction`` at position y [N]: at least the kinetic."""
        kinetic = self.kinetic(direction, y)
        return kinetic if self.f_s is None else max(self.f_s, kinetic)

    def viscous(self, direction: int) -> float:
        """Viscous friction moving in ``direction`` [kg/s]."""
        b = self.B_pos if direction > 0 else self.B_neg
        return self.B_eq if b is None else b

    def dead_band(self) -> tuple[float, float]:
        """The amplifier's dead band (positive, negative side) [V]."""
        pos = self.deadzone if self.deadzone_pos is None else self.deadzone_pos
        neg = self.deadzone if self.deadzone_neg is None else self.deadzone_neg
        return pos, neg

    def track(self, y: float) -> float:
        """Friction along the track at y [N] (linear in the table, held beyond it)."""
        ys, fs = self.track_y, self.track_f
        if not ys:
            return 0.0
        if y <= ys[0]:
            return fs[0]
        for i in range(1, len(ys)):
            if y <= ys[i]:
                w = (y - ys[i - 1]) / (ys[i] - ys[i - 1])
                return fs[i - 1] + w * (fs[i] - fs[i - 1])
        return fs[-1]

    def values(self) -> dict:
        """The parameters that differ from the defaults, {name: value} (a file's notes)."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value != f.default:
                out[f.name] = value
        return out
