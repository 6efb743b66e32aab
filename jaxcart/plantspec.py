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

from jaxcart.effects import REGISTRY, STAGE_ORDER, Param, effect_of_param
from jaxcart.errors import UserError
from jaxcart.params import Plant

FORMAT = "jaxcart-plant"
VERSION = 1

#: The plant's own parameters (the handout's appendix and the corrections M, gamma_scale).
PLANT_PARAMS = (
    Param("M", "kg", 1e-3, 100.0, 0.94, None, "cart plus added mass Mc + Mw"),
    Param("B_eq", "kg/s", 0.0, 200.0, 5.4, None, "equivalent viscous friction"),
    Param("gamma_scale", "", 0.01, 100.0, 1.0, None, "multiplier on the input gain gamma"),
    Param("Rm", "ohm", 1e-3, 1e3, 2.6, None, "armature resistance"),
    Param("Kt", "N m/A", 0.0, 10.0, 0.00767, None, "motor torque constant"),
    Param("Km", "V s/rad", 0.0, 10.0, 0.00767, None, "back-EMF constant"),
    Param("Jm", "kg m^2", 0.0, 1.0, 3.9e-7, None, "rotor moment of inertia"),
    Param("Kg", "", 1e-3, 1e3, 3.71, None, "gearbox ratio"),
    Param("r_mp", "m", 1e-5, 1.0, 6.35e-3, None, "motor pinion radius"),
    Param("eta_g", "", 1e-3, 1.0, 1.0, None, "gearbox efficiency"),
    Param("eta_m", "", 1e-3, 1.0, 1.0, None, "motor efficiency"),
)
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
    motor_connected: bool = True,
    effects: Mapping | None = None,
    where: str = "plant",
) -> Plant:
    """The handout's nominal plant with named parameters set; the one plant builder.

    values: {name: value} in SI units; a name of an effect's parameter adds that effect (its
    other parameters at their defaults). effects: {effect name: {parameter: value}} (a plant
    file's ``[effects.NAME]`` tables; an empty table adds the effect with its defaults).
    motor_connected: False for the tap test. where: names the source in error messages.
    Raises :class:`UserError` naming the key and the allowed values for an unknown name, a
    value out of its declared range, or an effect given twice.
    """
    values = dict(values or {})
    own: dict = {}
    by_effect: dict[str, dict] = {}
    for name, value in values.items():
        if name in _OWN:
            own[name] = _value(name, value, where)
            continue
        cls = effect_of_param(name)
        if cls is None:
            raise UserError(
                f"{where}: unknown plant parameter {name!r}; known: {', '.join(parameter_names())}"
            )
        by_effect.setdefault(cls.name, {})[name] = _value(name, value, where)
    for effect_name, table in dict(effects or {}).items():
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
    built = []
    for effect_name, params in by_effect.items():
        try:
            built.append(REGISTRY[effect_name](**params))
        except (TypeError, ValueError) as exc:
            raise UserError(
                f"{where}: effect {effect_name}: {' '.join(str(exc).split())}"
            ) from None
    built.sort(key=lambda e: (STAGE_ORDER[e.stage], e.order))
    try:
        return Plant(effects=tuple(built), motor_connected=motor_connected, **own)
    except ValueError as exc:
        raise UserError(f"{where}: {' '.join(str(exc).split())}") from None


def with_values(plant: Plant, values: Mapping, *, where: str = "plant") -> Plant:
    """``plant`` with named values set (unvalidated, so traced values pass: used by fits and
    batches); a name of an effect the plant lacks adds that effect."""
    have = set(plant.param_names())
    new: dict[str, dict] = {}
    for name in values:
        if name not in have:
            cls = effect_of_param(name)
            if cls is None:
                raise UserError(
                    f"{where}: unknown plant parameter {name!r}; known: "
                    f"{', '.join(parameter_names())}"
                )
            new.setdefault(cls.name, {})
    if new:
        added = [REGISTRY[n]() for n in new]
        effects = sorted((*plant.effects, *added), key=lambda e: (STAGE_ORDER[e.stage], e.order))
        plant = dataclasses.replace(plant, effects=tuple(effects))
    return plant.replace(**dict(values))


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
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)
    return path


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
    allowed = {"format", "version", "motor_connected", "structure", "effects", "plant", "fit"}
    for key in meta:
        if key not in allowed:
            raise UserError(f"{path}: unknown key {key!r}; allowed: {', '.join(sorted(allowed))}")
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


def load_plant(path, *, where: str = "--plant") -> Plant:
    """A plant from a plant file, or from an experiment file's [plant] table (its kind's
    nominal plant with those values); the one reader behind every ``--plant FILE`` option."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{where} {path}: no such file; give a plant file (.toml)")
    try:
        head = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except (tomllib.TOMLDecodeError, OSError, UnicodeDecodeError):
        head = {}
    if head.get("format") == FORMAT or path.suffix.lower() != ".toml":
        return read_plant_file(path)[0]
    from jaxcart.files import read_experiment  # an experiment file: its [plant] applies

    return read_experiment(path).plant()


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
