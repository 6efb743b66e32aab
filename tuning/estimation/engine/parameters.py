"""What the estimation engine knows of each parameter, derived from the effects registry.

Every registered effect's :class:`jaxcart.effects.Param` (and the plant's own, in
:mod:`jaxcart.plantspec`) declares its unit, valid and plausible ranges, neutral value and role
(drive, cart, sensor); nothing here is spelled per effect. A fitted name is ``base`` (one value
shared by every recording), ``base@i`` (the value of recording ``i`` alone) or ``base[k]``
(element ``k`` of a vector parameter); the nuisances ``y0@i``, ``yd0@i`` are a recording's
start position [m] and velocity [m/s].

Internal coordinates: a parameter that cannot be negative is fitted as its logarithm (relative
steps); any other as value / scale, with the scale its typical size (0.1 for plant values,
1 mm and 0.1 m/s for the nuisances).
"""

from __future__ import annotations

import math

import numpy as np

from jaxcart import plantspec
from jaxcart.effects import REGISTRY

#: Internal unit of a parameter fitted linearly [SI].
LINEAR_SCALE = 0.1
#: The nuisances of a recording: internal unit and bounds [SI].
NUISANCE = {"y0": (1e-3, (-2.0, 2.0)), "yd0": (0.1, (-10.0, 10.0))}
#: The plant's own parameters a fit corrects (the rest of the appendix is held).
CORRECTABLE = ("B_eq", "M", "gamma_scale")
#: Where a limit never acts stands in for its neutral inf in a batch (far above any run) [SI].
FAR = 1e4


def base_name(name: str) -> str:
    """``v_sat@2`` -> ``v_sat``, ``f_track[1]`` -> ``f_track``."""
    return name.split("@")[0].split("[")[0]


def recording_of(name: str) -> int | None:
    """The recording a per-recording name belongs to (``v_sat@2`` -> 2), else None."""
    return int(name.split("@")[1]) if "@" in name else None


def spec(name: str):
    """The :class:`jaxcart.effects.Param` declaration of a fitted name (KeyError if none)."""
    return plantspec.param(base_name(name))


def is_log(name: str) -> bool:
    """Fitted as a logarithm: every parameter that cannot be negative (not the nuisances)."""
    b = base_name(name)
    if b in NUISANCE:
        return False
    try:
        return spec(b).log
    except KeyError:
        return True


def _scale(name: str) -> float:
    b = base_name(name)
    return NUISANCE[b][0] if b in NUISANCE else LINEAR_SCALE


def to_theta(name: str, value: float) -> float:
    """The internal coordinate of a value [SI] (inverse of :func:`to_value`)."""
    if is_log(name):
        return math.log(max(float(value), 1e-300))
    return float(value) / _scale(name)


def to_value(name: str, theta, xp=np):
    """A parameter's value [SI] from its internal coordinate."""
    return xp.exp(theta) if is_log(name) else _scale(name) * theta


def value_slope(name: str, value: float) -> float:
    """d value / d theta at ``value`` (the Jacobian factor of standard errors)."""
    return float(value) if is_log(name) else _scale(name)


def bounds(name: str) -> tuple[float, float]:
    """A fit's bounds [SI]: the plausible range of a lab cart where declared, else the valid
    range (strictly positive for a logarithm)."""
    b = base_name(name)
    if b in NUISANCE:
        return NUISANCE[b][1]
    return spec(b).fit_range


#: A fitted value within this fraction of its range (of its bound, for a logarithm) of a
#: bound sits on it: the optimizer was stopped by the range, not by the data.
EDGE_FRACTION = 1e-3


def at_edge(name: str, value: float) -> tuple[str, float] | None:
    """("upper" | "lower", the bound [SI]) where ``value`` sits on an edge of the range a fit
    holds ``name`` in (:func:`bounds`), else None. Such a value is the range's answer, not an
    estimate: the data pushed it as far as the fit allows."""
    lo, hi = bounds(name)
    value = float(value)
    if is_log(name):
        if value >= hi * (1 - EDGE_FRACTION):
            return "upper", hi
        return ("lower", lo) if value <= lo * (1 + EDGE_FRACTION) else None
    width = EDGE_FRACTION * (hi - lo)
    if value >= hi - width:
        return "upper", hi
    return ("lower", lo) if value <= lo + width else None


