"""One plant spec: a plant from names and values, and plant files (TOML) that round-trip exactly.

Every reader of plants goes through :func:`build_plant`: experiment ``[plant]`` tables, plant
files, ``tune``, ``fit``, ``lab`` and ``diagnose``. Names are SI-unit parameters: the plant's own
(``M``, ``B_eq``, ``gamma_scale``, and the appendix constants) and every registered effect's
(``v_sat``, ``f_c``, ``f_s``, ``delay``, ``deadzone``, ``k_s``, ``y_rest``, ``i_max``,
``quantization``, ``f_track``); naming an effect's parameter adds that effect.

A plant file (docs/design.md, "Plant files"):

    format = "jaxcart-plant"
    version = 1
    motor_connected = true          # false: the tap test's unplugged motor
    structure = ["delay", "coulomb"]  # the effects, in loop order (checked against the tables)
    [plant]                         # the plant's own parameters that differ from the handout's
    B_eq = 4.1
    [effects.coulomb]               # one table per effect, its parameters inside
    f_c = 0.44
    [effects.delay]
    delay = 0.003
    [fit]                           # optional: what a fit knows (standard errors, held, ...)

>>> p = build_plant({"B_eq": 4.0, "f_c": 0.3})
>>> p.structure, float(p.get("f_c"))
(('coulomb',), 0.3)
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from hw.atomicio import write_text
from hw.devices.sim import PLANT_FILE_KEYS
from hw.handout import APPENDIX, VALID
from jaxcart.effects import REGISTRY, STAGE_ORDER, Effect, Param, effect_of_param
from jaxcart.errors import UserError
from jaxcart.params import Plant

FORMAT = "jaxcart-plant"
VERSION = 1

#: The plant's own parameters (the handout's appendix and the corrections M, gamma_scale).
PLANT_PARAMS = (
    # Plausible: the cart is 0.57 kg, 0.94 kg with its weight; the handout's B_eq is 5.4 kg/s
    # and real IP02 taps fit 1.4-1.5 kg/s; a motor gain off by more than a factor 2 is a wrong
    # motor, not a correction.
    Param("M", "kg", *VALID["M"], APPENDIX["M"], None, "cart plus added mass Mc + Mw",
          plausible=(0.4, 3.0)),
    Param("B_eq", "kg/s", *VALID["B_eq"], APPENDIX["B_eq"], None, "equivalent viscous friction",
          plausible=(0.5, 30.0)),
    Param("gamma_scale", "", *VALID["gamma_scale"], APPENDIX["gamma_scale"], None,
          "multiplier on the input gain gamma", role="drive", plausible=(0.5, 2.0)),
    Param("Rm", "ohm", *VALID["Rm"], APPENDIX["Rm"], None, "armature resistance"),
    Param("Kt", "N m/A", *VALID["Kt"], APPENDIX["Kt"], None, "motor torque constant"),
    Param("Km", "V s/rad", *VALID["Km"], APPENDIX["Km"], None, "back-EMF constant"),
    Param("Jm", "kg m^2", *VALID["Jm"], APPENDIX["Jm"], None, "rotor moment of inertia"),
    Param("Kg", "", *VALID["Kg"], APPENDIX["Kg"], None, "gearbox ratio"),
    Param("r_mp", "m", *VALID["r_mp"], APPENDIX["r_mp"], None, "motor pinion radius"),
    Param("eta_g", "", *VALID["eta_g"], APPENDIX["eta_g"], None, "gearbox efficiency"),
    Param("eta_m", "", *VALID["eta_m"], APPENDIX["eta_m"], None, "motor efficiency"),
)  # fmt: skip
_OWN = {p.name: p for p in PLANT_PARAMS}
_NOMINAL = Plant()


def param(name: str) -> Param:
    """The declaration (unit, range, start) of any plant or effect parameter by name."""
    if name in _OWN:
        return _OWN[name]
    cls = effect_of_param(name)
    if cls is None:
        raise KeyError(name)
    return cls.param(name)


def parameter_names() -> tuple[str, ...]:
    """Every name a plant spec accepts: the plant's own, then each registered effect's."""
    return tuple(_OWN) + tuple(n for cls in REGISTRY.values() for n in cls.param_names())


def unit(name: str) -> str:
    """SI unit of a parameter ("" for a ratio)."""
    return param(name).unit


def _value(name: str, value, where: str):
    """A validated float (or tuple of floats for a vector parameter)."""
    decl = param(name)
    if decl.size:
        if isinstance(value, int | float) and not isinstance(value, bool):
            value = [value] * decl.size
        if not isinstance(value, list | tuple | np.ndarray) or len(value) < 2:
            raise UserError(f"{where}: {name} = {value!r}: give a list of 2 or more numbers")
        items = [_scalar(name, v, where) for v in value]
        _check(decl, items, where)
        return tuple(items)
    value = _scalar(name, value, where)
    _check(decl, value, where)
    return value


def _scalar(name, value, where) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise UserError(f"{where}: {name} = {value!r}: give a number ({_unit_text(name)})")
    return float(value)


def _unit_text(name):
    u = unit(name)
    return f"in {u}" if u else "a ratio"


def _check(decl: Param, value, where: str) -> None:
    try:
        decl.check(value, where)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def build_plant(
    values: Mapping | None = None,
    *,
    base: Plant | None = None,
    effects=None,
    motor_connected: bool | None = None,
    where: str = "plant",
    check: bool = True,
) -> Plant:
    """``base`` (None: the handout's nominal plant) with named parameters set; the one plant
    builder (:func:`handout_plant`, :func:`tap_plant`, experiment files' [plant], plant files,
    fits, the tuner's robust sets, the lab and diagnose all call it).

    values: {name: value} in SI units; a name of an effect's parameter sets it on the base's
    effect of that kind, or adds that effect (its other parameters at their defaults).
    effects: {effect name: {parameter: value}} (a plant file's ``[effects.NAME]`` tables; an
    empty table adds the effect with its defaults), or effect objects, added as they are.
    motor_connected: False for the tap test (None: the base's). where: names the source in
    error messages. check: validate every value against its declaration (numbers in range);
    False passes values as given, so traced values of fits and batches pass.
    Raises :class:`UserError` naming the key and the allowed values for an unknown name, a
    value out of its declared range, or an effect given twice.
    """
    base = _NOMINAL if base is None else base
    own, by_effect = _sorted_values(dict(values or {}), where, check)
    extra = []
    if isinstance(effects, Mapping):
        _add_tables(by_effect, effects, where)
    elif effects:
        extra = list(effects)
        if not all(isinstance(e, Effect) for e in extra):
            raise UserError(f"{where}: effects must be effect objects or a table per effect")
    built = []
    for effect in (*base.effects, *extra):
        mine = by_effect.pop(type(effect).name, None)
        built.append(_effect(type(effect).name, mine, where, effect) if mine else effect)
    built += [_effect(name, params, where) for name, params in by_effect.items()]
    built.sort(key=lambda e: (STAGE_ORDER[e.stage], e.order))
    connected = base.motor_connected if motor_connected is None else motor_connected
    try:
        return dataclasses.replace(base, effects=tuple(built), motor_connected=connected, **own)
    except ValueError as exc:
        raise UserError(f"{where}: {' '.join(str(exc).split())}") from None


def _sorted_values(values: dict, where: str, check: bool) -> tuple[dict, dict]:
    """({own parameter: value}, {effect name: {parameter: value}}) of named values."""
    own: dict = {}
    by_effect: dict[str, dict] = {}
    for name, value in values.items():
        if name in _OWN:
            own[name] = _value(name, value, where) if check else value
            continue
        cls = effect_of_param(name)
        if cls is None:
            raise UserError(
                f"{where}: unknown plant parameter {name!r}; known: {', '.join(parameter_names())}"
            )
        by_effect.setdefault(cls.name, {})[name] = _value(name, value, where) if check else value
    return own, by_effect


def _add_tables(by_effect: dict, tables: Mapping, where: str) -> None:
    """Adds a plant file's [effects.NAME] tables (validated) to ``by_effect``."""
    for effect_name, table in tables.items():
        if effect_name not in REGISTRY:
            raise UserError(
                f"{where}: unknown effect {effect_name!r}; known: {', '.join(REGISTRY)}"
            )
        if not isinstance(table, Mapping):
            raise UserError(f"{where}: effects.{effect_name} must be a table of its parameters")
        cls = REGISTRY[effect_name]
        if effect_name in by_effect:
            twice = ", ".join(by_effect[effect_name])
            raise UserError(
                f"{where}: effect {effect_name!r} is named twice (its {twice} given outside "
                f"[effects.{effect_name}] too); give each effect once"
            )
        chosen = by_effect.setdefault(effect_name, {})
        for name, value in table.items():
            if name not in cls.param_names():
                raise UserError(
                    f"{where}: effects.{effect_name}: unknown parameter {name!r}; known: "
                    f"{', '.join(cls.param_names()) or '(none)'}"
                )
            chosen[name] = _value(name, value, f"{where} effects.{effect_name}")


def _effect(name: str, params: dict, where: str, old: Effect | None = None) -> Effect:
    """The effect ``name`` with ``params`` set (on ``old``, or on the registry's defaults)."""
    try:
        if old is None:
            return REGISTRY[name](**params)
        return dataclasses.replace(old, **params)
    except (TypeError, ValueError) as exc:
        raise UserError(f"{where}: effect {name}: {' '.join(str(exc).split())}") from None


def handout_plant(**values) -> Plant:
    """The handout's nominal model (appendix values, B_eq = 5.4 kg/s, no effects), with named
    parameters set; naming an effect's parameter adds the effect (``f_c=0.3`` adds Coulomb
    friction, ``v_sat=6.0`` an amplifier limit). See :func:`build_plant`."""
    return build_plant(values, where="handout_plant()")


def tap_plant(*, effects=(), **values) -> Plant:
    """The tap test: motor unplugged (B_emf = 0, no drive), with named parameters set and
    ``effects`` (effect objects) added. See :func:`build_plant`."""
    return build_plant(values, effects=effects, motor_connected=False, where="tap_plant()")


def check_plant_overrides(overrides, where: str = "plant overrides") -> dict:
    """Validated {name: value} of plant overrides (SI units; Python floats, tuples for a
    vector), as an experiment file's [plant] holds them; ``where`` names the source in
    errors (one line: the name, the value, the allowed range)."""
    overrides = dict(overrides)
    own, by_effect = _sorted_values(overrides, where, check=True)
    build_plant(overrides, where=where)  # the effects' own checks (f_s >= f_c, ...)
    checked = {**own, **{k: v for table in by_effect.values() for k, v in table.items()}}
    return {k: checked[k] for k in overrides}


def plant_values(plant: Plant, *, all_own: bool = False) -> dict:
    """{name: value} (Python floats; tuples for vectors) of the plant's own parameters that
    differ from the handout's (all of them with ``all_own``) and of every effect parameter.
    ``build_plant(plant_values(p), motor_connected=p.motor_connected)`` rebuilds ``p``."""
    out = {}
    for name in _OWN:
        value = float(getattr(plant, name))
        if all_own or value != float(getattr(_NOMINAL, name)):
            out[name] = value
    for effect in plant.effects:
        for name, value in effect.values().items():
            out[name] = _plain(value)
    return out


def effect_tables(plant: Plant) -> dict:
    """{effect name: {parameter: value}} of the plant's effects, in loop order."""
    ordered = sorted(plant.effects, key=lambda e: (STAGE_ORDER[e.stage], e.order))
    return {type(e).name: {k: _plain(v) for k, v in e.values().items()} for e in ordered}


def _plain(value):
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return float(arr)
    return tuple(float(v) for v in arr.reshape(-1))


# ---------------------------------------------------------------- plant files


def write_plant_file(path, plant: Plant, *, fit: Mapping | None = None, force: bool = False):
    """Write ``plant`` as a plant file (TOML); ``fit`` adds a [fit] table (standard errors,
    held and unidentifiable parameters, RMS, sources). Refuses to overwrite without
    ``force``. Returns the path."""
    path = Path(path)
    if path.suffix.lower() != ".toml":
        raise UserError(f"{path}: a plant file is TOML; give a name ending in .toml")
    if path.exists() and not force:
        raise UserError(f"{path} exists; choose another name or pass --force to overwrite it")
    lines = [
        f'format = "{FORMAT}"',
        f"version = {VERSION}",
        f"motor_connected = {'true' if plant.motor_connected else 'false'}",
        "structure = [" + ", ".join(json.dumps(n) for n in plant.structure) + "]   # loop order",
    ]
    own = {k: v for k, v in plant_values(plant).items() if k in _OWN}
    lines += ["", "[plant]   # SI units; parameters not named here are the handout's"]
    lines += [f"{k} = {toml_value(v)}   # [{unit(k)}]" for k, v in own.items()]
    for name, table in effect_tables(plant).items():
        lines += ["", f"[effects.{name}]"]
        lines += [f"{k} = {toml_value(v)}   # [{unit(k)}]" for k, v in table.items()]
    if fit:
        lines += ["", "[fit]"] + _toml_table(fit, "fit")

    return write_text(path, "\n".join(lines) + "\n", force=True)  # checked above


def read_plant_file(path) -> tuple[Plant, dict]:
    """(plant, fit table) from a plant file; one-line :class:`UserError` for any problem."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"plant file {path} not found; give the path of a .toml plant file")
    try:
        meta = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except tomllib.TOMLDecodeError as exc:
        raise UserError(
            f"{path}: not valid TOML ({' '.join(str(exc).split())}); an effect or key given "
            "twice is one cause: give each once"
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read it ({exc})") from None
    if meta.get("format") != FORMAT:
        raise UserError(
            f"{path}: format = {meta.get('format')!r}; a plant file starts with "
            f'format = "{FORMAT}" (written by jaxcart fit / diagnose)'
        )
    for key in meta:
        if key not in PLANT_FILE_KEYS:
            allowed = ", ".join(sorted(PLANT_FILE_KEYS))
            raise UserError(f"{path}: unknown key {key!r}; allowed: {allowed}")
    motor = meta.get("motor_connected", True)
    if not isinstance(motor, bool):
        raise UserError(f"{path}: motor_connected = {motor!r}: give true or false")
    tables = meta.get("effects", {})
    if not isinstance(tables, Mapping):
        raise UserError(f"{path}: effects must be tables [effects.NAME] of their parameters")
    listed = meta.get("structure")
    if listed is not None and not (
        isinstance(listed, list) and all(isinstance(n, str) for n in listed)
    ):
        raise UserError(f"{path}: structure = {listed!r}: give a list of effect names")
    plant_table = meta.get("plant", {})
    if not isinstance(plant_table, Mapping):
        raise UserError(f"{path}: [plant] must be a table of parameters")
    plant = build_plant(plant_table, motor_connected=motor, effects=tables, where=str(path))
    if listed is not None:
        if len(listed) != len(set(listed)):
            raise UserError(f"{path}: structure = {listed}: an effect is named twice")
        if set(listed) != set(plant.structure):
            raise UserError(
                f"{path}: structure = {listed} but the tables give {list(plant.structure)}; "
                "make the list match the [effects.NAME] tables"
            )
    return plant, dict(meta.get("fit", {}))


def toml_value(value) -> str:
    """A TOML literal for a float, bool, string or list of them."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    x = float(value)
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return repr(x)


def _toml_table(table: Mapping, prefix: str) -> list[str]:
    """Lines of a TOML table: scalars and lists inline, nested mappings as inline tables."""
    lines = []
    for key, value in table.items():
        if isinstance(value, Mapping):
            inner = ", ".join(f"{json.dumps(str(k))} = {toml_value(v)}" for k, v in value.items())
            lines.append(f"{key} = {{ {inner} }}")
        elif value is None:
            continue
        else:
            lines.append(f"{key} = {toml_value(value)}")
    return lines


def describe_plant(plant: Plant) -> str:
    """One line naming the plant's structure and values: "nominal (handout), B_eq = 4.1 kg/s;
    coulomb: f_c = 0.44 N"."""
    own = {k: v for k, v in plant_values(plant).items() if k in _OWN}
    parts = ["nominal (handout)" if not plant.effects else "+".join(plant.structure)]
    if own:
        parts.append(", ".join(f"{k} = {_fmt(v)} {unit(k)}".rstrip() for k, v in own.items()))
    for name, table in effect_tables(plant).items():
        values = ", ".join(f"{k} = {_fmt(v)} {unit(k)}".rstrip() for k, v in table.items())
        parts.append(f"{name}: {values}")
    if not plant.motor_connected:
        parts.append("motor unplugged")
    return "; ".join(parts)


def _fmt(value) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(f"{v:.4g}" for v in value) + "]"
    return f"{value:.4g}"
