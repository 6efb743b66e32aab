"""The names a fit knows and the plants it makes: the parameters a fit offers and their
aliases (``v_limit`` = ``v_sat``), vector elements (``f_track[2]``), the internal coordinates
(:mod:`tuning.estimation.engine.parameters`), a plant with named values."""

from __future__ import annotations

import numpy as np

from jaxcart import plantspec
from jaxcart.errors import UserError
from jaxcart.params import Plant
from tuning.estimation.engine import parameters
from tuning.estimation.engine.parameters import base_name

#: Other names for parameters: the issue's "v_limit" is the amplifier's saturation v_sat.
ALIASES = {"v_limit": "v_sat"}


def not_fitted() -> dict:
    """{parameter: why} of the parameters a fit does not offer: a sensor's, read from the data."""
    return {
        p.name: f"the sensor's {p.doc} is read from each recording (every position is a whole "
        "number of them); it is not fitted"
        for cls in plantspec.REGISTRY.values()
        for p in cls.params
        if p.role == "sensor"
    }


def fittable() -> tuple:
    """Parameters a fit offers: the plant's corrections and every registered effect's (naming
    one adds its effect; a vector such as f_track is fitted element by element, as f_track[0],
    f_track[1], ...), from the registry as it is now."""
    skip = not_fitted()
    effects = [p.name for c in plantspec.REGISTRY.values() for p in c.params if p.name not in skip]
    return parameters.CORRECTABLE + tuple(effects)


def default_start() -> dict:
    """Starting values [SI] for parameters a plant does not have yet: each one's declared start
    (a vector's, element by element)."""
    out = {}
    for n in fittable():
        if n in ("B_eq", "M"):
            continue
        decl = plantspec.param(n)
        out[n] = (decl.start,) * decl.size if decl.size else decl.start
    return out


def unit_of(name: str) -> str:
    """The SI unit of a fitted name (``v_sat@2``, ``f_track[1]``, the alias ``v_limit``)."""
    try:
        return plantspec.unit(canonical(base_name(name)))
    except KeyError:
        return ""


def canonical(name: str) -> str:
    """The plant's name for a parameter (``v_limit`` -> ``v_sat``)."""
    return ALIASES.get(name, name)


def parse_params(text) -> tuple[str, ...]:
    """Parameter names from "B_eq,f_c" (or a sequence of names), checked against the known."""
    names = [n.strip() for n in text.split(",")] if isinstance(text, str) else list(text)
    names = [n for n in names if n]
    known = _known_names()
    expanded = []
    for n in names:
        skip = not_fitted()
        if canonical(n) in skip:
            raise UserError(f"--params: {n}: {skip[canonical(n)]}")
        if base_name(n) in known and "[" in n:
            expanded.append(n)  # one element of a vector, as returned by the fit
            continue
        size = plantspec.param(canonical(n)).size if canonical(n) in known else 0
        if size:
            expanded += [f"{n}[{i}]" for i in range(size)]
            continue
        expanded.append(n)
        if canonical(n) not in known:
            raise UserError(
                f"--params: unknown parameter {n!r}; fit any of "
                f"{', '.join(fittable())} (v_limit = v_sat), or another plant "
                f"parameter: {', '.join(sorted(known))}"
            )
    if len({canonical(n) for n in expanded}) != len(expanded):
        raise UserError(f"--params {','.join(names)}: a parameter is named twice")
    return tuple(expanded)


def _element(name: str) -> int | None:
    return int(name[name.index("[") + 1 : -1]) if "[" in name else None


def _known_names() -> set:
    return set(fittable()) | set(plantspec.parameter_names())


def _drives_nothing(name: str, plant: Plant) -> bool:
    """True for an effect's parameter of the drive (amplifier, motor) on an unplugged motor."""
    return (
        not plant.motor_connected
        and plantspec.effect_of_param(base_name(name)) is not None
        and parameters.is_drive(name)
    )


def with_values(plant: Plant, values: dict) -> Plant:
    """``plant`` with named values [SI] through the plant spec (a name of an effect the plant
    lacks adds it). Names the plant cannot have (a drive effect on a tap) are ignored."""
    values = {canonical(k): v for k, v in values.items()}
    values = {k: v for k, v in values.items() if not _drives_nothing(k, plant)}
    return plantspec.build_plant(values, base=plant, check=False)


def plant_values(plant: Plant, names=None) -> dict:
    """{name: float} of those ``names`` (default: every fittable one) the plant has."""
    names = fittable() if names is None else names
    have = set(plant.param_names())
    return {n: float(plant.get(n)) for n in names if n in have}


def _default_start(name: str) -> float:
    start = default_start().get(base_name(name), 1.0)
    return float(start[_element(name)] if isinstance(start, tuple) else start)


def _initial_value(name, value):
    """A starting value [SI]: a float, or a tuple of floats for a vector parameter."""
    try:
        if isinstance(value, list | tuple | np.ndarray):
            return tuple(float(v) for v in value)
        return float(value)
    except (TypeError, ValueError):
        raise UserError(f"initial value {name} = {value!r}: give a number (SI units)") from None