def neutral(name: str) -> float | None:
    """The value at which a parameter's effect does nothing (inf for a limit), or None."""
    return spec(name).neutral


def is_drive(name: str) -> bool:
    """A parameter of the motor and amplifier: acts only with the motor connected."""
    try:
        return spec(name).role == "drive"
    except KeyError:
        return False


def candidates(span: float | None = None) -> dict:
    """The effects a diagnosis searches over: {effect name: the parameters a candidate of it
    frees} (its own and those of the effects it stands on), in registry order. ``span``: the
    stretch of track the recordings cover together [m] (the range of their positions); an
    effect that declares ``covers`` (a map along the track) is a candidate only where
    span >= covers (None: not known, and such an effect is left out)."""
    out = {}
    for name, cls in REGISTRY.items():
        if cls.not_candidate:
            continue
        if cls.covers and (span is None or span < cls.covers):
            continue
        names = [p.name for r in cls.requires for p in REGISTRY[r].params]
        out[name] = tuple(dict.fromkeys(names + [p.name for p in cls.params]))
    return out


def named_by(effect: str) -> tuple[str, ...]:
    """The effects a candidate names (stiction names Coulomb friction and stiction)."""
    return (*REGISTRY[effect].requires, effect)


def superset() -> tuple[str, ...]:
    """Every parameter a diagnosis may free: the plant's corrections, then every candidate
    effect's, in registry order."""
    names = list(CORRECTABLE)
    for params in candidates().values():
        names += [n for n in params if n not in names]
    return tuple(names)


def stand_in(name: str) -> float:
    """The neutral value of a parameter as a batch simulates it (a limit's inf -> :data:`FAR`)."""
    v = neutral(name)
    if v is None:
        return spec(name).start
    return FAR if math.isinf(v) else float(v)


def consistent(values: dict) -> dict:
    """``values`` through every effect's own constraints (static friction above kinetic)."""
    for cls in REGISTRY.values():
        values = cls.consistent(values)
    return values


def plausible(name: str, value: float) -> bool:
    """Inside the range a cart of this lab has (every value is, where none is declared)."""
    rng = spec(name).plausible
    return rng is None or rng[0] <= value <= rng[1]


def concealing_friction() -> str | None:
    """The effect other candidates stand on (kinetic Coulomb friction): it conceals the others
    (a delay, a current limit under it help little alone), so the search pairs it with each."""
    need = [r for n in candidates() for r in REGISTRY[n].requires]
    return need[0] if need else None


def friction_family(effect: str) -> bool:
    """The concealing friction itself, or a candidate that stands on it (stiction)."""
    base = concealing_friction()
    return effect == base or base in REGISTRY[effect].requires if effect in REGISTRY else False


def redundant(parts) -> bool:
    """A structure naming an effect beside one that already holds it (stiction holds
    Coulomb friction)."""
    parts = set(parts)
    return any(r in parts for p in parts if p in REGISTRY for r in REGISTRY[p].requires)


def encoder() -> tuple[str, str]:
    """(effect, parameter) of the sensor the recordings' counts come from (the encoder and
    its count size [m])."""
    for name, cls in REGISTRY.items():
        for p in cls.params:
            if p.role == "sensor":
                return name, p.name
    raise LookupError("no sensor effect is registered")


def start_for(name: str, peaks: dict | None = None, y_mean: float = 0.0) -> float:
    """A fit's start value of a parameter [SI] from the data where its declared start would
    not act: a limit below the run's largest command (current), ``peaks`` {"command" [V],
    "current" [A]} (from its declared start a limit above them never acts and its gradient is
    zero); a breakaway level at the largest force the drive held the cart at rest with,
    ``peaks["held"]`` [N] (``Param.starts_at``); a position (a spring's rest) where the cart
    was, ``y_mean`` [m]; else declared."""
    decl = spec(name)
    if decl.starts_at and (peaks or {}).get(decl.starts_at):
        return float(peaks[decl.starts_at])
    cls = plantspec.effect_of_param(base_name(name))
    top = (peaks or {}).get(cls.limits) if cls is not None and cls.limits else None
    if top:
        return 0.7 * float(top)
    if decl.neutral is None and decl.unit == "m" and cls is not None:
        return float(y_mean)
    return decl.start
